"""Issue 30, a strong lens the nominal does not know, through the own matcher (the pattern engine off, as when its
database is absent or its 0.01 edge-ratio tolerance misses a wide distorted frame): the matcher's proposal is a few
bright stars, which every k1 verifies alike, at a step of its scan of scales through the lens-free nominal. Before,
the frame was extended through that camera and lost (44 % of its bright stars found); the k1 searched over the
frame's predicted stars (:func:`hostlink.images.extend._radial_search_by_hits`) identifies it, its own focal length
the true one, no name wrong."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_identify_field_widths import ID_MAGLIM, _ambiguous
from test_identify_wide_distortion import NOMINAL_FOCAL_ERROR, _nominal, mustache_frames

from hostlink.images.identify import identify_session

#: A 3:2 detector 55 deg across (64 deg on the diagonal), the mustache lens of test_identify_wide_distortion
#: (-20 % / +8 % of the radius at the corner), a principal point 4/-3 px off the centre.
FOV_DEG = 55.0
SIZE_PX = (1600, 1067)
#: Simulated to Hp 7 (two frames, 0.3 px centroid noise, 5 % false stars): frame 1 is the one whose scan finds a
#: true proposal (frame 0's anchors under this lens match at no scanned scale: the matcher's, not verification's).
MAGLIM = 7.0
FRAME = 1


def test_wide_mustache_frame_through_the_own_matcher_gets_its_lens_searched():
    camera, session = mustache_frames(SIZE_PX, FOV_DEG, MAGLIM, frames=2)
    truth = session.star_id.copy()
    blind = replace(session, star_id=np.zeros_like(truth), ra_deg=None, dec_deg=None)
    result = identify_session(blind, _nominal(camera), maglim=ID_MAGLIM, use_engine=False)
    frame = result.report()["per_frame"][FRAME]
    assert frame["status"] == "identified"
    in_frame = session.frame == session.frame[session.frame_starts[FRAME]]
    star_id = result.session.star_id
    named = in_frame & (star_id != 0)
    detectable = in_frame & (truth != 0) & (session.mag <= ID_MAGLIM) & ~_ambiguous(truth, camera.focal_length_px)
    # the acceptance figures of the wide-lens tests: >= 95 % of the detectable stars, <= 0.5 % of the names wrong
    assert np.count_nonzero(star_id[detectable] == truth[detectable]) >= 0.95 * np.count_nonzero(detectable)
    assert np.count_nonzero(named & (star_id != truth)) <= 0.005 * np.count_nonzero(named)
    # the frame's own focal length: the true one within the vote's relative tolerance (0.5 %), not the scan's step
    assert abs(frame["scale"] * (1.0 + NOMINAL_FOCAL_ERROR) - 1.0) < 0.005
