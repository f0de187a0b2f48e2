"""A noise floor that grows with field radius (hostlink.calibration.noisefield): floor(q)^2 = b + c q, q the squared
field radius over the half-diagonal. The estimator is the restricted maximum likelihood (checked against a bounded
quasi-Newton minimiser and finite differences); the likelihood-ratio choice has the false-alarm rate of the
Self-Liang mixture; on simulated sessions with a radial floor the components are recovered within their standard
errors and the fit's weights reach the Cramer-Rao bound of the true noise where the constant floor's fall short (the
first-order sandwich covariance, itself checked against direct draws); on sessions with a constant floor (or none)
the constant model is chosen and the fit is the constant model's, bit for bit."""

import numpy as np
import pytest
import scipy.optimize
import scipy.stats
from synthetic_sessions import synthetic_session
from test_calibration_chunked import assert_same_camera
from test_calibration_noise_floor import floor_session

from hostlink.calibration.data import build_data
from hostlink.calibration.floorfit import noise_model_text
from hostlink.calibration.frames import inverse_3x3
from hostlink.calibration.model import parameter_columns
from hostlink.calibration.noisefield import (
    LR_CRITICAL,
    _gradient,
    boundary_tail,
    fisher_errors,
    minus_two_log_l,
    radial_components,
)
from hostlink.calibration.noisefloor import (
    NoiseSums,
    chunk_noise_sums,
    field_geometry,
    field_q,
    variance_components,
    with_floor,
)
from hostlink.calibration.normal import accumulate_normals, reduced_normal
from hostlink.calibration.outcome import result_extras
from hostlink.calibration.run import calibrate, calibrate_chunks
from hostlink.calibration.source import ChunkSource, frames_of
from hostlink.files.params import load_params
from onboard.params import ESTIMATE_NAMES

CAMERA = load_params("builtin:seed004_camera")
NOMINAL = load_params("builtin:seed004_nominal")
ALL = parameter_columns(ESTIMATE_NAMES)
#: The radial truth: 0.005 px at the centre, 0.4 px at the half-diagonal (coma and astigmatism of a wide lens whose
#: corners are 80x the centre's variance); the given noise 0.005-0.05 px (bright stars: the floor is most of it).
B_PX2, C_PX2 = 0.005**2, 0.4**2 - 0.005**2
SIGMA_RANGE_PX = (0.005, 0.05)
SESSIONS = 8
FRAMES = 500


def radial_session(seed: int, frames: int = FRAMES):
    """(data with the given sigma_px, the noise-free data carrying each star's true noise, the true attitudes)."""
    ss = synthetic_session(CAMERA, frames, noise_px=0.0, seed=seed)
    rng = np.random.default_rng(30_000 + seed)
    n = ss.data.n_obs
    sigma = np.exp(rng.uniform(*np.log(SIGMA_RANGE_PX), n))
    frame = ss.data.frame_index()
    truth = build_data(ss.x_true_px, ss.y_true_px, ss.data.r, frame, sigma_px=sigma)
    true = np.sqrt(sigma**2 + B_PX2 + C_PX2 * field_q(truth, field_geometry(NOMINAL)))
    x = ss.x_true_px + true * rng.standard_normal(n)
    y = ss.y_true_px + true * rng.standard_normal(n)
    noise_free = build_data(ss.x_true_px, ss.y_true_px, ss.data.r, frame, sigma_px=true)
    return build_data(x, y, ss.data.r, frame, sigma_px=sigma), noise_free, ss.attitudes_true


def _blocks(noise_free, attitudes, w):
    return accumulate_normals(noise_free, CAMERA.model_vector(), attitudes, ALL, w, np.ones(ALL.size))


def sandwich_ratio(noise_free, attitudes, w_fit: np.ndarray) -> float:
    """sqrt(tr(F Cov_w) / K): Cov_w = S_w^-1 M S_w^-1 the first-order covariance of the camera fitted with weights
    ``w_fit`` (attitudes eliminated per frame: the gradient of star i is G_i = J_i - P_i A_f^-1 B_f^T, and
    M = sum w_i^2 v_i G_i^T G_i with v_i its true variance), F the Fisher information of the true noise. 1 at the
    Cramer-Rao bound; the expected NEES / K of the fit is its square."""
    v = noise_free.sigma_px**2
    b1, b2 = _blocks(noise_free, attitudes, w_fit), _blocks(noise_free, attitudes, w_fit**2 * v)
    m = inverse_3x3(b1.a) @ b1.b.transpose(0, 2, 1)
    cross = np.einsum("mkj,mjl->kl", b2.b, m)
    middle = b2.u - cross - cross.T + np.einsum("mjk,mjl,mlq->kq", m, b2.a, m)
    s_inv = np.linalg.inv(reduced_normal(b1)[0])
    fisher = reduced_normal(_blocks(noise_free, attitudes, 1.0 / v))[0]
    return float(np.sqrt(np.trace(fisher @ s_inv @ middle @ s_inv) / ALL.size))


def nees(out, noise_free, attitudes) -> float:
    err = (out.theta - CAMERA.model_vector())[ALL]
    return float(err @ reduced_normal(_blocks(noise_free, attitudes, 1.0 / noise_free.sigma_px**2))[0] @ err)


@pytest.fixture(scope="module")
def radial_runs():
    """Per session: (auto outcome, constant outcome, components at the auto result, sandwich ratios of the auto and
    constant weights, NEES of the auto and constant fits)."""
    runs = []
    for seed in range(SESSIONS):
        data, noise_free, att = radial_session(seed)
        auto = calibrate(data, NOMINAL, estimate=ESTIMATE_NAMES)
        const = calibrate(data, NOMINAL, estimate=ESTIMATE_NAMES, noise_model="constant")
        kept = data.select(~(auto.voted_out | auto.gated))[0]
        comps = variance_components(chunk_noise_sums(kept, auto.theta, auto.noise_weights))
        ratios = [
            sandwich_ratio(noise_free, att, 1.0 / with_floor(data, o.noise_weights).sigma_px ** 2)
            for o in (auto, const)
        ]
        runs.append((auto, const, comps, *ratios, nees(auto, noise_free, att), nees(const, noise_free, att)))
    return runs


def _bins(n: int, seed: int, b: float, c: float):
    """Per-star 'bins' as the sums carry them: r = 2 (a star's two axes, no attitude), |e|^2 = v chi-square(2)."""
    rng = np.random.default_rng(seed)
    s2 = np.exp(rng.uniform(*np.log((0.005, 0.5)), n)) ** 2
    q = rng.uniform(0.0, 1.0, n)
    e2 = (s2 + b + c * q) * rng.chisquare(2.0, n)
    return np.full(n, 2.0), e2, s2, q


def _sums(r, e2, s2, q) -> NoiseSums:
    return NoiseSums(np.arange(r.size), r, e2, r * s2, r * q)


def test_the_score_is_the_likelihoods_gradient():
    """Central differences of -2 log L (step 1e-6 of each component) against the analytic gradient, to 1e-5
    relative: the differences' own error is their rounding, eps |-2 log L| / h = 4.5e-7 (|-2 log L| ~2000 here), and
    their truncation, largest for the small b (measured 8.5e-8 relative at most, on components of 3.5-720)."""
    r, e2, s2, q = _bins(500, 1, 0.01, 0.05)
    t = np.column_stack([s2, np.ones_like(s2), q])
    theta = np.array([1.1, 0.012, 0.04])
    numeric = []
    for k in range(3):
        d = np.zeros(3)
        d[k] = 1e-6
        numeric.append((minus_two_log_l(r, e2, t, theta + d) - minus_two_log_l(r, e2, t, theta - d)) / 2e-6)
    assert np.allclose(_gradient(r, e2, t, theta), numeric, rtol=1e-5)


def test_the_fisher_information_is_half_the_expected_hessian():
    """The standard errors' Fisher information F = 1/2 sum r T T^T / v^2 against central second differences of
    -2 log L (step 1e-5 of each component) at the expected residuals |e|^2 = r v, where the Hessian of -2 log L is
    2F exactly: to 1e-4 (the differences' truncation error, measured 1.4e-5 at this step); the errors are the
    square roots of the inverse's diagonal."""
    r, _, s2, q = _bins(500, 1, 0.01, 0.05)
    t = np.column_stack([s2, np.ones_like(s2), q])
    theta = np.array([1.1, 0.012, 0.04])
    e2 = r * (t @ theta)
    h = 1e-5 * np.eye(3)
    hessian = np.array(
        [
            [
                minus_two_log_l(r, e2, t, theta + h[i] + h[j])
                - minus_two_log_l(r, e2, t, theta + h[i] - h[j])
                - minus_two_log_l(r, e2, t, theta - h[i] + h[j])
                + minus_two_log_l(r, e2, t, theta - h[i] - h[j])
                for j in range(3)
            ]
            for i in range(3)
        ]
    ) / (4e-10)
    err = fisher_errors(r, t, theta, np.ones(3, dtype=bool))
    assert np.allclose(err, np.sqrt(np.diag(np.linalg.inv(0.5 * hessian))), rtol=1e-4, atol=0.0)


def _bounded_reference(r, e2, t) -> float:
    """The minimum of -2 log L over a >= 1e-6, b, c >= 0 by scipy's L-BFGS-B (its own convergence: ftol 1e-15)."""
    ref = scipy.optimize.minimize(
        lambda p: minus_two_log_l(r, e2, t, p),
        [1.0, 0.01, 0.01],
        bounds=[(1e-6, None), (0.0, None), (0.0, None)],
        method="L-BFGS-B",
        options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10_000},
    )
    return float(ref.fun)


@pytest.mark.parametrize(("b", "c"), [(0.01, 0.05), (0.0, 0.09), (0.01, 0.0)])
def test_fisher_scoring_finds_the_bounded_maximum(b, c):
    """The scoring's (a, b, c) against scipy's L-BFGS-B on the same -2 log L with b, c >= 0: the same value to 1e-6
    (interior, and each of b and c at the boundary)."""
    r, e2, s2, q = _bins(3000, 2, b, c)
    t = np.column_stack([s2, np.ones_like(s2), q])
    ours = radial_components(r, e2, t, np.array([1.0, 0.01, 0.0]))
    assert minus_two_log_l(r, e2, t, ours) <= _bounded_reference(r, e2, t) + 1e-6
    assert np.all(ours >= 0.0)


def test_the_choice_has_the_mixtures_false_alarm_rate():
    """400 draws with a constant floor (0.1 px, inside its range): the likelihood ratio is 1/2 chi-square(0) +
    1/2 chi-square(1) (Self and Liang 1987), so P(LR > 2.706) = 0.05: 20 of 400 expected, binomial sd 4.4, held to
    8-34 (-2.8 to +3.2 sd); the radial model chosen (LR > 9.55: 1e-3) in 0.4 expected, held to at most 3 (Poisson
    P(>= 4) = 8e-4). With no floor at all: test_no_floor_and_sigma_growing_with_radius_keeps_the_false_alarm_rate."""
    lrs = np.array([variance_components(_sums(*_bins(2000, 100 + k, 0.01, 0.0))).lr for k in range(400)])
    assert 8 <= np.count_nonzero(lrs > scipy.stats.chi2.isf(0.10, 1)) <= 34
    assert np.count_nonzero(lrs > LR_CRITICAL) <= 3
    assert LR_CRITICAL == pytest.approx(scipy.stats.chi2.isf(0.002, 1), abs=1e-4)


def test_the_sums_do_not_depend_on_how_the_frames_are_split():
    """The sums of two halves of a session merged are the sums of the whole (same bins, sums to 1e-9)."""
    data, _, _ = radial_session(3, frames=40)
    noise = field_geometry(NOMINAL)
    whole = chunk_noise_sums(data, CAMERA.model_vector(), noise)
    parts = chunk_noise_sums(frames_of(data, 0, 17), CAMERA.model_vector(), noise).merge(
        chunk_noise_sums(frames_of(data, 17, 40), CAMERA.model_vector(), noise)
    )
    assert np.array_equal(whole.key, parts.key)
    for a, b in zip(whole.columns()[1:], parts.columns()[1:], strict=True):
        assert np.allclose(a, b, rtol=1e-9, atol=0.0)


def test_the_radial_floor_is_chosen_and_recovered_within_its_standard_errors(radial_runs):
    """Each session: the radial model chosen, b, c and the scale^2 within 3 of their standard errors (inverse Fisher
    information of the three components) of the truth; over the 8, the spread of c agrees with its stated error (the
    ratio of the two within the 99 % range of sqrt(chi-square(7) / 7) from sampling alone: 0.376-1.702, from scipy;
    the 95 % range is 0.491-1.512)."""
    cs, c_sigmas = [], []
    for auto, _, comps, *_ in radial_runs:
        assert auto.noise_model["model"] == "radial" and comps.model == "radial", auto.noise_model
        assert abs(comps.floor_px**2 - B_PX2) <= 3.0 * comps.b_sigma_px2, comps
        assert abs(comps.edge_px2 - C_PX2) <= 3.0 * comps.c_sigma_px2, comps
        assert abs(comps.scale**2 - 1.0) <= 3.0 * comps.a_sigma, comps  # the given sigma_px is the rest: scale 1
        assert auto.noise_model["lr"] > LR_CRITICAL
        cs.append(comps.edge_px2)
        c_sigmas.append(comps.c_sigma_px2)
    lo, hi = np.sqrt(scipy.stats.chi2.ppf([0.005, 0.995], len(cs) - 1) / (len(cs) - 1))
    assert lo <= np.std(cs, ddof=1) / np.mean(c_sigmas) <= hi, (np.std(cs, ddof=1), np.mean(c_sigmas))


def test_the_radial_weights_reach_the_bound_where_the_constant_ones_fall_short(radial_runs):
    """First order (the sandwich covariance of the weights each fit used, per session): the radial floor's within
    1.1x of the Cramer-Rao bound of the true noise (measured 1.000), the constant floor's beyond it (measured 1.19-1.20:
    the corner stars' weights 10-20x too high, the centre's too low). The fits themselves: sqrt(mean NEES / K) over
    the 8 sessions (chi-square(10) each: sd of the ratio ~0.08) of the radial within 1.1x."""
    for _, _, _, auto_ratio, const_ratio, _, _ in radial_runs:
        assert auto_ratio <= 1.1, auto_ratio
        assert const_ratio > 1.1, const_ratio
    ratio = np.sqrt(np.mean([run[5] for run in radial_runs]) / ALL.size)
    assert ratio <= 1.1, f"{ratio:.3f}x the bound"


def test_the_sandwich_is_the_spread_of_weighted_fits():
    """The sandwich of :func:`sandwich_ratio` against direct draws: 300 noise draws on a noise-free session (200
    frames) solved by one weighted Gauss-Newton step from the truth (the fit's linearisation), mis-weighted by a
    constant floor; the mean NEES / K of the draws (relative sd ~sqrt(2 / (K 300)) = 2.6 % for chi-square-like
    NEES) within 10 % of the sandwich's square."""
    _, noise_free, att = radial_session(5, frames=200)
    v = noise_free.sigma_px**2
    w = np.full(v.size, 1.0 / v.mean())  # one weight for every star: the floor taken constant
    rng = np.random.default_rng(7)
    fisher = reduced_normal(_blocks(noise_free, att, 1.0 / v))[0]
    values = []
    for _ in range(300):
        noise = np.sqrt(v)[:, None] * rng.standard_normal((v.size, 2))
        blocks = accumulate_normals(noise_free, CAMERA.model_vector(), att, ALL, w, np.ones(ALL.size), values=noise)
        s, rhs, _ = reduced_normal(blocks)
        d = np.linalg.solve(s, rhs)
        values.append(float(d @ fisher @ d))
    measured = np.mean(values) / ALL.size
    assert measured == pytest.approx(sandwich_ratio(noise_free, att, w) ** 2, rel=0.10)


@pytest.mark.parametrize("floor_px", [0.1, 0.0])
def test_a_constant_floor_keeps_the_constant_model_and_its_fit(floor_px):
    """Sessions of a constant floor (0.1 px) and of none (tests/test_calibration_noise_floor.py's): the constant
    model chosen in each of 3, and the fit bit for bit the constant model's (the same weights: no regression)."""
    for seed in range(3):
        data = floor_session(seed, floor_px)[0]
        auto = calibrate(data, NOMINAL, estimate=ESTIMATE_NAMES)
        const = calibrate(data, NOMINAL, estimate=ESTIMATE_NAMES, noise_model="constant")
        assert auto.noise_model["model"] == "constant", auto.noise_model
        assert auto.noise_model["lr"] < LR_CRITICAL
        assert np.array_equal(auto.theta, const.theta)
        assert auto.noise_floor_px == const.noise_floor_px == auto.noise_floor_edge_px


def test_the_result_says_which_model_and_its_values(radial_runs):
    """The result file's extras carry the model, its components with their standard errors and the likelihood
    ratio; the report's line names the radial floor with them."""
    auto = radial_runs[0][0]
    extras = result_extras(auto)
    record = extras["noise_model"]
    assert record["model"] == "radial" and record["lr"] > record["lr_critical"] == LR_CRITICAL
    assert record["edge_sigma_px2"] > 0 and record["floor_edge_px"] > record["floor_centre_px"]
    assert extras["noise_floor_edge_px"] > extras["noise_floor_px"]
    text = noise_model_text(record)
    assert "growing with field radius" in text and f"{record['floor_edge_px']:.4f} px" in text


def test_the_radial_floor_does_not_depend_on_how_the_frames_are_chunked():
    """A radial session (200 frames) calibrated in memory and as three chunks of frames: the same model, the same
    components (1e-9 relative: only the summation order differs) and the same camera (tests/test_calibration_chunked.
    py's tolerance)."""
    data = radial_session(6, frames=200)[0]
    whole = calibrate(data, NOMINAL, estimate=ESTIMATE_NAMES)
    chunks = ChunkSource(tuple(frames_of(data, a, b) for a, b in ((0, 61), (61, 140), (140, 200))))
    parts = calibrate_chunks(chunks, NOMINAL, ESTIMATE_NAMES)
    assert whole.noise_model["model"] == parts.noise_model["model"] == "radial"
    for key in ("floor_px2", "edge_px2", "lr"):
        assert parts.noise_model[key] == pytest.approx(whole.noise_model[key], rel=1e-9, abs=1e-15)
    assert_same_camera(whole, parts)


def test_stars_of_one_sigma_px_leave_the_centre_floor_unseparated_and_the_growth_stated():
    """Every star given the same sigma_px (0.05 px): the scale and b cannot be told apart (their errors inf, as the
    constant floor's are), c still can: chosen, its error finite and the truth within 3 of it."""
    data = radial_session(1, frames=200)[0]
    same = build_data(data.x_px, data.y_px, data.r, data.frame_index(), sigma_px=np.full(data.n_obs, 0.05))
    record = calibrate(same, NOMINAL, estimate=ESTIMATE_NAMES).noise_model
    assert record["model"] == "radial"
    assert record["floor_sigma_px2"] == np.inf
    assert 0.0 < record["edge_sigma_px2"] < np.inf
    assert abs(record["edge_px2"] - C_PX2) <= 3.0 * record["edge_sigma_px2"]


@pytest.mark.parametrize(("seed", "b_start"), [(45, 0.02), (133, 0.02), (40, 0.2), (3, 1e-14)])
def test_scoring_does_not_stop_where_a_step_is_cut_at_the_boundary(seed, b_start):
    """Sessions whose maximum has b = 0 (300 stars, no floor, c = 0.09): a step cut short where b reaches 0 (or a
    start at b = 1e-14) moved little and ended the scoring there, 0.01-0.33 above the bounded minimum of -2 log L
    (a 0.907 for 0.820). Now: L-BFGS-B's value to 1e-6 (its own convergence, ftol 1e-15 of ~1e3), and the
    Karush-Kuhn-Tucker conditions: the gradient 0 on the positive components (1e-4 of its terms' size: they are
    O(r / v) ~ 1e3), not negative on those at 0."""
    rng = np.random.default_rng(seed)
    n = 3000 if b_start < 1e-9 else 300
    s2 = np.exp(rng.uniform(*np.log((0.005, 0.5)), n)) ** 2
    q = rng.uniform(0.0, 1.0, n)
    r = np.full(n, 2.0)
    e2 = (s2 + 0.09 * q) * rng.chisquare(2.0, n)
    t = np.column_stack([s2, np.ones_like(s2), q])
    ours = radial_components(r, e2, t, np.array([1.0, b_start, 0.0]))
    assert minus_two_log_l(r, e2, t, ours) <= _bounded_reference(r, e2, t) + 1e-6
    grad = _gradient(r, e2, t, ours)
    scale = np.abs(t).T @ (r / (t @ ours))
    assert np.all(np.abs(grad[ours > 0.0]) <= 1e-4 * scale[ours > 0.0]), (ours, grad)
    assert np.all(grad[ours == 0.0] >= -1e-4 * scale[ours == 0.0]), (ours, grad)


def _cone_projection_lr(m: np.ndarray, draws: int, seed: int) -> np.ndarray:
    """Asymptotic LR draws by direct projection (not the polar formula): Z ~ N(0, m^-1) in (b, c), LR = the
    m-distance^2 of Z to the b ray less that to the quadrant b, c >= 0 (its nearest of the two edge rays, or 0
    inside)."""
    z = np.random.default_rng(seed).multivariate_normal(np.zeros(2), np.linalg.inv(m), draws)

    def dist2(p):
        d = z - p
        return np.einsum("ni,ij,nj->n", d, m, d)

    on_b = np.column_stack([np.maximum(z @ m[:, 0] / m[0, 0], 0.0), np.zeros(draws)])
    on_c = np.column_stack([np.zeros(draws), np.maximum(z @ m[:, 1] / m[1, 1], 0.0)])
    to_quadrant = np.where(np.all(z >= 0.0, axis=1), 0.0, np.minimum(dist2(on_b), dist2(on_c)))
    return dist2(on_b) - to_quadrant


@pytest.mark.parametrize("phi_deg", [35.0, 90.0, 148.0])
def test_the_boundary_tail_is_the_projections_distribution(phi_deg):
    """:func:`boundary_tail` (the polar formula) against 2e5 direct projections on a metric of that angle, at
    x = 2.706 and 9.55: within 4 binomial sd of the draws; at 90 deg (b and c orthogonal) it is the equal mixture of
    Self and Liang to 1e-6 of itself (the 20000-point grid)."""
    phi = np.radians(phi_deg)
    m = np.array([[1.0, np.cos(phi)], [np.cos(phi), 1.0]])
    lrs = _cone_projection_lr(m, 200_000, 11)
    for x in (2.706, LR_CRITICAL):
        p = boundary_tail(x, phi)
        assert abs(np.mean(lrs > x) - p) <= 4.0 * np.sqrt(p * (1.0 - p) / lrs.size) + 1.0 / lrs.size, (x, p)
    assert boundary_tail(LR_CRITICAL, np.pi / 2) == pytest.approx(0.5 * scipy.stats.chi2.sf(LR_CRITICAL, 1), rel=1e-6)


def test_no_floor_and_sigma_growing_with_radius_keeps_the_false_alarm_rate():
    """400 draws with no floor at all (b = c = 0) and sigma_px = 0.02 (1 + q): the b and c directions at ~148 deg in
    the Fisher metric, where 9.55 would choose the radial floor 2.4x as often as claimed (2.4e-3, by the polar
    formula). The threshold used is that angle's 1e-3 point (~11.2), and the rate at 2.706 is the formula's (~0.09,
    not the equal mixture's 0.05): within 3 binomial sd (0.043) of it; the radial model chosen at most 3 times (0.4
    expected: Poisson P(>= 4) = 8e-4)."""
    lrs, criticals, tails = [], [], []
    for k in range(400):
        rng = np.random.default_rng(500 + k)
        n = 2000
        q = rng.uniform(0.0, 1.0, n)
        s2 = (0.02 * (1.0 + q) * np.exp(rng.normal(0.0, 0.05, n))) ** 2
        r = np.full(n, 2.0)
        comps = variance_components(_sums(r, s2 * rng.chisquare(2.0, n), s2, q))
        lrs.append(comps.lr)
        criticals.append(comps.lr_critical)
        if k == 0:
            t = np.column_stack([s2, np.ones_like(s2), q])
            fisher = 0.5 * (t * (r / s2**2)[:, None]).T @ t
            mb = fisher[1:, 1:] - np.outer(fisher[1:, 0], fisher[0, 1:]) / fisher[0, 0]
            phi = np.arccos(mb[0, 1] / np.sqrt(mb[0, 0] * mb[1, 1]))
            tails = [boundary_tail(2.706, phi), boundary_tail(LR_CRITICAL, phi)]
    lrs, criticals = np.array(lrs), np.array(criticals)
    assert tails[1] > 2.0e-3  # the defect this guards against: 9.55 alone would be 2x too lenient here
    assert np.all(criticals > LR_CRITICAL + 1.0)
    assert abs(np.mean(lrs > 2.706) - tails[0]) <= 3.0 * np.sqrt(tails[0] * (1.0 - tails[0]) / lrs.size)
    assert np.count_nonzero(lrs > criticals) <= 3


def test_stars_of_one_sigma_px_state_no_precision_for_the_constant_floor_either():
    """Per-star bins of one sigma_px (0.05 px; the sums' s2 then exactly equal): the constant floor's Fisher
    information is singular, and the inverse of it had stated the scale and floor to 0 +- 0 (the negative diagonal
    clipped); their errors are inf, as the radial model's are, and a sigma_px spread of 30 % gives finite ones."""
    rng = np.random.default_rng(0)
    n = 2000
    q, r = rng.uniform(0.0, 1.0, n), np.full(n, 2.0)
    for spread, finite in ((0.0, False), (0.3, True)):
        s2 = (0.05 * (1.0 + spread * rng.standard_normal(n))) ** 2
        comps = variance_components(_sums(r, (s2 + 0.01) * rng.chisquare(2.0, n), s2, q))
        assert comps.model == "constant"
        assert np.isfinite([comps.a_sigma, comps.b_sigma_px2]).tolist() == [finite, finite], comps
        assert comps.a_sigma > 0.0 and comps.b_sigma_px2 > 0.0


def test_an_unknown_noise_model_is_refused_with_or_without_sigma_px():
    """noise_model is checked before any pass: 'radial' (not a choice: the data choose it under 'auto') was refused
    only when the session had sigma_px, and then as 'calibration failed'; now a one-line option error either way."""
    from hostlink.calibration.outcome import check_run_options
    from hostlink.errors import UserError

    data = synthetic_session(CAMERA, 20, noise_px=0.05, seed=1).data
    assert data.sigma_px is None
    given = build_data(data.x_px, data.y_px, data.r, data.frame_index(), sigma_px=np.full(data.n_obs, 0.05))
    for session in (data, given):
        with pytest.raises(ValueError, match="unknown noise model 'radial'"):
            calibrate(session, NOMINAL, estimate=ESTIMATE_NAMES, noise_model="radial")
    with pytest.raises(
        UserError, match="^noise_model: unknown noise model 'Constant' \\(choose from auto, constant\\)$"
    ):
        check_run_options(None, 100, "Constant")
    check_run_options(None, 100, "constant")
