"""Issue 30, a camera the project has never seen, read out mirrored (a flipped image: x -> width - 1 - x).

Found by scripts/newcamera.py on the granasat frames flipped left to right: ``identify`` named 1984 of the 3707 stars
it names in the same frames unflipped, its calibration rounds and the guided admission stopped at the first
calibration (which refuses odd parity), and with faint candidates in the session the command ended in an internal
error (a NaN focal length in the guided round's report, not strict JSON). Now the session is identified with x
flipped and written back in its own columns: the same names as unflipped, parity reported mirrored, and
``calibrate`` on it still ends in one line saying to flip x."""

import json
from dataclasses import replace

import numpy as np
import pytest

from hostlink.files.params import load_params
from hostlink.images.identify import flipped_x_camera, identify_iteratively
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from onboard.camera import pixels_to_unit
from onboard.params import Distortion

NOMINAL = load_params("builtin:seed004_nominal")
TRUE_CAMERA = replace(seed004_camera(), distortion=Distortion(k1=8e-9))
WIDTH = NOMINAL.image_size_px[0]
#: simulated stars fainter than this are written as faint candidates (an snr column), the rest as detected stars
CANDIDATE_MAG = 6.0


@pytest.fixture(scope="module")
def sessions():
    """8 frames to Hp 6.5, 0.1 px noise, identities removed; the stars fainter than Hp 6 as candidates; and the
    same session mirrored."""
    sim = simulate(SimConfig(camera=TRUE_CAMERA, frames=8, noise_px=0.1, min_stars=10, max_stars=40, maglim=6.5))
    s = sim.session
    candidate = s.mag > CANDIDATE_MAG
    extra = {"snr": np.where(candidate, "6.0", ""), "sigma_px": np.full(len(s), "0.1")}
    blind = replace(s, star_id=np.zeros_like(s.star_id), ra_deg=None, dec_deg=None, extra=extra)
    return blind, replace(blind, x_px=(WIDTH - 1) - blind.x_px), s.star_id, candidate


@pytest.fixture(scope="module")
def identified(sessions):
    normal, mirrored, *_ = sessions
    nominal = NOMINAL.with_focal_length_mm(TRUE_CAMERA.focal_length_mm * 0.92)  # 8 % short
    return identify_iteratively(normal, nominal), identify_iteratively(mirrored, nominal)


def test_a_mirrored_session_is_named_as_the_same_session_unmirrored(sessions, identified):
    *_, truth, candidate = sessions
    normal, mirrored = identified
    assert mirrored.mirrored is True and normal.mirrored is False
    assert all(f.mirrored for f in mirrored.frames if f.status == "identified")
    np.testing.assert_array_equal(mirrored.session.star_id, normal.session.star_id)
    named = mirrored.session.star_id != 0
    # not an equality of two empty identifications: measured 117 of the 122 detected stars named (no reason is
    # known for 0.95: it leaves a margin of one star)
    assert np.count_nonzero(named & ~candidate) >= 0.95 * np.count_nonzero(~candidate)
    assert np.count_nonzero(named & (mirrored.session.star_id != truth)) == 0
    # the rows are written back in their own columns
    np.testing.assert_array_equal(mirrored.session.x_px, sessions[1].x_px)


def test_a_mirrored_session_calibrates_in_its_rounds_and_admits_its_candidates(identified):
    normal, mirrored = identified
    assert [r["stars_identified"] for r in mirrored.rounds] == [r["stars_identified"] for r in normal.rounds]
    assert mirrored.rounds[0]["calibration"].startswith("residual")
    guided = mirrored.rounds[-1]
    assert guided["round"] == "guided" and guided["status"] == "admitted" and guided["added"] > 0
    json.dumps(mirrored.report(), allow_nan=False)  # strict JSON, as the report file is written


def test_the_flipped_camera_maps_a_flipped_pixel_to_the_mirrored_direction():
    """pixels_to_unit of the flipped camera at (W - 1 - x, y) is the direction of (x, y) with its x negated (the
    distortion's terms odd in x included: p1 and s1 change sign, the others not)."""
    camera = replace(TRUE_CAMERA, distortion=Distortion(k1=8e-9, p1=3e-7, p2=-2e-7, s1=1e-7, s2=4e-7))
    theta, flipped = camera.model_vector(np.float64), flipped_x_camera(camera).model_vector(np.float64)
    x, y = np.array([10.0, 300.0, 1000.0]), np.array([20.0, 700.0, 500.0])
    b = pixels_to_unit(x, y, theta)
    b_flipped = pixels_to_unit((WIDTH - 1) - x, y, flipped)
    np.testing.assert_allclose(b_flipped, b * np.array([-1.0, 1.0, 1.0]), rtol=0, atol=1e-15)
