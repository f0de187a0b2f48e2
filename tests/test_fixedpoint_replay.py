"""``hostlink replay --precision fixed``: the integer front end (onboard/fixedpoint.py) feeding the float32 filter,
scored like float32 in tests/test_replay_cli.py: 1000 frames of 10-30 stars at 0.05 px on the seed-004 camera
(hostlink.sky.simulate), against float64 and against the Cramer-Rao bound of the same session."""

import json
from dataclasses import dataclass

import numpy as np
from recursive_synth import SEED004_PAPER_START, SEED004_TRUE, make_frames
from test_replay_cli import NOMINAL, session_information

from hostlink.calibration.replay import replay_session
from hostlink.cli import main
from hostlink.files.params import load_params
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate
from onboard import fixedpoint, recursive
from onboard.camera import pixels_to_unit
from onboard.interstar import difference_residuals
from onboard.params import ESTIMATE_NAMES, params_from_dict
from onboard.prior import sigma_from_dict
from protocol.messages import dequantise_px, quantise_px


def _replay(tmp_path, session, precision):
    path = tmp_path / f"session_{id(session)}.csv"
    if not path.exists():
        write_session(path, session)
        (tmp_path / "nominal.json").write_text(json.dumps(NOMINAL))
    out = tmp_path / f"estimate_{id(session)}_{precision}.json"
    code = main(
        ["replay", str(path), "--nominal", str(tmp_path / "nominal.json"), "--out", str(out), "--precision", precision]
    )
    assert code == 0
    return load_params(out).model_vector(), json.loads(out.read_text())


def test_fixed_replay_matches_float64_within_5_percent_of_the_bound_and_stays_near_it(tmp_path):
    result = simulate(seed004_config(1000, seed=3))
    camera, info = session_information(result, 0.05)
    crb = np.sqrt(np.diag(np.linalg.inv(info)))
    fixed, doc = _replay(tmp_path, result.session, "fixed")
    ref, _ = _replay(tmp_path, result.session, "float64")
    assert doc["precision"] == "fixed"
    # the session's centroids are float; the fixed sensor takes them in the wire's 2^-10 px, so this includes the
    # wire rounding (2.8e-4 px RMS against 0.05 px): measured 0.75 % of the bound at most (float32: 0.2 %)
    diff = (fixed - ref) / crb
    assert np.all(np.abs(diff) < 0.05), diff  # the acceptance: under 5 % of the bound
    err = fixed - camera.model_vector()
    assert np.all(np.abs(err / crb) < 3.5), err / crb  # each parameter: a 1-in-2000 event for an efficient estimator
    assert err @ info @ err / 10 < 1.3**2 * 2.3  # chi2(10)/10 below its 99.9 % point at 1.3x the bound
    sig = sigma_from_dict(doc["sigma"])[[ESTIMATE_NAMES.index(n) for n in doc["estimated"]]]
    sig[0] *= 1000.0 / camera.pixel_pitch_um
    assert np.all((sig / crb > 0.9) & (sig / crb < 1.3)), sig / crb  # the filter's own sigma, as for float32

    # the same centroids on the wire grid for both: what is left is the front end's own error (measured 0.05 %
    # of the bound, float32's 0.4 %)
    wire = result.session.select(np.ones(len(result.session), bool))
    wire.x_px = dequantise_px(quantise_px(wire.x_px))
    wire.y_px = dequantise_px(quantise_px(wire.y_px))
    fixed_w, _ = _replay(tmp_path, wire, "fixed")
    ref_w, _ = _replay(tmp_path, wire, "float64")
    assert np.all(np.abs((fixed_w - ref_w) / crb) < 0.01), (fixed_w - ref_w) / crb  # 20x the measured 0.05 %


@dataclass(frozen=True)
class _FloatFrontEnd:
    """A front end computing the residuals with the float camera model: the seam must then change nothing."""

    x_px: np.ndarray
    y_px: np.ndarray
    r: np.ndarray

    def residuals(self, theta, rows, pi, pj):
        b = pixels_to_unit(self.x_px[rows].astype(theta.dtype), self.y_px[rows].astype(theta.dtype), theta)
        return difference_residuals(b, self.r[rows].astype(theta.dtype), pi, pj), theta.astype(np.float64)


def test_the_front_end_seam_takes_the_same_stars_in_the_same_pair_order():
    # misidentified and unidentified rows make the selection and the pair ordering non-trivial
    frames = make_frames(SEED004_TRUE, 60, 0.05, misid_fraction=0.05, seed=7)
    plain = recursive.create(SEED004_PAPER_START, dtype=np.float64)
    seam = recursive.create(SEED004_PAPER_START, dtype=np.float64)
    for k, fr in enumerate(frames):
        ident = fr.identified.copy()
        ident[k % fr.x_px.size] = False
        recursive.update(plain, fr.x_px, fr.y_px, fr.r, ident)
        recursive.update(seam, fr.x_px, fr.y_px, fr.r, ident, front_end=_FloatFrontEnd(fr.x_px, fr.y_px, fr.r))
    a, b = recursive.state_vector(plain), recursive.state_vector(seam)
    # same residuals up to float64 rounding (pixels_to_unit vs the Jacobian routine's own b): 1e-9 relative
    np.testing.assert_allclose(b, a, rtol=1e-9, atol=0)
    assert plain.updates == seam.updates


def test_fixed_frames_with_an_off_detector_centroid_skip_that_star():
    result = simulate(seed004_config(30, seed=11))
    s = result.session.select(np.ones(len(result.session), bool))
    first = next(s.frame_slices())
    s.x_px[first.start] = 4000.0  # off the 1024-px detector by more than S: the formats cannot hold it
    fixed = replay_session(s, params_from_dict(NOMINAL), precision="fixed")
    ref = replay_session(result.session, params_from_dict(NOMINAL), precision="fixed")
    assert fixed.trace["n_used"][0] == ref.trace["n_used"][0] - 1  # that star alone left out, no error raised
    assert fixed.trace["n_used"][1:] == ref.trace["n_used"][1:]


def test_fixed_replay_refuses_a_nominal_outside_the_fixed_range_in_one_line(tmp_path, capsys):
    result = simulate(seed004_config(3, seed=12))
    write_session(tmp_path / "s.csv", result.session)
    nominal = dict(NOMINAL, distortion={"k1": -1e-5})  # monotonic, so a valid set, but a 1000 % correction
    (tmp_path / "n.json").write_text(json.dumps(nominal))
    code = main(
        [
            "replay",
            str(tmp_path / "s.csv"),
            "--nominal",
            str(tmp_path / "n.json"),
            "--out",
            str(tmp_path / "e.json"),
            "--precision",
            "fixed",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "fixed-point range" in err and err.count("\n") == 1


def test_replay_help_documents_the_fixed_precision(capsys):
    try:
        main(["replay", "--help"])
    except SystemExit:
        pass
    out = " ".join(capsys.readouterr().out.split())
    assert "fixed (integer front end" in out and "Q30 unit vectors" in out


def test_fixed_frame_residuals_come_back_in_the_filters_dtype():
    fr = make_frames(SEED004_TRUE, 1, 0.05, seed=3)[0]
    front = fixedpoint.FixedFrame(
        quantise_px(fr.x_px), quantise_px(fr.y_px), fixedpoint.quantise_unit_q30(fr.r), SEED004_TRUE.image_size_px
    )
    rows = np.arange(fr.x_px.size)
    pi, pj = np.array([0, 0]), np.array([1, 2])
    e, theta_q = front.residuals(SEED004_TRUE.model_vector(np.float32), rows, pi, pj)
    assert e.dtype == np.float32 and theta_q.dtype == np.float64
    b = pixels_to_unit(dequantise_px(quantise_px(fr.x_px)), dequantise_px(quantise_px(fr.y_px)), theta_q)
    # against float64 at the noise-free reference (the residual is the noise itself, 1e-7..1e-5): float32's
    # relative 6e-8 plus the front end's |b_i - b_j| 2 sqrt(3) 5.4 2^-30 <= 3e-9 (field diagonal 0.18 rad; derived in
    # tests/test_fixedpoint_camera.py; measured 6e-11)
    np.testing.assert_allclose(e, difference_residuals(b, fr.r, pi, pj), rtol=1e-6, atol=3e-9)
