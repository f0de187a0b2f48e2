"""The own lost-in-space matcher's pyramid pre-filter (hostlink.images.identify._pyramid_may_hit) is a necessary
condition only: on narrow-field frames (f = 200 mm, 3.8 deg, where it skips most of the k-d tree's work) the matcher
proposes exactly what it proposes without it, at the true focal length and at a wrong one, for a normal and a
mirrored detector."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hostlink.images.identify import MATCH_STARS, _sky, anchor_candidates, pair_catalogue
from hostlink.sky.catalogue import load_catalogue
from hostlink.sky.simulate import SimConfig, simulate
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams, Distortion

#: 1024 x 1024 px of 13 um at f = 200 mm: a 3.8 deg field, 8-12 stars to Hp 8 per frame.
NARROW = CameraParams(200.0, 13.0, (515.0, 508.0), (1024, 1024), Distortion(k1=-2e-10))
NOMINAL = CameraParams(200.0, 13.0, (511.5, 511.5), (1024, 1024))
#: Catalogue depth of the pair index: the simulated stars go to Hp 8.
DEPTH_MAG = 8.0
#: Anchor pairs among the brightest 5 (10 pairs, 3 third stars each): the comparison without the pre-filter is slow.
ANCHOR_STARS = 5


@pytest.fixture(scope="module")
def narrow():
    """Two frames with false stars (25 % of the real ones) and 0.1 px noise, and the pair index of the field."""
    cfg = SimConfig(
        camera=NARROW, frames=2, noise_px=0.1, min_stars=8, max_stars=12, maglim=DEPTH_MAG, false_star_fraction=0.25
    )
    sim = simulate(cfg)
    sky = _sky(load_catalogue())
    half_diagonal = 0.5 * math.hypot(*NOMINAL.image_size_px) / (0.9 * NOMINAL.focal_length_px)
    return sim.session, sky, pair_catalogue(sky, 2.0 * math.atan(half_diagonal), DEPTH_MAG)


def _proposals(b, pairs, tree, focal_px):
    found = anchor_candidates(b, pairs, tree, pairs.rows, focal_px, anchor_stars=ANCHOR_STARS)
    return [(rows.tolist(), stars.tolist(), mirrored) for rows, stars, mirrored in found]


@pytest.mark.parametrize(
    ("scale", "mirrored"), [(1.0, False), (1.0, True), (1.004, False)], ids=["normal", "mirrored", "focal+0.4%"]
)
def test_prefilter_leaves_the_matchers_proposals_unchanged(narrow, scale, mirrored):
    session, sky, pairs = narrow
    twin = cKDTree(pairs.tree.data)  # the same stars, but not the index's own tree: the pre-filter is not applied
    theta = NOMINAL.model_vector(np.float64)
    theta[0] *= scale
    frames_with_a_true_proposal = 0
    for k in range(session.n_frames):
        a, z = int(session.frame_starts[k]), int(session.frame_starts[k + 1])
        x_px = (NOMINAL.image_size_px[0] - 1) - session.x_px[a:z] if mirrored else session.x_px[a:z]
        bright = np.argsort(session.mag[a:z], kind="stable")[:MATCH_STARS]
        b = pixels_to_unit(x_px[bright], session.y_px[a:z][bright], theta)
        filtered = _proposals(b, pairs, pairs.tree, theta[0])
        assert filtered == _proposals(b, pairs, twin, theta[0])
        truth = session.star_id[a:z][bright]
        frames_with_a_true_proposal += any(
            p == mirrored and np.array_equal(sky.hip[stars[:2]], truth[rows[:2]]) for rows, stars, p in filtered
        )
    if scale == 1.0:  # the comparison covered real matches (frame 1's brightest three are false stars)
        assert frames_with_a_true_proposal >= 1
