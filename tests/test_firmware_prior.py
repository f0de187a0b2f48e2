"""The parameter set's 1-sigma prior in the sensor: stored in the A/B banks with the set (CRC over both), validated
like the parameters (a refused sigma names its field), and the estimator restarted from it after a commit (cold-start
prior where unknown, no burn-in when every estimated parameter has one); an accepted estimate carries its own sigma."""

import numpy as np
import pytest

from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.sensor import EmulatedSensor, session_frames
from hostlink.links.operations import accept_estimate, read_active_params, safe_upload, stream_frames
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from onboard import banks, recursive
from onboard.firmware import Firmware, RecursiveEstimator
from onboard.params import ESTIMATE_NAMES, CameraParams
from onboard.prior import CORRELATION_INFLATION
from protocol.crc import crc32
from protocol.messages import NakCode

NOMINAL = CameraParams(
    focal_length_mm=70.0, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
)
CAMERA = seed004_camera()
SIGMA = np.array([7e-4, 1.3, 1.29, 1.4e-10, 5.8e-16, 7.4e-22, 2.2e-8, 2.1e-8, 2e-8, 2e-8])


def stage(store, table):
    assert isinstance(banks.stage_begin(store, len(table)), int)
    assert banks.stage_chunk(store, 0, table) is None
    return crc32(table)


def commit(store, crc):
    """COMMIT bound to the current staging session and the active generation."""
    return banks.commit(store, crc, store.stage_nonce, banks.active_generation(store))


def test_the_sigma_is_committed_with_the_set_and_survives_a_reboot():
    store = banks.factory_store(NOMINAL)
    table = banks.params_to_table(CAMERA, SIGMA)
    crc = stage(store, table)
    assert banks.stage_verify(store, crc) is None and commit(store, crc) == 2
    rebooted = banks.boot(store.flash)
    generation, active, active_crc = banks.active_set(rebooted)
    assert (generation, active_crc) == (2, crc)
    np.testing.assert_array_equal(banks.table_to_sigma(active), SIGMA.astype(np.float32))  # float32, bit for bit
    assert np.all(np.isnan(banks.table_to_sigma(banks.params_to_table(CAMERA))))  # no sigma = unknown


@pytest.mark.parametrize(
    ("index", "value", "field"),
    [(1, -1.0, "sigma.principal_point_px[0]"), (0, np.inf, "sigma.focal_length_mm"), (9, -2e-8, "sigma.distortion.s2")],
    ids=["negative", "infinite", "negative-distortion"],
)
def test_a_bad_sigma_is_refused_with_its_field_and_nothing_commits(index, value, field):
    store = banks.factory_store(NOMINAL)
    sigma = SIGMA.copy()
    sigma[index] = value
    table = banks.params_to_table(CAMERA, sigma)
    crc = stage(store, table)
    refusal = banks.stage_verify(store, crc)
    assert refusal.code == NakCode.INVALID_PARAMS and refusal.text.startswith(field + ":")
    assert commit(store, crc).code == NakCode.NOT_VERIFIED and banks.active_set(store)[0] == 1


def test_nan_and_zero_sigmas_are_accepted_as_unknown():
    store = banks.factory_store(NOMINAL)
    sigma = SIGMA.copy()
    sigma[2], sigma[5] = np.nan, 0.0
    crc = stage(store, banks.params_to_table(CAMERA, sigma))
    assert banks.stage_verify(store, crc) is None


def test_a_commit_restarts_the_estimator_from_the_set_sigma():
    s = EmulatedSensor(Firmware(banks.factory_store(NOMINAL), RecursiveEstimator()), iter(()))
    cold = recursive.sigma(s.firmware._est_state)
    assert s.firmware._est_state.config.burn_in_frames == 300  # factory set: no sigma, a cold start
    safe_upload(LoopbackLink(s), CAMERA, sigma=SIGMA)
    state = s.firmware._est_state
    got = np.array([recursive.sigma(state)[n] for n in ESTIMATE_NAMES])
    # float32 sigma on the wire, float32 scale in the state: relative rounding ~1e-7
    np.testing.assert_allclose(got, CORRELATION_INFLATION * SIGMA, rtol=1e-6)
    assert state.config.burn_in_frames == 0 and got[1] < cold["x0"] / 10
    partial = SIGMA.copy()
    partial[3:] = np.nan  # distortion unknown: cold-start prior there, burn-in kept
    safe_upload(LoopbackLink(s), CAMERA, sigma=partial)
    state = s.firmware._est_state
    cold_new = recursive.default_prior_sigma(CAMERA)
    np.testing.assert_allclose(recursive.sigma(state)["k1"], cold_new[3], rtol=1e-6)
    assert state.config.burn_in_frames == 300


def test_accept_sends_the_estimate_sigma_and_the_estimator_restarts_from_it():
    sim = simulate(SimConfig(camera=CAMERA, frames=20, noise_px=0.05, seed=9))
    s = EmulatedSensor(Firmware(banks.factory_store(NOMINAL), RecursiveEstimator()), iter(session_frames(sim.session)))
    link = LoopbackLink(s)
    assert len(stream_frames(link, 15).frames) == 15
    result, estimate = accept_estimate(link, force=True)  # 15 updates: not converged
    np.testing.assert_array_equal(result.sigma, np.asarray(estimate.sigma, dtype=np.float32))
    np.testing.assert_array_equal(read_active_params(link).sigma, result.sigma)
    got = recursive.sigma(s.firmware._est_state)
    np.testing.assert_allclose(got["x0"], CORRELATION_INFLATION * estimate.sigma[1], rtol=1e-6)
