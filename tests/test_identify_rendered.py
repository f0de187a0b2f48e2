"""Issue 11, identification scored on images: frames rendered by the project (hostlink.sky.render: the real sky
through a distorted true camera, Gaussian PSF, shot and read noise, hot pixels, saturation), centroided by
hostlink.images.centroid, then identified lost in space with nominal focal errors of -10 %, 0 and +10 % and with a
mirrored detector. Every detectable star (a true star the centroider found) is scored against the render's truth."""

from dataclasses import replace

import numpy as np
import pytest

from hostlink.files.params import load_params
from hostlink.files.session import Session
from hostlink.images.centroid import centroid_pixels
from hostlink.images.identify import identify_session
from hostlink.sky.render import RenderConfig, render_frame
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from onboard.params import Distortion

NOMINAL = load_params("builtin:seed004_nominal")
#: seed 004's camera with a radial distortion of 3 px at the corners that the nominal does not know
TRUE_CAMERA = replace(seed004_camera(), distortion=Distortion(k1=8e-9))
FRAMES = 6
#: A detection is the image of a true star when it lies within this distance [px] of the star's true centroid (the
#: centroid error at these signal-to-noise ratios is < 0.1 px; the nearest other star is tens of px away).
MATCH_PX = 1.0


def _render_session(mirrored: bool) -> tuple[Session, np.ndarray]:
    """The rendered frames as a session of centroids (star_id 0) and the truth star id of each row (0: not a star)."""
    cfg = SimConfig(camera=TRUE_CAMERA, frames=FRAMES, noise_px=0.0, min_stars=8, max_stars=400, maglim=6.5, seed=21)
    sim = simulate(cfg)
    frames, xs, ys, mags, truth = [], [], [], [], []
    for k in range(FRAMES):
        rendered = render_frame(sim, k, RenderConfig(seed=5), mirrored=mirrored)
        det = centroid_pixels(rendered.image_adu)
        d = np.hypot(det.x_px[:, None] - rendered.truth_x_px[None], det.y_px[:, None] - rendered.truth_y_px[None])
        nearest = np.argmin(d, axis=1) if rendered.truth_x_px.size else np.zeros(det.x_px.size, dtype=np.int64)
        is_star = d[np.arange(det.x_px.size), nearest] < MATCH_PX if rendered.truth_x_px.size else nearest < 0
        truth.append(np.where(is_star, rendered.truth_star_id[nearest], 0))
        frames.append(np.full(det.x_px.size, k, dtype=np.int64))
        xs.append(det.x_px)
        ys.append(det.y_px)
        mags.append(det.mag)
    n = sum(f.size for f in frames)
    t0 = sim.session.t_utc[sim.session.frame_starts[:-1]]
    frame = np.concatenate(frames)
    session = Session(
        frame=frame,
        t_utc=np.asarray(t0[frame], dtype=object),
        star_id=np.zeros(n, dtype=np.int64),
        x_px=np.concatenate(xs),
        y_px=np.concatenate(ys),
        mag=np.concatenate(mags),
    )
    return session, np.concatenate(truth)


@pytest.fixture(scope="module")
def rendered():
    return {mirrored: _render_session(mirrored) for mirrored in (False, True)}


@pytest.mark.parametrize("mirrored", [False, True], ids=["normal", "mirrored"])
@pytest.mark.parametrize("focal_error", [-0.10, 0.0, 0.10], ids=["f-10%", "f+0%", "f+10%"])
def test_rendered_frames_identify_99_percent_of_detectable_stars_with_none_wrong(rendered, focal_error, mirrored):
    session, truth = rendered[mirrored]
    nominal = NOMINAL.with_focal_length_mm(TRUE_CAMERA.focal_length_mm * (1.0 + focal_error))
    result = identify_session(session, nominal, maglim=7.5)
    star_id = result.session.star_id
    detectable = truth != 0
    assert np.count_nonzero(detectable) >= 8 * FRAMES  # the render and centroider found the stars at all
    assert np.count_nonzero((star_id != 0) & (star_id != truth)) == 0
    assert np.count_nonzero(star_id[detectable] == truth[detectable]) >= 0.99 * np.count_nonzero(detectable)
    assert result.n_frames_identified == FRAMES
    assert result.mirrored == mirrored and all(f.mirrored == mirrored for f in result.frames)
