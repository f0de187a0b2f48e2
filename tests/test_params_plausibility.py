"""Physical plausibility of a parameter set (onboard.params.check_plausible), the one check the host runs before
sending a set and the sensor runs before committing it: a one-to-one mapping over the whole detector, a bounded
distortion displacement, the principal point on the detector and the focal length near the sensor's design."""

import dataclasses

import numpy as np
import pytest

from hostlink.sky.simulate import seed004_camera
from onboard.params import (
    CameraParams,
    Distortion,
    ParameterError,
    PlausibilityLimits,
    check_plausible,
    farthest_corner_radius2_px2,
    max_distortion_displacement_px,
    min_mapping_determinant,
    min_radial_slope,
)
from onboard.prior import validate_sigma

CAMERA = seed004_camera()
DESIGN = PlausibilityLimits(design_focal_length_mm=70.0)
#: OpenCV's normalised coefficients (k1 = -0.12, k2 = 0.3) written into the px^-2, px^-4 fields (issue 15)
OPENCV_SIZED = dataclasses.replace(CAMERA, distortion=Distortion(k1=-0.12, k2=0.3))
#: every Weng term at a realistic size (0.5-2 px at the detector corner), as tests/test_fixedpoint_camera.py
REALISTIC = dataclasses.replace(
    CAMERA, distortion=Distortion(k1=-2.0e-10, k2=3.5e-15, k3=-4e-21, p1=2e-7, p2=-1.5e-7, s1=1e-7, s2=-2e-7)
)


def refusal(params, limits=DESIGN, dtype=np.float64) -> str:
    with pytest.raises(ParameterError) as info:
        check_plausible(params, limits, dtype)
    text = str(info.value)
    assert "\n" not in text  # one line
    return text


@pytest.mark.parametrize("params", [CAMERA, REALISTIC], ids=["seed004", "realistic-all-terms"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_real_cameras_are_plausible_in_both_precisions(params, dtype):
    check_plausible(params, DESIGN, dtype)  # raises if not


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_opencv_sized_distortion_is_refused_as_not_one_to_one(dtype):
    text = refusal(OPENCV_SIZED, dtype=dtype)
    assert text.startswith("distortion: radial mapping is not one-to-one")


def test_the_fold_of_opencv_sized_distortion_is_invisible_to_the_jacobian_grid_alone():
    # why the exact radial test exists: the map folds at r ~ 1 px, between the 64 px grid points, and outside the
    # fold both Jacobian factors are negative, so the grid's determinant is positive everywhere
    assert min_mapping_determinant(OPENCV_SIZED)[0] > 0
    assert min_radial_slope(OPENCV_SIZED.distortion, farthest_corner_radius2_px2(OPENCV_SIZED))[0] < 0


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_one_to_one_but_huge_distortion_is_refused_by_the_displacement_bound(dtype):
    text = refusal(dataclasses.replace(CAMERA, distortion=Distortion(k1=-0.12)), dtype=dtype)
    assert text.startswith("distortion: implausible: displacement") and "5% of the half-diagonal" in text


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_displacement_bound_is_five_percent_of_the_half_diagonal(dtype):
    half_diagonal = 0.5 * np.hypot(1024, 1024)  # 724.1 px
    r2 = farthest_corner_radius2_px2(CAMERA)  # the farthest corner from (500, 530): r = 745 px
    k1_edge = 0.05 * half_diagonal / np.sqrt(r2) ** 3  # pure k1 moves that corner by exactly the bound
    check_plausible(dataclasses.replace(CAMERA, distortion=Distortion(k1=-0.99 * k1_edge)), DESIGN, dtype)
    text = refusal(dataclasses.replace(CAMERA, distortion=Distortion(k1=-1.01 * k1_edge)), dtype=dtype)
    assert "bound 36.2 px" in text


def test_the_focal_length_must_be_within_five_percent_of_the_design():
    check_plausible(CAMERA.with_focal_length_mm(70.0 * 1.049), DESIGN)
    assert refusal(CAMERA.with_focal_length_mm(70.0 * 1.051)).startswith("focal_length_mm: implausible")
    assert "design value 70 mm" in refusal(CAMERA.with_focal_length_mm(35.0))
    check_plausible(CAMERA.with_focal_length_mm(35.0), None)  # a host that does not know the design skips the rule


def test_an_off_detector_principal_point_is_refused():
    assert refusal(dataclasses.replace(CAMERA, principal_point_px=(1100.0, 530.0))).startswith("principal_point_px[0]")


def test_the_radial_slope_minimum_matches_a_dense_finite_difference_scan():
    """Outside check of the closed form: r'(r) = r (1 - k1 r^2 - k2 r^4 - k3 r^6) sampled on 200 001 radii, slope by
    second-order differences (measured agreement 1e-10 relative; 1e-8 leaves room for the h^2 term). The middle case
    has its minimum inside the interval (r = 447 px, a root of P'), the other two at the far corner."""
    for dist in (Distortion(k1=-0.12, k2=0.3), Distortion(k1=2e-7, k2=-3e-13, k3=1e-19), REALISTIC.distortion):
        s_max = farthest_corner_radius2_px2(CAMERA)
        r = np.linspace(0.0, np.sqrt(s_max), 200_001)
        rp = r * (1 - dist.k1 * r**2 - dist.k2 * r**4 - dist.k3 * r**6)
        slope = np.gradient(rp, r, edge_order=2)
        closed, _ = min_radial_slope(dist, s_max)
        assert closed == pytest.approx(slope.min(), rel=1e-8)


def test_float32_displacement_agrees_with_float64():
    d64, _ = max_distortion_displacement_px(REALISTIC, np.float64)
    d32, _ = max_distortion_displacement_px(REALISTIC, np.float32)
    assert d32 == pytest.approx(d64, rel=1e-5)  # float32 evaluation of a cubic in r: a few ulps of 1e-7 each


def test_a_narrow_field_camera_with_its_own_design_is_plausible():
    narrow = CameraParams(200.0, 3.45, (2060.0, 2030.0), (4096, 4096), Distortion(k1=-4.0e-11))
    check_plausible(narrow, PlausibilityLimits(200.0))


def host_verdict(table):
    """The field a float64 (host) check refuses ``table`` for, or None."""
    from onboard import banks

    try:
        with np.errstate(all="ignore"):
            params = banks.table_to_params(table)
            check_plausible(params, DESIGN, np.float64)
            validate_sigma(banks.table_to_sigma(table))
    except ParameterError as exc:
        return exc.field
    return None


def test_the_sensor_check_answers_every_table_with_a_verdict_never_an_exception():
    """5 000 seeded tables: random bit patterns, special values (NaN, inf, 0, huge, tiny) and perturbations of a real
    set, each field independently; the sensor's check (float32) returns None or a one-line refusal, warns about
    nothing, and refuses exactly what the host's float64 check refuses, for the same field (none of these sets lies
    within float32 rounding of a bound)."""
    import warnings

    from onboard import banks
    from protocol.param_table import decode_table, encode_table

    rng = np.random.default_rng(15)
    base = decode_table(banks.params_to_table(REALISTIC)).astype(np.float64)
    special = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e38, -1e38, 1e-38, 1.0, -1.0, 2.0**24, 2.0**24 + 2])
    verdicts = {"accepted": 0, "refused": 0}
    for _ in range(5000):
        values = base.copy()
        for i in np.flatnonzero(rng.random(len(values)) < 0.3):
            kind = rng.integers(3)
            if kind == 0:
                with np.errstate(invalid="ignore"):  # a signalling-NaN bit pattern
                    values[i] = np.frombuffer(rng.integers(0, 256, 4, dtype=np.uint8).tobytes(), "<f4")[0]
            elif kind == 1:
                values[i] = special[rng.integers(len(special))]
            else:
                values[i] = base[i] * (1 + rng.normal(0, 0.1)) + rng.normal(0, 1e-9)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            refusal = banks.check_table(encode_table(values), DESIGN)
        host = host_verdict(encode_table(values))
        assert (refusal is None) == (host is None) and (refusal is None or refusal.text.split(":")[0] == host), host
        if refusal is None:
            verdicts["accepted"] += 1
        else:
            assert refusal.code == banks.NakCode.INVALID_PARAMS and "\n" not in refusal.text and refusal.text
            verdicts["refused"] += 1
    assert verdicts["accepted"] > 100 and verdicts["refused"] > 1000  # both branches exercised
