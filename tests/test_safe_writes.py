"""Every file the project writes is written safely (issue 33): through a temporary file created exclusively under an
unpredictable name in the target's directory, then renamed onto the target. Per writer: a symbolic link planted at
the first temporary name the writer draws, and one planted at the target itself, both pointing at a victim file; the
victim must be untouched, the planted temporary link left as it was (never opened), and the target a regular file
holding what was written (the link at the target replaced, not written through)."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hostlink.files import atomic

VICTIM_TEXT = "victim: must never change\n"


@pytest.fixture
def planted(tmp_path, monkeypatch):
    """Plants a symbolic link to the victim at the first temporary name drawn for every target; returns the list of
    (target, planted temporary link) pairs and the victim."""
    victim = tmp_path / "victim.txt"
    victim.write_text(VICTIM_TEXT)
    real = atomic.temporary_name
    links: list[tuple[Path, Path]] = []
    seen: set[Path] = set()

    def planting(path: Path, suffix: str = ".tmp") -> Path:
        name = real(path, suffix)
        if path not in seen:  # the writer's first draw for this target: a link is already there
            seen.add(path)
            os.symlink(victim, name)
            links.append((path, name))
        return name

    monkeypatch.setattr(atomic, "temporary_name", planting)
    return SimpleNamespace(victim=victim, links=links)


def _plant_targets(victim: Path, targets: list[Path]) -> None:
    for target in targets:
        target.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(victim, target)


def _check(planted, targets: list[Path]) -> None:
    assert planted.victim.read_text() == VICTIM_TEXT
    assert planted.links, "the writer drew no temporary name: it did not go through hostlink.files.atomic"
    for target, link in planted.links:
        assert link.is_symlink() and Path(os.readlink(link)) == planted.victim  # left alone, never opened
        assert target in targets or not target.is_symlink()
    for target in targets:
        assert target.exists() and not target.is_symlink() and target.stat().st_size > 0


def _session():
    from hostlink.files.session import Session

    n = 4
    return Session(
        frame=np.array([0, 0, 1, 1], dtype=np.int64),
        t_utc=np.array(["2026-01-01T00:00:00.000000"] * 2 + ["2026-01-01T00:00:01.000000"] * 2, dtype=object),
        star_id=np.arange(1, n + 1, dtype=np.int64),
        x_px=np.linspace(10, 20, n),
        y_px=np.linspace(30, 40, n),
    )


def _write_session_csv(out: Path) -> list[Path]:
    from hostlink.files.session import write_session

    write_session(out / "s.csv", _session())
    return [out / "s.csv"]


def _write_session_parquet(out: Path) -> list[Path]:
    from hostlink.files.session import write_session

    write_session(out / "s.parquet", _session())
    return [out / "s.parquet"]


def _stream_session(out: Path) -> list[Path]:
    """``hostlink stream``'s writer: frame by frame into the partial file, renamed at the end."""
    from hostlink.files.session import SessionWriter

    s = _session()
    with SessionWriter(out / "streamed.csv") as writer:
        writer.append(s.select(s.frame == 0))
        writer.append(s.select(s.frame == 1))
    return [out / "streamed.csv"]


def _params(out: Path) -> list[Path]:
    from hostlink.emulator.setup import DEFAULT_CAMERA
    from hostlink.files.params import load_params, save_params

    save_params(out / "p.json", load_params(DEFAULT_CAMERA))
    return [out / "p.json"]


def _truth(out: Path) -> list[Path]:
    from hostlink.files.truth import write_truth

    write_truth(out / "truth.json", {"focal_length_mm": 70.0})
    return [out / "truth.json"]


def _attitude(out: Path) -> list[Path]:
    from hostlink.files.attitude import write_attitudes

    att = SimpleNamespace(
        ship_ypr_deg=None,
        n_frames=1,
        frame=np.array([0]),
        t_utc=["2026-01-01T00:00:00"],
        n_stars=np.array([5]),
        n_used=np.array([5]),
        C=np.eye(3)[None],
        residual_rms_arcsec=np.array([1.0]),
        status=["ok"],
    )
    write_attitudes(out / "att.csv", att)
    return [out / "att.csv"]


def _trace(out: Path) -> list[Path]:
    from hostlink.files.trace import TRACE_COLUMNS, TraceWriter

    with TraceWriter(out / "trace.csv") as writer:
        writer.append({c: ["2026-01-01T00:00:00"] if c == "t_utc" else [1] for c in TRACE_COLUMNS})
    return [out / "trace.csv"]


def _rejected_report(out: Path) -> list[Path]:
    from hostlink.calibration.rejected import RejectedStars, write_rejected

    one = np.array([1])
    write_rejected(out / "rejected.csv", RejectedStars(one, one, one, np.array(["outlier"]), np.array([2.0])))
    return [out / "rejected.csv"]


def _json_report(out: Path) -> list[Path]:
    """The JSON reports (``identify --report``, the bench's summary.json) and texts (README of ``example``)."""
    atomic.write_json(out / "report.json", {"ok": True})
    atomic.write_text(out / "README.txt", "text\n")
    return [out / "report.json", out / "README.txt"]


def _plot(out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure()
    fig.add_subplot().plot([0, 1], [0, 1])
    atomic.save_figure(out / "plot.png", fig)
    return [out / "plot.png"]


def _export_c(out: Path) -> list[Path]:
    from hostlink.portkit.export_c import write_c

    return [Path(p) for p in write_c(out / "c")]


def _vectors(out: Path) -> list[Path]:
    from hostlink.portkit.vectors import write_vectors

    return [Path(p) for p in write_vectors(out / "vectors")]


def _catalogue_cache(out: Path) -> list[Path]:
    from hostlink.sky.catalogue import Catalogue, _write_cache

    z = np.zeros(2)
    _write_cache(out / "hip.npz", Catalogue(np.array([1, 2], np.int64), z, z, z, z, z, z))
    return [out / "hip.npz"]


def _spool_chunk(out: Path) -> list[Path]:
    from hostlink.calibration.data import CalibrationData, save_chunk

    data = CalibrationData(
        x_px=np.zeros(2),
        y_px=np.zeros(2),
        r=np.tile([0.0, 0.0, 1.0], (2, 1)),
        frame_starts=np.array([0, 2]),
        frame_number=np.array([0]),
        star_id=np.array([1, 2]),
    )
    save_chunk(out / "c.spool", data)
    return [out / "c.spool"]


WRITERS = {
    "session-csv": _write_session_csv,
    "session-parquet": _write_session_parquet,
    "stream-session": _stream_session,
    "params": _params,
    "truth": _truth,
    "attitude": _attitude,
    "trace": _trace,
    "rejected-report": _rejected_report,
    "json-report-and-text": _json_report,
    "plot": _plot,
    "export-c": _export_c,
    "vectors": _vectors,
    "catalogue-cache": _catalogue_cache,
    "spool-chunk": _spool_chunk,
}


@pytest.mark.parametrize("name", list(WRITERS))
def test_a_symlink_planted_at_a_temporary_name_or_the_target_is_never_written_through(name, tmp_path, planted):
    write = WRITERS[name]
    first = write(tmp_path / "first")  # learns the targets a writer of several files writes
    targets = [tmp_path / "second" / t.relative_to(tmp_path / "first") for t in first]
    _plant_targets(planted.victim, targets)
    planted.links.clear()
    assert sorted(write(tmp_path / "second")) == sorted(targets)
    _check(planted, targets)
    for a, b in zip(sorted(first), sorted(targets), strict=True):
        if a.suffix in (".csv", ".json", ".txt", ".h", ".c"):
            assert a.read_bytes() == b.read_bytes()  # the same content as where nothing was planted


def test_the_emulated_flash_refuses_a_symlink_and_creates_a_new_image_without_following_one(tmp_path, planted):
    from hostlink.emulator.flash import FileFlash
    from hostlink.errors import UserError
    from onboard.banks import FLASH_BYTES

    os.symlink(planted.victim, tmp_path / "linked.bin")
    with pytest.raises(UserError, match="symbolic link"):
        FileFlash(tmp_path / "linked.bin")
    flash = FileFlash(tmp_path / "new.bin")  # a new image: created whole, past the planted temporary name
    flash.close()
    _check(planted, [tmp_path / "new.bin"])
    assert (tmp_path / "new.bin").stat().st_size == FLASH_BYTES


def test_temporary_names_are_unpredictable_and_created_exclusively(tmp_path):
    names = {atomic.temporary_name(tmp_path / "a.csv") for _ in range(100)}
    assert len(names) == 100 and all(n.parent == tmp_path and n.name.startswith(".a.csv.") for n in names)
    fd, first = atomic.create_exclusive(tmp_path / "a.csv")
    os.close(fd)
    with pytest.raises(FileExistsError):
        os.open(first, atomic._CREATE_FLAGS, 0o666)  # the flags never open what is there


@pytest.mark.parametrize(
    "link",
    [
        "serial:spy://loop://?file={out}@115200",
        "can:slcan:spy://loop://?file={out}@500000",
        "modbus-rtu:spy://loop://?file={out}@19200,unit=1",
    ],
    ids=["serial", "can-slcan", "modbus-rtu"],
)
def test_a_port_url_that_would_write_a_file_is_refused_unless_allowed(link, tmp_path, monkeypatch):
    from hostlink.errors import UserError
    from hostlink.links import open_link

    monkeypatch.delenv("HOSTLINK_ALLOW_URL_FILES", raising=False)
    out = tmp_path / "spied.txt"
    with pytest.raises(UserError, match="HOSTLINK_ALLOW_URL_FILES=1"):
        open_link(link.format(out=out), timeout_s=0.2)
    assert not out.exists()  # refused before pyserial opened anything


def test_a_spy_url_is_opened_when_allowed_and_its_file_is_written(tmp_path, monkeypatch):
    from hostlink.links import open_link

    monkeypatch.setenv("HOSTLINK_ALLOW_URL_FILES", "1")
    out = tmp_path / "spied.txt"
    master, slave = os.openpty()  # spy:// wraps a device port
    try:
        with open_link(f"serial:spy://{os.ttyname(slave)}?file={out}@115200", timeout_s=0.2):
            pass
    finally:
        os.close(master)
        os.close(slave)
    assert out.exists()  # the user asked for it: pyserial's spy handler made its log


def test_the_pattern_database_cache_is_never_unpickled_and_is_written_safely(tmp_path, monkeypatch, planted):
    """The identification cache lives in the user's cache folder: a file planted there must not run code when read
    (it was read with pickle.load). It is now the engine's own format; a pickle that would create a marker file when
    unpickled, planted under the cache's name, is regenerated over, and the marker never appears."""
    pytest.importorskip("tetra3rs")
    import pickle

    from hostlink.images import solver_adapter as sa
    from hostlink.sky.catalogue import cache_dir, load_catalogue

    catalogue = load_catalogue(maglim=5.0)  # (the Hipparcos cache is read from the real cache folder first)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    fov_min, fov_max = 10.0 / (1 + sa.FOV_MARGIN), 10.0 * (1 + sa.FOV_MARGIN)
    target = cache_dir() / sa._cache_name(fov_min, fov_max, 5.0, len(catalogue))
    target.parent.mkdir(parents=True)
    marker = tmp_path / "code-ran"

    class _Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    target.write_bytes(pickle.dumps(_Payload()))
    first = sa.pattern_database(catalogue, 10.0, 5.0)
    assert not marker.exists()
    assert target.is_file() and not target.is_symlink()
    again = sa.pattern_database(catalogue, 10.0, 5.0)  # read back from the cache (the engine's format)
    assert again.num_patterns == first.num_patterns > 0
    _check(planted, [target])
