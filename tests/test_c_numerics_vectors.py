"""The C numerical core (onboard/c: camera, ud, fixedpoint, interstar) against the golden vectors
(``hostlink vectors``, hostlink/portkit/vectors.py): the fixed-point front end bit-exact (every integer the
vectors hold, the camera's conversion included), the float32 functions within each output's stated tolerance
(gamma_n of the magnitudes the operations act on: operation order and the absence of FMA are all that differ).

The library is built once with the flight-code flags (-std=c99 -Wall -Wextra -Werror -pedantic -Wconversion
-Wshadow -ffp-contract=off) and called through ctypes (hostlink/portkit/estimator_c.py)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from hostlink.portkit import estimator_c, vectors
from hostlink.portkit.estimator_c import FixedCamera, ptr, ref
from hostlink.portkit.vectors import decode_array

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")


@pytest.fixture(scope="module")
def lib():
    return estimator_c.load()


@pytest.fixture(scope="module")
def docs():
    return vectors.generate_vectors()


def _cases(docs, name):
    for case in docs[name]["cases"]:
        inp = {k: decode_array(v) for k, v in case["inputs"].items()}
        out = {k: decode_array(v) for k, v in case["outputs"].items()}
        tol = {
            k: (decode_array(v["abs"]) if isinstance(v["abs"], dict) else v["abs"])
            for k, v in case["tolerance"].items()
        }
        yield inp, out, tol


def _within(got, expected, tol) -> float:
    """The largest |got - expected| / tolerance (<= 1 passes)."""
    diff = np.abs(np.asarray(got, np.float64) - np.asarray(expected, np.float64).reshape(np.shape(got)))
    t = np.broadcast_to(np.asarray(tol, np.float64), diff.shape)
    return float(np.max(np.where(diff == 0, 0.0, diff / t)))


def _f32(a):
    return np.ascontiguousarray(a, dtype=np.float32)


def test_c_pixel_to_direction_float32_meets_the_vector_tolerances(lib, docs):
    worst = 0.0
    for inp, out, tol in _cases(docs, "pixel_to_direction.float32.json"):
        theta, x, y = _f32(inp["theta"]), _f32(inp["x_px"]), _f32(inp["y_px"])
        n = x.size
        u, v, b = np.zeros(n, np.float32), np.zeros(n, np.float32), np.zeros((n, 3), np.float32)
        lib.camera_ideal_offsets(ptr(x), ptr(y), n, ptr(theta), ptr(u), ptr(v))
        lib.camera_offsets_to_unit(ptr(u), ptr(v), n, float(theta[0]), ptr(b))
        b2 = np.zeros((n, 3), np.float32)
        lib.camera_pixels_to_unit(ptr(x), ptr(y), n, ptr(theta), ptr(b2))
        assert np.array_equal(b, b2)  # one job in one place: pixels_to_unit is the two steps
        for name, got in (("u_ideal_px", u), ("v_ideal_px", v), ("b", b)):
            worst = max(worst, _within(got, out[name], tol[name]))
    assert worst <= 1.0


def _equal(got, expected) -> bool:
    return np.array_equal(np.asarray(got).ravel(), np.asarray(expected, dtype=np.asarray(got).dtype).ravel())


def test_c_camera_jacobians_float32_are_bit_exact_with_the_vectors(lib, docs):
    # every sum in the reference model's order (onboard.linalg32), no FMA: the same float32 bits (within the
    # vectors' tolerance a fortiori: a port that sums in another order is held to the tolerance, this one to the bit)
    worst = 0.0
    for inp, out, tol in _cases(docs, "camera_jacobians.float32.json"):
        theta, x, y = _f32(inp["theta"]), _f32(inp["x_px"]), _f32(inp["y_px"])
        n = x.size
        b, jt, jc = np.zeros((n, 3), np.float32), np.zeros((n, 3, 10), np.float32), np.zeros((n, 3, 2), np.float32)
        lib.camera_unit_vector_jacobians(ptr(x), ptr(y), n, ptr(theta), ptr(b), ptr(jt), ptr(jc))
        for name, got in (("b", b), ("j_theta", jt), ("j_centroid", jc)):
            assert _equal(got, out[name]), name
            worst = max(worst, _within(got, out[name], tol[name]))
    assert worst == 0.0


def test_c_fixed_point_front_end_is_bit_exact_with_the_vectors(lib, docs):
    const = {k: decode_array(v) for k, v in docs["pixel_to_direction.fixed.json"]["constants"].items()}
    table = np.ctypeslib.as_array((np.ctypeslib.ctypes.c_int64 * 25).in_dll(lib, "fixedpoint_rsqrt_table_q30"))
    assert table.tolist() == const["rsqrt_table_q30"].tolist()
    n_checked = 0
    for inp, out, _ in _cases(docs, "pixel_to_direction.fixed.json"):
        cam = FixedCamera()
        w, h = (int(v) for v in inp["image_size_px"])
        assert lib.fixedpoint_camera(ptr(_f32(inp["theta"])), w, h, ref(cam)) == 0
        assert [cam.s, cam.x0_q, cam.y0_q, cam.qw, cam.f_w] == [int(out[k]) for k in ("s", "x0_q", "y0_q", "qw", "f_w")]
        assert list(cam.coef_m) == out["coef_m"].tolist() and list(cam.coef_e) == out["coef_e"].tolist()
        assert np.array_equal(np.array(cam.theta_q), out["theta_q"])  # the double the integers stand for, exact
        for k in range(inp["x_q10"].size):
            u, v = np.zeros(1, np.int64), np.zeros(1, np.int64)
            assert (
                lib.fixedpoint_ideal_offsets_q30(int(inp["x_q10"][k]), int(inp["y_q10"][k]), ref(cam), ptr(u), ptr(v))
                == 0
            )
            b = np.zeros(3, np.int64)
            lib.fixedpoint_offsets_to_unit_q30(int(u[0]), int(v[0]), ref(cam), ptr(b))
            assert [u[0], v[0]] == [out["u_ideal_q30"][k], out["v_ideal_q30"][k]]
            assert b.tolist() == out["b_q30"][k].tolist()  # tolerance 0: integers, one rounding rule
            n_checked += 1
    assert n_checked == 32


def test_c_fixed_point_residuals_are_bit_exact_with_the_vectors(lib, docs):
    for inp, out, _ in _cases(docs, "interstar_residual.fixed.json"):
        b, r = (np.ascontiguousarray(inp[k], np.int64) for k in ("b_q30", "r_q30"))
        pi, pj = (np.ascontiguousarray(inp[k], np.int32) for k in ("pair_i", "pair_j"))
        e = np.zeros(pi.size, np.int64)
        lib.fixedpoint_difference_residuals_q61(ptr(b), ptr(r), ptr(pi), ptr(pj), pi.size, ptr(e))
        assert e.tolist() == out["e_q61"].tolist()


def test_c_interstar_float32_is_bit_exact_with_the_vectors(lib, docs):
    worst = 0.0
    for inp, out, tol in _cases(docs, "interstar_residual.float32.json"):
        b, r, jb = _f32(inp["b"]), _f32(inp["r"]), _f32(inp["jb"])
        pi, pj = (np.ascontiguousarray(inp[k], np.int32) for k in ("pair_i", "pair_j"))
        e, h = np.zeros(pi.size, np.float32), np.zeros((pi.size, 10), np.float32)
        lib.interstar_difference_residuals(ptr(b), ptr(r), ptr(pi), ptr(pj), pi.size, ptr(e))
        lib.interstar_difference_jacobian(ptr(b), ptr(jb), 10, ptr(pi), ptr(pj), pi.size, ptr(h))
        assert _equal(e, out["e"]) and _equal(h, out["h"])  # the model's order: the same bits
        worst = max(worst, _within(e, out["e"], tol["e"]), _within(h, out["h"], tol["h"]))
        # the pair set itself: the same (0,1), (0,k), (1,k) as the Python model
        ci, cj = np.zeros(pi.size, np.int32), np.zeros(pi.size, np.int32)
        assert lib.interstar_independent_pairs(b.shape[0], ptr(ci), ptr(cj)) == pi.size
        assert ci.tolist() == pi.tolist() and cj.tolist() == pj.tolist()
    assert worst == 0.0


def test_c_bierman_update_is_bit_exact_with_the_vectors(lib, docs):
    worst = 0.0
    for inp, out, tol in _cases(docs, "ud_update.float32.json"):
        u, d, xi, h = (np.array(inp[k], dtype=np.float32, order="C") for k in ("u", "d", "xi", "h"))
        s = np.zeros(1, np.float32)
        innovation = lib.ud_bierman_update(ptr(u), ptr(d), ptr(xi), ptr(h), float(inp["y"]), d.size, ptr(s))
        got = {"u": u, "d": d, "xi": xi, "innovation": np.float32(innovation), "innovation_variance": s[0]}
        for name, value in got.items():
            assert _equal(value, out[name]), name  # the model's order: the same bits
            worst = max(worst, _within(value, out[name], tol[name]))
    assert worst == 0.0


def _python_fixed_camera(theta, size):
    from onboard import fixedpoint

    try:
        return fixedpoint.fixed_camera(theta, size)
    except fixedpoint.FixedRangeError:
        return None


def test_c_fixed_point_camera_and_front_end_match_python_at_the_range_extremes(lib):
    # principal point at a corner, strong distortion near the range limit, detectors of several sizes: the C
    # refuses exactly the sets Python refuses, and is bit-exact on every corner and on random centroids
    from onboard import fixedpoint

    rng = np.random.default_rng(27)
    n_sets = n_refused = 0
    for size in ((1024, 1024), (2048, 1536), (640, 480), (4000, 3000)):
        w, h = size
        for _trial in range(40):
            s_px = float(1 << fixedpoint.detector_shift(size))
            theta = np.array(
                [
                    rng.uniform(0.1, 8.0) * s_px,
                    rng.choice([-0.5, w - 0.5, rng.uniform(-0.6, w - 0.4)]),
                    rng.choice([-0.5, h - 0.5, rng.uniform(-0.6, h - 0.4)]),
                    rng.normal(0, 0.2) / s_px**2,
                    rng.normal(0, 0.05) / s_px**4,
                    rng.normal(0, 0.01) / s_px**6,
                    *(rng.normal(0, 0.05, 4) / s_px),
                ],
                dtype=np.float32,
            )
            cam_py = _python_fixed_camera(theta, size)
            cam = FixedCamera()
            status = lib.fixedpoint_camera(ptr(theta), w, h, ref(cam))
            assert (status == 0) == (cam_py is not None), (status, theta)
            n_sets += 1
            if cam_py is None:
                n_refused += 1
                continue
            assert np.array_equal(np.array(cam.theta_q), cam_py.theta_q)
            xs = np.concatenate([[-512, w * 1024 - 512, -512, w * 1024 - 512], rng.integers(-512, w * 1024 - 512, 20)])
            ys = np.concatenate([[-512, -512, h * 1024 - 512, h * 1024 - 512], rng.integers(-512, h * 1024 - 512, 20)])
            b_py = fixedpoint.pixels_to_unit_q30(xs.astype(np.int64), ys.astype(np.int64), cam_py)
            for k in range(xs.size):
                u, v, b = np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(3, np.int64)
                assert lib.fixedpoint_ideal_offsets_q30(int(xs[k]), int(ys[k]), ref(cam), ptr(u), ptr(v)) == 0
                lib.fixedpoint_offsets_to_unit_q30(int(u[0]), int(v[0]), ref(cam), ptr(b))
                assert b.tolist() == b_py[k].tolist()
    assert 0 < n_refused < n_sets  # both verdicts exercised


def test_c_integer_primitives_match_python(lib):
    from onboard import fixedpoint

    rng = np.random.default_rng(5)
    n = np.concatenate([[0, 1, 2, 3, 4, (1 << 62) - 1], rng.integers(0, 1 << 62, 300), rng.integers(0, 1 << 20, 100)])
    assert [lib.fixedpoint_isqrt(int(v)) for v in n] == fixedpoint.isqrt(n.astype(np.int64)).tolist()
    num = rng.integers(-(1 << 61), 1 << 61, 300)
    den = rng.integers(1, 1 << 31, 300)
    got = [lib.fixedpoint_div_round(int(a), int(b)) for a, b in zip(num, den, strict=True)]
    assert got == fixedpoint.div_round(num, den).tolist()


def test_c_agee_turner_and_pair_ordering_match_python(lib):
    from onboard import interstar, ud

    rng = np.random.default_rng(8)
    for _ in range(50):
        k = 10
        u = (np.triu(rng.normal(0, 0.3, (k, k)), 1) + np.eye(k)).astype(np.float32)
        d = (10.0 ** rng.uniform(-3, 0, k)).astype(np.float32)
        a = np.zeros(k, np.float32)
        a[rng.integers(0, k)] = 1.0
        c = np.float32(10.0 ** rng.uniform(-4, 0))
        u_c, d_c, a_c = u.copy(), d.copy(), a.copy()
        ud.agee_turner_update(u, d, a, c)
        lib.ud_agee_turner_update(ptr(u_c), ptr(d_c), ptr(a_c), float(c), k)
        # the same operations in the same order (one column: no sum to reorder): equal to the bit
        assert np.array_equal(u, u_c) and np.array_equal(d, d_c)
    for n in (3, 5, 17, 32):
        for _ in range(20):
            x, y = (rng.uniform(0, 1024, n).astype(np.float32) for _ in range(2))
            order = np.zeros(n, np.int32)
            lib.interstar_order_for_pairs(ptr(x), ptr(y), n, ptr(order))
            assert order.tolist() == interstar.order_for_pairs(x, y).tolist()


def test_c_pair_covariance_is_bit_exact_with_python(lib):
    from onboard import camera, interstar

    theta = vectors.vector_camera().model_vector(np.float32)
    rng = np.random.default_rng(3)
    x, y = (rng.uniform(0, 1023, 12).astype(np.float32) for _ in range(2))
    b, _, jc = camera.unit_vector_jacobians(x, y, theta)
    pi, pj = interstar.independent_pairs(12)
    r_py = interstar.pair_covariance(b, jc, pi, pj, 0.05)
    r_c = np.zeros_like(r_py)
    lib.interstar_pair_covariance(ptr(_f32(b)), ptr(_f32(jc)), ptr(pi), ptr(pj), pi.size, 0.05, ptr(r_c))
    # each entry summed over the stars the two pairs share in the order onboard.interstar states: the same bits
    assert np.array_equal(r_c, r_py)


def test_c_refraction_float32_meets_the_vector_tolerances(lib, docs):
    worst = 0.0
    for inp, out, tol in _cases(docs, "refraction_by_addition.float32.json"):
        r, zen = _f32(inp["r"]), _f32(inp["zenith"])
        a, b = float(inp["a_rad"]), float(inp["b_rad"])
        n = r.shape[0]
        cz, sz, t = np.zeros(n, np.float32), np.zeros(n, np.float32), np.zeros((n, 3), np.float32)
        lib.refraction_zenith_geometry(ptr(r), n, ptr(zen), ptr(cz), ptr(sz), ptr(t))
        refr = np.array(
            [lib.refraction_from_true_zenith(float(c), float(s), a, b) for c, s in zip(cz, sz, strict=True)]
        )
        app = np.zeros((n, 3), np.float32)
        lib.refraction_refract_toward_zenith(ptr(r), n, ptr(zen), a, b, ptr(app))
        worst = max(worst, _within(refr, out["refraction_rad"], tol["refraction_rad"]))
        worst = max(worst, _within(app, out["apparent"], tol["apparent"]))
    assert worst <= 1.0


def test_c_refraction_fixed_point_is_bit_exact_with_the_vectors(lib, docs):
    n_checked = 0
    for inp, out, _ in _cases(docs, "refraction_by_addition.fixed.json"):
        r, zen, beta = (np.ascontiguousarray(inp[k], np.int64) for k in ("r_q30", "zenith_q30", "beta_q48"))
        a, b = (int(v) for v in inp["ab_q56"])
        n = r.shape[0]
        for with_refraction, name in ((0, "aberrated_q30"), (1, "observed_q30")):
            got = np.zeros((n, 3), np.int64)
            lib.refraction_topocentric_observed_q30(ptr(r), n, ptr(zen), ptr(beta), with_refraction, a, b, ptr(got))
            assert got.tolist() == out[name].tolist()
            n_checked += n
    assert n_checked == 4 * 2 * 16


def test_c_apparent_place_fixed_point_is_bit_exact_with_the_vectors(lib, docs):
    for inp, out, _ in _cases(docs, "apparent_place.fixed.json"):
        inst = estimator_c.fixed_instant(inp)
        r0, pm, plx = (np.ascontiguousarray(inp[k], np.int64) for k in ("r0_q30", "pm_q46", "parallax_q48"))
        got = np.zeros_like(r0)
        lib.apparent_place_vectors_q30(ptr(r0), ptr(pm), ptr(plx), r0.shape[0], ref(inst), ptr(got))
        assert got.tolist() == out["apparent_q30"].tolist()


def test_c_attitude_meets_the_vector_tolerance(lib, docs):
    worst = 0.0
    for inp, out, tol in _cases(docs, "attitude.float32.json"):
        b, r, w = _f32(inp["b"]), _f32(inp["r"]), _f32(inp["weights"])
        c = np.zeros((3, 3), np.float32)
        assert lib.attitude_from_vectors(ptr(b), ptr(r), ptr(w), b.shape[0], ptr(c)) == 0
        worst = max(worst, _within(c, out["c"], tol["c"]))
    assert worst <= 1.0
    # collinear stars are refused, as onboard.attitude.DegenerateGeometry
    b = _f32(np.tile([[0.0, 0.0, 1.0]], (3, 1)))
    c = np.zeros((3, 3), np.float32)
    assert lib.attitude_from_vectors(ptr(b), ptr(b), None, 3, ptr(c)) == 1


def test_c_aberration_change_matches_python_within_float32_rounding(lib):
    from onboard.apparent import aberration_change

    rng = np.random.default_rng(4)
    p = rng.normal(size=(50, 3))
    p = _f32(p / np.linalg.norm(p, axis=1)[:, None])
    v = _f32(rng.normal(size=3) * 1e-4)
    want = aberration_change(p, v)
    got = np.zeros_like(p)
    for k in range(p.shape[0]):
        lib.apparent_aberration_change(ptr(p[k]), ptr(v), ptr(got[k]))
    # the same operations in the same order, a 3-term dot product summed in another order at most: gamma_8 of |v|
    assert np.max(np.abs(got - want)) <= vectors.gamma(8) * 2 * float(np.linalg.norm(v))


def test_c_apparent_place_float32_meets_the_vector_tolerances(lib, docs):
    worst = 0.0
    for inp, out, tol in _cases(docs, "apparent_place.float32.json"):
        t = estimator_c.TimeTT(int(inp["t_tt_day"]), int(inp["t_tt_frac"]))
        tod = np.zeros((3, 3), np.float32)
        lib.earth_true_of_date_matrix(t, ptr(tod))
        r0, pm, plx = _f32(inp["r0"]), _f32(inp["pm_rad_yr"]), _f32(inp["parallax_mas"])
        got = np.zeros_like(r0)
        lib.apparent_place_vectors(ptr(r0), ptr(pm), ptr(plx), r0.shape[0], float(inp["epoch_jyear"]), t, ptr(got))
        worst = max(worst, _within(tod, out["tod_matrix"], tol["tod_matrix"]))
        worst = max(worst, _within(got, out["apparent"], tol["apparent"]))
    assert worst <= 1.0
