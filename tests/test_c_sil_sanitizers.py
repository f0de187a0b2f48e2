"""Software in the loop under AddressSanitizer and UndefinedBehaviorSanitizer: the C numerical core (onboard/c) and
a harness (tests/c/sil_vectors.c) built with the flight-code flags plus -fsanitize=address,undefined
-fno-sanitize-recover=all run every golden vector and a short session through the recursive estimator (float32 and
fixed) with no finding (any finding aborts the run with a non-zero status). The results are those of the
production build: the fixed-point ones bit-exact with the vectors, the float32 ones within their tolerances, and the
estimator's final state byte-identical to the ctypes (-O2) build's after the same frames."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_replay_cli import NOMINAL

from hostlink.portkit import estimator_c, vectors
from hostlink.portkit.estimator_c import CEstimator
from hostlink.portkit.vectors import decode_array
from hostlink.sky.references import session_references
from hostlink.sky.simulate import seed004_config, simulate
from onboard import recursive
from onboard.params import ESTIMATE_NAMES, params_from_dict

CC = shutil.which("cc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc) on this machine")
HARNESS = Path(__file__).parent / "c" / "sil_vectors.c"


@pytest.fixture(scope="module")
def sil(tmp_path_factory):
    exe = tmp_path_factory.mktemp("sil") / "sil"
    cmd = [
        CC,
        *estimator_c.STRICT_FLAGS,
        *estimator_c.SANITIZE_FLAGS,
        "-O1",
        f"-I{estimator_c.c_dir()}",
        "-o",
        str(exe),
        str(HARNESS),
        *map(str, estimator_c.sources()),
        "-lm",
    ]
    built = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    if built.returncode != 0 and "sanitize" in built.stderr and "cannot find" in built.stderr:
        pytest.skip("the compiler has no sanitizer runtime")
    assert built.returncode == 0, built.stderr

    def run(lines: list[str]) -> list[list[str]]:
        env = dict(os.environ, ASAN_OPTIONS="detect_leaks=1:abort_on_error=1", UBSAN_OPTIONS="print_stacktrace=1")
        proc = subprocess.run(
            [str(exe)], input="\n".join(lines) + "\n", capture_output=True, text=True, timeout=300, env=env
        )
        assert proc.returncode == 0 and "runtime error" not in proc.stderr, proc.stderr[-3000:]
        out = [line.split()[1:] for line in proc.stdout.splitlines()]
        assert len(out) == len(lines)
        return out

    return run


def _hex(values) -> str:
    return " ".join(float(v).hex() for v in np.ravel(values))


def _ints(values) -> str:
    return " ".join(str(int(v)) for v in np.ravel(values))


def _floats(tokens) -> np.ndarray:
    return np.array([float.fromhex(t) for t in tokens], dtype=np.float64)


def _equal(expected):
    """A check that the harness's integers equal ``expected`` (row-major): fixed point is bit-exact."""
    want = [int(v) for v in np.ravel(expected)]
    return lambda got: [int(t) for t in got] == want


def _cases(docs, name):
    for case in docs[name]["cases"]:
        inp = {k: decode_array(v) for k, v in case["inputs"].items()}
        out = {k: decode_array(v) for k, v in case["outputs"].items()}
        tol = {
            k: decode_array(v["abs"]) if isinstance(v["abs"], dict) else v["abs"] for k, v in case["tolerance"].items()
        }
        yield inp, out, tol


def _ratio(got, expected, tol) -> float:
    diff = np.abs(np.asarray(got, np.float64) - np.asarray(expected, np.float64).ravel())
    t = np.broadcast_to(np.asarray(tol, np.float64), np.shape(expected)).ravel()
    return float(np.max(np.where(diff == 0, 0.0, diff / t)))


def test_sanitized_core_runs_every_golden_vector_without_a_finding(sil):
    docs = vectors.generate_vectors()
    lines, checks = [], []
    for inp, out, tol in _cases(docs, "pixel_to_direction.float32.json"):
        n = inp["x_px"].size
        lines.append(f"P {n} {_hex(inp['theta'])} {_hex(inp['x_px'])} {_hex(inp['y_px'])}")
        checks.append(lambda g, out=out, tol=tol: _ratio(_floats(g), out["b"], tol["b"]) <= 1)
    for inp, out, tol in _cases(docs, "camera_jacobians.float32.json"):
        n = inp["x_px"].size
        lines.append(f"J {n} {_hex(inp['theta'])} {_hex(inp['x_px'])} {_hex(inp['y_px'])}")

        def jac(g, n=n, out=out, tol=tol):
            f = _floats(g)
            parts = (f[: 3 * n], f[3 * n : 33 * n], f[33 * n :])
            return all(
                _ratio(p, out[k], tol[k]) <= 1 for p, k in zip(parts, ("b", "j_theta", "j_centroid"), strict=True)
            )

        checks.append(jac)
    for inp, out, _ in _cases(docs, "pixel_to_direction.fixed.json"):
        w, h = inp["image_size_px"]
        n = inp["x_q10"].size
        lines.append(f"F {w} {h} {_hex(inp['theta'])} {n} {_ints(inp['x_q10'])} {_ints(inp['y_q10'])}")
        want = [int(out[k]) for k in ("s", "x0_q", "y0_q", "qw", "f_w")] + out["b_q30"].ravel().tolist()
        checks.append(lambda g, want=want: [int(t) for t in g] == want)
    for inp, out, _ in _cases(docs, "interstar_residual.fixed.json"):
        p, n = inp["pair_i"].size, inp["b_q30"].shape[0]
        lines.append(
            f"E {p} {n} {_ints(inp['b_q30'])} {_ints(inp['r_q30'])} {_ints(inp['pair_i'])} {_ints(inp['pair_j'])}"
        )
        checks.append(_equal(out["e_q61"]))
    for inp, out, tol in _cases(docs, "ud_update.float32.json"):
        k = inp["d"].size
        lines.append(f"U {k} {_hex(inp['u'])} {_hex(inp['d'])} {_hex(inp['xi'])} {_hex(inp['h'])} {_hex(inp['y'])}")

        def bierman(g, k=k, out=out, tol=tol):
            f = _floats(g)
            parts = {"u": f[: k * k], "d": f[k * k : k * k + k], "xi": f[k * k + k : k * k + 2 * k]}
            parts |= {"innovation": f[-2:-1], "innovation_variance": f[-1:]}
            return all(_ratio(v, out[name], tol[name]) <= 1 for name, v in parts.items())

        checks.append(bierman)
    for inp, out, _ in _cases(docs, "refraction_by_addition.fixed.json"):
        n = inp["r_q30"].shape[0]
        a, b = inp["ab_q56"]
        for flag, name in ((0, "aberrated_q30"), (1, "observed_q30")):
            lines.append(
                f"R {n} {_ints(inp['r_q30'])} {_ints(inp['zenith_q30'])} {_ints(inp['beta_q48'])} {a} {b} {flag}"
            )
            checks.append(_equal(out[name]))
    for inp, out, _ in _cases(docs, "apparent_place.fixed.json"):
        n = inp["r0_q30"].shape[0]
        fields = " ".join(
            _ints(inp[k])
            for k in ("years_q20", "earth_bary_q30", "sun_to_earth_q30", "deflection_k_q70", "beta_q44", "tod_q30")
        )
        lines.append(f"A {n} {_ints(inp['r0_q30'])} {_ints(inp['pm_q46'])} {_ints(inp['parallax_q48'])} {fields}")
        checks.append(_equal(out["apparent_q30"]))
    for inp, out, tol in _cases(docs, "attitude.float32.json"):
        n = inp["b"].shape[0]
        lines.append(f"T {n} {_hex(inp['b'])} {_hex(inp['r'])} {_hex(inp['weights'])}")
        checks.append(lambda g, out=out, tol=tol: g[0] == "0" and _ratio(_floats(g[1:]), out["c"], tol["c"]) <= 1)
    for inp, out, tol in _cases(docs, "apparent_place.float32.json"):
        n = inp["r0"].shape[0]
        lines.append(
            f"G {n} {_hex(inp['r0'])} {_hex(inp['pm_rad_yr'])} {_hex(inp['parallax_mas'])} "
            f"{_hex(inp['epoch_jyear'])} {int(inp['t_tt_day'])} {int(inp['t_tt_frac'])}"
        )

        def apparent(g, out=out, tol=tol):
            f = _floats(g)
            return (
                _ratio(f[:9], out["tod_matrix"], tol["tod_matrix"]) <= 1
                and _ratio(f[9:], out["apparent"], tol["apparent"]) <= 1
            )

        checks.append(apparent)
    results = sil(lines)
    failed = [line.split()[0] for line, g, check in zip(lines, results, checks, strict=True) if not check(g)]
    assert failed == []
    assert len(lines) == 24  # 2 + 1 + 2 + 2 + 3 + 8 + 2 + 2 + 2 cases


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_sanitized_estimator_runs_a_session_to_the_production_builds_bytes(sil, precision):
    nominal = params_from_dict(NOMINAL)
    session = simulate(seed004_config(120, seed=5)).session
    refs = session_references(session)
    config = recursive.RecursiveConfig()
    production = CEstimator(nominal, ESTIMATE_NAMES, config)
    d = nominal.distortion.as_tuple()
    x0, y0 = nominal.principal_point_px
    w, h = nominal.image_size_px
    mask = estimator_c.estimated_mask(ESTIMATE_NAMES)
    lines = [f"C {_hex([nominal.focal_length_mm, nominal.pixel_pitch_um, x0, y0])} {w} {h} {_hex(d)} {mask}"]
    for rows in session.frame_slices():
        x, y, r, ident = session.x_px[rows], session.y_px[rows], refs.r[rows], refs.usable[rows]
        r = np.where(ident[:, None], r, 0.0)  # unidentified rows carry no reference (NaN in the session)
        production.update(x, y, r, ident, precision)
        flag = int(precision == "fixed")
        lines.append(f"X {flag} {x.size} {_hex(x)} {_hex(y)} {_hex(r)} {_ints(ident)}")
    lines.append("Z")
    out = sil(lines)
    assert out[0] == ["0"]
    assert all(o[0] == "0" for o in out[1:-1])  # every frame ran (status 0)
    # the same bits as the -O2 build: -ffp-contract=off and IEEE float32 leave the optimiser nothing to change
    assert bytes.fromhex(out[-1][0]) == production.save_state()
    assert production.to_python().updates > 100
