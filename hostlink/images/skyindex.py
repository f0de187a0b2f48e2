"""The catalogue as lost-in-space identification (:mod:`hostlink.images.identify`) indexes it: the J2000 unit vectors
(:func:`catalogue_directions`, :class:`_Sky`) and their k-d tree (guided admission and the blends' companions use
both), held by a :class:`SkyIndex` that its caller builds once per catalogue; the own matcher's table of catalogue
pairs sorted by angle (:func:`pair_catalogue`) and what the rounds of
:func:`hostlink.images.identify.identify_iteratively` share of it (:class:`PairCache`); the places written for the
identified rows (:func:`catalogue_radec_deg`); and the widest field the camera model describes (:func:`check_field`)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from hostlink.files.session import Session
from hostlink.images import solver_adapter
from hostlink.images.pairtable import (  # noqa: F401 - _dot_rows, _ties_by_stars: imported from here by the matcher
    ANGLE_SAMPLE_PAIRS,
    PAIR_BUILD_ANGLE_BUCKETS,
    _dot_rows,
    _ties_by_stars,
    angle_index,
    find_pairs,
    pair_angles,
    sky_columns,
    sorted_pairs,
)
from hostlink.sky.catalogue import Catalogue
from onboard.camera import radec_to_unit
from onboard.params import CameraParams


@dataclass(frozen=True)
class _Sky:
    """The catalogue as J2000.0 unit vectors, with magnitudes and Hipparcos numbers (sorted, as the catalogue)."""

    hip: np.ndarray
    r: np.ndarray
    mag: np.ndarray


def catalogue_directions(catalogue: Catalogue) -> np.ndarray:
    """The J2000 unit vectors (S, 3) of ``catalogue``'s stars (``stars_at_j2000``, read-only): ``erfa.pmsafe`` over
    the whole catalogue, costly enough (docs/realsky.md, "Figures behind the speed choices") that a caller that asks
    more than once holds a :class:`SkyIndex`."""
    from hostlink.sky.apparent import stars_at_j2000

    stars = stars_at_j2000(catalogue)
    r_all = radec_to_unit(stars.ra_rad, stars.dec_rad)
    r_all.setflags(write=False)
    return r_all


class SkyIndex:
    """One catalogue as identification indexes it, each part built on first use and kept by this object (no module
    state): its J2000 unit vectors (:func:`catalogue_directions`), their k-d tree (``scipy.spatial.cKDTree``, for the
    guided admission and the blends' companions) and the :class:`_Sky`. Built once by whoever holds the catalogue
    (:class:`PairCache` for the rounds of :func:`hostlink.images.identify.identify_iteratively`) and passed along."""

    def __init__(self, catalogue: Catalogue) -> None:
        self.catalogue = catalogue

    @functools.cached_property
    def directions(self) -> np.ndarray:
        return catalogue_directions(self.catalogue)

    @functools.cached_property
    def tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.directions)

    @functools.cached_property
    def sky(self) -> _Sky:
        return _Sky(self.catalogue.hip, self.directions, self.catalogue.mag)


def sky_index(catalogue: Catalogue, held: SkyIndex | None = None) -> SkyIndex:
    """``held`` when it indexes ``catalogue`` (the same object), else a new :class:`SkyIndex` of it: for a function
    whose caller may hold one."""
    return held if held is not None and held.catalogue is catalogue else SkyIndex(catalogue)


def _sky(catalogue: Catalogue) -> _Sky:
    """The :class:`_Sky` of ``catalogue`` (a new :class:`SkyIndex`'s, for a caller that asks once)."""
    return SkyIndex(catalogue).sky


def _mirror_x(x_px: np.ndarray, theta: np.ndarray, mirrored: bool) -> np.ndarray:
    """Column coordinates mirrored about the principal point's column when ``mirrored`` (a mirrored detector seen
    through a proper camera), unchanged otherwise."""
    return 2.0 * theta[1] - x_px if mirrored else x_px


@dataclass(frozen=True)
class PairCatalogue:
    """Every pair of catalogue stars closer than ``max_angle_rad``, sorted by angle: the fallback matcher's index.

    a, b: (P,) int32 indices into the :class:`_Sky` arrays (a < b), in ascending order of their separation;
    angle_sample_rad: the separation of every :data:`~hostlink.images.pairtable.ANGLE_SAMPLE_PAIRS`-th pair (the
    others computed again where a search needs them: :func:`pair_window`); r: the sky's unit vectors (indexed by a
    and b); rows: the sky indices of the stars taking part (brighter than the limit), and tree: a k-d tree of their
    unit vectors (``scipy.spatial.cKDTree``)."""

    a: np.ndarray
    b: np.ndarray
    angle_sample_rad: np.ndarray
    max_angle_rad: float
    r: np.ndarray
    rows: np.ndarray
    tree: object
    #: (S,) uint16: each sky star's rank among ``rows`` (None when more than 65536 stars take part): a 16-bit sort
    #: key, which numpy's stable sort orders in linear time (radix sort), for :func:`_pairs_of_angle`
    rank16: np.ndarray | None
    #: the three columns of ``r`` (x, y, z), each contiguous (:func:`sky_columns`), for :func:`_dot_rows`
    columns: tuple[np.ndarray, np.ndarray, np.ndarray]


def pair_window(pairs: PairCatalogue, lo_rad: float, hi_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(a, b) of the pairs of ``pairs`` whose angle lies in [``lo_rad``, ``hi_rad``), in their order (views)."""
    lo, hi = (_index(pairs, angle_rad, "left") for angle_rad in (lo_rad, hi_rad))
    return pairs.a[lo:hi], pairs.b[lo:hi]


def _index(pairs: PairCatalogue, angle_rad: float, side: str) -> int:
    """``np.searchsorted`` of ``angle_rad`` among the angles of ``pairs`` (:func:`angle_index`)."""
    return angle_index(pairs.angle_sample_rad, pairs.columns, pairs.a, pairs.b, angle_rad, side)


def pair_arrays(pairs: PairCatalogue) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The table's (a, b, angle_rad), every angle computed (:func:`pair_angles`): what a table of all the angles
    would hold (for tests and inspection)."""
    return pairs.a, pairs.b, pair_angles(pairs.columns, pairs.a, pairs.b)


def pair_catalogue(sky: _Sky, max_angle_rad: float, maglim: float) -> PairCatalogue:
    """The pairs of stars brighter than ``maglim`` within ``max_angle_rad`` (k-d trees on the unit vectors,
    ``scipy.spatial.cKDTree``, within the chord 2 sin(angle / 2): :func:`hostlink.images.pairtable.find_pairs`), in
    the order (angle, a, b): pairs of exactly the same angle (a double star's partners, angles that round alike) in
    the order of their sky indices, not the tree's traversal, so that a table cut from a larger one
    (:meth:`PairCache.pairs`) is the same table (:func:`hostlink.images.pairtable.sorted_pairs`: 8 bytes a pair and
    the sampled angles; the build's peak is its 9 bytes a pair of staging)."""
    from scipy.spatial import cKDTree

    rows = np.flatnonzero(sky.mag <= maglim)
    chord = 2.0 * math.sin(0.5 * max_angle_rad)
    points = sky.r[rows]
    columns = sky_columns(sky.r)
    edges = max_angle_rad * np.sqrt(np.arange(1, PAIR_BUILD_ANGLE_BUCKETS) / PAIR_BUILD_ANGLE_BUCKETS)
    a, b, samples = sorted_pairs(find_pairs(points, rows, chord, columns, edges), edges.size + 1, columns)
    tree = cKDTree(points)
    return PairCatalogue(a, b, samples, max_angle_rad, sky.r, rows, tree, _rank16(sky, rows), columns)


def _rank16(sky: _Sky, rows: np.ndarray) -> np.ndarray | None:
    """:attr:`PairCatalogue.rank16` of the stars ``rows`` (None for more than 65536 stars)."""
    if rows.size > 1 << 16:
        return None
    rank16 = np.zeros(sky.r.shape[0], dtype=np.uint16)
    rank16[rows] = np.arange(rows.size, dtype=np.uint16)
    return rank16


#: :class:`PairCache` builds its table this much wider than asked [fraction of the angle]: the next round of
#: :func:`identify_iteratively` asks for the detector's diagonal through its calibrated focal length, which differs
#: from the round before's by the calibration's change (0.5 % on openstartracker), and a table wider than asked is cut
#: to it in a few array passes where building it again takes seconds (20 million pairs to Hp 9 on a 9-deg field).
PAIR_CACHE_ANGLE_MARGIN = 0.05
#: ... and this much deeper [mag]: the next round asks as deep as its identified stars go, which moves with the stars
#: a round adds (0.004 mag deeper in round 2 on openstartracker, where the table to Hp 8.66 took 2.5 s to build again);
#: 0.05 mag more stars (~7 %) make the one build ~15 % longer.
PAIR_CACHE_MAG_MARGIN = 0.05


class PairCache:
    """What the rounds of one :func:`identify_iteratively` share and do not change: the catalogue as unit vectors
    and their tree (:class:`SkyIndex`), the own matcher's pair table (:func:`pair_catalogue`, built once a little
    wider than asked and cut to each round's angle and depth: the same table a fresh build gives; the last cut held,
    a round asking for the same depth over no wider an angle gets its leading part) and the engine's pattern
    database."""

    def __init__(self) -> None:
        self._indexes: dict[int, tuple[Catalogue, SkyIndex]] = {}
        self._table: PairCatalogue | None = None
        self._table_maglim = -math.inf
        #: the last cut and what it was cut from and to: (the table, the sky's magnitudes, the depth, the cut)
        self._cut: tuple[PairCatalogue, np.ndarray, float, PairCatalogue] | None = None
        self._databases: dict[tuple, tuple[Catalogue, object]] = {}
        self._subsets: dict[tuple, tuple[Catalogue, Catalogue]] = {}

    def bright(self, catalogue: Catalogue, maglim: float) -> Catalogue:
        """The stars of ``catalogue`` at least ``maglim`` bright (one subset per catalogue and limit)."""
        key = (id(catalogue), maglim)
        held = self._subsets.get(key)
        if held is None or held[0] is not catalogue:
            held = (catalogue, catalogue.subset(np.flatnonzero(catalogue.mag <= maglim)))
            self._subsets[key] = held
        return held[1]

    def index(self, catalogue: Catalogue) -> SkyIndex:
        """The :class:`SkyIndex` of ``catalogue`` (one per catalogue object)."""
        held = self._indexes.get(id(catalogue))
        if held is None or held[0] is not catalogue:
            held = (catalogue, SkyIndex(catalogue))
            self._indexes[id(catalogue)] = held
        return held[1]

    def sky(self, catalogue: Catalogue) -> _Sky:
        """:func:`_sky` of ``catalogue`` (computed once per catalogue object, :meth:`index`)."""
        return self.index(catalogue).sky

    def database(self, catalogue: Catalogue, fov_deg: float, maglim: float | None):
        """:func:`solver_adapter.pattern_database` (read once)."""
        key = (id(catalogue), fov_deg, maglim)
        held = self._databases.get(key)
        if held is None or held[0] is not catalogue:
            held = (catalogue, solver_adapter.pattern_database(catalogue, fov_deg, maglim))
            self._databases[key] = held
        return held[1]

    def pairs(self, sky: _Sky, max_angle_rad: float, maglim: float) -> PairCatalogue:
        """:func:`pair_catalogue` (``sky``, ``max_angle_rad``, ``maglim``), cut from the table held when it covers
        them (the same sky, as wide and as deep), else built (:data:`PAIR_CACHE_ANGLE_MARGIN` wider,
        :data:`PAIR_CACHE_MAG_MARGIN` deeper) and held."""
        table = self._table
        if table is None or table.r is not sky.r or max_angle_rad > table.max_angle_rad or maglim > self._table_maglim:
            wide = max_angle_rad * (1.0 + PAIR_CACHE_ANGLE_MARGIN)
            deep = maglim + PAIR_CACHE_MAG_MARGIN
            deep = max(deep, self._table_maglim) if table is not None and table.r is sky.r else deep
            table = pair_catalogue(sky, wide, deep)
            self._table, self._table_maglim = table, deep
        held = self._cut
        same_depth = held is not None and held[0] is table and held[1] is sky.mag and held[2] == maglim
        if same_depth and max_angle_rad <= held[3].max_angle_rad:
            return _narrower(held[3], max_angle_rad)
        held = self._cut = None  # the cut before is let go before this one is made (two at once: 0.1 GB more)
        cut = _cut(table, sky, max_angle_rad, maglim, self._table_maglim)
        self._cut = (table, sky.mag, maglim, cut)
        return cut


def _narrower(pairs: PairCatalogue, max_angle_rad: float) -> PairCatalogue:
    """The pairs of ``pairs`` within ``max_angle_rad`` (no wider than its own): its leading part, as it is in
    (angle, a, b) order, with the same stars taking part (the same table :func:`_cut` gives)."""
    return replace(_leading(pairs, max_angle_rad), max_angle_rad=max_angle_rad)


def _leading(pairs: PairCatalogue, max_angle_rad: float) -> PairCatalogue:
    """``pairs`` with its arrays and samples sliced to the pairs within ``max_angle_rad`` (views, not copies)."""
    n = _index(pairs, max_angle_rad, "right")
    samples = pairs.angle_sample_rad[: -(-n // ANGLE_SAMPLE_PAIRS)]
    return replace(pairs, a=pairs.a[:n], b=pairs.b[:n], angle_sample_rad=samples)


def _cut(table: PairCatalogue, sky: _Sky, max_angle_rad: float, maglim: float, table_maglim: float) -> PairCatalogue:
    """The pairs of ``table`` (built to ``table_maglim``) within ``max_angle_rad`` of stars brighter than ``maglim``:
    ``table`` is in (angle, a, b) order, and so is every subset of it. The table's arrays sliced to the angle (views)
    when no star is left out, else the pairs of both stars bright enough copied (:func:`_pairs_of_stars`)."""
    from scipy.spatial import cKDTree

    cut = replace(_leading(table, max_angle_rad), max_angle_rad=max_angle_rad)
    if maglim < table_maglim:
        bright = sky.mag <= maglim
        if np.count_nonzero(bright) < table.rows.size:  # else the same stars (none between the depths): the same
            rows = np.flatnonzero(bright)
            a, b, samples = _pairs_of_stars(cut, bright)
            cut = replace(cut, a=a, b=b, angle_sample_rad=samples, rows=rows, tree=cKDTree(sky.r[rows]))
            cut = replace(cut, rank16=_rank16(sky, rows))
    return cut


#: :func:`_pairs_of_stars` tests this many pairs at a time [pairs]: its temporaries stay a few MB whatever the table.
CUT_BLOCK_PAIRS = 1 << 20


def _pairs_of_stars(pairs: PairCatalogue, bright: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, samples) of the pairs of ``pairs`` both of whose stars are ``bright`` ((S,) bool), in their order:
    counted block by block (:data:`CUT_BLOCK_PAIRS`), then taken block by block into arrays of that size (the cut
    costs its own 8 bytes a pair, not a (P,) mask of the table); the samples the angles of every
    :data:`ANGLE_SAMPLE_PAIRS`-th kept pair (:func:`pair_angles`: the bits a build of the cut gives)."""
    starts = range(0, pairs.a.size, CUT_BLOCK_PAIRS)

    def kept(start: int) -> np.ndarray:
        stop = start + CUT_BLOCK_PAIRS
        return bright[pairs.a[start:stop]] & bright[pairs.b[start:stop]]

    counts = [int(np.count_nonzero(kept(start))) for start in starts]
    a = np.empty(sum(counts), dtype=pairs.a.dtype)
    b = np.empty(sum(counts), dtype=pairs.b.dtype)
    at = 0
    for start, count in zip(starts, counts, strict=True):
        keep = kept(start)
        a[at : at + count] = pairs.a[start : start + CUT_BLOCK_PAIRS][keep]
        b[at : at + count] = pairs.b[start : start + CUT_BLOCK_PAIRS][keep]
        at += count
    return a, b, pair_angles(pairs.columns, a[::ANGLE_SAMPLE_PAIRS], b[::ANGLE_SAMPLE_PAIRS])


#: The widest diagonal field [deg] the camera model (a pinhole with polynomial distortion, docs/camera-model.md)
#: describes: at 60 deg off axis a fisheye's equidistant image (r = f theta) lies 40 % inside the pinhole's
#: (r = f tan theta), more than the polynomial's few-% corrections can bend, and at 90 deg the pinhole has none.
MAX_DIAGONAL_FIELD_DEG = 120.0


def diagonal_field_deg(camera: CameraParams) -> float:
    """The detector's diagonal field through the pinhole of ``camera`` [deg]."""
    width, height = camera.image_size_px
    return math.degrees(2.0 * math.atan(0.5 * math.hypot(width, height) / camera.focal_length_px))


def check_field(camera: CameraParams) -> None:
    """A one-line :class:`UserError` for a lens too wide for the camera model (:data:`MAX_DIAGONAL_FIELD_DEG`)."""
    from hostlink.errors import UserError

    field = diagonal_field_deg(camera)
    if field > MAX_DIAGONAL_FIELD_DEG:
        raise UserError(
            f"the nominal camera sees {field:.0f} deg across the diagonal: a lens this wide (a fisheye) is outside "
            f"the camera model (a pinhole with polynomial distortion, up to {MAX_DIAGONAL_FIELD_DEG:.0f} deg); "
            "check the nominal focal length"
        )


def _field_sr(camera: CameraParams) -> float:
    """The detector's field [sr] through the pinhole of ``camera`` (4 asin(sin(a) sin(b)) for a rectangle of half
    angles a, b about the axis)."""
    width, height = camera.image_size_px
    a = math.atan(0.5 * width / camera.focal_length_px)
    b = math.atan(0.5 * height / camera.focal_length_px)
    return 4.0 * math.asin(math.sin(a) * math.sin(b))


def _with_identities(session: Session, star_id: np.ndarray, catalogue: Catalogue) -> Session:
    """``session`` with ``star_id``; when the file has ra_deg/dec_deg, the newly identified rows get theirs (the
    geocentric apparent place at the frame's time, docs/file-formats.md; the J2000 place when the time is unknown)."""
    out = replace(session, star_id=star_id)
    if session.ra_deg is None or session.dec_deg is None:
        return out
    new = np.flatnonzero((star_id != 0) & (session.star_id == 0))
    ra, dec = session.ra_deg.copy(), session.dec_deg.copy()
    if new.size:
        from hostlink.sky.apparent import hip_lookup

        ra[new], dec[new] = catalogue_radec_deg(session, catalogue, hip_lookup(catalogue, star_id[new]), new)
    return replace(out, ra_deg=ra, dec_deg=dec)


def catalogue_radec_deg(
    session: Session, catalogue: Catalogue, cat_rows: np.ndarray, rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(ra, dec) [deg] of the catalogue stars ``cat_rows`` as the session's rows ``rows`` see them: the geocentric
    apparent place at the row's frame time (docs/file-formats.md), the J2000 place when the time is unknown."""
    from hostlink.sky.apparent import apparent_radec_deg, stars_at_j2000

    if session.time_known:
        jd1, jd2 = session.frame_times_jd()
        frame_of_row = np.repeat(np.arange(jd1.size), np.diff(session.frame_starts))[rows]
        return apparent_radec_deg(catalogue, cat_rows, jd1[frame_of_row], jd2[frame_of_row])
    stars = stars_at_j2000(catalogue, cat_rows)
    return np.degrees(stars.ra_rad), np.degrees(stars.dec_rad)
