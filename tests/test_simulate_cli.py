"""``hostlink simulate`` on the command line: files written, preset, and one-line errors with non-zero exit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hostlink.cli import main
from hostlink.files.params import data_file
from hostlink.files.session import read_session
from hostlink.files.truth import read_truth


def test_preset_seed004_writes_session_and_truth(tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["simulate", "--preset", "seed004", "--frames", "30", "--out", str(out)]) == 0
    s = read_session(out)
    truth = read_truth(tmp_path / "s.truth.json")
    assert s.n_frames == 30
    assert np.bincount(s.frame).min() >= 10  # seed 004: at least 10 stars a frame
    assert truth["camera"] == json.loads(data_file("seed004_camera.json").read_text())
    assert truth["noise_px"] == 0.05 and truth["maglim"] == 6.0
    assert truth["attitude"].shape == (30, 3, 3)
    assert "wrote 30 frames" in capsys.readouterr().out


def test_camera_file_and_every_option_reach_the_truth(tmp_path):
    out = tmp_path / "g.csv"
    args = [
        "simulate",
        "--camera",
        str(data_file("seed004_camera.json")),
        "--frames",
        "12",
        "--out",
        str(out),
        "--noise-px",
        "0.1",
        "--min-stars",
        "5",
        "--max-stars",
        "9",
        "--maglim",
        "6.5",
        "--seed",
        "4",
        "--t0",
        "2026-06-01T20:00:00Z",
        "--interval",
        "2",
        "--misid",
        "0.1",
        "--false-stars",
        "0.2",
        "--focal-drift-um",
        "15",
        "--focal-drift-period",
        "6",
        "--site",
        "39.9,116.4,50",
        "--weather",
        "10,1013,0.5",
        "--zenith-range",
        "10,60",
        "--dut1",
        "0.2",
    ]
    assert main(args) == 0
    truth = read_truth(tmp_path / "g.truth.json")
    assert truth["noise_px"] == 0.1 and truth["min_stars"] == 5 and truth["max_stars"] == 9
    assert truth["maglim"] == 6.5 and truth["seed"] == 4 and truth["frame_interval_s"] == 2.0
    assert truth["t0_utc"] == "2026-06-01T20:00:00Z" and truth["dut1_s"] == 0.2
    assert truth["misid_fraction"] == 0.1 and truth["false_star_fraction"] == 0.2
    assert truth["focal_drift_um"] == 15.0 and truth["focal_drift_period_frames"] == 6.0
    assert truth["site"]["lat_deg"] == 39.9 and truth["weather"]["pressure_hpa"] == 1013.0
    assert truth["zenith_range_deg"] == [10.0, 60.0] and truth["refraction"] is True
    s = read_session(out)
    real = np.bincount(s.frame[s.star_id != 0])
    assert real.min() >= 5 and real.max() <= 9


def test_scripted_attitudes_file_sets_the_frames(tmp_path):
    first = tmp_path / "a.csv"
    assert main(["simulate", "--preset", "seed004", "--frames", "3", "--out", str(first)]) == 0
    att = read_truth(tmp_path / "a.truth.json")["attitude"].reshape(3, 9)
    att_csv = tmp_path / "att.csv"
    names = [f"c{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
    body = [f"{k}," + ",".join(repr(float(v)) for v in row) for k, row in enumerate(att)]
    lines = ["frame," + ",".join(names), *body]
    att_csv.write_text("\n".join(lines) + "\n")
    second = tmp_path / "b.csv"
    assert main(["simulate", "--preset", "seed004", "--attitudes", str(att_csv), "--out", str(second)]) == 0
    np.testing.assert_array_equal(read_truth(tmp_path / "b.truth.json")["attitude"].reshape(3, 9), att)


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--frames", "5"], "--camera is required"),
        (["--camera", "missing.json", "--frames", "5"], "no such file"),
        (["--preset", "seed004", "--frames", "0"], "frames"),
        (["--preset", "seed004", "--noise-px", "-0.1"], "noise"),
        (["--preset", "seed004", "--misid", "2"], "--misid"),
        (["--preset", "seed004", "--t0", "2026-02-30T00:00:00Z"], "start time"),
        (["--preset", "seed004", "--weather", "10,1013"], "--weather needs --site"),
        (["--preset", "seed004", "--site", "95,0,0"], "latitude"),
        # UT1 - UTC is kept within 0.9 s by IERS: 10 h is a unit mistake, NaN garbage (both once ran silently)
        (["--preset", "seed004", "--site", "39,116,50", "--dut1", "36000"], "--dut1"),
        (["--preset", "seed004", "--site", "39,116,50", "--dut1", "nan"], "--dut1"),
        (["--preset", "seed004", "--zenith-range", "a,b"], "--zenith-range"),
        (["--preset", "seed004", "--frames", "2", "--min-stars", "200", "--max-stars", "200"], "min-stars"),
    ],
)
def test_bad_input_is_one_line_error_with_nonzero_exit(tmp_path, capsys, args, needle):
    code = main(["simulate", "--out", str(tmp_path / "x.csv"), *args])
    err = capsys.readouterr().err
    assert code != 0
    assert needle in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "x.csv").exists()


def test_unparsable_number_is_an_argparse_one_liner(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["simulate", "--preset", "seed004", "--frames", "many", "--out", str(tmp_path / "x.csv")])
    assert info.value.code != 0
    assert capsys.readouterr().err.count("\n") == 1
