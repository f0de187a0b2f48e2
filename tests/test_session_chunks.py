"""Sessions read in chunks (hostlink.files.session.read_session_chunks): whole frames whatever the chunk size and
wherever the reader's blocks fall, several files as one session in time order, the same one-line errors as the
whole-file reader, and the Parquet format (hostlink.files.columnar) round trip."""

import numpy as np
import pyarrow.parquet as pq
import pytest

from hostlink.errors import UserError
from hostlink.files import columnar
from hostlink.files.session import (
    Session,
    SessionWriter,
    concatenate_sessions,
    read_session,
    read_session_chunks,
    write_session,
)
from hostlink.files.session import parse as session_parse  # the CSV reader, which reads CSV_BLOCK_BYTES

HEADER = "frame,t_utc,star_id,x_px,y_px,mag,ra_deg,dec_deg\n"


def _session(n_frames: int, first_frame: int = 0, t0_s: int = 0, seed: int = 0) -> Session:
    """Frames of 1 to 4 stars (some unidentified, some without magnitude), one second apart from 02:00:00 + t0_s,
    values rounded to the decimals the CSV writer keeps, so that CSV and Parquet both read them back exactly."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, 5, size=n_frames)
    n = int(counts.sum())
    frame = np.repeat(np.arange(first_frame, first_frame + n_frames), counts)
    seconds = np.repeat(t0_s + np.arange(n_frames), counts)
    t_utc = np.array([f"2026-03-14T{2 + s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}.000Z" for s in seconds], object)
    star_id = rng.integers(1, 100_000, size=n)
    star_id[rng.random(n) < 0.2] = 0
    ra = np.where(star_id != 0, np.round(rng.uniform(0, 360, n), 10), np.nan)
    dec = np.where(star_id != 0, np.round(rng.uniform(-90, 90, n), 10), np.nan)
    mag = np.where(rng.random(n) < 0.1, np.nan, np.round(rng.uniform(1, 7, n), 3))
    return Session(
        frame=frame,
        t_utc=t_utc,
        star_id=star_id,
        x_px=np.round(rng.uniform(0, 1023, n), 6),
        y_px=np.round(rng.uniform(0, 1023, n), 6),
        mag=mag,
        ra_deg=ra,
        dec_deg=dec,
        extra={"snr": np.array([str(k) for k in range(n)], dtype=object)},
    )


def _assert_same(a: Session, b: Session) -> None:
    assert np.array_equal(a.frame, b.frame) and np.array_equal(a.star_id, b.star_id)
    assert list(a.t_utc) == list(b.t_utc)
    for name in ("x_px", "y_px", "mag", "ra_deg", "dec_deg"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or np.array_equal(x, y, equal_nan=True), name
    assert {k: list(v) for k, v in a.extra.items()} == {k: list(v) for k, v in b.extra.items()}


@pytest.fixture(params=["csv", "parquet"])
def fmt(request):
    return request.param


def test_chunks_hold_whole_frames_and_join_into_the_whole_session_at_every_chunk_size(tmp_path, fmt):
    s = _session(23)
    path = tmp_path / f"s.{fmt}"
    write_session(path, s)
    whole = read_session(path)
    for chunk_frames in range(1, 26):
        chunks = list(read_session_chunks(path, chunk_frames))
        assert [c.n_frames for c in chunks[:-1]] == [chunk_frames] * (len(chunks) - 1)
        assert 1 <= chunks[-1].n_frames <= chunk_frames
        _assert_same(concatenate_sessions(chunks), whole)
        # no frame is split: each chunk starts where the previous one's last frame ended
        firsts = [int(c.frame[0]) for c in chunks]
        lasts = [int(c.frame[-1]) for c in chunks]
        assert all(f > last for f, last in zip(firsts[1:], lasts[:-1], strict=True))


@pytest.mark.parametrize("batch_rows", range(1, 9))
def test_frames_cut_by_the_parquet_reader_batches_at_any_row_are_rejoined(tmp_path, monkeypatch, batch_rows):
    s = _session(12, seed=batch_rows)
    write_session(tmp_path / "s.parquet", s)
    monkeypatch.setattr(columnar, "READ_BATCH_ROWS", batch_rows)  # batch edges fall inside frames at every row
    for chunk_frames in (1, 2, 5, 12):
        chunks = list(read_session_chunks(tmp_path / "s.parquet", chunk_frames))
        _assert_same(concatenate_sessions(chunks), s)
        assert sum(c.n_frames for c in chunks) == 12


@pytest.mark.parametrize("block_bytes", [160, 211, 307, 401, 997])
def test_frames_cut_by_the_csv_reader_blocks_are_rejoined(tmp_path, monkeypatch, block_bytes):
    s = _session(30, seed=block_bytes)
    write_session(tmp_path / "s.csv", s)
    whole = read_session(tmp_path / "s.csv")
    monkeypatch.setattr(session_parse, "CSV_BLOCK_BYTES", block_bytes)  # a row is ~100 bytes: blocks of 1-9 rows
    for chunk_frames in (1, 3, 30):
        _assert_same(concatenate_sessions(list(read_session_chunks(tmp_path / "s.csv", chunk_frames))), whole)


def test_parquet_round_trip_is_exact_with_nulls_for_missing_values_and_whole_frame_row_groups(tmp_path, monkeypatch):
    s = _session(40)
    monkeypatch.setattr(columnar, "ROW_GROUP_ROWS", 7)  # many row groups, cut between frames
    with SessionWriter(tmp_path / "s.parquet") as writer:
        for k in range(0, 40, 3):  # appended a few frames at a time, as `hostlink stream` does
            writer.append(s.select(np.isin(s.frame, np.arange(k, k + 3))))
    r = read_session(tmp_path / "s.parquet")
    _assert_same(r, s)  # float64 stored as is: bit for bit
    meta = pq.ParquetFile(tmp_path / "s.parquet")
    assert meta.schema_arrow.metadata[b"hostlink.session"] == columnar.SCHEMA_VERSION.encode()
    assert meta.metadata.num_row_groups > 3
    table = meta.read()
    assert table.column("mag").null_count == int(np.isnan(s.mag).sum())  # NaN written as null
    assert str(table.schema.field("frame").type) == "int64" and str(table.schema.field("t_utc").type) == "string"
    groups = [meta.read_row_group(g).column("frame").to_numpy() for g in range(meta.metadata.num_row_groups)]
    assert all(a[-1] != b[0] for a, b in zip(groups[:-1], groups[1:], strict=True))  # no frame spans two groups


def test_csv_and_parquet_read_the_same_session(tmp_path):
    s = _session(15)
    write_session(tmp_path / "s.csv", s)
    write_session(tmp_path / "s.parquet", s)
    _assert_same(read_session(tmp_path / "s.csv"), read_session(tmp_path / "s.parquet"))


def test_an_empty_session_round_trips_and_yields_no_chunk(tmp_path, fmt):
    s = _session(3).select(np.zeros(0, dtype=np.int64))
    path = tmp_path / f"e.{fmt}"
    write_session(path, s)
    r = read_session(path)
    assert len(r) == 0 and r.ra_deg is not None and r.mag is not None and list(r.extra) == ["snr"]
    assert list(read_session_chunks(path)) == []


def test_several_nights_form_one_session_in_time_order_with_their_frame_numbers(tmp_path, fmt):
    nights = [_session(5, first_frame=0, t0_s=3600 * k, seed=k) for k in range(3)]  # the counter restarts nightly
    names = ["c", "a", "b"]  # file names not in time order
    for name, night in zip(names, nights, strict=True):
        write_session(tmp_path / f"{name}.{fmt}", night)
    expected = concatenate_sessions(nights)
    from_glob = read_session(str(tmp_path / f"*.{fmt}"))
    from_list = read_session([tmp_path / f"{n}.{fmt}" for n in ("a", "b", "c")])
    _assert_same(from_glob, expected)
    _assert_same(from_list, expected)
    chunks = list(read_session_chunks(str(tmp_path / f"*.{fmt}"), chunk_frames=4))
    assert [c.n_frames for c in chunks] == [4, 1, 4, 1, 4, 1]  # a chunk never spans two files
    assert from_glob.n_frames == 15


@pytest.mark.parametrize(
    "second, message",
    [
        (dict(first_frame=0, t0_s=2), "starts before"),
        (dict(first_frame=4, t0_s=3600), "has the number of the last frame"),
    ],
)
def test_files_that_overlap_or_merge_frames_are_refused(tmp_path, second, message):
    write_session(tmp_path / "a.csv", _session(5))
    write_session(tmp_path / "b.csv", _session(5, **second))
    with pytest.raises(UserError, match=message) as info:
        read_session([tmp_path / "a.csv", tmp_path / "b.csv"])
    assert "\n" not in str(info.value)


def test_files_with_other_columns_or_without_time_beside_timed_ones_are_refused(tmp_path):
    write_session(tmp_path / "a.csv", _session(3))
    (tmp_path / "b.csv").write_text("frame,t_utc,star_id,x_px,y_px\n20,2026-03-14T05:00:00Z,1,1,1\n")
    with pytest.raises(UserError, match="need the same columns"):
        read_session([tmp_path / "a.csv", tmp_path / "b.csv"])
    untimed = _session(2, first_frame=40)
    untimed.t_utc[:] = ""
    write_session(tmp_path / "c.csv", untimed)
    with pytest.raises(UserError, match="gives no time"):
        read_session([tmp_path / "a.csv", tmp_path / "c.csv"])
    with pytest.raises(UserError, match="no file matches"):
        read_session(str(tmp_path / "none*.csv"))


def test_frames_out_of_order_across_a_chunk_boundary_are_refused_with_their_line(tmp_path, fmt):
    s = _session(6)
    s.frame[s.frame == 3] = 1  # frame 3 renumbered 1: after frame 2, not in time order
    path = tmp_path / f"s.{fmt}"
    write_session(path, s)
    first_bad = int(np.argmax(s.frame < np.maximum.accumulate(s.frame)))
    where = f"line {first_bad + 2}" if fmt == "csv" else f"row {first_bad + 1}"
    for chunk_frames in (1, 2, 3, 6):  # the bad frame first in its chunk, or inside it
        with pytest.raises(UserError, match=f"{where}: frames are not in time order") as info:
            list(read_session_chunks(path, chunk_frames))
        assert "\n" not in str(info.value)


def test_a_bad_value_far_into_a_csv_is_named_by_its_line(tmp_path, monkeypatch):
    s = _session(40)
    write_session(tmp_path / "s.csv", s)
    lines = (tmp_path / "s.csv").read_text().splitlines()
    k = len(lines) - 3
    fields = lines[k].split(",")
    fields[3] = "abc"
    lines[k] = ",".join(fields)
    (tmp_path / "s.csv").write_text("\n".join(lines) + "\n")
    monkeypatch.setattr(session_parse, "CSV_BLOCK_BYTES", 400)  # the bad line is several blocks in
    with pytest.raises(UserError, match=f"line {k + 1}, column x_px: not a number: 'abc'"):
        list(read_session_chunks(tmp_path / "s.csv", 4))
    lines[k] = ",".join(fields[:-1])  # one field short
    (tmp_path / "s.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match=f"line {k + 1}: expected 9 fields, found 8"):
        read_session(tmp_path / "s.csv")


def test_a_time_that_differs_inside_a_frame_cut_by_a_reader_batch_is_refused(tmp_path, monkeypatch):
    s = _session(4, seed=3)
    rows = np.flatnonzero(s.frame == 2)
    if rows.size < 2:  # make frame 2 two rows long
        s = concatenate_sessions([s.select(np.arange(rows[0] + 1)), s.select(np.arange(rows[0], len(s)))])
        rows = np.flatnonzero(s.frame == 2)
    s.t_utc[rows[-1]] = "2026-03-14T02:59:59.000Z"
    write_session(tmp_path / "s.parquet", s)
    monkeypatch.setattr(columnar, "READ_BATCH_ROWS", int(rows[-1]))  # the frame's last row starts the next batch
    with pytest.raises(UserError, match=f"row {rows[-1] + 1}: t_utc differs from the rest of frame 2"):
        list(read_session_chunks(tmp_path / "s.parquet", 10))


@pytest.mark.parametrize(
    "column, values, message",
    [
        ("x_px", [1.0, float("nan")], "row 2, column x_px: not finite"),
        ("frame", [0.0, 1.5], "row 2, column frame: not an integer"),
        ("star_id", [1, -3], "row 2, column star_id: negative Hipparcos number"),
        ("t_utc", ["2026-03-14T02:00:00Z", "soon"], "column t_utc: "),
        ("y_px", ["1", "x"], "row 2, column y_px: not a number: 'x'"),
        ("x_px", [True, False], "column x_px: expected numbers, found bool"),
    ],
)
def test_a_bad_parquet_session_is_a_one_line_error_naming_row_and_column(tmp_path, column, values, message):
    import pyarrow as pa

    good = {
        "frame": [0, 1],
        "t_utc": ["2026-03-14T02:00:00Z", "2026-03-14T02:00:01Z"],
        "star_id": [1, 2],
        "x_px": [1.0, 2.0],
        "y_px": [1.0, 2.0],
    }
    pq.write_table(pa.table(good | {column: values}), tmp_path / "bad.parquet")
    with pytest.raises(UserError, match=message) as info:
        read_session(tmp_path / "bad.parquet")
    assert "\n" not in str(info.value)


def test_a_file_that_is_not_parquet_is_a_one_line_error(tmp_path):
    (tmp_path / "x.parquet").write_text("frame,t_utc\n")
    with pytest.raises(UserError, match="not a Parquet file") as info:
        read_session(tmp_path / "x.parquet")
    assert "\n" not in str(info.value)
    with pytest.raises(UserError, match="no such file"):
        read_session(tmp_path / "missing.parquet")


def test_a_parquet_stream_interrupted_leaves_a_readable_partial_file(tmp_path):
    s = _session(6)
    with pytest.raises(KeyboardInterrupt), SessionWriter(tmp_path / "s.parquet") as writer:
        writer.append(s.select(s.frame < 3))
        raise KeyboardInterrupt
    assert not (tmp_path / "s.parquet").exists()
    partial = writer.partial
    assert partial.parent == tmp_path and partial.name.endswith(".partial")
    _assert_same(_read_as_parquet(partial), s.select(s.frame < 3))


def _read_as_parquet(path):
    """A partial file has no .parquet ending: read it through a copy that has."""
    target = path.with_name("recovered.parquet")
    target.write_bytes(path.read_bytes())
    return read_session(target)


def test_chunk_frames_must_be_a_whole_number_of_at_least_one(tmp_path):
    write_session(tmp_path / "s.csv", _session(2))
    for bad in (0, -1, 2.5):
        with pytest.raises(UserError, match="chunk_frames"):
            list(read_session_chunks(tmp_path / "s.csv", bad))


def test_stream_and_simulate_write_parquet_holding_what_they_write_as_csv(tmp_path, capsys):
    from hostlink.cli import main
    from hostlink.emulator.loopback import LoopbackLink
    from hostlink.emulator.setup import build_sensor
    from hostlink.links.operations import record_session

    for fmt in ("csv", "parquet"):  # the same sensor frames, recorded in both formats
        record_session(LoopbackLink(build_sensor(sim_frames=6, seed=4, estimator=False)), 6, tmp_path / f"r.{fmt}")
        assert main(["simulate", "--preset", "seed004", "--frames", "4", "--out", str(tmp_path / f"s.{fmt}")]) == 0
    capsys.readouterr()
    # stream: CSV keeps 10 decimals, exact on the wire's 2^-10 px grid, so both read back the same numbers
    _assert_same(read_session(tmp_path / "r.csv"), read_session(tmp_path / "r.parquet"))
    assert read_session(tmp_path / "r.parquet").n_frames == 6
    csv, parquet = read_session(tmp_path / "s.csv"), read_session(tmp_path / "s.parquet")
    assert np.max(np.abs(csv.x_px - parquet.x_px)) <= 5e-7  # simulate's CSV: 6 decimals; Parquet: float64 as is
    assert (tmp_path / "s.truth.json").exists() and list(csv.t_utc) == list(parquet.t_utc)


def test_reading_in_chunks_holds_one_chunk_whatever_the_length_of_the_file(tmp_path, monkeypatch, fmt):
    import tracemalloc

    monkeypatch.setattr(session_parse, "CSV_BLOCK_BYTES", 4096)  # small reader blocks, so that a file of a few
    monkeypatch.setattr(columnar, "READ_BATCH_ROWS", 64)  # thousand rows is read in many of them

    def peak_bytes(path, whole: bool) -> int:
        tracemalloc.start()
        if whole:
            assert len(read_session(path))
        else:
            for chunk in read_session_chunks(path, 10):
                assert chunk.n_frames <= 10
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return peak

    paths = {}
    for n_frames in (100, 1000):
        paths[n_frames] = tmp_path / f"s{n_frames}.{fmt}"
        write_session(paths[n_frames], _session(n_frames, seed=n_frames))
    peak_bytes(paths[100], whole=False)  # the first read imports pyarrow's modules: not the reader's memory
    small, large = peak_bytes(paths[100], whole=False), peak_bytes(paths[1000], whole=False)
    grown_whole = peak_bytes(paths[1000], whole=True) - peak_bytes(paths[100], whole=True)
    # the whole session in memory grows by ~0.8 kB a frame (measured: ~800 kB for the 900 more frames); in chunks
    # the reader holds a block and a chunk (measured: the same peak, ~56 kB, for both files). Allowed: 100 kB, an
    # eighth of what holding the file would add
    assert grown_whole > 500_000, grown_whole
    assert large - small < 100_000, (small, large)


def test_many_time_stamps_parse_in_one_pass_to_the_same_bits_as_one_at_a_time():
    from hostlink.files.times import VECTOR_PARSE_FROM, parse_iso_utc, parse_iso_utc_many

    rng = np.random.default_rng(5)
    texts = []
    for k in range(300):
        decimals = "".join(str(d) for d in rng.integers(0, 10, size=int(rng.integers(0, 13))))
        second = f"{int(rng.integers(0, 60)):02d}" + (f".{decimals}" if decimals else "")
        zone = ["Z", "+00:00", "-0000", ""][k % 4]
        texts.append(
            f"{2000 + k % 25}-{1 + k % 12:02d}-{1 + k % 28:02d}{'T '[k % 2]}{k % 24:02d}:{k % 60:02d}:{second}{zone}"
        )
    texts += [
        " 2016-12-31T23:59:60.500Z ",
        "2026-03-14T02:10:00.125Z\n",
        "٢٠٢٦-03-14T02:10:00Z",
    ]  # leap second, blanks,
    # Arabic-Indic digits (Python's \d takes them; RE2's does not: the one-at-a-time parser decides)
    assert len(texts) >= VECTOR_PARSE_FROM
    jd1, jd2 = parse_iso_utc_many(texts)
    one1, one2 = zip(*(parse_iso_utc_many([t]) for t in texts), strict=True)
    assert np.array_equal(jd1, np.concatenate(one1)) and np.array_equal(jd2, np.concatenate(one2))
    assert parse_iso_utc(texts[-1]) == (2026, 3, 14, 2, 10, 0.0)
    with pytest.raises(ValueError, match=r"not an ISO 8601 UTC time: '2026-03-14T02:10'"):
        parse_iso_utc_many([*texts, "2026-03-14T02:10"])
