"""Lost-in-space identification of a session's unidentified stars (``star_id`` 0) against the bundled Hipparcos
catalogue (issue 11, ``hostlink identify``), tolerant of a nominal focal length off by up to 10 %, unknown distortion,
false stars (hot pixels, noise) and a mirrored detector.

Per frame:

1. Propose: the pattern engine (:mod:`hostlink.images.solver_adapter`, tetra3rs) matches the frame's centroids,
   brightest first, to catalogue 4-star patterns over a field range covering the nominal +-12 %. It tries the
   whole frame, then only the brightest 30, 20, 15 and 10 centroids (false stars among the bright ones spoil its
   patterns). Frames it cannot match go to the project's own pair-anchored matcher (:func:`anchor_candidates`,
   a hypothesise-and-test over catalogue pairs of the same angle) at the focal length the session's identified
   frames measured (one camera for the whole session); without the engine, over a scan of focal lengths. The own
   matcher gives a frame at most :data:`MAX_ANCHOR_PAIRS` anchor pairs (an operation count, in the order of
   :func:`_anchor_schedule`); a frame it has not identified within them is "no match within N anchor pairs".
2. Re-derive with the project's own code, trusting nothing of the engine but its pairs (centroid, Hipparcos number):
   directions b through the nominal camera (for a mirrored detector with x mirrored about the principal point),
   reference directions r at J2000.0 (annual aberration changes an interstar angle by at most 20.5" x the angle in
   radians: 2" over a 6 deg pair, far inside the tolerances below), the focal-length scale from the pairs' own
   interstar angles (:func:`hostlink.calibration.robust.estimate_scale`), and the parity from the handedness of
   star triples (:func:`hostlink.calibration.robust.triple_handedness`): the parity that verifies is kept, whatever
   the engine said.
3. Extend: the attitude (Markley's SVD, :func:`onboard.attitude.attitude_from_vectors`) of the consistent pairs
   predicts where every catalogue star of the field, down to one magnitude fainter than the faintest proposed
   match, falls on the detector; a centroid within :data:`EXTEND_RADIUS_PX` (scaled by the fit's residual) of
   exactly one predicted star, and nearer to it than any other centroid, is a candidate too. Two rounds.
4. Verify: every candidate goes through the project's interstar vote
   (:func:`hostlink.calibration.robust.vote_consistent_stars`, seed 000 eq. 3: interstar angles do not depend on
   the attitude) with the tolerances :data:`VERIFY_REL_TOL` and :data:`VERIFY_ABS_TOL_PX`, and must agree with at
   least :data:`VERIFY_MIN_AGREEMENT` of the others. A frame is accepted only if at least :data:`MIN_VERIFIED`
   stars verify, they are at least :data:`MIN_VERIFIED_FRACTION` of its candidates, and the triple handedness is
   unanimous to :data:`PARITY_MIN_AGREEMENT`; and at least :data:`MIN_COMPLETENESS` of the catalogue stars the
   solution puts on the detector, as bright as its median identified star, must be among the identified (a chance
   alignment of faint stars leaves the bright ones of its field unmatched); a matcher's proposal must also give the
   session's focal-length scale within :data:`SCALE_AGREEMENT`.

After every frame has been tried once, the frames not yet identified are tried again by the engine with the field
of view the identified frames measured and a tolerance of :data:`REFINED_FOV_TOLERANCE`, then by the own matcher.

From 8 to 50 deg fields (issue 30): a frame with :data:`REFINE_MIN_STARS` verified stars refines its own focal
length and radial terms on them (:func:`_refine_radial`), and its later candidates are predicted and verified
through that camera, so the match radius (:func:`_match_radius_px`) follows the centroid noise, not the lens; a star
that two catalogue stars could be is left unidentified (:func:`_ambiguous`); the own matcher's catalogue depth
follows the field (:func:`fallback_depth_mag`); a nominal wider than :data:`MAX_DIAGONAL_FIELD_DEG` (a fisheye) is
refused; a proposal no one scale verifies (a strong unknown lens) has k1 searched too (``verify._radial_search``).
:func:`identify_iteratively` identifies, calibrates and identifies again until a round adds nothing.

The stages, each in its module of :mod:`hostlink.images` (their names importable from here as well): the catalogue's
index and the pair table (``skyindex``), the own matcher (``matcher``), verification (``verify``), extension and the
photometric checks (``extend``), one frame (``confirm``), unresolved pairs (``blends``), the faint candidates
(``guided``); this module runs the session's frames and rounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from hostlink.files.session import Session
from hostlink.images import blends, guided, solver_adapter

# the stages live in their own modules (each under 500 lines); their names stay importable from here
from hostlink.images.confirm import (  # noqa: F401
    FrameIdentity,
    _boresight_and_roll,
    _finite,
    identify_frame,
)
from hostlink.images.extend import AMBIGUITY_MAG_MARGIN  # noqa: F401
from hostlink.images.matcher import (  # noqa: F401
    ANCHOR_STARS,
    DEEP_ANCHOR_STARS,
    DEEP_MATCH_STARS,
    FALLBACK_DEPTH_PERCENTILE,
    FALLBACK_MAG_MARGIN,
    MATCH_STARS,
    MAX_ANCHOR_PAIRS,
    SCAN_SCALES,
    _anchor_schedule,
    _pairs_of_angle,
    _pyramid_may_hit,
    anchor_candidates,
    fallback_angle_rad,
    fallback_depth_mag,
    prepare_cache,
)
from hostlink.images.skyindex import (  # noqa: F401
    MAX_DIAGONAL_FIELD_DEG,
    PairCache,
    PairCatalogue,
    SkyIndex,
    _field_sr,
    _Sky,
    _sky,
    _ties_by_stars,
    _with_identities,
    catalogue_radec_deg,
    check_field,
    diagonal_field_deg,
    pair_catalogue,
)
from hostlink.sky.catalogue import Catalogue
from onboard.params import CameraParams

#: Second pass: field-of-view tolerance once the identified frames have measured the focal length.
REFINED_FOV_TOLERANCE = 0.02


@dataclass(frozen=True)
class Identification:
    """The result of :func:`identify_session`: the session with the identified rows' ``star_id`` (and ra/dec when
    the file has those columns) filled in, and one :class:`FrameIdentity` per frame that had unidentified rows."""

    session: Session
    frames: tuple[FrameIdentity, ...]
    engine: str
    nominal_fov_deg: float
    #: one record per round of :func:`identify_iteratively` (empty for a single :func:`identify_session`)
    rounds: tuple[dict, ...] = ()
    #: the identified rows whose detection holds unresolved catalogue companions' light, one record each
    #: (:func:`hostlink.images.blends.blend_references`: row, hip, companions, offsets and sigma [px]): their ra/dec
    #: is the blend's expected centroid, their ``sigma_px`` grown by its uncertainty
    blends: tuple[dict, ...] = ()
    #: the camera the final round identified with (the nominal, or the calibration of the round before)
    camera: CameraParams | None = None
    #: the calibration (:class:`hostlink.calibration.run.CalibrationOutcome`) of ``session`` from ``camera`` when the
    #: rounds ran it (a round after it added nothing), so that what follows need not run it again (None otherwise);
    #: for its camera: its degeneracies leave out the report's fit from the mirrored principal point (``mirror_fit``)
    calibration: object | None = None

    @property
    def n_identified(self) -> int:
        return sum(f.n_identified for f in self.frames)

    @property
    def n_frames_identified(self) -> int:
        return sum(f.status == "identified" for f in self.frames)

    @property
    def mirrored(self) -> bool | None:
        """The session's parity: the majority of its identified frames (None when none was identified)."""
        votes = [f.mirrored for f in self.frames if f.status == "identified"]
        return None if not votes else sum(votes) > len(votes) / 2

    @property
    def scale(self) -> float:
        """Median F / F_nominal over the identified frames (NaN when none)."""
        s = [f.scale for f in self.frames if f.status == "identified"]
        return float(np.median(s)) if s else math.nan

    def report(self) -> dict:
        """JSON-ready report: totals, the session's parity and scale, and every frame."""
        return {
            "engine": self.engine,
            "frames": len(self.frames),
            "frames_identified": self.n_frames_identified,
            "stars_identified": self.n_identified,
            "parity": None if self.mirrored is None else ("mirrored" if self.mirrored else "normal"),
            "scale": _finite(self.scale),
            "rounds": list(self.rounds),
            "blends": list(self.blends),
            "per_frame": [f.as_dict() for f in self.frames],
        }


#: Frames the own matcher scans over every focal-length scale when the engine is installed but matched no frame
#: (each such scan costs seconds: docs/realsky.md, "A frame nothing matches"): the cost stays bounded, and one
#: identified frame gives every other its scale.
ENGINE_MISS_SCANNED_FRAMES = 3


@dataclass(frozen=True)
class _SessionContext:
    """What every frame of one :func:`identify_session` call shares: the session, the nominal camera and its
    horizontal field [deg], the catalogue as unit vectors, and the engine's pattern database (None without it)."""

    session: Session
    nominal: CameraParams
    fov_deg: float
    sky: _Sky
    database: object
    #: the tables rounds of :func:`identify_iteratively` share (None: built for this call alone)
    cache: PairCache | None = None


def _identify_frame_k(
    ctx: _SessionContext, k: int, database, fov_deg: float, tol: float, pairs=None, scales=()
) -> tuple[FrameIdentity, np.ndarray]:
    """:func:`identify_frame` on the unidentified rows of the session's ``k``-th frame."""
    session, starts = ctx.session, ctx.session.frame_starts
    a, b = int(starts[k]), int(starts[k + 1])
    rows = a + np.flatnonzero(session.star_id[a:b] == 0)
    mag = None if session.mag is None else session.mag[rows]
    return identify_frame(
        int(session.frame[a]),
        session.x_px[rows],
        session.y_px[rows],
        mag,
        ctx.nominal,
        ctx.sky,
        database,
        fov_deg,
        tol,
        pairs,
        scales,
    )


def _identified(results: dict[int, tuple[FrameIdentity, np.ndarray]], k: int) -> bool:
    return k in results and results[k][0].status == "identified"


def _fallback_pairs(ctx: _SessionContext, todo: list[int], results: dict) -> PairCatalogue:
    """The own matcher's pair index: as deep as the identified frames see (:data:`FALLBACK_DEPTH_PERCENTILE` of
    their stars' magnitudes plus :data:`FALLBACK_MAG_MARGIN`), but no deeper than the field's size needs
    (:func:`fallback_depth_mag`; the matcher works on the brightest centroids, and a 50-deg field's pairs to Hp 7.5
    take 40 s to index, to Hp 5.5 a second); pairs as wide as the detector's diagonal at the smallest scanned scale."""
    sky, nominal = ctx.sky, ctx.nominal
    found = [k for k in todo if _identified(results, k)]
    hips = np.concatenate([results[k][1] for k in found]) if found else np.zeros(0, np.int64)
    hips = hips[hips != 0]
    field_depth = fallback_depth_mag(sky.mag, _field_sr(nominal))
    depth = (
        min(
            float(np.percentile(sky.mag[np.searchsorted(sky.hip, hips)], FALLBACK_DEPTH_PERCENTILE))
            + FALLBACK_MAG_MARGIN,
            field_depth + FALLBACK_MAG_MARGIN,
        )
        if hips.size
        else field_depth
    )
    if ctx.cache is not None:
        return ctx.cache.pairs(sky, fallback_angle_rad(nominal), depth)
    return pair_catalogue(sky, fallback_angle_rad(nominal), depth)


def _engine_pass(ctx: _SessionContext, todo: list[int], progress) -> dict[int, tuple[FrameIdentity, np.ndarray]]:
    """Every frame through the engine at the nominal field (module docstring, step 1)."""
    results = {}
    for done, k in enumerate(todo):
        results[k] = _identify_frame_k(ctx, k, ctx.database, ctx.fov_deg, solver_adapter.FOV_MARGIN)
        if progress is not None:
            progress(done + 1, len(todo))
    return results


def _fallback_pass(ctx: _SessionContext, todo: list[int], results: dict) -> None:
    """The frames the engine left, through the own matcher (updating ``results``): at the engine's measured scale,
    or by a scan of scales (slow: up to :data:`MAX_ANCHOR_PAIRS` anchor pairs, ~0.1 s each): every frame when the
    engine is not there; when it is there but matched no frame (its patterns need stars the frames may lack), at most
    :data:`ENGINE_MISS_SCANNED_FRAMES` frames are scanned, the others then tried at the scale the first identified
    one measured (one camera for the session: the other frames need no scan)."""
    failed = [k for k in todo if not _identified(results, k)]
    if not failed:
        return
    width = ctx.nominal.image_size_px[0]
    engine_scale_known = any(_identified(results, k) for k in results)
    scan_budget = ENGINE_MISS_SCANNED_FRAMES if ctx.database is not None and not engine_scale_known else len(failed)
    scales = [results[k][0].scale for k in todo if _identified(results, k)]
    scale = float(np.median(scales)) if scales else math.nan
    pairs = _fallback_pairs(ctx, todo, results)
    tried_without_scale = []
    for k in failed:
        known = math.isfinite(scale)
        if not known and scan_budget <= 0:
            tried_without_scale.append(k)  # tried below, should a scanned frame measure the scale
            continue
        scan_budget -= 0 if known else 1
        refined = (
            solver_adapter.horizontal_fov_deg(ctx.nominal.focal_length_px * scale, width) if known else ctx.fov_deg
        )
        tol = REFINED_FOV_TOLERANCE if known else solver_adapter.FOV_MARGIN
        retry = _identify_frame_k(ctx, k, ctx.database, refined, tol, pairs, (scale,) if known else SCAN_SCALES)
        if k not in results or retry[0].status == "identified" or retry[0].n_candidates > results[k][0].n_candidates:
            results[k] = retry
        if not known and retry[0].status == "identified":
            scale = retry[0].scale
        elif not known:
            tried_without_scale.append(k)
    if math.isfinite(scale):
        refined = solver_adapter.horizontal_fov_deg(ctx.nominal.focal_length_px * scale, width)
        for k in tried_without_scale:  # the frames scanned before the session's scale was known
            retry = _identify_frame_k(ctx, k, None, refined, REFINED_FOV_TOLERANCE, pairs, (scale,))
            if retry[0].status == "identified":
                results[k] = retry


def identify_session(
    session: Session,
    nominal: CameraParams,
    catalogue: Catalogue | None = None,
    maglim: float | None = None,
    use_engine: bool = True,
    progress=None,
    database_fov_deg: float | None = None,
    cache: PairCache | None = None,
) -> Identification:
    """Identify every frame's unidentified rows (module docstring). ``nominal``: the camera as its user knows it
    (focal length within 10 %); ``catalogue``: default the bundled Hipparcos; ``maglim``: only stars at least this
    bright [Hp mag] (default all). ``use_engine``: False (or tetra3rs not installed) identifies with the project's
    own pair-anchored matcher alone. Rows already identified are kept as they are. ``progress(done, total)`` is called
    after each frame. The returned session has the identified rows' star_id (and ra_deg/dec_deg when the file has
    them: the geocentric apparent place with the time known, the J2000 place without) filled in. Stages: the engine
    (:func:`_engine_pass`), the own matcher for the frames it left (:func:`_fallback_pass`), the identities written.
    ``cache``: the tables the rounds of :func:`identify_iteratively` share (:class:`PairCache`; the same results)."""
    check_field(nominal)
    if np.any(guided.candidate_rows(session)):  # faint candidates build no pattern (guided.py)
        return guided.identify_without_candidates(
            session,
            lambda s: identify_session(s, nominal, catalogue, maglim, use_engine, progress, database_fov_deg, cache),
        )
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
    if maglim is not None:
        catalogue = (
            cache.bright(catalogue, maglim) if cache else catalogue.subset(np.flatnonzero(catalogue.mag <= maglim))
        )
    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, nominal.image_size_px[0])
    engine = use_engine and solver_adapter.engine_available()
    # ``database_fov_deg``: a later round of :func:`identify_iteratively` reuses the first round's database
    database = None
    if engine:
        database = (cache.database if cache else solver_adapter.pattern_database)(
            catalogue, database_fov_deg or fov, maglim
        )
    index = cache.index(catalogue) if cache else SkyIndex(catalogue)
    sky = index.sky
    ctx = _SessionContext(session, nominal, fov, sky, database, cache)
    starts = session.frame_starts
    todo = [k for k in range(session.n_frames) if np.any(session.star_id[starts[k] : starts[k + 1]] == 0)]
    # BLAS on one thread (as guided.identify_then_admit): the frames' products are thin (a refinement's least squares
    # of 3 N x 8, Gram matrices of a frame), and OpenBLAS's threads cost several times the CPU time they save
    from hostlink.calibration.data import one_blas_thread

    with one_blas_thread():
        results = _engine_pass(ctx, todo, progress) if engine else {}
        _fallback_pass(ctx, todo, results)
    star_id = session.star_id.copy()
    for k in todo:
        a, b = int(starts[k]), int(starts[k + 1])
        star_id[a + np.flatnonzero(session.star_id[a:b] == 0)] = results[k][1]
    frames = tuple(results[k][0] for k in todo)
    out = _with_identities(session, star_id, catalogue)
    scales = [f.scale for f in frames if f.status == "identified"]
    focal_px = nominal.focal_length_px * (float(np.median(scales)) if scales else 1.0)
    out, blended = blends.blend_references(out, session.star_id, catalogue, focal_px, index)
    name = solver_adapter.ENGINE_NAME + " + pair-anchored matching" if engine else "pair-anchored matching"
    return Identification(out, frames, name, fov, blends=tuple(blended))


#: :func:`identify_iteratively`: rounds at most (the first with the nominal camera). Each later round identifies
#: with the camera calibrated on the round before; on the real sets the second round adds the field-edge stars an
#: uncalibrated model misplaces and the third adds nothing.
MAX_ROUNDS = 4


def identify_iteratively(
    session: Session,
    nominal: CameraParams,
    catalogue: Catalogue | None = None,
    maglim: float | None = None,
    use_engine: bool = True,
    max_rounds: int = MAX_ROUNDS,
    progress=None,
    cache: PairCache | None = None,
) -> Identification:
    """:func:`_identify_iteratively`; a session found mirrored (odd parity, which the calibration refuses: its
    rounds and the guided admission would end at the first calibration) is identified again with x flipped,
    x -> width - 1 - x, and the nominal with it (:func:`flipped_x_camera`), then written back in its own columns.
    Its frames keep the parity ``mirrored`` and the attitude of the mirrored-back columns (as a mirrored frame's
    always was: x mirrored about the principal point); ``camera`` is that of the flipped detector, the one
    ``calibrate`` needs (the session's x flipped first, as its error on a mirrored session says). ``cache``: the
    catalogue's indexes and pair tables (:class:`PairCache`, default a new one), to share with other calls on the
    same catalogue (the same results)."""
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
    args = (catalogue, maglim, use_engine, max_rounds, progress, cache or PairCache())  # one cache for both parities
    result = _identify_iteratively(session, nominal, *args)
    if not result.mirrored:
        return result
    width = nominal.image_size_px[0]
    flipped = _identify_iteratively(_flipped_x_session(session, width), flipped_x_camera(nominal), *args)
    if flipped.mirrored is not False or flipped.n_identified < result.n_identified:
        return result
    frames = tuple(f if f.mirrored is None else replace(f, mirrored=not f.mirrored) for f in flipped.frames)
    return replace(flipped, session=_flipped_x_session(flipped.session, width), frames=frames)


def _flipped_x_session(session: Session, width_px: int) -> Session:
    """``session`` with every column mirrored, x -> width - 1 - x (docs/camera-model.md: x = 0 is the first
    column's centre)."""
    return replace(session, x_px=(width_px - 1) - session.x_px)


def flipped_x_camera(camera: CameraParams) -> CameraParams:
    """The camera of the same detector read with x -> width - 1 - x: the principal point's column mirrored, and the
    distortion terms odd in x (docs/camera-model.md: with u -> -u, dx -> -dx and dy unchanged when g1 = s1 + p1 and
    g3 = 2 p1 change sign, so p1 and s1 do) negated."""
    x0, y0 = camera.principal_point_px
    d = camera.distortion
    return replace(
        camera,
        principal_point_px=((camera.image_size_px[0] - 1) - x0, y0),
        distortion=replace(d, p1=-d.p1, s1=-d.s1),
    )


def _identify_iteratively(
    session: Session,
    nominal: CameraParams,
    catalogue: Catalogue,
    maglim: float | None = None,
    use_engine: bool = True,
    max_rounds: int = MAX_ROUNDS,
    progress=None,
    cache: PairCache | None = None,
) -> Identification:
    """Identify, calibrate, identify again with the calibrated camera, until a round adds nothing (at most
    ``max_rounds``; 1: :func:`identify_session` alone). Every round identifies the session's originally
    unidentified rows afresh (lost in space: the module docstring's checks apply in every round) with the camera
    the round before calibrated (:func:`hostlink.calibration.run.calibrate_session`, default method and
    parameters, the session's time or J2000 directions); the field edge, where an uncalibrated model errs most, is
    where the new stars are. A round is kept only when it identifies more stars than the one before; a calibration
    that fails (:meth:`CalibrationOutcome.failure`) ends the rounds. The result's ``rounds`` hold, per round: the
    camera used (focal length [px], where it came from), frames and stars identified, and the stars it added, lost
    and renamed against the round before. ``catalogue``: the one :func:`identify_iteratively` was given or loaded;
    ``cache``: what the rounds share (:class:`PairCache`; the guided admission uses its catalogue's
    :class:`SkyIndex`)."""
    from hostlink.calibration.run import calibrate_session
    from hostlink.errors import UserError

    if max_rounds < 1:
        raise UserError(f"rounds must be at least 1, got {max_rounds}")
    cache = cache if cache is not None else PairCache()  # what does not change between rounds
    if np.any(guided.candidate_rows(session)):  # faint candidates: held back, admitted after the rounds (guided.py)
        return guided.identify_then_admit(
            session,
            lambda s: _identify_iteratively(s, nominal, catalogue, maglim, use_engine, max_rounds, progress, cache),
            catalogue,
            cache.index(catalogue),
        )
    width = nominal.image_size_px[0]
    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, width)

    def one_round(camera: CameraParams) -> Identification:
        return identify_session(
            session, camera, catalogue, maglim, use_engine, progress, database_fov_deg=fov, cache=cache
        )

    result = one_round(nominal)
    new = session.star_id == 0
    rounds = [_round_record(1, "nominal", nominal, result, np.zeros_like(session.star_id), new)]
    camera, outcome = nominal, None
    for number in range(2, max_rounds + 1):
        if result.n_frames_identified == 0:
            break
        outcome = None
        try:
            outcome, _ = calibrate_session(result.session, camera, keep_failed=True, mirror_fit=False)
        except UserError as exc:
            rounds[-1]["calibration"] = f"failed: {exc}"
            break
        failure = outcome.failure()
        rounds[-1]["calibration"] = failure or f"residual {outcome.after.get('rms_px', math.nan):.3f} px"
        if failure:
            break
        trial = one_round(outcome.params)
        record = _round_record(
            number, f"calibrated in round {number - 1}", outcome.params, trial, result.session.star_id, new
        )
        rounds.append(record)
        if trial.n_identified <= result.n_identified:
            record["kept"] = False  # nothing new: the round before stands, and ``outcome`` is its calibration
            break
        result, camera, outcome = trial, outcome.params, None
    return replace(result, rounds=tuple(rounds), camera=camera, calibration=outcome)


def _round_record(
    number: int, source: str, camera: CameraParams, result: Identification, before: np.ndarray, new: np.ndarray
) -> dict:
    """One round's report (:func:`identify_iteratively`): over the rows the session left unidentified (``new``), the
    stars this round identified, added (unidentified the round before), lost and renamed against ``before``."""
    now = result.session.star_id
    return {
        "round": number,
        "camera": source,
        "focal_length_px": float(camera.focal_length_px),
        "frames_identified": result.n_frames_identified,
        "stars_identified": int(np.count_nonzero(new & (now != 0))),
        "added": int(np.count_nonzero(new & (now != 0) & (before == 0))),
        "lost": int(np.count_nonzero(new & (now == 0) & (before != 0))),
        "renamed": int(np.count_nonzero(new & (now != 0) & (before != 0) & (now != before))),
        "kept": True,
    }
