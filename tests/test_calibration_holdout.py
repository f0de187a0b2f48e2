"""The held-out judge (hostlink.calibration.holdout): stars left out of the fit, each judged with an attitude from
its frame's other stars, show the camera's true error and nothing the fit absorbed."""

import numpy as np
import pytest
from synthetic_sessions import synthetic_session

from hostlink.calibration.holdout import held_out_residuals_rad, hold_out_frames
from hostlink.files.session import Session
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams, Distortion

CAMERA = CameraParams(
    focal_length_mm=50.0,
    pixel_pitch_um=5.5,
    principal_point_px=(1023.5, 1023.5),
    image_size_px=(2048, 2048),
    distortion=Distortion(k1=-2e-9),
)


def _as_session(s) -> Session:
    d = s.data
    frame = np.repeat(d.frame_number, d.counts).astype(np.int64)
    n = frame.size
    return Session(
        frame=frame,
        t_utc=np.full(n, "", dtype=object),
        star_id=np.arange(1, n + 1, dtype=np.int64),
        x_px=d.x_px,
        y_px=d.y_px,
        mag=np.zeros(n),
    )


@pytest.fixture(scope="module")
def field():
    s = synthetic_session(CAMERA, n_frames=60, stars_per_frame=(8, 20), noise_px=0.1, seed=11)
    return s, _as_session(s), np.ones(s.data.x_px.size, dtype=bool)


def test_the_folds_hold_out_every_frame_exactly_once(field):
    _, session, usable = field
    folds = [hold_out_frames(session, usable, 3, k) for k in range(3)]
    assert np.array_equal(np.sum(folds, axis=0), np.ones(len(session), dtype=int))
    for held in folds:  # whole frames only
        for rows in session.frame_slices():
            assert held[rows].all() or not held[rows].any()
    with pytest.raises(ValueError):
        hold_out_frames(session, usable, 1, 0)


def test_the_true_camera_is_judged_at_the_noise_and_attitude_floor(field):
    s, session, usable = field
    theta = CAMERA.model_vector()
    held = hold_out_frames(session, usable, 3, 0)
    res = held_out_residuals_rad(session, lambda x, y: pixels_to_unit(x, y, theta), s.data.r, usable, held)
    assert np.isnan(res[~held]).all() and np.isfinite(res[held]).all()
    rms_px = float(np.sqrt(np.mean(res[held] ** 2))) * theta[0]
    # a held-out star's error is its own centroid noise (2 axes: sqrt(2) sigma) plus the attitude error of n - 1
    # others at the star (about sqrt(2 / (n - 1)) sigma, n = 8..20): 1.41-1.63 x 0.1 px; 20 % for ~250 stars
    assert 0.141 * 0.9 <= rms_px <= 0.163 * 1.2


def test_a_wrong_camera_is_judged_worse_than_the_true_one(field):
    s, session, usable = field
    held = hold_out_frames(session, usable, 3, 1)

    def rms(params: CameraParams) -> float:
        theta = params.model_vector()
        res = held_out_residuals_rad(session, lambda x, y: pixels_to_unit(x, y, theta), s.data.r, usable, held)
        return float(np.sqrt(np.nanmean(res[held] ** 2))) * theta[0]

    # 0.2 % in focal length moves a star at 1000 px from the centre by 2 px, 20 x the noise
    assert rms(CAMERA.with_focal_length_mm(50.1)) > 3.0 * rms(CAMERA)


@pytest.fixture(scope="module")
def sky_session():
    from hostlink.sky.simulate import seed004_config, simulate

    return simulate(seed004_config(frames=45, seed=7)).session


def test_cross_validation_judges_a_calibration_as_the_true_camera_is_judged(sky_session):
    """The calibrated cameras, each judged on the frames left out of its fit, come within 10 % of the true camera
    judged on the same stars: a fit near the Cramer-Rao bound moves a held-out star by far less than its noise
    (45 frames of about 20 stars: the fit's own error at a star is a few % of the centroid noise)."""
    from hostlink.calibration.data import calibration_data_from_session
    from hostlink.calibration.holdout import cross_validate
    from hostlink.files.params import data_file, load_params
    from hostlink.sky.simulate import seed004_camera

    nominal = load_params(data_file("seed004_nominal.json"))
    result = cross_validate(sky_session, nominal, folds=3)
    _, refs = calibration_data_from_session(sky_session, None, None, 0.0)
    theta = seed004_camera().model_vector()
    truth = []
    for fold in range(3):
        held = hold_out_frames(sky_session, refs.usable, 3, fold)
        res = held_out_residuals_rad(sky_session, lambda x, y: pixels_to_unit(x, y, theta), refs.r, refs.usable, held)
        truth.append(res[np.isfinite(res)] * theta[0])
    truth_rms_px = float(np.sqrt(np.mean(np.concatenate(truth) ** 2)))
    assert result.n_frames == 45 and result.n_stars == np.concatenate(truth).size
    assert result.rms_px <= 1.10 * truth_rms_px
    # the in-fit residual flatters (each fit absorbed part of its own noise); the held-out figure does not
    assert result.fit_rms_px < result.rms_px
    assert max(result.focal_length_mm) - min(result.focal_length_mm) < 0.01 * nominal.focal_length_mm


def test_cross_validation_needs_a_frame_per_fold(sky_session):
    from hostlink.calibration.holdout import cross_validate
    from hostlink.errors import UserError
    from hostlink.files.params import data_file, load_params

    nominal = load_params(data_file("seed004_nominal.json"))
    few = sky_session.select(sky_session.frame < sky_session.frame[0] + 2)
    with pytest.raises(UserError, match="need one per fold"):
        cross_validate(few, nominal, folds=3)


def test_calibrate_hold_out_reports_the_held_out_figure_beside_the_fit(sky_session, tmp_path, capsys):
    import json

    from hostlink.cli import main
    from hostlink.files.session import write_session

    path = tmp_path / "s.csv"
    write_session(path, sky_session)
    out = tmp_path / "c.json"
    args = ["calibrate", str(path), "--nominal", "builtin:seed004_nominal", "--out", str(out)]
    assert main([*args, "--hold-out", "3"]) == 0
    held = json.loads(out.read_text())["held_out"]
    assert held["folds"] == 3 and held["frames"] == 45 and held["stars"] == int((sky_session.star_id != 0).sum())
    assert held["fit_rms_px"] < held["rms_px"]
    assert f"RMS {held['rms_px']:.4g} px" in capsys.readouterr().out
    assert main([*args, "--hold-out", "1"]) == 2
    assert "--hold-out 1: expected K >= 2" in capsys.readouterr().err
