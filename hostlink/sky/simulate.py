"""The real-sky sensor simulator behind ``hostlink simulate`` (docs/file-formats.md): Hipparcos stars at their
geocentric apparent place at each frame's time, seen through the true camera, as a session plus its truth.

Per frame k (time t_k = t0 + k * interval, on the session file's 1 ms grid):

1. attitude C_k (b = C r): scripted, or drawn uniformly over SO(3) (space), or for a ground site with the boresight
   uniform in solid angle between the zenith distances ``zenith_range_deg`` and uniform azimuth and roll;
2. reference directions r: ``hostlink.sky.apparent`` (pyerfa apci13/atciq, ra = ri - eo) exactly at t_k; for a ground
   site the observed direction is r aberrated by the site's rotation velocity (diurnal aberration, <= 0.32",
   ``erfa.pvtob`` + ``erfa.ab``) and, with weather, then lifted toward the zenith by ERFA's refraction
   (``hostlink.sky.site.observed_directions_truth``; checked against ``erfa.atco13`` to 1e-4");
3. the true camera: F_k = 1000 f_k / p with f_k = f + A sin(2 pi k / P) (thermal drift, A in micrometres), the
   measured centroid is the exact inverse of the Weng model (``onboard.camera.unit_to_pixels``) plus independent
   Gaussian noise of ``noise_px`` per axis;
4. only stars whose measured centroid lies on the detector ([-0.5, w-0.5] x [-0.5, h-0.5]) are kept, the brightest
   ``max_stars``; a random-attitude frame with fewer than ``min_stars`` is redrawn (a scripted one is kept as is);
5. options: a fraction of the real stars get a wrong identity (another Hipparcos star among the 12 nearest the true
   one, not otherwise in the frame, with that star's reference direction), false stars (star_id 0, no ra/dec) are
   added at uniform random pixels, Poisson with mean ``false_star_fraction`` x the frame's real stars.

The CSV's ra_deg/dec_deg are always the geocentric apparent place (never refracted), as docs/file-formats.md defines
them.
The truth (camera, noise, per-frame C and f, misidentified and false rows, site, weather) is a compact JSON beside
the session (``SESSION.truth.json``, ``hostlink.files.truth``), with per-frame quantities stored as arrays.

Star lookup: the catalogue's apparent directions are evaluated once per half-day bucket of frame times; a frame's
candidates are the stars within the detector's half-diagonal field plus a margin (``_LOOKUP_MARGIN_RAD``, covering
the drift of aberration, precession-nutation and proper motion over half a day, < 1", and the refraction lift).
The candidates' exact directions then come from ERFA at each frame's own time: nothing is interpolated.

Camera files (package data, ``load_params("builtin:NAME")``): ``seed004_camera`` is seed 004's simulated camera
(f 70.2262 mm, 12 um, 1024 x 1024, principal point (500, 530), seed k1 2e-10, k2 -3.5e-15 converted by
``onboard.params.distortion_from_seed004``); ``seed004_nominal`` is what its user knows before calibrating: the
70 mm design focal length, the detector's pitch and size, the principal point at the image centre (511.5, 511.5)
and no distortion.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.params import BUILTIN_PREFIX, load_params
from hostlink.files.session import Session, SessionWriter, concatenate_sessions
from hostlink.files.times import frame_times_range, parse_iso_utc, parse_iso_utc_many
from hostlink.files.truth import TRUTH_FORMAT, TRUTH_PER_FRAME_KEYS, TRUTH_VERSION, TruthWriter
from hostlink.sky.apparent import (
    StarsJ2000,
    apparent_from_astrometry,
    frame_astrometry,
    radec_deg_of_units,
    stars_at_j2000,
)
from hostlink.sky.catalogue import load_catalogue
from hostlink.sky.site import (
    MAX_ZENITH_DISTANCE_DEG,
    local_north_east,
    observed_directions_truth,
    refract_directions_truth,
    refraction_observed_rad,
    site_velocity_true_of_date,
    zenith_distance_rad,
    zenith_true_of_date,
)
from onboard.camera import distortion_px, pixels_to_unit, unit_to_pixels
from onboard.params import CameraParams, params_to_dict
from onboard.site import Site, Weather

#: Lookup margin [rad] beyond the field radius: 60" covers the half-day drift of the lookup directions (< 1").
_LOOKUP_MARGIN_RAD = math.radians(60.0 / 3600.0)
#: Lookup directions are recomputed for every bucket of this many days of frame times.
_LOOKUP_BUCKET_DAYS = 0.5
#: Number of nearest catalogue neighbours among which a misidentified star's wrong identity is drawn.
_MISID_NEIGHBOURS = 12
#: Frames per processing chunk (bounds memory and sets the progress granularity).
_CHUNK_FRAMES = 2000
#: Random-attitude redraw rounds before giving up on ``min_stars``.
_MAX_ROUNDS = 200
#: Elements per block of the (frames x stars) lookup dot products (bounds memory to ~32 MB).
_LOOKUP_BLOCK = 4_000_000
#: False stars get a magnitude uniform in [maglim - this, maglim].
_FALSE_STAR_MAG_SPAN = 3.0


@dataclass
class SimConfig:
    """What to simulate. Units: noise [px per axis], focal drift amplitude [um of focal length] with a period in
    frames, zenith range [deg], frame interval [s]. ``attitudes``: scripted (frames, 3, 3) matrices C with b = C r
    (C maps the observed direction for a ground site: apparent + diurnal aberration [+ refraction with weather];
    the apparent direction otherwise)."""

    camera: CameraParams
    frames: int
    noise_px: float = 0.05
    min_stars: int = 10
    max_stars: int = 30
    maglim: float = 6.0
    seed: int = 0
    t0_iso: str = "2026-03-14T02:10:00.000Z"
    frame_interval_s: float = 1.0
    misid_fraction: float = 0.0
    false_star_fraction: float = 0.0
    focal_drift_um: float = 0.0
    focal_drift_period_frames: float = 3000.0
    site: Site | None = None
    weather: Weather | None = None
    zenith_range_deg: tuple[float, float] = (0.0, 75.0)
    attitudes: np.ndarray | None = None
    dut1_s: float = 0.0


@dataclass
class SimResult:
    """The simulated session and its truth (the JSON object written beside it)."""

    session: Session
    truth: dict = field(default_factory=dict)

    @property
    def attitude(self) -> np.ndarray:
        """Per-frame true attitude C (frames, 3, 3), b = C r."""
        return np.asarray(self.truth["attitude"], dtype=np.float64).reshape(-1, 3, 3)

    @property
    def focal_length_mm(self) -> np.ndarray:
        """Per-frame true focal length [mm]."""
        return np.asarray(self.truth["focal_length_mm"], dtype=np.float64)


def seed004_camera() -> CameraParams:
    """Seed 004's simulated camera (sec. 4): f 70.2262 mm, 12 um, 1024 x 1024, (x0, y0) = (500, 530),
    k1 = 2e-10, k2 = -3.5e-15 in the seed's convention: the package data ``builtin:seed004_camera``."""
    return load_params(BUILTIN_PREFIX + "seed004_camera")


def seed004_config(frames: int = 1000, seed: int = 0) -> SimConfig:
    """Seed 004's simulation setup: its camera, Hp <= 6, >= 10 stars per frame, 0.05 px noise, 1000 frames."""
    return SimConfig(camera=seed004_camera(), frames=frames, noise_px=0.05, min_stars=10, maglim=6.0, seed=seed)


# ----------------------------------------------------------------------------------------------------------------
# configuration checks


def _check_config(cfg: SimConfig) -> None:
    bad = UserError
    if not isinstance(cfg.frames, (int, np.integer)) or cfg.frames < 1:
        raise bad(f"frames must be a whole number >= 1, got {cfg.frames!r}")
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, (int, np.integer)) or cfg.seed < 0:
        raise bad(f"--seed must be a whole number >= 0, got {cfg.seed!r}")  # numpy's generators take no other
    if not (math.isfinite(cfg.noise_px) and cfg.noise_px >= 0):
        raise bad(f"noise must be a finite number >= 0 px, got {cfg.noise_px!r}")
    if not (1 <= cfg.min_stars <= cfg.max_stars):
        raise bad(f"need 1 <= min-stars <= max-stars, got {cfg.min_stars} and {cfg.max_stars}")
    if not math.isfinite(cfg.maglim):
        raise bad(f"magnitude limit must be finite, got {cfg.maglim!r}")
    if not (math.isfinite(cfg.frame_interval_s) and cfg.frame_interval_s > 0):
        raise bad(f"frame interval must be > 0 s, got {cfg.frame_interval_s!r}")
    for name, value in (("misid", cfg.misid_fraction), ("false-stars", cfg.false_star_fraction)):
        if not (math.isfinite(value) and 0 <= value < 1):
            raise bad(f"--{name} must be a fraction in [0, 1), got {value!r}")
    if not math.isfinite(cfg.focal_drift_um):
        raise bad(f"focal drift amplitude must be finite, got {cfg.focal_drift_um!r}")
    if not (math.isfinite(cfg.focal_drift_period_frames) and cfg.focal_drift_period_frames > 0):
        raise bad(f"focal drift period must be > 0 frames, got {cfg.focal_drift_period_frames!r}")
    if abs(cfg.focal_drift_um) / 1000.0 >= 0.5 * cfg.camera.focal_length_mm:
        raise bad(f"focal drift amplitude {cfg.focal_drift_um} um is not small against f")
    if cfg.weather is not None and cfg.site is None:
        raise bad("weather needs a site (refraction depends on where the sensor is)")
    zmin, zmax = (float(v) for v in cfg.zenith_range_deg)
    if not (0 <= zmin <= zmax <= 80):
        raise bad(f"zenith range must satisfy 0 <= min <= max <= 80 deg, got {zmin}, {zmax}")
    try:
        parse_iso_utc(cfg.t0_iso)
        parse_iso_utc_many([cfg.t0_iso])
    except ValueError as exc:
        raise bad(f"start time: {exc}") from None
    if cfg.attitudes is not None:
        att = np.asarray(cfg.attitudes, dtype=np.float64)
        if att.shape != (cfg.frames, 3, 3):
            raise bad(f"scripted attitudes must have shape ({cfg.frames}, 3, 3), got {att.shape}")
        err = np.abs(att @ np.swapaxes(att, 1, 2) - np.eye(3)).max(initial=0.0)
        if not (err < 1e-9 and np.all(np.linalg.det(att) > 0)):
            raise bad(f"scripted attitudes must be proper rotations (orthonormality error {err:.2g})")


# ----------------------------------------------------------------------------------------------------------------
# times and attitudes


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """n rotation matrices uniform over SO(3) (normalised Gaussian quaternions, Shoemake 1992)."""
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


def _ground_rotations(
    rng: np.random.Generator, zenith: np.ndarray, zenith_range_deg: tuple[float, float]
) -> np.ndarray:
    """Attitudes whose boresight (row 3 of C) has zenith distance uniform in solid angle within the range, uniform
    azimuth, and uniform roll about the boresight; ``zenith`` (n, 3) true of date."""
    n = zenith.shape[0]
    north, east = local_north_east(zenith)
    cos_lo, cos_hi = np.cos(np.radians(zenith_range_deg[1])), np.cos(np.radians(zenith_range_deg[0]))
    cz = rng.uniform(cos_lo, cos_hi, n)
    sz = np.sqrt(np.maximum(0.0, 1 - cz * cz))
    az = rng.uniform(0.0, 2 * np.pi, n)
    roll = rng.uniform(0.0, 2 * np.pi, n)
    horiz = np.cos(az)[:, None] * north + np.sin(az)[:, None] * east
    bore = cz[:, None] * zenith + sz[:, None] * horiz
    t1 = -sz[:, None] * zenith + cz[:, None] * horiz  # perpendicular to the boresight, in its vertical plane
    t2 = np.cross(bore, t1)
    x_s = np.cos(roll)[:, None] * t1 + np.sin(roll)[:, None] * t2
    y_s = np.cross(bore, x_s)
    return np.stack([x_s, y_s, bore], axis=1)


def focal_lengths_mm(cfg: SimConfig, frames: np.ndarray | None = None) -> np.ndarray:
    """Per-frame true focal length f_k = f + A sin(2 pi k / P) [mm] (A in um), of every frame or of ``frames``."""
    k = np.arange(cfg.frames, dtype=np.float64) if frames is None else np.asarray(frames, dtype=np.float64)
    return cfg.camera.focal_length_mm + cfg.focal_drift_um / 1000.0 * np.sin(
        2 * np.pi * k / cfg.focal_drift_period_frames
    )


def field_radius_rad(camera: CameraParams) -> float:
    """Largest angle from the boresight of any detector point (corners and edge midpoints), through the camera."""
    w, h = camera.image_size_px
    xs = np.array([-0.5, w - 0.5, -0.5, w - 0.5, w / 2 - 0.5, w / 2 - 0.5, -0.5, w - 0.5])
    ys = np.array([-0.5, -0.5, h - 0.5, h - 0.5, -0.5, h - 0.5, h / 2 - 0.5, h / 2 - 0.5])
    b = pixels_to_unit(xs, ys, camera.model_vector())
    return float(np.arccos(np.clip(b[:, 2].min(), -1.0, 1.0)))


def distortion_pad_px(camera: CameraParams) -> float:
    """How far [px] outside the detector an ideal point may lie and still be measured on it: the measured point is
    the ideal one plus the distortion (dx, dy) there, so 1.5 x the largest |(dx, dy)| on a 33 x 33 grid over the
    detector (the factor covers the grid spacing), plus 10 px."""
    w, h = camera.image_size_px
    gx, gy = np.meshgrid(np.linspace(-0.5, w - 0.5, 33), np.linspace(-0.5, h - 0.5, 33))
    theta = camera.model_vector()
    dx, dy = distortion_px(gx.ravel() - theta[1], gy.ravel() - theta[2], theta)
    return 1.5 * float(np.max(np.hypot(dx, dy))) + 10.0


# ----------------------------------------------------------------------------------------------------------------
# the simulation proper


@dataclass
class _SkyContext:
    """Everything fixed for a session: catalogue, its J2000 data, the lookup directions per half-day bucket of frame
    times, and per frame only what is small (bucket, focal scale; 16 bytes a frame). The per-frame ERFA astrometry,
    zenith and site velocity are made chunk by chunk (:class:`_ChunkSky`)."""

    cfg: SimConfig
    hip: np.ndarray
    mag: np.ndarray
    stars: StarsJ2000
    bucket: np.ndarray  # (F,) lookup bucket index
    lookup: list[np.ndarray]  # per bucket (N, 3) approximate apparent directions
    cos_lookup: float
    theta: np.ndarray  # model vector of the nominal (undrifted) camera
    focal_scale: np.ndarray  # (F,) F_k / F
    pad_px: float  # ideal points farther than this off the detector cannot be measured on it


@dataclass
class _ChunkSky:
    """The per-frame sky of frames ``first`` .. ``first + n - 1``: time strings, ERFA astrometry, equation of the
    origins, zenith and site velocity (true of date; None in space). Indexed by frame - ``first``."""

    first: int
    t_text: np.ndarray
    astrom: np.ndarray
    eo: np.ndarray
    zenith: np.ndarray | None
    site_velocity: np.ndarray | None


def _session_jd(cfg: SimConfig, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """UTC two-part Julian dates of every frame (16 bytes a frame), made :data:`_CHUNK_FRAMES` at a time so the
    time strings of a long session are never all in memory (the same values as :func:`frame_times`)."""
    jd1, jd2 = np.empty(n_frames), np.empty(n_frames)
    for a in range(0, n_frames, _CHUNK_FRAMES):
        b = min(n_frames, a + _CHUNK_FRAMES)
        _, jd1[a:b], jd2[a:b] = frame_times_range(cfg.t0_iso, cfg.frame_interval_s, a, b)
    return jd1, jd2


def _chunk_sky(cfg: SimConfig, jd1: np.ndarray, jd2: np.ndarray, a: int, b: int) -> _ChunkSky:
    t_text, _, _ = frame_times_range(cfg.t0_iso, cfg.frame_interval_s, a, b)
    astrom, eo = frame_astrometry(jd1[a:b], jd2[a:b])
    site = cfg.site
    zenith = zenith_true_of_date(jd1[a:b], jd2[a:b], site, cfg.dut1_s) if site is not None else None
    velocity = site_velocity_true_of_date(jd1[a:b], jd2[a:b], site, cfg.dut1_s) if site is not None else None
    return _ChunkSky(a, t_text, astrom, eo, zenith, velocity)


def _build_context(cfg: SimConfig, jd1: np.ndarray, jd2: np.ndarray) -> _SkyContext:
    cat = load_catalogue(cfg.maglim)
    if len(cat) < cfg.min_stars:
        raise UserError(f"only {len(cat)} Hipparcos stars have Hp <= {cfg.maglim}: fewer than --min-stars")
    stars = stars_at_j2000(cat)
    days = (jd1 - jd1[0]) + (jd2 - jd2[0])
    bucket = np.floor(days / _LOOKUP_BUCKET_DAYS).astype(np.int64)
    lookup = []
    for b in range(int(bucket.max()) + 1):
        members = np.flatnonzero(bucket == b)
        if members.size == 0:
            lookup.append(np.zeros((0, 3)))
            continue
        mid = members[members.size // 2]
        astrom, eo = frame_astrometry(jd1[mid : mid + 1], jd2[mid : mid + 1])
        lookup.append(apparent_from_astrometry(stars, astrom[0], eo[0]))
    focal_mm = focal_lengths_mm(cfg)
    radius = field_radius_rad(cfg.camera.with_focal_length_mm(float(focal_mm.min()))) + _LOOKUP_MARGIN_RAD
    if cfg.weather is not None:
        # refraction lifts a star by at most its value at the lowest pointing plus the field radius
        z_edge = min(math.radians(cfg.zenith_range_deg[1]) + radius, math.radians(MAX_ZENITH_DISTANCE_DEG))
        radius += float(refraction_observed_rad(np.array([z_edge]), cfg.weather)[0]) * 1.1
    if radius >= math.pi / 2:
        raise UserError("the camera's field of view is too wide for this simulator (>= 180 deg)")
    return _SkyContext(
        cfg=cfg,
        hip=cat.hip,
        mag=cat.mag,
        stars=stars,
        bucket=bucket,
        lookup=lookup,
        cos_lookup=math.cos(radius),
        theta=cfg.camera.model_vector(np.float64),
        focal_scale=focal_mm / cfg.camera.focal_length_mm,
        pad_px=distortion_pad_px(cfg.camera),
    )


def _candidates(ctx: _SkyContext, frames: np.ndarray, boresight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position in ``frames``, catalogue row) of every star within the lookup radius of each boresight."""
    out_f, out_s = [], []
    for b in np.unique(ctx.bucket[frames]):
        sel = np.flatnonzero(ctx.bucket[frames] == b)
        ref = ctx.lookup[b]
        block = max(1, _LOOKUP_BLOCK // max(1, ref.shape[0]))
        for a in range(0, sel.size, block):
            part = sel[a : a + block]
            fi, si = np.nonzero(boresight[part] @ ref.T > ctx.cos_lookup)
            out_f.append(part[fi])
            out_s.append(si)
    if not out_f:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_f).astype(np.int64), np.concatenate(out_s).astype(np.int64)


def _rank_within_groups(group: np.ndarray) -> np.ndarray:
    """Position of each element within its run of equal ``group`` values (``group`` sorted)."""
    n = group.size
    if n == 0:
        return np.zeros(0, np.int64)
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    run_start = np.repeat(starts, np.diff(np.r_[starts, n]))
    return np.arange(n) - run_start


def _observe(
    ctx: _SkyContext, sky: _ChunkSky, rng: np.random.Generator, frames: np.ndarray, att: np.ndarray
) -> dict[str, np.ndarray]:
    """Observe the sky in ``frames`` (global indices, within ``sky``'s chunk) with attitudes ``att`` (n, 3, 3): the
    kept rows, sorted by (frame, magnitude), at most max_stars per frame. Returns global frame, catalogue row, x, y,
    apparent r."""
    cfg = ctx.cfg
    pos, star = _candidates(ctx, frames, att[:, 2, :])
    frame = frames[pos]
    local = frame - sky.first
    r_app = apparent_from_astrometry(ctx.stars.take(star), sky.astrom[local], sky.eo[local])
    r_obs = r_app
    if cfg.site is not None:
        r_obs = observed_directions_truth(r_app, sky.zenith[local], sky.site_velocity[local], None)
    if cfg.weather is not None:
        # the refracted direction is the topocentric one (diurnal aberration can lower a star by 0.03" at 85 deg)
        zd = zenith_distance_rad(r_obs, sky.zenith[local])
        above = zd <= math.radians(MAX_ZENITH_DISTANCE_DEG)  # lower stars are beyond the refraction model
        pos, star, frame, r_app, local = pos[above], star[above], frame[above], r_app[above], local[above]
        r_obs = refract_directions_truth(r_obs[above], sky.zenith[local], cfg.weather)
    b = np.einsum("nij,nj->ni", att[pos], r_obs)
    # thermal drift: F_k b_x / b_z = F (s_k b_x) / b_z, so scaling b_x, b_y by s_k = F_k / F uses the nominal theta
    scale = ctx.focal_scale[frame]
    b_scaled = np.stack([b[:, 0] * scale, b[:, 1] * scale, b[:, 2]], axis=-1)
    w, h = cfg.camera.image_size_px
    pad = ctx.pad_px
    front = b_scaled[:, 2] > 0
    qu = np.where(front, ctx.theta[0] * b_scaled[:, 0] / np.where(front, b_scaled[:, 2], 1.0), np.inf)
    qv = np.where(front, ctx.theta[0] * b_scaled[:, 1] / np.where(front, b_scaled[:, 2], 1.0), np.inf)
    near = (
        front
        & (qu + ctx.theta[1] > -0.5 - pad)
        & (qu + ctx.theta[1] < w - 0.5 + pad)
        & (qv + ctx.theta[2] > -0.5 - pad)
        & (qv + ctx.theta[2] < h - 0.5 + pad)
    )
    pos, star, frame, r_app, b_scaled = pos[near], star[near], frame[near], r_app[near], b_scaled[near]
    try:
        x, y = unit_to_pixels(b_scaled, ctx.theta)
    except ValueError as exc:
        raise UserError(f"camera distortion cannot be inverted near the detector edge ({exc})") from None
    if cfg.noise_px > 0:
        x = x + rng.normal(0.0, cfg.noise_px, x.size)
        y = y + rng.normal(0.0, cfg.noise_px, y.size)
    on = (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
    frame, star, x, y, r_app = frame[on], star[on], x[on], y[on], r_app[on]
    order = np.lexsort((ctx.mag[star], frame))
    frame, star, x, y, r_app = frame[order], star[order], x[order], y[order], r_app[order]
    keep = _rank_within_groups(frame) < cfg.max_stars
    return {"frame": frame[keep], "star": star[keep], "x": x[keep], "y": y[keep], "r": r_app[keep]}


def _simulate_frames(
    ctx: _SkyContext, sky: _ChunkSky, rng: np.random.Generator, frames: np.ndarray, attitude_out: np.ndarray
) -> dict[str, np.ndarray]:
    """All frames of one chunk, redrawing random-attitude frames with too few stars; ``attitude_out`` (the chunk's
    frames, 3, 3) receives each frame's attitude."""
    cfg = ctx.cfg
    pending = frames
    parts: list[dict[str, np.ndarray]] = []
    for _ in range(_MAX_ROUNDS):
        if cfg.attitudes is not None:
            att = np.asarray(cfg.attitudes, dtype=np.float64)[pending]
        elif sky.zenith is not None:
            att = _ground_rotations(rng, sky.zenith[pending - sky.first], cfg.zenith_range_deg)
        else:
            att = random_rotations(rng, pending.size)
        attitude_out[pending - sky.first] = att
        rows = _observe(ctx, sky, rng, pending, att)
        counts = np.bincount(np.searchsorted(pending, rows["frame"]), minlength=pending.size)
        ok = np.ones(pending.size, bool) if cfg.attitudes is not None else counts >= cfg.min_stars
        accept = ok[np.searchsorted(pending, rows["frame"])]
        parts.append({k: v[accept] for k, v in rows.items()})
        pending = pending[~ok]
        if pending.size == 0:
            break
    else:
        raise UserError(
            f"{pending.size} frame(s) found fewer than {cfg.min_stars} stars of Hp <= {cfg.maglim} in "
            f"{_MAX_ROUNDS} random pointings: lower --min-stars or raise --maglim"
        )
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _misidentify(
    ctx: _SkyContext, rng: np.random.Generator, frame: np.ndarray, star: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rows to misidentify and their wrong catalogue rows: each is one of the ``_MISID_NEIGHBOURS`` nearest catalogue
    stars to the true one, neither the true star nor any star of that frame; a second pick of the same wrong star in
    a frame is dropped (that row stays correctly identified)."""
    from scipy.spatial import cKDTree

    chosen = np.flatnonzero(rng.random(star.size) < ctx.cfg.misid_fraction)
    if chosen.size == 0:
        return chosen, chosen
    ref = ctx.lookup[0]
    k = min(_MISID_NEIGHBOURS + 1, ref.shape[0])
    _, neigh = cKDTree(ref).query(ref[star[chosen]], k=k)
    neigh = np.atleast_2d(neigh)
    n_cat = np.int64(ref.shape[0])
    in_frame = np.isin(frame[chosen, None] * n_cat + neigh, frame * n_cat + star)
    valid = ~in_frame & (neigh != star[chosen, None])
    pick_key = np.where(valid, rng.random(neigh.shape), np.inf)
    col = np.argmin(pick_key, axis=1)
    has = np.isfinite(pick_key[np.arange(chosen.size), col])
    chosen, wrong = chosen[has], neigh[has, col[has]]
    _, first = np.unique(frame[chosen] * n_cat + wrong, return_index=True)
    first = np.sort(first)
    return chosen[first], wrong[first]


@dataclass
class SimChunk:
    """One chunk of a simulated session (whole frames, in order): its rows, and its part of the truth: per frame of
    the chunk ``attitude`` (n, 3, 3), ``focal_length_mm``, ``real_stars_per_frame``; ``misidentified_rows``,
    ``misidentified_true_star_id`` and ``false_rows`` as rows of the whole session (0-based data rows)."""

    session: Session
    attitude: np.ndarray
    focal_length_mm: np.ndarray
    real_stars_per_frame: np.ndarray
    misidentified_rows: np.ndarray
    misidentified_true_star_id: np.ndarray
    false_rows: np.ndarray


def _chunk_rows(
    ctx: _SkyContext, sky: _ChunkSky, rng: np.random.Generator, frames: np.ndarray, first_row: int
) -> SimChunk:
    """Simulate the frames ``frames`` (one chunk): stars, then misidentifications and false stars among them."""
    cfg = ctx.cfg
    attitude = np.zeros((frames.size, 3, 3))
    rows = _simulate_frames(ctx, sky, rng, frames, attitude)
    order = np.lexsort((ctx.mag[rows["star"]], rows["frame"]))
    frame, star, x, y, r_ref = (rows[k][order] for k in ("frame", "star", "x", "y", "r"))
    mag = ctx.mag[star]
    star_id = ctx.hip[star]
    real_per_frame = np.bincount(frame - sky.first, minlength=frames.size)

    # misidentified: wrong Hipparcos number and the wrong star's reference direction, true centroid and magnitude
    mis_rows = np.zeros(0, np.int64)
    mis_true = np.zeros(0, np.int64)
    if cfg.misid_fraction > 0:
        mis_rows, wrong = _misidentify(ctx, rng, frame, star)
        mis_true = star_id[mis_rows].copy()
        star_id[mis_rows] = ctx.hip[wrong]
        local = frame[mis_rows] - sky.first
        r_ref[mis_rows] = apparent_from_astrometry(ctx.stars.take(wrong), sky.astrom[local], sky.eo[local])
    is_mis = np.zeros(frame.size, bool)
    is_mis[mis_rows] = True

    # false stars: Poisson per frame, uniform on the detector, no identity and no reference direction
    is_false = np.zeros(frame.size, bool)
    if cfg.false_star_fraction > 0:
        n_false = rng.poisson(cfg.false_star_fraction * real_per_frame)
        f_frame = np.repeat(frames, n_false)
        w, h = cfg.camera.image_size_px
        m = f_frame.size
        frame = np.concatenate([frame, f_frame])
        star_id = np.concatenate([star_id, np.zeros(m, np.int64)])
        x = np.concatenate([x, rng.uniform(-0.5, w - 0.5, m)])
        y = np.concatenate([y, rng.uniform(-0.5, h - 0.5, m)])
        mag = np.concatenate([mag, rng.uniform(cfg.maglim - _FALSE_STAR_MAG_SPAN, cfg.maglim, m)])
        r_ref = np.concatenate([r_ref, np.full((m, 3), np.nan)])
        is_mis = np.concatenate([is_mis, np.zeros(m, bool)])
        is_false = np.concatenate([is_false, np.ones(m, bool)])
        order = np.lexsort((mag, frame))
        frame, star_id, x, y, mag, r_ref, is_mis, is_false = (
            a[order] for a in (frame, star_id, x, y, mag, r_ref, is_mis, is_false)
        )
        # keep the true identities aligned with the reordered misidentified rows
        mis_true = _realign(order, mis_rows, mis_true)
        mis_rows = np.flatnonzero(is_mis)

    ra_deg = np.full(frame.size, np.nan)
    dec_deg = np.full(frame.size, np.nan)
    known = ~is_false
    if np.any(known):
        ra_deg[known], dec_deg[known] = radec_deg_of_units(r_ref[known])
    session = Session(
        frame=frame.astype(np.int64),
        t_utc=sky.t_text[frame - sky.first],
        star_id=star_id.astype(np.int64),
        x_px=x,
        y_px=y,
        mag=mag,
        ra_deg=ra_deg,
        dec_deg=dec_deg,
    )
    return SimChunk(
        session=session,
        attitude=attitude,
        focal_length_mm=focal_lengths_mm(cfg, frames),
        real_stars_per_frame=real_per_frame,
        misidentified_rows=first_row + mis_rows.astype(np.int64),
        misidentified_true_star_id=np.asarray(mis_true, dtype=np.int64),
        false_rows=first_row + np.flatnonzero(is_false).astype(np.int64),
    )


def simulate_chunks(config: SimConfig, progress: Callable[[int, int], None] | None = None) -> Iterator[SimChunk]:
    """Simulate a session (see the module docstring) chunk by chunk: :data:`_CHUNK_FRAMES` frames at a time, each
    with its own misidentified and false stars, so memory holds one chunk (plus 16 bytes a frame) whatever the
    session's length. ``progress(done_frames, total)`` is called after each chunk. Raises UserError (one line) for
    an inconsistent configuration or a sky that cannot give ``config.min_stars`` stars per frame. A session of one
    chunk (up to 2000 frames) is the same, draw for draw, as before the simulation was chunked."""
    cfg = config
    _check_config(cfg)
    rng = np.random.default_rng(cfg.seed)
    n_frames = int(cfg.frames)
    jd1, jd2 = _session_jd(cfg, n_frames)
    ctx = _build_context(cfg, jd1, jd2)
    first_row = 0
    for a in range(0, n_frames, _CHUNK_FRAMES):
        b = min(n_frames, a + _CHUNK_FRAMES)
        chunk = _chunk_rows(ctx, _chunk_sky(cfg, jd1, jd2, a, b), rng, np.arange(a, b), first_row)
        first_row += len(chunk.session)
        if progress is not None:
            progress(b, n_frames)
        yield chunk


def simulate(config: SimConfig, progress: Callable[[int, int], None] | None = None) -> SimResult:
    """Simulate a session and its truth in memory (:func:`simulate_chunks`, collected). Raises UserError (one line)
    for an inconsistent configuration or a sky that cannot give ``config.min_stars`` stars per frame."""
    chunks = list(simulate_chunks(config, progress))
    session = concatenate_sessions([c.session for c in chunks])

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(c, name) for c in chunks])

    truth = _truth(
        config,
        cat("attitude"),
        cat("misidentified_rows"),
        cat("misidentified_true_star_id"),
        cat("false_rows"),
        cat("real_stars_per_frame"),
    )
    return SimResult(session=session, truth=truth)


def write_simulation(
    config: SimConfig,
    session_path: str | Path,
    truth_path: str | Path,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[int, int]:
    """Simulate a session straight to its files, chunk by chunk (:func:`simulate_chunks`): the session through
    :class:`hostlink.files.session.SessionWriter` (CSV, or Parquet for ``*.parquet``) and the truth through
    :class:`hostlink.files.truth.TruthWriter`, in memory bounded by one chunk whatever the number of frames. Both
    files appear only when the whole simulation succeeded. Returns (frames, rows)."""
    header = _truth_header(config)
    sessions = SessionWriter(session_path)
    try:
        with TruthWriter(truth_path, header, TRUTH_PER_FRAME_KEYS) as truth:
            _write_chunks(config, progress, sessions, truth)
            sessions.commit()  # before the truth is written: a truth file always has its session
    except BaseException:
        sessions.discard()  # a simulation that failed part way (or was interrupted) leaves no file, not even .partial
        raise
    return int(config.frames), int(sessions.rows)


def _write_chunks(config: SimConfig, progress, sessions: SessionWriter, truth: TruthWriter) -> None:
    """Each chunk of the simulation appended to the session and truth writers as it is made."""
    for chunk in simulate_chunks(config, progress):
        sessions.append(chunk.session)
        truth.append(
            {
                "attitude": chunk.attitude.reshape(-1, 9),
                "focal_length_mm": chunk.focal_length_mm,
                "real_stars_per_frame": chunk.real_stars_per_frame,
                "misidentified_rows": chunk.misidentified_rows,
                "misidentified_true_star_id": chunk.misidentified_true_star_id,
                "false_rows": chunk.false_rows,
            }
        )


def _realign(order: np.ndarray, old_rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` attached to rows ``old_rows`` (before the permutation ``order``), listed in new row order."""
    if old_rows.size == 0:
        return values
    new_pos = np.empty_like(order)
    new_pos[order] = np.arange(order.size)
    return values[np.argsort(new_pos[old_rows], kind="stable")]


def _truth(
    cfg: SimConfig,
    attitude: np.ndarray,
    mis_rows: np.ndarray,
    mis_true: np.ndarray,
    false_rows: np.ndarray,
    real_per_frame: np.ndarray,
) -> dict:
    return {
        **_truth_header(cfg),
        "attitude": attitude.reshape(-1, 9).tolist(),
        "focal_length_mm": focal_lengths_mm(cfg).tolist(),
        "real_stars_per_frame": real_per_frame.astype(int).tolist(),
        "misidentified_rows": [int(v) for v in mis_rows],
        "misidentified_true_star_id": [int(v) for v in mis_true],
        "false_rows": [int(v) for v in false_rows],
    }


def _truth_header(cfg: SimConfig) -> dict:
    """The truth's keys that do not grow with the session (every key but ``TRUTH_PER_FRAME_KEYS``)."""
    refracted = cfg.weather is not None
    return {
        "format": TRUTH_FORMAT,
        "version": TRUTH_VERSION,
        "camera": params_to_dict(cfg.camera),
        "noise_px": float(cfg.noise_px),
        "seed": int(cfg.seed),
        "frames": int(cfg.frames),
        "t0_utc": cfg.t0_iso,
        "frame_interval_s": float(cfg.frame_interval_s),
        "maglim": float(cfg.maglim),
        "min_stars": int(cfg.min_stars),
        "max_stars": int(cfg.max_stars),
        "misid_fraction": float(cfg.misid_fraction),
        "false_star_fraction": float(cfg.false_star_fraction),
        "focal_drift_um": float(cfg.focal_drift_um),
        "focal_drift_period_frames": float(cfg.focal_drift_period_frames),
        "site": asdict(cfg.site) if cfg.site is not None else None,
        "weather": asdict(cfg.weather) if cfg.weather is not None else None,
        "dut1_s": float(cfg.dut1_s),
        "zenith_range_deg": [float(v) for v in cfg.zenith_range_deg] if cfg.site is not None else None,
        "attitude_source": "scripted" if cfg.attitudes is not None else "random",
        "reference": "geocentric apparent place, true equator and equinox of date (ERFA apci13/atciq, ra = ri - eo)",
        "attitude_maps": (
            "apparent direction"
            if cfg.site is None
            else "observed direction (apparent + diurnal aberration + ERFA refraction)"
            if refracted
            else "topocentric direction (apparent + diurnal aberration)"
        ),
        "refraction": refracted,
        "diurnal_aberration": cfg.site is not None,
        "attitude_layout": "per frame c11 c12 c13 c21 c22 c23 c31 c32 c33 (row-major), b = C r",
    }
