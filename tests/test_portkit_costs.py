"""The cost table's counted formulas equal an instrumented run of the code they describe, and the measured rows
scale as the code's structure says (linearly in N, plus a per-call constant)."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.portkit import costs
from hostlink.portkit.costs import Ops, count_operations, counted
from onboard import apparent, fixedpoint, interstar, refraction, ud
from onboard.camera import pixels_to_unit, unit_vector_jacobians
from onboard.recursive import RecursiveConfig, update_cost_flops


def test_the_instrumented_counter_counts_a_known_expression_and_restores_numpy():
    a, b, c = (counted(np.arange(6, dtype=np.float32)) for _ in range(3))
    ops = count_operations(lambda: np.sqrt(a * b + c) / np.float32(2) + np.sum(a))
    assert ops == Ops(mul=6, add=6 + 5 + 6, div=6, sqrt=6)  # a b + c, the sum (5 additions), the final + (6)
    zeros, asarray = np.zeros, np.asarray
    count_operations(lambda: np.zeros(3))
    assert np.zeros is zeros and np.asarray is asarray  # the wrapped numpy functions are restored after counting


def test_the_counter_sees_work_behind_np_asarray():
    # onboard functions begin with r = np.asarray(r); that must not hide the rest of their work from the count
    a = counted(np.arange(4, dtype=np.int64))
    assert count_operations(lambda x: np.asarray(x) * 3 + 1, a) == Ops(mul=4, add=4)
    assert count_operations(lambda: np.asarray(np.arange(4)) * 3) == Ops()  # plain inputs stay plain


@pytest.mark.parametrize("n_stars", [3, 7, 32])
def test_counted_front_end_formulas_equal_an_instrumented_run(n_stars):
    x, y, r = costs._stars(n_stars)
    theta = costs._theta()
    assert count_operations(pixels_to_unit, counted(x), counted(y), counted(theta)) == costs.pixel_to_direction_ops(
        n_stars
    )
    cam = fixedpoint.fixed_camera(theta.astype(np.float64), (1024, 1024))
    xs = np.rint(x.astype(np.float64) * 1024).astype(np.int64)
    ys = np.rint(y.astype(np.float64) * 1024).astype(np.int64)
    got = count_operations(fixedpoint.pixels_to_unit_q30, counted(xs), counted(ys), cam)
    assert got == costs.pixel_to_direction_fixed_ops(n_stars)
    i, j = interstar.independent_pairs(n_stars)
    b = pixels_to_unit(x, y, theta)
    got = count_operations(interstar.difference_residuals, counted(b), counted(r), i, j)
    assert got == costs.interstar_residual_ops(i.size)
    bq, rq = fixedpoint.pixels_to_unit_q30(xs, ys, cam), fixedpoint.quantise_unit_q30(r)
    got = count_operations(fixedpoint.difference_residuals_q61, counted(bq), counted(rq), i, j)
    assert got == costs.interstar_residual_ops(i.size, fixed=True)
    _, jb, _ = unit_vector_jacobians(x, y, theta)
    got = count_operations(interstar.difference_jacobian, counted(b), counted(jb), i, j)
    assert got == costs.interstar_jacobian_ops(i.size, 10)


@pytest.mark.parametrize("n_states", [1, 4, 10])
def test_bierman_update_formula_equals_an_instrumented_run(n_states):
    k = n_states
    rng = np.random.default_rng(k)
    u = np.triu(rng.normal(size=(k, k))).astype(np.float32)
    np.fill_diagonal(u, 1)
    w = ud.bierman_work(k, np.float32)
    work = ud.BiermanWork(*(counted(a) for a in (w.f, w.v, w.alpha, w.alpha_prev, w.cols)))
    args = (counted(u), counted(np.ones(k, np.float32)), counted(np.zeros(k, np.float32)))
    got = count_operations(ud.bierman_update, *args, counted(rng.normal(size=k).astype(np.float32)), 0.5, work)
    assert got == costs.bierman_update_ops(k)
    assert got.flops == 6 * k * k + 7 * k


@pytest.mark.parametrize(
    "measure", [costs.unit_vector_jacobian_ops, costs.refraction_ops, costs.apparent_place_ops, costs.attitude_ops]
)
def test_measured_rows_grow_linearly_in_the_number_of_stars(measure):
    # per-star work plus a per-call constant (the apparent place's Earth state and matrix, the attitude's 3 x 3
    # algebra): equal steps in N give equal steps in every count
    c8, c16, c32 = (measure(n).as_dict() for n in (8, 16, 32))
    for cat in costs.CATEGORIES:
        assert c32[cat] - c16[cat] == 2 * (c16[cat] - c8[cat]), cat
    assert c16["mul"] > c8["mul"]


def test_cost_table_reuses_the_estimators_own_budget_model():
    rows = {(r.function, r.precision): r for r in costs.cost_table(24, 6)}
    assert rows[("estimator_frame", "float32")].extra["flops"] == update_cost_flops(24, 6)
    assert rows[("pixel_to_direction", "float32")].ops == costs.pixel_to_direction_ops(24)
    linearisations = RecursiveConfig().max_iterations + 2  # the fixed front end runs once per linearisation
    front = costs.pixel_to_direction_fixed_ops(24) + costs.interstar_residual_ops(45, fixed=True)
    assert rows[("estimator_frame_front_end", "fixed")].ops == front.scaled(linearisations)
    text = costs.format_table(list(rows.values()), 24, 6)
    assert "N = 24 stars, P = 45 pairs, K = 6 states" in text
    with pytest.raises(ValueError, match="at least 3 stars"):
        costs.cost_table(2)


@pytest.mark.parametrize("n_stars", [3, 7, 32])
def test_counted_fixed_point_site_correction_and_apparent_place_equal_an_instrumented_run(n_stars):
    from onboard.site import Weather
    from onboard.timescale import make_time

    _, _, r = costs._stars(n_stars, np.float64)
    coef = refraction.fixed_refraction(Weather(10.0, 1013.25, 0.5))
    zenith = fixedpoint.quantise_unit_q30(np.array([0.0, 0.6, 0.8]))
    beta = refraction.beta_q48(np.array([210.0, -340.0, 120.0]))
    got = count_operations(
        refraction.topocentric_observed_q30, counted(fixedpoint.quantise_unit_q30(r)), zenith, beta, coef
    )
    assert got == costs.refraction_fixed_ops(n_stars)
    rng = np.random.default_rng(n_stars)
    pm = rng.normal(0.0, 1e-6, (n_stars, 3))
    r0, pm_q, plx_q = apparent.fixed_catalogue(r, pm, rng.uniform(0.0, 300.0, n_stars))
    inst = apparent.fixed_instant(make_time(9497, 1 << 31), apparent.EPOCH_HIPPARCOS_JYEAR)
    got = count_operations(apparent.apparent_place_vectors_q30, counted(r0), counted(pm_q), counted(plx_q), inst)
    assert got == costs.apparent_place_fixed_ops(n_stars)


def test_bank_record_row_counts_the_generated_c_crc_loop():
    from hostlink.portkit.export_c import generate_c
    from onboard.banks import BANK_RECORD_BYTES

    source = "".join(generate_c().values())
    assert source.count(costs.CRC32_BYTE_STEP_C) == 1  # the one CRC loop the formula counts, as generated
    ops = costs.bank_record_verify_ops()
    assert ops.shift == 4 * (BANK_RECORD_BYTES - 4) + 1  # 2 XOR, mask, shift per byte before the CRC; final XOR
    rows = {(r.function, r.precision): r for r in costs.cost_table(8, 10)}
    assert rows[("bank_record_verify", "bytes")].ops == ops
    assert rows[("apparent_place_instant", "float64")].ops == costs.apparent_instant_ops()  # once per frame
    assert rows[("apparent_place", "fixed")].ops == costs.apparent_place_fixed_ops(8)
    assert rows[("refraction_by_addition", "fixed")].ops == costs.refraction_fixed_ops(8)
