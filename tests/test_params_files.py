"""Camera parameter files: load, validate, save; the seed 004 sign conversion; one-line errors naming the field."""

import json
import math
import subprocess
import sys

import pytest

from hostlink.errors import UserError
from hostlink.files.params import load_params, save_params
from onboard.params import (
    CameraParams,
    Distortion,
    ParameterError,
    distortion_from_seed004,
    distortion_to_seed004,
    params_from_dict,
    params_to_dict,
    validate_params,
)

GOOD = {
    "focal_length_mm": 70.2262,
    "pixel_pitch_um": 12.0,
    "principal_point_px": [500.0, 530.0],
    "image_size_px": [1024, 1024],
    "distortion": {"k1": -2e-10, "k2": 3.5e-15},
}


def test_missing_distortion_keys_are_zero_and_round_trip_is_exact(tmp_path):
    params = params_from_dict(GOOD)
    assert params.distortion.k3 == 0 and params.distortion.s2 == 0
    path = tmp_path / "cam.json"
    save_params(path, params, extras={"method": "test", "sigma": {"f": 1e-4}})
    again = load_params(path)
    assert again == params
    data = json.loads(path.read_text())
    assert data["method"] == "test" and set(data["distortion"]) == {"k1", "k2", "k3", "p1", "p2", "s1", "s2"}


@pytest.mark.parametrize(
    "mutation, field",
    [
        ({"focal_length_mm": -70.0}, "focal_length_mm"),
        ({"focal_length_mm": 0.0}, "focal_length_mm"),
        ({"focal_length_mm": math.nan}, "focal_length_mm"),
        ({"pixel_pitch_um": math.inf}, "pixel_pitch_um"),
        ({"principal_point_px": [1200.0, 530.0]}, "principal_point_px[0]"),
        ({"principal_point_px": [500.0, -0.6]}, "principal_point_px[1]"),
        ({"principal_point_px": [500.0]}, "principal_point_px"),
        ({"image_size_px": [1024.5, 1024]}, "image_size_px[0]"),
        ({"distortion": {"k1": "big"}}, "distortion.k1"),
        ({"distortion": {"q9": 1.0}}, "distortion.q9"),
        ({"distortion": {"k1": math.nan}}, "distortion.k1"),
        # k1 = +2e-6 px^-2: at the corner (r ~ 724 px) the correction folds the image back (d(u')/du < 0)
        ({"distortion": {"k1": 2e-6}}, "distortion"),
    ],
)
def test_invalid_values_are_refused_naming_the_field(mutation, field):
    data = {**GOOD, **mutation}
    with pytest.raises(ParameterError) as info:
        params_from_dict(data)
    assert info.value.field == field
    assert "\n" not in str(info.value)


def test_missing_key_is_named():
    data = dict(GOOD)
    del data["pixel_pitch_um"]
    with pytest.raises(ParameterError, match="pixel_pitch_um: missing"):
        params_from_dict(data)


def test_principal_point_on_the_detector_edge_is_accepted():
    validate_params(params_from_dict({**GOOD, "principal_point_px": [-0.5, 1023.5]}))


def test_file_errors_are_one_line_user_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        load_params(bad)
    with pytest.raises(UserError, match="no such file"):
        load_params(tmp_path / "missing.json")
    nan = tmp_path / "nan.json"
    nan.write_text(json.dumps({**GOOD, "focal_length_mm": float("nan")}))  # Python writes NaN
    with pytest.raises(UserError, match="focal_length_mm: must be finite"):
        load_params(nan)


def test_seed004_conversion_flips_the_radial_signs_and_inverts():
    """Seed 004 eq. 6: x_hat = x_d + (x_d - x0)(k1 r^2 + k2 r^4). Ours: u' = u - u (k1 r^2 + k2 r^4). So the same
    ideal point needs k = -k_seed. Checked on a point, not just on the signs."""
    from onboard.camera import ideal_offsets

    d = distortion_from_seed004(2.0e-10, -3.5e-15)
    assert (d.k1, d.k2) == (-2.0e-10, 3.5e-15)
    assert distortion_to_seed004(d) == (2.0e-10, -3.5e-15)
    cam = CameraParams(70.2262, 12.0, (500.0, 530.0), (1024, 1024), d)
    xd, yd = 900.0, 100.0
    r2 = (xd - 500.0) ** 2 + (yd - 530.0) ** 2
    x_hat = xd + (xd - 500.0) * (2.0e-10 * r2 - 3.5e-15 * r2**2)
    import numpy as np

    u_i, _ = ideal_offsets(np.array([xd]), np.array([yd]), cam.model_vector())
    assert abs((u_i[0] + 500.0) - x_hat) < 1e-12


def test_vector_round_trip_keeps_every_field():
    # every field distinct, distortion of a real lens (k2, k3 scaled by px^-2 per power: one-to-one over the detector)
    scale = [1.0, 1e-7, 1e-14, 1.0, 1.0, 1.0, 1.0]
    params = CameraParams(
        50.0, 5.5, (1000.0, 990.0), (2048, 2048), Distortion(*[1e-9 * (k + 1) * scale[k] for k in range(7)])
    )
    again = params.with_vector(params.vector())
    assert again == params
    assert params_from_dict(params_to_dict(params)) == params
    assert abs(params.model_vector()[0] - 1000 * 50.0 / 5.5) < 1e-9


def test_cli_reports_bad_parameter_file_in_one_line_with_nonzero_exit(tmp_path):
    bad = tmp_path / "neg.json"
    bad.write_text(json.dumps({**GOOD, "focal_length_mm": -1.0}))
    session = tmp_path / "s.csv"
    session.write_text("frame,t_utc,star_id,x_px,y_px\n0,2026-03-14T02:10:00.000Z,1,10,10\n")
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "hostlink.cli",
            "replay",
            str(session),
            "--nominal",
            str(bad),
            "--out",
            str(tmp_path / "o.json"),
        ],
        capture_output=True,
        text=True,
    )
    assert out.returncode != 0
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "focal_length_mm" in lines[0] and "Traceback" not in out.stderr


def test_model_vector_round_trip_converts_focal_length_between_px_and_mm():
    params = CameraParams(50.0, 5.5, (1000.0, 990.0), (2048, 2048), Distortion(k1=1e-9, s2=-2e-8))
    again = params.with_model_vector(params.model_vector())
    # f -> F = 1000 f / p -> F p / 1000 rounds twice: a few float64 ulps
    assert abs(again.focal_length_mm - params.focal_length_mm) < 1e-13 * params.focal_length_mm
    assert again.with_focal_length_mm(params.focal_length_mm) == params
