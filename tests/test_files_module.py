"""The files room: one atomic writer, package data by name, one time module, the parameter-table layout, the trace
reader and writer."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from hostlink.errors import UserError
from hostlink.files.atomic import AtomicFile, write_json, write_text
from hostlink.files.params import builtin_names, data_file, load_params, params_path
from hostlink.files.times import frame_times, iso_plus_seconds, iso_to_t_us, parse_iso_utc_many, t_us_to_iso
from hostlink.files.trace import TRACE_COLUMNS, read_trace, write_trace
from onboard.params import params_from_dict
from protocol.param_table import (
    CAMERA_FIELDS,
    DISTORTION_NAMES,
    ESTIMATE_NAMES,
    SIGMA_FIELDS,
    camera_fields_from_file,
    camera_file_from_fields,
)


def test_atomic_write_replaces_the_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "sub" / "a.json"
    write_json(path, {"x": 1})
    write_json(path, {"x": 2})
    assert json.loads(path.read_text()) == {"x": 2}
    assert sorted(p.name for p in path.parent.iterdir()) == ["a.json"]


def test_a_failed_write_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    path = tmp_path / "a.txt"
    write_text(path, "old\n")
    with pytest.raises(ZeroDivisionError):
        with AtomicFile(path) as handle:
            handle.write("half of the new")
            raise ZeroDivisionError  # the writer fails half way
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_a_kept_partial_file_stays_beside_the_target_until_committed(tmp_path):
    # the session writer's partial file: rows received before a failure are kept, then renamed or left for the user
    path = tmp_path / "s.csv"
    writer = AtomicFile(path, suffix=".partial", newline="")
    writer.open().write("frame\n1\n")
    partial = writer.temporary
    assert partial.parent == tmp_path and partial.name.startswith(".s.csv.") and partial.name.endswith(".partial")
    writer.abandon(keep=True)
    assert partial.read_text() == "frame\n1\n" and not path.exists()
    writer.commit()
    assert path.read_text() == "frame\n1\n" and not partial.exists()


def test_strict_json_refuses_nan_and_writes_nothing(tmp_path):
    path = tmp_path / "a.json"
    with pytest.raises(ValueError):
        write_json(path, {"x": float("nan")})
    assert list(tmp_path.iterdir()) == []


def test_an_unwritable_path_is_a_one_line_error_naming_the_file(tmp_path):
    (tmp_path / "plain").write_text("a file, not a folder")
    with pytest.raises(UserError, match=r"plain/a\.txt: cannot write \(") as caught:
        write_text(tmp_path / "plain" / "a.txt", "x")
    assert "\n" not in str(caught.value)


def test_builtin_names_resolve_to_the_package_data():
    assert {"seed004_nominal", "seed004_camera"} <= set(builtin_names())
    assert params_path("builtin:seed004_nominal") == data_file("seed004_nominal.json")
    nominal = load_params("builtin:seed004_nominal")
    assert nominal == params_from_dict(json.loads(data_file("seed004_nominal.json").read_text()))
    assert (nominal.focal_length_mm, nominal.principal_point_px) == (70.0, (511.5, 511.5))


def test_an_unknown_builtin_name_lists_the_known_ones():
    with pytest.raises(UserError, match="builtin:nope: no such built-in parameter file .*builtin:seed004_nominal"):
        load_params("builtin:nope")


def test_wire_time_round_trip_is_exact_to_the_microsecond():
    for text in ("2026-03-14T02:10:00.125Z", "2026-03-14T02:10:00.125001Z", "1999-12-31T23:59:59.999999Z"):
        assert t_us_to_iso(iso_to_t_us(text)) == text
    # a time without decimals or zone is the same instant; POSIX time of a known date (2026-03-14 = day 20526)
    assert iso_to_t_us("2026-03-14 00:00:00") == 20526 * 86400 * 1_000_000
    # a leap second maps onto the next minute (POSIX time does not count it)
    assert iso_to_t_us("2016-12-31T23:59:60.500Z") == iso_to_t_us("2017-01-01T00:00:00.500Z")


def test_frame_times_and_iso_plus_seconds_agree_on_the_millisecond_grid():
    text, jd1, jd2 = frame_times("2026-03-14T23:59:59.000Z", 0.25, 9)
    assert list(text[[0, 4, 8]]) == ["2026-03-14T23:59:59.000Z", "2026-03-15T00:00:00.000Z", "2026-03-15T00:00:01.000Z"]
    assert [iso_plus_seconds("2026-03-14T23:59:59.000Z", 0.25 * k) for k in range(9)] == list(text)
    j1, j2 = parse_iso_utc_many(text)
    np.testing.assert_array_equal(jd1 + jd2, j1 + j2)


def test_the_parameter_layout_is_the_documented_one():
    # docs/links.md spells the table's camera fields; every module imports them from protocol.param_table
    text = (Path(__file__).resolve().parents[1] / "docs" / "links.md").read_text()
    listed = re.findall(r"`(\w+)`", text[text.index("the 13 camera fields (") :].split(")", 1)[0])
    assert listed == [*CAMERA_FIELDS[:6], DISTORTION_NAMES[0], DISTORTION_NAMES[-1]]  # doc writes `k1` .. `s2`
    assert DISTORTION_NAMES == ("k1", "k2", "k3", "p1", "p2", "s1", "s2") and len(CAMERA_FIELDS) == 13
    assert ESTIMATE_NAMES == ("f", "x0", "y0", *DISTORTION_NAMES)
    assert SIGMA_FIELDS == tuple(
        f"sigma_{name}" for name in (*CAMERA_FIELDS[:1], *CAMERA_FIELDS[2:4], *DISTORTION_NAMES)
    )


def test_a_parameter_file_object_survives_the_table_fields_round_trip():
    doc = json.loads(data_file("seed004_camera.json").read_text())
    fields = camera_fields_from_file(doc)
    assert tuple(fields) == CAMERA_FIELDS
    assert camera_file_from_fields(fields) == doc


def test_trace_round_trip_keeps_types_and_values(tmp_path):
    trace = {c: [] for c in TRACE_COLUMNS}
    for k in range(3):
        for c in TRACE_COLUMNS:
            trace[c].append({"t_utc": f"2026-03-14T02:10:0{k}.000Z", "skipped": "" if k else "too few stars"}.get(c, k))
    trace["focal_length_mm"] = [70.123456789, 70.2, 70.25]
    path = tmp_path / "trace.csv"
    write_trace(path, trace)
    back = read_trace(path)
    assert tuple(back) == TRACE_COLUMNS
    assert back["frame"].dtype == np.int64 and back["frame"].tolist() == [0, 1, 2]
    assert back["focal_length_mm"].tolist() == [70.123456789, 70.2, 70.25]  # 9 decimals of a mm are written
    assert back["skipped"].tolist() == ["too few stars", "", ""]


def test_commands_take_builtin_names_for_parameter_files(tmp_path, capsys):
    from hostlink.cli import main
    from hostlink.files.truth import read_truth

    out = tmp_path / "s.csv"
    assert main(["simulate", "--camera", "builtin:seed004_camera", "--frames", "2", "--out", str(out)]) == 0
    assert read_truth(tmp_path / "s.truth.json")["camera_params"] == load_params("builtin:seed004_camera")
    capsys.readouterr()
    code = main(["simulate", "--camera", "builtin:seed004", "--frames", "2", "--out", str(out)])
    err = capsys.readouterr().err
    assert code != 0 and "builtin:seed004: no such built-in parameter file" in err and err.count("\n") == 1
