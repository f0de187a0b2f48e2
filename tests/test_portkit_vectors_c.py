"""The golden vectors serve their purpose: a straightforward C translation of the front end (pixel to direction in
float32 and in fixed point, the Q61 interstar residual), compiled with FMA contraction at -O2 (a different
rounding from numpy's), meets every float32 tolerance, and its fixed-point results are bit-exact. The translation
below is what a firmware engineer would write from the reference; it is test code, not part of the kit."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from hostlink.portkit import vectors
from hostlink.portkit.vectors import decode_array

CC = shutil.which("cc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc) on this machine")

_PORT = r"""
#include <inttypes.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static float f32(const char *hex)
{
    uint32_t bits = (uint32_t)strtoul(hex, NULL, 16);
    float v;
    memcpy(&v, &bits, sizeof v);
    return v;
}
static void put32(float v)
{
    uint32_t bits;
    memcpy(&bits, &v, sizeof bits);
    printf(" %08" PRIx32, bits);
}

/* camera.ideal_offsets + offsets_to_unit, float32 (docs/camera-model.md, seed 000 eq. 7) */
static void pixel_to_direction(const float th[10], float x, float y)
{
    float k1 = th[3], k2 = th[4], k3 = th[5], p1 = th[6], p2 = th[7], s1 = th[8], s2 = th[9];
    float g1 = s1 + p1, g2 = s2 + p2, g3 = p1 + p1, g4 = p2 + p2;
    float u = x - th[1], v = y - th[2];
    float r2 = u * u + v * v;
    float radial = r2 * (k1 + r2 * (k2 + r2 * k3));
    float dx = (g1 + g3) * u * u + g4 * u * v + g1 * v * v + u * radial;
    float dy = g2 * u * u + g3 * u * v + (g2 + g4) * v * v + v * radial;
    float up = u - dx, vp = v - dy;
    float n = sqrtf(up * up + vp * vp + th[0] * th[0]);
    put32(up); put32(vp); put32(up / n); put32(vp / n); put32(th[0] / n);
}

/* fixedpoint.py: rshift_round, ideal_offsets_q30, rsqrt_q30, offsets_to_unit_q30 (arithmetic right shift of
 * negative int64: GCC and Clang define >> so; a port to another compiler must check it) */
static int64_t rr(int64_t a, int n) { return (a + ((int64_t)1 << (n - 1))) >> n; }
static int64_t coef_m[7], coef_e[7], table[64];
static int64_t term(int64_t p, int k) { return rr(p * coef_m[k], (int)coef_e[k]); }
static int bitlen(int64_t x) { int n = 0; while (x > 0) { ++n; x >>= 1; } return n; }

static void front_end(int s, int64_t x0q, int64_t y0q, int qw, int64_t fw, int first, int iters, int64_t xq,
                      int64_t yq)
{
    const int Q = 30;
    int shift = 20 - s;
    int64_t u = (xq * ((int64_t)1 << shift)) - x0q, v = (yq * ((int64_t)1 << shift)) - y0q;
    int64_t uu = rr(u * u, Q), vv = rr(v * v, Q), uv = rr(u * v, Q);
    int64_t r2 = uu + vv, r4 = rr(r2 * r2, Q), r6 = rr(rr(r4, 1) * r2, Q - 1);
    int64_t radial = term(r2, 0) + term(r4, 1) + term(r6, 2);
    int64_t ru = rr(u * radial, Q), rv = rr(v * radial, Q), uv2 = uv + uv;
    int64_t dx = ru + term(3 * uu + vv, 3) + term(uv2, 4) + term(r2, 5);
    int64_t dy = rv + term(uu + 3 * vv, 4) + term(uv2, 3) + term(r2, 6);
    int64_t ui = u - dx, vi = v - dy;
    int down = Q - qw;
    int64_t wu = rr(ui, down), wv = rr(vi, down);
    int64_t n2 = wu * wu + wv * wv + fw * fw;
    int sh = bitlen(n2) - Q - 1;
    sh += (sh + 1) & 1;
    int64_t a = rr(n2, sh);
    int64_t y = table[(a >> 26) - first];
    for (int i = 0; i < iters; ++i) {
        int64_t t1 = rr(a * y, Q + 1);
        int64_t t2 = rr(t1 * y, Q);
        y = rr(y * (3 * ((int64_t)1 << Q) - t2), Q + 1);
    }
    int k = (Q + 1 + sh) >> 1;
    printf(" %" PRId64 " %" PRId64 " %" PRId64 " %" PRId64 " %" PRId64, ui, vi, rr(wu * y, k), rr(wv * y, k),
           rr(fw * y, k));
}

int main(void)
{
    char op[8];
    while (scanf("%7s", op) == 1) {
        if (op[0] == 'P') {
            char h[12][16];
            float th[10];
            for (int i = 0; i < 12; ++i) if (scanf("%15s", h[i]) != 1) return 1;
            for (int i = 0; i < 10; ++i) th[i] = f32(h[i]);
            printf("O");
            pixel_to_direction(th, f32(h[10]), f32(h[11]));
            printf("\n");
        } else if (op[0] == 'T') { /* the rsqrt table: T first n t0 t1 ... */
            int n;
            if (scanf("%d", &n) != 1 || n > 64) return 1;
            for (int i = 0; i < n; ++i) if (scanf("%" SCNd64, &table[i]) != 1) return 1;
        } else if (op[0] == 'Q') {
            int s, qw, first, iters;
            int64_t x0q, y0q, fw, xq, yq;
            if (scanf("%d %" SCNd64 " %" SCNd64, &s, &x0q, &y0q) != 3) return 1;
            for (int i = 0; i < 7; ++i) if (scanf("%" SCNd64, &coef_m[i]) != 1) return 1;
            for (int i = 0; i < 7; ++i) if (scanf("%" SCNd64, &coef_e[i]) != 1) return 1;
            if (scanf("%d %" SCNd64 " %d %d %" SCNd64 " %" SCNd64, &qw, &fw, &first, &iters, &xq, &yq) != 6) return 1;
            printf("O");
            front_end(s, x0q, y0q, qw, fw, first, iters, xq, yq);
            printf("\n");
        } else if (op[0] == 'E') { /* Q61 residual of one pair: bi bj ri rj (3 each) */
            int64_t c[12], sb = 0, sr = 0;
            for (int i = 0; i < 12; ++i) if (scanf("%" SCNd64, &c[i]) != 1) return 1;
            for (int i = 0; i < 3; ++i) {
                int64_t db = c[i] - c[3 + i], dr = c[6 + i] - c[9 + i];
                sb += db * db;
                sr += dr * dr;
            }
            printf("O %" PRId64 "\n", sb - sr);
        }
        fflush(stdout);
    }
    return 0;
}
"""


@pytest.fixture(scope="module")
def port(tmp_path_factory):
    directory = tmp_path_factory.mktemp("port")
    vectors.write_vectors(directory / "vectors")
    (directory / "port.c").write_text(_PORT)
    exe = directory / "port"
    flags = ["-std=gnu99", "-O2", "-march=native", "-ffp-contract=fast", "-Wall", "-Wextra", "-Werror"]
    result = subprocess.run(
        [CC, *flags, "-o", str(exe), str(directory / "port.c"), "-lm"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr

    def run(lines: list[str]) -> list[list[str]]:
        proc = subprocess.run([str(exe)], input="\n".join(lines) + "\n", capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr
        return [line.split()[1:] for line in proc.stdout.splitlines()]

    return run, directory / "vectors"


def _doc(directory, name: str) -> dict:
    return json.loads((directory / name).read_text())


def test_c_float32_pixel_to_direction_meets_the_vector_tolerances(port):
    run, directory = port
    doc = _doc(directory, "pixel_to_direction.float32.json")
    worst = 0.0
    for case in doc["cases"]:
        inputs = case["inputs"]
        theta_hex = inputs["theta"]["hex"]
        lines = [
            f"P {' '.join(theta_hex)} {x} {y}"
            for x, y in zip(inputs["x_px"]["hex"], inputs["y_px"]["hex"], strict=True)
        ]
        got = np.array([[int(h, 16) for h in row] for row in run(lines)], dtype=np.uint32).view(np.float32)
        for col, name in ((slice(0, 1), "u_ideal_px"), (slice(1, 2), "v_ideal_px"), (slice(2, 5), "b")):
            expected = decode_array(case["outputs"][name]).reshape(got[:, col].shape).astype(np.float64)
            tol = case["tolerance"][name]["abs"]
            ratio = float(np.max(np.abs(got[:, col].astype(np.float64) - expected))) / tol
            assert ratio <= 1.0, name
            worst = max(worst, ratio)
    assert worst < 0.5  # FMA contraction and -O2 move the results by a few ulp: well inside the derived bounds


def test_c_fixed_point_front_end_is_bit_exact_with_the_vectors(port):
    run, directory = port
    doc = _doc(directory, "pixel_to_direction.fixed.json")
    const = {k: decode_array(v) for k, v in doc["constants"].items()}
    table = const["rsqrt_table_q30"]
    lines = [f"T {table.size} {' '.join(str(int(v)) for v in table)}"]
    expected = []
    for case in doc["cases"]:
        out = {k: decode_array(v) for k, v in case["outputs"].items()}
        inp = {k: decode_array(v) for k, v in case["inputs"].items()}
        first, iters = int(const["rsqrt_table_first_bin"]), int(const["rsqrt_iterations"])
        cam = [out["s"], out["x0_q"], out["y0_q"], *out["coef_m"], *out["coef_e"], out["qw"], out["f_w"], first, iters]
        for k in range(inp["x_q10"].size):
            values = [*cam, inp["x_q10"][k], inp["y_q10"][k]]
            lines.append("Q " + " ".join(str(int(v)) for v in values))
            expected.append([out["u_ideal_q30"][k], out["v_ideal_q30"][k], *out["b_q30"][k]])
    got = run(lines)
    assert len(got) == len(expected) > 20
    for g, e in zip(got, expected, strict=True):
        assert [int(v) for v in g] == [int(v) for v in e]  # tolerance 0: integer arithmetic, one rounding rule


def test_c_fixed_point_residuals_are_bit_exact_with_the_vectors(port):
    run, directory = port
    doc = _doc(directory, "interstar_residual.fixed.json")
    lines, expected = [], []
    for case in doc["cases"]:
        inp = {k: decode_array(v) for k, v in case["inputs"].items()}
        e = decode_array(case["outputs"]["e_q61"])
        for p in range(e.size):
            i, j = int(inp["pair_i"][p]), int(inp["pair_j"][p])
            vals = [*inp["b_q30"][i], *inp["b_q30"][j], *inp["r_q30"][i], *inp["r_q30"][j]]
            lines.append("E " + " ".join(str(int(v)) for v in vals))
            expected.append(int(e[p]))
    assert [int(g[0]) for g in run(lines)] == expected
