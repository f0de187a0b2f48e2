"""Every command's options with wrong types, values and files: one line on stderr, a non-zero exit code, never an
internal error or a traceback (the CLI contract of hostlink/cli.py and BRIEF "bad input").

Most cases run in this process (``hostlink.cli.main``, fast); the ones that start an emulator or that depend on what
third-party libraries print on the real stderr (python-can's interface modules log their missing drivers) run the
console script in a subprocess with a deadline, so a case that wrongly succeeds fails instead of hanging."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hostlink.cli import main

#: Placeholders in the cases: {S} a valid session, {N} a valid nominal, {DEEP} 100,000 nested '[', {DEEPOBJ} nested
#: objects, {BIGINT} an integer of 5,000 digits, {NOTJSON}, {BIN} bytes that are not UTF-8, {ARR} a JSON array,
#: {TYPE_F}, {TYPE_PP}, {TYPE_DIST}, {TYPE_SIZE}, {TYPE_SIGMA} parameter files with every key but one value of the
#: wrong type, {BADCSV} a CSV without the required columns, {EMPTY} an empty file, {T} a fresh directory, {FILE} a
#: regular file (so {FILE}/x is a path that cannot be created, even by root), {MISSING} a path that does not exist,
#: {LONGNAME} a file name of 5,000 characters. A
#: case may end with ``=> TEXT``: the one line must contain TEXT (the refusal is for the reason the case is about).
IN_PROCESS = [
    # parameter files, every reader of them
    "simulate --camera {DEEP} --frames 2 --out {T}/o.csv => nested too deeply",
    "simulate --camera {DEEPOBJ} --frames 2 --out {T}/o.csv => nested too deeply",
    "simulate --camera {BIGINT} --frames 2 --out {T}/o.csv => more than 4300 digits",
    "simulate --camera {BIN} --frames 2 --out {T}/o.csv",
    "simulate --camera {ARR} --frames 2 --out {T}/o.csv",
    "simulate --camera {NOTJSON} --frames 2 --out {T}/o.csv",
    "simulate --camera {MISSING} --frames 2 --out {T}/o.csv",
    "simulate --camera builtin:no_such_camera --frames 2 --out {T}/o.csv",
    "identify --nominal {DEEP} --out {T}/o.csv {S}",
    "calibrate --nominal {DEEP} --out {T}/o.json {S}",
    "calibrate --nominal {BIGINT} --out {T}/o.json {S}",
    "replay --nominal {DEEPOBJ} --out {T}/o.json {S}",
    "attitude --params {DEEP} --out {T}/o.csv {S}",
    "upload --link serial:{MISSING}@9600 {DEEP} => nested too deeply",
    "upload --link serial:{MISSING}@9600 {BIGINT}",
    "upload --link serial:{MISSING}@9600 {ARR}",
    "upload --link serial:{MISSING}@9600 {MISSING}",
    # the right keys with values of the wrong type: refused naming the field, never read as something else
    "upload --link serial:{MISSING}@9600 {TYPE_F} => focal_length_mm: expected a number",
    "upload --link serial:{MISSING}@9600 {TYPE_PP} => principal_point_px: expected a list of two numbers",
    "upload --link serial:{MISSING}@9600 {TYPE_DIST} => distortion: expected an object",
    "upload --link serial:{MISSING}@9600 {TYPE_SIZE} => image_size_px[0]: expected a number",
    "upload --link serial:{MISSING}@9600 {TYPE_SIGMA} => sigma.focal_length_mm",
    "replay --nominal {TYPE_DIST} --out {T}/o.json {S} => distortion: expected an object",
    "simulate --camera {TYPE_F} --frames 2 --out {T}/o.csv => focal_length_mm: expected a number",
    "attitude --params {TYPE_PP} --out {T}/o.csv {S} => principal_point_px",
    "bench --camera {DEEP} --quiet --out {T}/b",
    "bench --nominal {MISSING} --quiet --out {T}/b",
    # simulate: wrong types and values
    "simulate --camera builtin:seed004_camera --frames abc --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames -1 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --noise-px nan --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --noise-px -1 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --min-stars 20 --max-stars 5 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --t0 yesterday --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --interval 0 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --misid 2 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --zenith-range 50,10 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --attitudes {BADCSV} --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --site 100,0,0 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --site a,b,c --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --site 10,10,10 --weather 20,-5 --out {T}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --out {FILE}/o.csv",
    "simulate --camera builtin:seed004_camera --frames 2 --seed -1 --out {T}/o.csv => --seed must be a whole number",
    "simulate --camera builtin:seed004_camera --frames 2 --out {T}/{LONGNAME} => cannot write",
    "replay --nominal {N} --out {T}/o.json --trace {T}/{LONGNAME} {S} => cannot write",
    "bench --seed -1 --frames 2 --quiet --out {T}/b => --seed must be a whole number",
    # session readers
    "calibrate --nominal {N} --out {T}/o.json {MISSING}",
    "calibrate --nominal {N} --out {T}/o.json {BADCSV}",
    "calibrate --nominal {N} --out {T}/o.json {EMPTY}",
    "calibrate --nominal {N} --out {T}/o.json {BIN}",
    "calibrate --nominal {N} --out {T}/o.json --estimate focal {S}",
    "calibrate --nominal {N} --out {T}/o.json --method newton {S}",
    "calibrate --nominal {N} --out {T}/o.json --max-iter 0 {S}",
    "calibrate --nominal {N} --out {T}/o.json --site 1,2 {S}",
    "identify --nominal {N} --out {T}/o.csv {BADCSV}",
    "replay --nominal {N} --out {T}/o.json --precision float16 {S}",
    "replay --nominal {N} --out {T}/o.json --noise-px 0 {S}",
    "replay --nominal {N} --out {T}/o.json --noise-px nan {S}",
    "replay --nominal {N} --out {T}/o.json {BIN}",
    "attitude --params {N} --out {T}/o.csv --mounting a,b {S}",
    "attitude --params {N} --out {T}/o.csv --min-stars 0 {S}",
    "attitude --params {N} --out {T}/o.csv {BADCSV}",
    "centroid --out {T}/o.csv {MISSING}",
    "centroid --out {T}/o.csv --time yesterday {BIN}",
    "import-can --out {T}/o.csv {MISSING}",
    "import-can --out {T}/o.csv {BIN}",
    # links: malformed strings, ports that are not there, bad numbers
    "stream --link bogus --frames 1 --out {T}/o.csv",
    "stream --link serial:{MISSING}@9600 --frames 1 --out {T}/o.csv",
    "stream --link serial:/dev/null@fast --frames 1 --out {T}/o.csv",
    "stream --link can:no_such_interface:0 --frames 1 --out {T}/o.csv => not available here",
    "stream --link can:slcan:socket://127.0.0.1:1@500000 --frames 1 --out {T}/o.csv",
    "stream --link modbus-tcp:127.0.0.1:notaport --frames 1 --out {T}/o.csv",
    "stream --link modbus-tcp:127.0.0.1:1,unit=abc --frames 1 --out {T}/o.csv",
    "stream --link modbus-rtu:{MISSING} --frames 1 --out {T}/o.csv",
    "stream --link serial:{MISSING}@9600 --frames 1 --timeout 0 --out {T}/o.csv",
    "stream --link serial:{MISSING}@9600 --frames 1 --timeout nan --out {T}/o.csv",
    "params --link serial:{MISSING}@9600",
    "monitor --link serial:{MISSING}@9600 --count -1",
    "monitor --link serial:{MISSING}@9600 --interval 0",
    "monitor --link serial:{MISSING}@9600 --every-frames -1 => --every-frames",
    "accept --link serial:{MISSING}@9600",
    # output folders and sizes
    "example {FILE}",
    "export-c {FILE}",
    "vectors --stars 0 {T}/v",
    "costs --stars 2",
    "costs --states 11",
    "bench --frames 0 --quiet --out {T}/b",
    "bench --drift-um nan --quiet --out {T}/b",
    "bench --transport usb --quiet --out {T}/b",
]

#: Cases run as the console script (see the module docstring).
SUBPROCESS = [
    "stream --link can:kvaser:0@500000 --frames 1 --out {T}/o.csv => CAN interface kvaser is not available here (",
    "stream --link can:pcan:PCAN_USBBUS1@250000 --frames 1 --out {T}/o.csv",
    "emulate --transport modbus --option rtu_port=abc => expected a TCP port",
    "emulate --transport modbus --option rtu_port=70000 => expected a TCP port",
    "emulate --transport serial --option rtu_port=5020 => not a setting of the serial emulator (known: none)",
    "emulate --transport modbus --option bogus=1 => (known: rtu_port)",
    "emulate --transport can --option noequals => expected KEY=VALUE",
    "emulate --transport modbus --unit 0 => 1..247",
    "emulate --transport serial --nominal {DEEP} => nested too deeply",
    "emulate --transport serial --camera {BIGINT}",
    "emulate --transport serial --replay {BADCSV}",
    "emulate --transport serial --replay {EMPTY}",
    "emulate --transport serial --sim-frames 0",
    "emulate --transport serial --seed -1 => --seed must be a whole number",
    "emulate --transport serial --estimate focal",
    "emulate --transport serial --flash {FILE}/flash.bin",
    "emulate --transport serial --power-cut-after 3",
    "emulate --transport serial --estimator-mflops 0",
]

#: Longest a refused command may take in a subprocess [s]: a refusal is immediate (about 1 s of imports); far longer
#: means the command did not refuse (an emulator serving), so the case fails instead of hanging the suite.
_DEADLINE_S = 120


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("bad_options")
    texts = {
        "DEEP": "[" * 100_000,
        "DEEPOBJ": '{"a":' * 100_000,
        "BIGINT": '{"focal_length_mm": 1' + "0" * 5000 + "}",
        "NOTJSON": "focal_length_mm = 70",
        "ARR": "[1, 2, 3]",
        "BADCSV": "frame,when\n1,2\n",
        "EMPTY": "",
    }
    good = '"focal_length_mm": 70.0, "pixel_pitch_um": 12.0, "principal_point_px": [511.5, 511.5]'
    texts |= {
        "TYPE_F": '{"focal_length_mm": "70", "pixel_pitch_um": 12.0, "principal_point_px": [511.5, 511.5], '
        '"image_size_px": [1024, 1024]}',
        "TYPE_PP": '{"focal_length_mm": 70.0, "pixel_pitch_um": 12.0, "principal_point_px": 511.5, '
        '"image_size_px": [1024, 1024]}',
        "TYPE_DIST": "{" + good + ', "image_size_px": [1024, 1024], "distortion": 0}',
        "TYPE_SIZE": "{" + good + ', "image_size_px": ["1024", "1024"]}',
        "TYPE_SIGMA": "{" + good + ', "image_size_px": [1024, 1024], "sigma": {"focal_length_mm": "0.1"}}',
    }
    paths = {}
    for key, text in texts.items():
        path = d / (key.lower() + (".csv" if key in ("BADCSV", "EMPTY") else ".json"))
        path.write_text(text)
        paths[key] = str(path)
    (d / "bin.json").write_bytes(b"\xff\xfe\x00\x01 not utf-8")
    paths["BIN"] = str(d / "bin.json")
    (d / "regular_file").write_text("a file, not a folder\n")
    paths["FILE"] = str(d / "regular_file")
    paths["MISSING"] = str(d / "no_such_file")
    paths["LONGNAME"] = "n" * 5000  # a file name longer than any file system takes (ENAMETOOLONG)
    paths["S"] = str(d / "session.csv")
    assert main(["simulate", "--camera", "builtin:seed004_camera", "--frames", "3", "--out", paths["S"]]) == 0
    paths["N"] = "builtin:seed004_nominal"
    return paths


def _argv(case: str, files: dict[str, str], tmp_path) -> list[str]:
    return case.partition(" => ")[0].format(T=str(tmp_path), **files).split()


def _assert_one_line_refusal(code: int | None, stderr: str, case: str) -> None:
    lines = stderr.strip().splitlines()
    assert code not in (0, None), f"{case!r} exited 0"
    assert len(lines) == 1, f"{case!r} printed {len(lines)} lines on stderr: {stderr!r}"
    assert "internal error" not in stderr and "Traceback" not in stderr, f"{case!r}: {stderr!r}"
    assert case.partition(" => ")[2] in stderr, f"{case!r} refused for another reason: {stderr!r}"


@pytest.mark.parametrize("case", IN_PROCESS)
def test_bad_option_is_one_line_and_a_non_zero_exit(case, files, tmp_path, capsys):
    try:
        code = main(_argv(case, files, tmp_path))
    except SystemExit as exc:  # argparse refuses a wrong type or choice by exiting 2
        code = exc.code
    _assert_one_line_refusal(code, capsys.readouterr().err, case)


@pytest.mark.parametrize("case", SUBPROCESS)
def test_bad_option_of_the_console_script_is_one_line(case, files, tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "hostlink.cli", *_argv(case, files, tmp_path)],
        capture_output=True,
        text=True,
        timeout=_DEADLINE_S,
        stdin=subprocess.DEVNULL,
    )
    _assert_one_line_refusal(out.returncode, out.stderr, case)


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "--camera", "builtin:seed004_camera", "--frames", "2", "--out"],
        ["replay", "--nominal", "builtin:seed004_nominal", "{S}", "--out"],
        ["attitude", "--params", "builtin:seed004_camera", "{S}", "--out"],
        ["calibrate", "--nominal", "builtin:seed004_nominal", "{S}", "--out"],
        ["identify", "--nominal", "builtin:seed004_nominal", "{S}", "--out"],
    ],
    ids=lambda argv: argv[0],
)
@pytest.mark.parametrize("path", ["", "."])
def test_an_output_path_that_names_no_file_is_one_line(argv, path, files, capsys):
    try:
        code = main([a.format(**files) for a in argv] + [path])
    except SystemExit as exc:
        code = exc.code
    _assert_one_line_refusal(code, capsys.readouterr().err, f"{argv[0]} --out {path!r}")


def test_a_library_warning_is_one_line_naming_the_command(files, tmp_path, capsys):
    """A session dated 2040 is read (within the span of hostlink.files.times.YEARS), but ERFA warns that no
    leap-second table reaches it: the warning is one line like the command's errors, not Python's two lines with a
    source path."""
    late = tmp_path / "late.csv"
    late.write_text(Path(files["S"]).read_text().replace("2026-", "2040-"))
    code = main(["replay", "--nominal", files["N"], "--out", str(tmp_path / "r.json"), str(late)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 0
    assert len(lines) == 1 and lines[0].startswith("hostlink replay: warning: ErfaWarning: ")
    assert "dubious year" in lines[0]


@pytest.mark.parametrize("year", ["1959", "2101", "2900", "9999"])
def test_a_session_dated_outside_the_years_erfa_serves_is_refused_in_one_line(files, tmp_path, capsys, year):
    """UTC starts in 1960 and ERFA's Earth ephemeris holds its accuracy to 2100: a session dated outside is refused
    in one line naming the year, before any ERFA call could warn "dubious year" and compute anyway."""
    far = tmp_path / "far.csv"
    far.write_text(Path(files["S"]).read_text().replace("2026-", f"{year}-"))
    code = main(["replay", "--nominal", files["N"], "--out", str(tmp_path / "r.json"), str(far)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(lines) == 1 and lines[0].startswith("hostlink replay: error: ")
    assert f"year {year} is outside 1960..2100" in lines[0] and "Warning" not in lines[0]
    assert not (tmp_path / "r.json").exists()
