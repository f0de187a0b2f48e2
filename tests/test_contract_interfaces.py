"""docs/file-formats.md / docs/camera-model.md promises found broken by the contract audit, each pinned by the CLI or
file behaviour an outside tool sees."""

import csv
import json

import numpy as np

from hostlink.cli import main
from hostlink.files.session import Session, read_session, write_session
from hostlink.files.truth import read_truth

NOMINAL = {
    "focal_length_mm": 70.0,
    "pixel_pitch_um": 12.0,
    "principal_point_px": [511.5, 511.5],
    "image_size_px": [1024, 1024],
    "distortion": {},
}


def _one_line_user_error(capsys, code: int, command: str) -> str:
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"hostlink {command}: error: "), err  # a user error, not "internal error"
    return err


def _tiny_session(tmp_path):
    path = tmp_path / "s.csv"
    path.write_text(
        "frame,t_utc,star_id,x_px,y_px,ra_deg,dec_deg\n"
        "0,2026-03-14T02:10:00Z,1,100,100,10.0,20.0\n"
        "0,2026-03-14T02:10:00Z,2,200,100,10.1,20.0\n"
        "0,2026-03-14T02:10:00Z,3,100,200,10.0,20.1\n"
    )
    return path


def test_a_parameter_file_that_is_not_utf8_is_a_one_line_user_error(tmp_path, capsys):
    # "Each command prints a clear one-line error and exits non-zero on bad input": a binary file given as the
    # parameter file used to escape as an internal UnicodeDecodeError (exit 1).
    binary = tmp_path / "camera.json"
    binary.write_bytes(b"\x00\x01\xff\xfe")
    session = _tiny_session(tmp_path)
    code = main(["calibrate", str(session), "--nominal", str(binary), "--out", str(tmp_path / "r.json")])
    err = _one_line_user_error(capsys, code, "calibrate")
    assert "camera.json" in err
    code = main(["attitude", str(session), "--params", str(binary), "--out", str(tmp_path / "a.csv")])
    _one_line_user_error(capsys, code, "attitude")


def test_bench_report_folder_that_cannot_be_created_is_a_one_line_user_error(tmp_path, capsys):
    # --out DIR under a regular file cannot be a folder: a user mistake, refused before any work starts.
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder\n")
    code = main(["bench", "--out", str(blocker / "report"), "--quiet"])
    err = _one_line_user_error(capsys, code, "bench")
    assert "report" in err


def test_unknown_magnitudes_are_written_as_empty_fields_not_nan(tmp_path):
    # mag is an optional magnitude: a sensor that sends none (CAN star frames carry no magnitude) must not put the
    # text "nan" in the session file; an empty field is "no magnitude", and it reads back as missing.
    session = Session(
        frame=np.array([0, 0], dtype=np.int64),
        t_utc=np.array(["2026-03-14T02:10:00.000Z"] * 2, dtype=object),
        star_id=np.array([5, 0], dtype=np.int64),
        x_px=np.array([1.0, 2.0]),
        y_px=np.array([3.0, 4.0]),
        mag=np.array([np.nan, 4.5]),
    )
    path = tmp_path / "s.csv"
    write_session(path, session)
    rows = list(csv.DictReader(path.open()))
    assert [r["mag"] for r in rows] == ["", "4.500"]
    again = read_session(path)
    assert np.isnan(again.mag[0]) and again.mag[1] == 4.5


def test_a_nominal_with_an_empty_distortion_object_is_accepted(tmp_path):
    # "distortion may be empty" / "Missing distortion keys are zero" (a regression guard for the audit's check).
    from hostlink.files.params import load_params

    path = tmp_path / "nominal.json"
    path.write_text(json.dumps(NOMINAL))
    params = load_params(path)
    assert params.distortion.as_tuple() == (0.0,) * 7


def test_files_saved_with_a_utf8_byte_order_mark_read_as_without_it(tmp_path):
    # Spreadsheets save "CSV UTF-8" with a byte-order mark; the header's first name is still `frame` (and a JSON file
    # with a BOM is still the same parameter file). Users expect the same result as without the mark.
    from hostlink.files.params import load_params, load_params_with_extras

    plain = _tiny_session(tmp_path)
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    a, b = read_session(plain), read_session(bom)
    assert np.array_equal(a.frame, b.frame) and np.array_equal(a.x_px, b.x_px) and b.extra == {}
    nominal = tmp_path / "nominal.json"
    nominal.write_bytes(b"\xef\xbb\xbf" + json.dumps({**NOMINAL, "sigma": {"focal_length_mm": 0.1}}).encode())
    assert load_params(nominal).focal_length_mm == 70.0
    assert load_params_with_extras(nominal)[1]["sigma"] == {"focal_length_mm": 0.1}


def test_scripted_attitudes_saved_with_a_byte_order_mark_are_read(tmp_path, capsys):
    # simulate --attitudes takes "CSV with c11..c33": a spreadsheet's BOM must not hide the first column's name.
    nominal = tmp_path / "camera.json"
    nominal.write_text(json.dumps(NOMINAL))
    att = tmp_path / "att.csv"
    att.write_bytes(b"\xef\xbb\xbfc11,c12,c13,c21,c22,c23,c31,c32,c33\n1,0,0,0,1,0,0,0,1\n")
    out = tmp_path / "s.csv"
    code = main(
        [
            "simulate",
            "--camera",
            str(nominal),
            "--frames",
            "1",
            "--out",
            str(out),
            "--attitudes",
            str(att),
            "--min-stars",
            "1",
            "--maglim",
            "7",
        ]
    )
    assert code == 0, capsys.readouterr().err
    truth = read_truth(tmp_path / "s.truth.json")
    assert np.allclose(np.reshape(truth["attitude"][0], (3, 3)), np.eye(3))


def test_southern_western_sites_and_frost_weather_parse_with_a_space_after_the_option(tmp_path, capsys):
    # `--site LAT_DEG,LON_DEG,HEIGHT_M` with a negative latitude (south) or `--weather TEMP_C,...` below 0 C start
    # with '-': argparse used to take "-33.9,-70.7,2400" for an option ("expected one argument").
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps(NOMINAL))
    out = tmp_path / "s.csv"
    code = main(
        [
            "simulate",
            "--camera",
            str(camera),
            "--frames",
            "1",
            "--out",
            str(out),
            "--site",
            "-33.9,-70.7,2400",
            "--weather",
            "-5,750,30",
            "--dut1",
            "-0.2",
        ]
    )
    assert code == 0, capsys.readouterr().err
    truth = read_truth(tmp_path / "s.truth.json")
    assert (truth["site"]["lat_deg"], truth["site"]["lon_deg"], truth["site"]["height_m"]) == (-33.9, -70.7, 2400)
    assert (truth["weather"]["temp_c"], truth["weather"]["rel_humidity"], truth["dut1_s"]) == (-5, 0.3, -0.2)
