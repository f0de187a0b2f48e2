"""The onboard recursive estimator (onboard/recursive.py) on synthetic frames: convergence against the Cramer-Rao
bound, float32 against float64, misidentification gating, focal drift tracking, save/restore, bounded buffers."""

import numpy as np
import pytest
from recursive_synth import SEED004_PAPER_START, SEED004_TRUE, batch_ml, crb_information, make_frames, sky_frames

from onboard import recursive as rc
from onboard.params import ESTIMATE_NAMES

NOISE_PX = 0.05


def _run(frames, nominal=SEED004_PAPER_START, names=ESTIMATE_NAMES, dtype=np.float32, config=None):
    st = rc.create(nominal, names, config, dtype)
    results = [rc.update(st, f.x_px, f.y_px, f.r, f.identified) for f in frames]
    return st, results


def _normalised_error(st, frames):
    info = crb_information(SEED004_TRUE, frames, NOISE_PX, st.idx)
    crb = np.sqrt(np.diag(np.linalg.inv(info)))
    err = rc.state_vector(st)[st.idx] - SEED004_TRUE.model_vector()[st.idx]
    return err, crb, info


@pytest.fixture(scope="module")
def cold_start_runs():
    frames = make_frames(SEED004_TRUE, 1000, NOISE_PX, seed=11)
    return frames, _run(frames, dtype=np.float32)[0], _run(frames, dtype=np.float64)[0]


def test_cold_start_from_a_nominal_without_distortion_reaches_the_cramer_rao_bound(cold_start_runs):
    frames, st32, _ = cold_start_runs
    err, crb, info = _normalised_error(st32, frames)
    # each parameter inside 3.5 sigma of the bound (a 1-in-2000 event per parameter for an efficient estimator)
    assert np.all(np.abs(err / crb) < 3.5), err / crb
    # Mahalanobis distance per parameter: chi2(10)/10 for an efficient estimator, < 1.3^2 * 2.3 at the 99.9 % point
    assert err @ info @ err / err.size < 1.3**2 * 2.3
    # the filter's own sigma is the bound (within the burn-in's cost, measured 1.00-1.14) and never optimistic
    ratio = np.sqrt(np.diag(rc.covariance(st32))) / crb
    assert np.all((ratio > 0.9) & (ratio < 1.3)), ratio


N_SEEDS = 6


@pytest.fixture(scope="module")
def seed004_sessions():
    """N_SEEDS seed-004 sessions of the project's sky simulator (1000 frames, 10-30 stars, 0.05 px), each with the
    recursive float32 estimate, the batch ML estimate of the same pairs, and the bound, all in units of the CRB."""
    rec, ml, sig = [], [], []
    for seed in range(N_SEEDS):
        camera, frames, info = sky_frames(seed, 1000, NOISE_PX)
        crb = np.sqrt(np.diag(np.linalg.inv(info)))
        st = rc.create(SEED004_PAPER_START, ESTIMATE_NAMES, None, np.float32)
        for x, y, r, ok in frames:
            rc.update(st, x, y, r, ok)
        rec.append((rc.state_vector(st) - camera.model_vector()) / crb)
        ml.append((batch_ml(camera, frames, noise_px=NOISE_PX) - camera.model_vector()) / crb)
        sig.append(np.sqrt(np.diag(rc.covariance(st))) / crb)
    return np.array(rec), np.array(ml), np.array(sig)


@pytest.mark.slow  # Monte Carlo (issue 29: the fast lane is pytest -m 'not slow')
def test_every_parameter_is_within_1_3x_of_the_bound_over_several_sessions(seed004_sessions):
    rec, ml, sig = seed004_sessions
    # The batch ML of the same pairs attains the bound (validates the CRB used): the RMS of 6 standard normals is
    # below sqrt(chi2_6(0.999) / 6) = 1.93 with probability 0.999 (measured 0.90-1.05 over 24 sessions).
    assert np.all(np.sqrt(np.mean(ml**2, axis=0)) < 1.93), ml
    # The filter's own excess, paired against the ML on the same data: var(rec) = var(ML) + var(rec - ML) for an
    # asymptotically unbiased rec, so RMS(rec - ML) / CRB < sqrt(1.3^2 - 1) = 0.83 is the 1.3x acceptance per
    # parameter. Measured 0.38-0.62 on these 6 sessions, 0.39-0.51 over 24 (burn-in 300 frames, power 2; 0.56-0.64 on
    # x0/y0/p/s over 24 with the former 200-frame linear burn-in).
    excess = np.sqrt(np.mean((rec - ml) ** 2, axis=0))
    assert np.all(excess < 0.83), excess
    # Direct: the RMS of 6 normalised errors of an estimator at 1.3x the bound is below 1.3 sqrt(chi2_6(0.999) / 6)
    # = 2.5 with probability 0.999 (measured <= 0.94 here, <= 1.11 for every parameter over 24 sessions).
    assert np.all(np.sqrt(np.mean(rec**2, axis=0)) < 2.5), rec
    # the reported sigma: never optimistic by more than the 6-session spread allows, and within the burn-in's cost
    assert np.all((sig.mean(axis=0) > 0.95) & (sig.mean(axis=0) < 1.2)), sig.mean(axis=0)  # measured 1.04-1.12


def test_float32_estimate_differs_from_float64_by_under_5_percent_of_the_bound(cold_start_runs):
    frames, st32, st64 = cold_start_runs
    _, crb, _ = _normalised_error(st64, frames)
    diff = (rc.state_vector(st32) - rc.state_vector(st64))[st32.idx] / crb
    assert np.all(np.abs(diff) < 0.05), diff  # measured < 0.01


def test_static_camera_does_not_trigger_the_drift_detector(cold_start_runs):
    _, st32, st64 = cold_start_runs
    assert not st32.drift_on and not st64.drift_on


def test_misidentified_stars_are_rejected_and_the_estimate_stays_within_2x_of_the_bound():
    frames = make_frames(SEED004_TRUE, 1000, NOISE_PX, seed=21, misid_fraction=0.03)
    st, results = _run(frames)
    mis = np.concatenate([f.misidentified for f in frames])
    rejected = np.zeros_like(mis)
    offset = 0
    for f, res in zip(frames, results, strict=True):
        rejected[offset + np.array(res.rejected_stars, dtype=int)] = True
        offset += f.x_px.size
    assert np.count_nonzero(rejected & mis) >= 0.97 * np.count_nonzero(mis)  # a few near-misses may pass
    assert np.count_nonzero(rejected & ~mis) <= 0.005 * np.count_nonzero(~mis)  # false rejections (5 sigma gate)
    err, crb, _ = _normalised_error(st, frames)
    assert np.all(np.abs(err / crb) < 2 * 3.5), err / crb


@pytest.mark.slow  # a long drifting run (issue 29: the fast lane is pytest -m 'not slow')
def test_a_sinusoidal_focal_drift_of_6_um_is_tracked_to_under_1_um_rms():
    n = 3000
    f_mm = SEED004_TRUE.focal_length_mm + 6e-3 * np.sin(2 * np.pi * np.arange(n) / n)
    frames = make_frames(SEED004_TRUE, n, NOISE_PX, seed=5, focal_mm=f_mm)
    st = rc.create(SEED004_PAPER_START, ESTIMATE_NAMES, None, np.float32)
    est = np.empty(n)
    for k, fr in enumerate(frames):
        rc.update(st, fr.x_px, fr.y_px, fr.r, fr.identified)
        est[k] = rc.current_params(st).focal_length_mm
    assert st.drift_on and st.drift_frame <= 600  # detected within the first window after the burn-in
    rms_um = 1000 * np.sqrt(np.mean((est[1000:] - f_mm[1000:]) ** 2))
    assert rms_um < 1.0, rms_um  # measured 0.48 um


def test_a_few_parameters_refined_from_a_ground_calibration_converge():
    ground = SEED004_TRUE.with_vector(SEED004_TRUE.vector() + np.array([0.02, 1.5, -1.0] + [0.0] * 7))
    frames = make_frames(SEED004_TRUE, 300, NOISE_PX, seed=8)
    st, _ = _run(frames, nominal=ground, names=("f", "x0", "y0"))
    err, crb, _ = _normalised_error(st, frames)
    assert np.all(np.abs(err / crb) < 3.5), err / crb
    assert abs(err[0]) * 12e-3 < 1e-4  # f within 0.1 um (started 20 um off)


def test_save_and_restore_continue_bit_for_bit():
    frames = make_frames(SEED004_TRUE, 160, NOISE_PX, seed=4)
    st, _ = _run(frames[:100])
    blob = rc.save_state(st)
    clone = rc.restore_state(blob, SEED004_PAPER_START)
    for fr in frames[100:]:
        rc.update(st, fr.x_px, fr.y_px, fr.r, fr.identified)
        rc.update(clone, fr.x_px, fr.y_px, fr.r, fr.identified)
    assert rc.save_state(st) == rc.save_state(clone)
    with pytest.raises(ValueError, match="different nominal"):
        rc.restore_state(blob, SEED004_TRUE)
    with pytest.raises(ValueError, match="bad magic"):
        rc.restore_state(b"\0" * len(blob), SEED004_PAPER_START)
    with pytest.raises(ValueError, match="data bytes"):
        rc.restore_state(blob[:-4], SEED004_PAPER_START)


def test_state_buffers_are_allocated_once_and_keep_their_dtype():
    frames = make_frames(SEED004_TRUE, 20, NOISE_PX, seed=6, min_stars=40, max_stars=45)
    st = rc.create(SEED004_PAPER_START, ESTIMATE_NAMES, None, np.float32)
    buffers = {n: getattr(st, n) for n in ("x_hi", "x_lo", "u", "d", "q", "ring_g", "ring_v", "u0", "d0", "xi")}
    results = [rc.update(st, f.x_px, f.y_px, f.r, f.identified) for f in frames]
    for name, arr in buffers.items():
        assert getattr(st, name) is arr and arr.dtype == np.float32, name
    assert max(r.n_used for r in results) == 32  # capped at max_stars: the per-frame work bound holds
    assert max(r.n_pairs + r.n_pairs_rejected for r in results) <= 2 * 32 - 3


def test_frames_with_too_few_stars_are_skipped_without_changing_the_state():
    st = rc.create(SEED004_PAPER_START, ESTIMATE_NAMES, None, np.float32)
    fr = make_frames(SEED004_TRUE, 1, NOISE_PX, seed=1, min_stars=2, max_stars=2)[0]
    before = rc.save_state(st)
    res = rc.update(st, fr.x_px, fr.y_px, fr.r, fr.identified)
    assert (
        res.skipped and rc.state_vector(st).tolist() == rc.create(SEED004_PAPER_START).theta_nom.astype(float).tolist()
    )
    assert rc.save_state(st) != before  # the frame counter advanced


def test_bad_configuration_is_refused_with_a_message():
    with pytest.raises(ValueError, match="unknown parameter"):
        rc.parse_estimate_names("f,q9")
    with pytest.raises(ValueError, match="dtype"):
        rc.create(SEED004_PAPER_START, dtype=np.float16)
    with pytest.raises(ValueError, match="prior_sigma"):
        rc.create(SEED004_PAPER_START, config=rc.RecursiveConfig(prior_sigma=(1.0,) * 3))
    assert rc.parse_estimate_names("y0, f") == ("f", "y0")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_star_reported_twice_in_a_frame_is_used_once(dtype):
    # A centroid repeated in a frame (same position, same reference) adds a pair of zero length and zero variance:
    # float64 Cholesky then failed (the firmware reset its estimator) and float32 whitened rounding noise with a huge
    # weight (x0/y0 moved by ~1 px). It carries no information, so the frame must give exactly the undoubled result.
    frames = make_frames(SEED004_TRUE, 31, NOISE_PX, seed=21, min_stars=10, max_stars=12)
    st, _ = _run(frames[:30], dtype=dtype)
    fr = frames[30]
    plain = rc.restore_state(rc.save_state(st), SEED004_PAPER_START)
    rc.update(plain, fr.x_px, fr.y_px, fr.r, fr.identified)
    used = np.flatnonzero(fr.identified)
    for j in (used[0], used[3]):
        twice = rc.restore_state(rc.save_state(st), SEED004_PAPER_START)
        res = rc.update(
            twice,
            np.append(fr.x_px, fr.x_px[j]),
            np.append(fr.y_px, fr.y_px[j]),
            np.vstack([fr.r, fr.r[j]]),
            np.append(fr.identified, fr.identified[j]),
        )
        assert not res.skipped
        # the same arithmetic on the same stars: bit for bit
        assert rc.save_state(twice) == rc.save_state(plain), j
