"""The estimator seam of the C firmware core (onboard/c/estimator_seam.h, fwcore's; implemented by
onboard/c/estimator_seam.c with the numerical core) against onboard.firmware.RecursiveEstimator, the Python seam:
started from the same active table (cold, and with a refined sigma prior), fed the same frames in double, they hold
the same saved-state bytes after every frame (bit-exact in float32 and fixed, as tests/test_c_recursive.py proves for
the estimator alone: the seam adds the conversion of the frame and of its configuration, RecursiveConfig's double
centroid_noise_px), report the same estimate, sigma, mask and update count, and declare the same cost."""

from __future__ import annotations

import ctypes
import shutil

import numpy as np
import pytest
from test_replay_cli import NOMINAL

from hostlink.portkit import estimator_c
from hostlink.portkit.estimator_c import SeamConfig, ptr, ref
from hostlink.sky.references import session_references
from hostlink.sky.simulate import seed004_config, simulate
from onboard import banks, recursive
from onboard.firmware import RecursiveEstimator
from onboard.params import ESTIMATE_NAMES, params_from_dict
from onboard.recursive import RecursiveConfig
from protocol.param_table import decode_table

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")

_COLD = np.full(10, np.nan)
_REFINED = np.array([0.004, 0.8, 0.8, 2e-10, 4e-16, np.nan, 3e-8, 3e-8, 3e-8, 3e-8])


@pytest.mark.parametrize(("precision", "sigma"), [("float32", _COLD), ("fixed", _COLD), ("float32", _REFINED)])
def test_c_seam_reports_the_python_seams_estimate(precision, sigma):
    lib = estimator_c.load()
    nominal = params_from_dict(NOMINAL)
    table = banks.params_to_table(nominal, sigma)
    py = RecursiveEstimator(ESTIMATE_NAMES, RecursiveConfig(centroid_noise_px=0.05), precision=precision)
    state = py.start(banks.table_to_params(table), banks.table_to_sigma(table))
    cfg = SeamConfig(estimator_c.estimated_mask(ESTIMATE_NAMES), int(precision == "fixed"), 0.05)
    c_state = ctypes.create_string_buffer(int(lib.estimator_seam_state_bytes()) + 16)
    fields = np.ascontiguousarray(decode_table(table), dtype=np.float32)
    assert lib.estimator_seam_start(c_state, ref(cfg), ptr(fields)) == 0

    def c_estimate():
        values, sig = np.zeros(10, np.float32), np.zeros(10, np.float32)
        mask, n = ctypes.c_uint32(), ctypes.c_uint32()
        lib.estimator_seam_estimate(c_state, ptr(values), ptr(sig), ctypes.byref(mask), ctypes.byref(n))
        return values, sig, mask.value, n.value

    blob = ctypes.create_string_buffer(1 << 16)

    def c_saved_state() -> bytes:
        # the seam's state begins with its recursive_state_t (estimator_seam_state.h), and a pointer to a struct points
        # to its first member (C99 6.7.2.1p13): recursive_save_state reads the seam's filter as it stands
        n_bytes = lib.recursive_save_state(c_state, blob, len(blob))
        assert n_bytes > 0
        return bytes(blob.raw[:n_bytes])

    values, sig, mask, n = c_estimate()
    v_py, s_py, m_py, n_py = py.estimate(state)
    assert c_saved_state() == recursive.save_state(state)  # the same start, to the bit
    assert np.array_equal(values, v_py) and (mask, n) == (m_py, n_py) == (0x3FF, 0)
    assert np.allclose(sig, s_py, rtol=1e-6)  # the prior's sigma (float32 of a double: 1 ulp)
    session = simulate(seed004_config(300, seed=9)).session
    refs = session_references(session)
    n_frames = differing = 0
    for rows in session.frame_slices():
        x, y, ident = session.x_px[rows], session.y_px[rows], refs.usable[rows]
        r = np.where(ident[:, None], refs.r[rows], 0.0)  # the firmware's rows: 0.0 where not identified
        py.update(state, x, y, r, ident)
        args = (ptr(np.ascontiguousarray(x)), ptr(np.ascontiguousarray(y)), ptr(np.ascontiguousarray(r)))
        assert lib.estimator_seam_update(c_state, x.size, *args, ptr(np.ascontiguousarray(ident, np.uint8))) == 0
        differing += c_saved_state() != recursive.save_state(state)
        n_frames += 1
    assert n_frames == 300 and differing == 0, (
        f"seam {precision}: {n_frames} frames, {differing} with a differing state"
    )
    values, sig, mask, n = c_estimate()
    v_py, s_py, m_py, n_py = py.estimate(state)
    assert (mask, n) == (m_py, n_py) and n > 250  # the session updates the filter: a comparison of something
    # the same float32 state read in double by the same operations, rounded to float32
    assert np.array_equal(values, v_py)
    # the 1-sigma: the diagonal of U D U^T summed in double in two orders (C loops, numpy's matmul) agrees within
    # 1.1e-15 (tests/test_c_recursive.py); its float32 rounding can then differ only where the double lies that
    # close to a rounding boundary: at most 1 float32 ulp apart
    ulps = np.abs(sig.view(np.int32) - s_py.astype(np.float32).view(np.int32))
    assert np.all(ulps <= 1), f"seam {precision}: 1-sigma at most {ulps.max()} float32 ulp apart"
    for n_stars in (0, 3, 17, 32, 255):
        assert lib.estimator_seam_cost_flops(ref(cfg), n_stars) == py.cost_flops(n_stars)
