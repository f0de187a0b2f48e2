"""What the C firmware core costs on a Cortex-M, measured on the emulated processor (``hostlink costs --target``):
the golden vectors run there and checked as on the host, a replayed session's recursive updates at 8, 16 and 32
stars, the upload commands (stage chunk, verify, commit with its flash writes) and refraction by addition, each
with its exact instruction count and the deepest stack it reached; flash and static RAM from the linked image.

The checks are the host's (tests/test_c_numerics_vectors.py): fixed-point outputs equal to the vectors' integers,
float32 outputs within each output's stated tolerance (hostlink/portkit/vectors.py). The session's estimator on the
target is compared with the Python sensor's (onboard.firmware.RecursiveEstimator) fed the same frames: the saved
state's bytes after every frame (the report's frames_state_differs_from_python; the filter is bit-exact, see
docs/port-kit.md), and the estimate after the session in units of its 1-sigma (issue 27's acceptance: within 0.01).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass, field

import numpy as np

from hostlink.portkit import vectors
from hostlink.portkit.cortexm import Arg, Machine, Target, flash_breakdown
from hostlink.portkit.estimator_c import FixedCamera, SeamConfig, TimeTT, fixed_instant

#: Star counts of the update rows (issue 28).
UPDATE_STARS = (8, 16, 32)
#: Stars of the refraction-by-addition row (a frame's catalogue stars).
REFRACTION_STARS = 32
#: Frame period the share is quoted against [s] (a 10 Hz sensor).
FRAME_PERIOD_S = 0.1
#: The estimate after the session within this many of its 1-sigma of the Python sensor's (issue 27's acceptance).
ESTIMATE_AGREEMENT_SIGMA = 0.01


@dataclass(frozen=True)
class VectorResult:
    """One vector file on the target: the worst |got - expected| / tolerance over its outputs (0 when bit-exact;
    fixed point and bytes must be exact) and whether it passed."""

    file: str
    worst_ratio: float
    passed: bool


@dataclass(frozen=True)
class Row:
    what: str
    stars: int | None
    precision: str
    instructions: int
    cycles: int | None
    stack_bytes: int
    note: str = ""


@dataclass
class TargetReport:
    target: Target
    flash_bytes: int
    ram_bytes: int
    state_bytes: int
    firmware_state_bytes: int = 0
    image_ram_bytes: int = 0
    stack_bytes: int = 0
    vectors: list[VectorResult] = field(default_factory=list)
    rows: list[Row] = field(default_factory=list)
    session: dict = field(default_factory=dict)
    flash_by_origin: dict = field(default_factory=dict)
    optimise: str = "O2"

    @property
    def vectors_passed(self) -> bool:
        return bool(self.vectors) and all(v.passed for v in self.vectors)

    def as_json(self) -> dict:
        return {
            "target": self.target.name,
            "description": self.target.description,
            "precision": self.target.precision,
            "clock_hz": self.target.clock_hz,
            "optimise": self.optimise,
            "flash_bytes": self.flash_bytes,
            "ram_bytes": self.ram_bytes,
            "flash_by_origin": self.flash_by_origin,
            "ram_parts": {
                "data_bss": self.image_ram_bytes,
                "firmware_state": self.firmware_state_bytes,
                "estimator_state": self.state_bytes,
            },
            "estimator_state_bytes": self.state_bytes,
            "stack_bytes": self.stack_bytes,
            "vectors_passed": self.vectors_passed,
            "vectors": [{"file": v.file, "worst_ratio": v.worst_ratio, "passed": v.passed} for v in self.vectors],
            "session": self.session,
            "rows": [
                {
                    "what": r.what,
                    "stars": r.stars,
                    "precision": r.precision,
                    "instructions": r.instructions,
                    "cycles": r.cycles,
                    "stack_bytes": r.stack_bytes,
                }
                for r in self.rows
            ],
        }


# --------------------------------------------------------------------------------------------- vectors
def _cases(doc: dict):
    for case in doc["cases"]:
        inp = {k: vectors.decode_array(v) for k, v in case["inputs"].items()}
        out = {k: vectors.decode_array(v) for k, v in case["outputs"].items()}
        tol = {
            k: (vectors.decode_array(v["abs"]) if isinstance(v["abs"], dict) else v["abs"])
            for k, v in case["tolerance"].items()
        }
        yield inp, out, tol


def _within(got, expected, tol) -> float:
    """The largest |got - expected| / tolerance (<= 1 passes; 0 when equal)."""
    g = np.asarray(got, np.float64)
    diff = np.abs(g - np.asarray(expected, np.float64).reshape(g.shape))
    t = np.broadcast_to(np.asarray(tol, np.float64), diff.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.max(np.where(diff == 0, 0.0, diff / t), initial=0.0))


def _exact(got, expected) -> float:
    return 0.0 if np.asarray(got).tolist() == np.asarray(expected).tolist() else float("inf")


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def _i64(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def _i32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int32)


def _pixel_to_direction_float32(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, tol in _cases(doc):
        theta, x, y = _f32(inp["theta"]), _f32(inp["x_px"]), _f32(inp["y_px"])
        n = x.size
        u, v, b = np.zeros(n, np.float32), np.zeros(n, np.float32), np.zeros((n, 3), np.float32)
        m.call("camera_ideal_offsets", x, y, n, theta, u, v)
        m.call("camera_offsets_to_unit", u, v, n, Arg("f32", float(theta[0])), b)
        b2 = np.zeros((n, 3), np.float32)
        m.call("camera_pixels_to_unit", x, y, n, theta, b2)
        worst = max(worst, _exact(b2, b))  # pixels_to_unit is the two steps
        for name, got in (("u_ideal_px", u), ("v_ideal_px", v), ("b", b)):
            worst = max(worst, _within(got, out[name], tol[name]))
    return worst


def _camera_jacobians(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, tol in _cases(doc):
        theta, x, y = _f32(inp["theta"]), _f32(inp["x_px"]), _f32(inp["y_px"])
        n = x.size
        b, jt, jc = np.zeros((n, 3), np.float32), np.zeros((n, 3, 10), np.float32), np.zeros((n, 3, 2), np.float32)
        m.call("camera_unit_vector_jacobians", x, y, n, theta, b, jt, jc)
        for name, got in (("b", b), ("j_theta", jt), ("j_centroid", jc)):
            worst = max(worst, _within(got, out[name], tol[name]))
    return worst


def _pixel_to_direction_fixed(m: Machine, doc: dict) -> float:
    worst = 0.0
    table = m.read(m.address("fixedpoint_rsqrt_table_q30"), 25 * 8)
    const = {k: vectors.decode_array(v) for k, v in doc["constants"].items()}
    worst = max(worst, _exact(np.frombuffer(table, "<i8"), const["rsqrt_table_q30"]))
    for inp, out, _ in _cases(doc):
        cam = FixedCamera()
        w, h = (int(v) for v in inp["image_size_px"])
        status, _ = m.call("fixedpoint_camera", _f32(inp["theta"]), Arg("i32", w), Arg("i32", h), cam, returns="i32")
        worst = max(worst, _exact(status, 0))
        got = [cam.s, cam.x0_q, cam.y0_q, cam.qw, cam.f_w]
        worst = max(worst, _exact(got, [int(out[k]) for k in ("s", "x0_q", "y0_q", "qw", "f_w")]))
        worst = max(worst, _exact(list(cam.coef_m), out["coef_m"]), _exact(list(cam.coef_e), out["coef_e"]))
        worst = max(worst, _exact(np.array(cam.theta_q), out["theta_q"]))
        for k in range(inp["x_q10"].size):
            u, v, b = np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(3, np.int64)
            xq, yq = Arg("i64", int(inp["x_q10"][k])), Arg("i64", int(inp["y_q10"][k]))
            status, _ = m.call("fixedpoint_ideal_offsets_q30", xq, yq, cam, u, v, returns="i32")
            m.call("fixedpoint_offsets_to_unit_q30", Arg("i64", int(u[0])), Arg("i64", int(v[0])), cam, b)
            worst = max(worst, _exact(status, 0), _exact([u[0], v[0]], [out["u_ideal_q30"][k], out["v_ideal_q30"][k]]))
            worst = max(worst, _exact(b, out["b_q30"][k]))
    return worst


def _interstar_fixed(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, _ in _cases(doc):
        pi, pj = _i32(inp["pair_i"]), _i32(inp["pair_j"])
        e = np.zeros(pi.size, np.int64)
        m.call("fixedpoint_difference_residuals_q61", _i64(inp["b_q30"]), _i64(inp["r_q30"]), pi, pj, pi.size, e)
        worst = max(worst, _exact(e, out["e_q61"]))
    return worst


def _interstar_float32(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, tol in _cases(doc):
        b, r, jb = _f32(inp["b"]), _f32(inp["r"]), _f32(inp["jb"])
        pi, pj = _i32(inp["pair_i"]), _i32(inp["pair_j"])
        e, h = np.zeros(pi.size, np.float32), np.zeros((pi.size, 10), np.float32)
        m.call("interstar_difference_residuals", b, r, pi, pj, pi.size, e)
        m.call("interstar_difference_jacobian", b, jb, 10, pi, pj, pi.size, h)
        worst = max(worst, _within(e, out["e"], tol["e"]), _within(h, out["h"], tol["h"]))
        ci, cj = np.zeros(pi.size, np.int32), np.zeros(pi.size, np.int32)
        n_pairs, _ = m.call("interstar_independent_pairs", b.shape[0], ci, cj, returns="u32")
        worst = max(worst, _exact([n_pairs, *ci, *cj], [pi.size, *pi, *pj]))
    return worst


def _ud_update(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, tol in _cases(doc):
        u, d, xi, h = (np.array(inp[k], dtype=np.float32, order="C") for k in ("u", "d", "xi", "h"))
        s = np.zeros(1, np.float32)
        innovation, _ = m.call("ud_bierman_update", u, d, xi, h, Arg("f32", float(inp["y"])), d.size, s, returns="f32")
        got = {"u": u, "d": d, "xi": xi, "innovation": np.float32(innovation), "innovation_variance": s[0]}
        for name, value in got.items():
            worst = max(worst, _within(value, out[name], tol[name]))
    return worst


def _refraction_float32(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, tol in _cases(doc):
        r, zen = _f32(inp["r"]), _f32(inp["zenith"])
        a, b = float(inp["a_rad"]), float(inp["b_rad"])
        n = r.shape[0]
        cz, sz, t = np.zeros(n, np.float32), np.zeros(n, np.float32), np.zeros((n, 3), np.float32)
        m.call("refraction_zenith_geometry", r, n, zen, cz, sz, t)
        refr = [
            m.call(
                "refraction_from_true_zenith",
                Arg("f32", float(c)),
                Arg("f32", float(s)),
                Arg("f64", a),
                Arg("f64", b),
                returns="f32",
            )[0]
            for c, s in zip(cz, sz, strict=True)
        ]
        app = np.zeros((n, 3), np.float32)
        m.call("refraction_refract_toward_zenith", r, n, zen, Arg("f64", a), Arg("f64", b), app)
        worst = max(worst, _within(np.float32(refr), out["refraction_rad"], tol["refraction_rad"]))
        worst = max(worst, _within(app, out["apparent"], tol["apparent"]))
    return worst


def _refraction_fixed(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, _ in _cases(doc):
        r, zen, beta = (_i64(inp[k]) for k in ("r_q30", "zenith_q30", "beta_q48"))
        a, b = (int(v) for v in inp["ab_q56"])
        n = r.shape[0]
        for with_refraction, name in ((0, "aberrated_q30"), (1, "observed_q30")):
            got = np.zeros((n, 3), np.int64)
            args = (r, n, zen, beta, Arg("i32", with_refraction), Arg("i64", a), Arg("i64", b), got)
            m.call("refraction_topocentric_observed_q30", *args)
            worst = max(worst, _exact(got, out[name]))
    return worst


def _apparent_fixed(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, _ in _cases(doc):
        inst = fixed_instant(inp)
        r0, pm, plx = (_i64(inp[k]) for k in ("r0_q30", "pm_q46", "parallax_q48"))
        got = np.zeros_like(r0)
        m.call("apparent_place_vectors_q30", r0, pm, plx, r0.shape[0], inst, got)
        worst = max(worst, _exact(got, out["apparent_q30"]))
    return worst


def _apparent_float32(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, tol in _cases(doc):
        t = TimeTT(int(inp["t_tt_day"]), int(inp["t_tt_frac"]))
        day, frac = Arg("i32", t.day), Arg("u32", t.frac)  # a two-word structure by value: two core words
        tod = np.zeros((3, 3), np.float32)
        m.call("earth_true_of_date_matrix", day, frac, tod)
        r0, pm, plx = _f32(inp["r0"]), _f32(inp["pm_rad_yr"]), _f32(inp["parallax_mas"])
        got = np.zeros_like(r0)
        epoch = Arg("f64", float(inp["epoch_jyear"]))
        m.call("apparent_place_vectors", r0, pm, plx, r0.shape[0], epoch, day, frac, got)
        worst = max(worst, _within(tod, out["tod_matrix"], tol["tod_matrix"]))
        worst = max(worst, _within(got, out["apparent"], tol["apparent"]))
    return worst


def _attitude(m: Machine, doc: dict) -> float:
    worst = 0.0
    for inp, out, tol in _cases(doc):
        b, r, w = _f32(inp["b"]), _f32(inp["r"]), _f32(inp["weights"])
        c = np.zeros((3, 3), np.float32)
        status, _ = m.call("attitude_from_vectors", b, r, w, b.shape[0], c, returns="i32")
        worst = max(worst, _exact(status, 0), _within(c, out["c"], tol["c"]))
    return worst


class _BankRecord(ctypes.Structure):
    """banks_record_t (onboard/c/banks.h)."""

    _fields_ = [
        ("seq", ctypes.c_uint32),
        ("generation", ctypes.c_uint32),
        ("nonce_counter", ctypes.c_uint32),
        ("epoch", ctypes.c_uint32),
        ("table", ctypes.c_uint8 * 92),
    ]


def _as_bytes(value) -> bytes:
    return value if isinstance(value, bytes) else bytes(np.asarray(value, np.uint8))


def _bank_record(m: Machine, doc: dict) -> float:
    from onboard import banks

    worst = 0.0
    size, ssize = banks.BANK_RECORD_BYTES, banks.STAGE_RECORD_BYTES
    for inp, out, _ in _cases(doc):
        rec = _BankRecord(int(inp["seq"]), int(inp["generation"]), int(inp["nonce_counter"]), int(inp["epoch"]))
        rec.table[:] = list(_as_bytes(inp["table"]))
        encoded = np.zeros(size, np.uint8)
        m.call("banks_encode_bank_record", rec, encoded)
        worst = max(worst, _exact(list(encoded.tobytes()), list(_as_bytes(out["bank_record"]))))
        worst = max(worst, _exact(int.from_bytes(encoded[-4:].tobytes(), "little"), int(out["record_crc32"])))
        stage = np.zeros(ssize, np.uint8)
        m.call("banks_encode_stage_record", Arg("u32", int(inp["stage_counter"])), Arg("u32", int(inp["epoch"])), stage)
        worst = max(worst, _exact(list(stage.tobytes()), list(_as_bytes(out["stage_record"]))))
        blobs = _as_bytes(inp["verify_records"])
        valid, generation = [], []
        for k in range(0, len(blobs), size):
            got = _BankRecord()
            ok, _ = m.call(
                "banks_decode_bank_record", np.frombuffer(blobs[k : k + size], np.uint8).copy(), got, returns="i32"
            )
            valid.append(bool(ok))
            generation.append(got.generation if ok else 0)
        worst = max(worst, _exact(valid, out["verify_valid"]), _exact(generation, out["verify_generation"]))
        stages = _as_bytes(inp["verify_stage_records"])
        svalid, counters = [], []
        for k in range(0, len(stages), ssize):
            counter, epoch = np.zeros(1, np.uint32), np.zeros(1, np.uint32)
            raw = np.frombuffer(stages[k : k + ssize], np.uint8).copy()
            ok, _ = m.call("banks_decode_stage_record", raw, counter, epoch, returns="i32")
            svalid.append(bool(ok))
            counters.append(int(counter[0]) if ok else 0)
        worst = max(worst, _exact(svalid, out["verify_stage_valid"]), _exact(counters, out["verify_stage_counter"]))
    return worst


#: Vector file -> its check on the target (the host's, tests/test_c_numerics_vectors.py).
VECTOR_CHECKS = {
    "pixel_to_direction.float32.json": _pixel_to_direction_float32,
    "pixel_to_direction.fixed.json": _pixel_to_direction_fixed,
    "camera_jacobians.float32.json": _camera_jacobians,
    "interstar_residual.float32.json": _interstar_float32,
    "interstar_residual.fixed.json": _interstar_fixed,
    "ud_update.float32.json": _ud_update,
    "refraction_by_addition.float32.json": _refraction_float32,
    "refraction_by_addition.fixed.json": _refraction_fixed,
    "apparent_place.float32.json": _apparent_float32,
    "apparent_place.fixed.json": _apparent_fixed,
    "attitude.float32.json": _attitude,
    "bank_record.bytes.json": _bank_record,
}


def run_vectors(m: Machine, docs: dict[str, dict] | None = None) -> list[VectorResult]:
    """Every golden vector file with a C function on the target, checked as on the host."""
    docs = vectors.generate_vectors() if docs is None else docs
    out = []
    for name, check in VECTOR_CHECKS.items():
        m.reset_scratch()
        worst = check(m, docs[name])
        out.append(VectorResult(name, worst, worst <= 1.0))
    return out


# --------------------------------------------------------------------------------------------- the estimator
def _frame_rows(frame, n_stars: int):
    """The first ``n_stars`` identified stars of a frame (x, y, r, identified), or None if it has fewer."""
    x, y, r, ident = frame
    rows = np.flatnonzero(np.asarray(ident, bool))[:n_stars]
    if rows.size < n_stars:
        return None
    return (
        np.ascontiguousarray(x[rows], np.float64),
        np.ascontiguousarray(y[rows], np.float64),
        np.ascontiguousarray(r[rows], np.float64),
        np.ones(n_stars, np.uint8),
    )


def measure_updates(m: Machine, nominal, frames: list, n_stars: int, precision: str, noise_px: float = 0.05):
    """The estimator seam (onboard/c/estimator_seam.h, the path firmware.c takes) started cold from the nominal
    set on the target and fed ``frames`` cut to their first ``n_stars`` identified stars; the Python seam
    (onboard.firmware.RecursiveEstimator) fed the same. Returns (per-update :class:`~hostlink.portkit.cortexm.Call`
    list, the target's estimate minus the Python one in units of the Python 1-sigma, worst over parameters, the
    target's (estimate, 1-sigma) in float32, the frames after which the target's saved state (recursive_save_state
    of the seam's filter) differs from onboard.recursive.save_state's bytes)."""
    from onboard import banks
    from onboard.firmware import RecursiveEstimator
    from onboard.params import ESTIMATE_NAMES
    from onboard.recursive import RecursiveConfig, drift_focal_mm_per_frame_for, save_state
    from protocol.param_table import decode_table

    table = banks.params_to_table(nominal, np.full(10, np.nan))
    walk_mm = drift_focal_mm_per_frame_for(nominal.focal_length_mm)  # as the emulated sensor's (setup.py)
    config = RecursiveConfig(centroid_noise_px=noise_px, drift_focal_mm_per_frame=walk_mm)
    py = RecursiveEstimator(ESTIMATE_NAMES, config, precision=precision)
    py_state = py.start(banks.table_to_params(table), banks.table_to_sigma(table))
    cfg = SeamConfig((1 << len(ESTIMATE_NAMES)) - 1, int(precision == "fixed"), noise_px, walk_mm)
    m.reset_scratch()
    n_state, _ = m.call("estimator_seam_state_bytes", returns="u32")
    state = m.alloc(n_state + 16)
    status, _ = m.call("estimator_seam_start", state, cfg, _f32(decode_table(table)), returns="i32")
    if status != 0:
        raise ValueError(f"the target's estimator refused the nominal set (status {status})")
    calls = []
    differing = 0
    mark = m.mark()
    for frame in frames:
        cut = _frame_rows(frame, n_stars)
        if cut is None:
            continue
        x, y, r, ident = cut
        py.update(py_state, x, y, r, ident.astype(bool))
        status, cost = m.call("estimator_seam_update", state, n_stars, x, y, r, ident, returns="i32")
        m.release(mark)
        if status != 0:
            raise ValueError(f"the target's update failed (status {status}) where the Python one did not")
        calls.append(cost)
        # the seam's state begins with its recursive_state_t (estimator_seam_state.h): its saved bytes each frame
        expected = save_state(py_state)
        blob = np.zeros(len(expected), np.uint8)
        n_bytes, _ = m.call("recursive_save_state", state, blob, blob.size, returns="u32")
        m.release(mark)
        differing += n_bytes != blob.size or blob.tobytes() != expected
    values, sigma = np.zeros(10, np.float32), np.zeros(10, np.float32)
    mask, count = np.zeros(1, np.uint32), np.zeros(1, np.uint32)
    m.call("estimator_seam_estimate", state, values, sigma, mask, count)
    v_py, s_py, m_py, n_py = py.estimate(py_state)
    if (int(mask[0]), int(count[0])) != (int(m_py), int(n_py)):
        raise ValueError("the target's estimator used other frames than the Python sensor's")
    deviation = float(np.max(np.abs(values.astype(np.float64) - np.asarray(v_py, np.float64)) / np.asarray(s_py)))
    return calls, deviation, (values, sigma), differing


# --------------------------------------------------------------------------------------------- the commands
#: Bytes per STAGE_CHUNK (hostlink.links.serial_link's chunk: the smallest a link sends, so the most chunks).
CHUNK_BYTES = 32


def _fw_call(m: Machine, fw: int, message) -> tuple[object, object, dict]:
    """One command through firmware_handle (sil_handle) on the target: (decoded reply, Call, flash operations)."""
    from protocol import messages as msg

    raw = np.frombuffer(msg.encode(message), np.uint8).copy()
    reply = np.zeros(128, np.uint8)
    n = np.zeros(1, np.uint32)
    erases, programmed = m.read_u32("cortexm_flash_erases"), m.read_u32("cortexm_flash_programmed_bytes")
    mark = m.mark()
    result, cost = m.call("sil_handle", fw, raw, raw.size, reply, reply.size, n, returns="i32")
    m.release(mark)
    if result != 0:
        raise ValueError(f"the target's firmware gave no reply to {type(message).__name__} (result {result})")
    flash = {
        "sector_erases": m.read_u32("cortexm_flash_erases") - erases,
        "programmed_bytes": m.read_u32("cortexm_flash_programmed_bytes") - programmed,
    }
    return msg.decode(bytes(reply[: int(n[0])])), cost, flash


def measure_commands(m: Machine, factory, new_set, precision: str) -> dict[str, tuple]:
    """A whole upload on the target's firmware (firmware.c through sil_binding.c, booted on a fresh flash with
    ``factory`` as generation 1): STAGE_BEGIN, the table in CHUNK_BYTES chunks, STAGE_VERIFY, COMMIT. Returns
    command -> (Call, flash operations) (the chunk's worst); every reply must be the Ack a Python sensor gives."""
    from onboard import banks
    from onboard.recursive import drift_focal_mm_per_frame_for
    from protocol import messages as msg
    from protocol.param_table import TABLE_BYTES, table_crc

    m.reset_scratch()
    m.write(0x6000_0000, b"\xff" * banks.FLASH_BYTES)  # a fresh (erased) flash device
    fw_bytes, _ = m.call("sil_firmware_bytes", returns="u32")
    est_bytes, _ = m.call("sil_estimator_bytes", returns="u32")
    fw, est = (m.alloc(fw_bytes + 16) + 15) & ~15, (m.alloc(est_bytes + 16) + 15) & ~15
    callbacks = [m.address(f) | 1 for f in ("cortexm_flash_read", "cortexm_flash_erase", "cortexm_flash_program")]
    budget_flops, frame_s = 50e6, 0.1  # onboard.firmware.EstimatorBudget's defaults
    result, boot = m.call(
        "sil_boot",
        fw,
        *callbacks,
        m.address("cortexm_random32") | 1,
        np.arange(12, dtype=np.uint8),  # the device's unique ID
        Arg("u32", 0),  # no plausibility limits
        Arg("f64", 0.0),
        Arg("f64", 0.0),
        Arg("f64", 0.0),
        np.frombuffer(b"design value\0", np.uint8).copy(),
        Arg("u32", 0),  # no fixed-point range rule (it goes with the limits)
        np.frombuffer(banks.params_to_table(factory), np.uint8).copy(),
        est,
        Arg("u32", 0x3FF),
        Arg("u32", int(precision == "fixed")),
        Arg("f64", 0.05),
        Arg("f64", drift_focal_mm_per_frame_for(factory.focal_length_mm)),  # as the emulated sensor's
        Arg("f64", budget_flops),
        Arg("f64", frame_s),
        returns="i32",
    )
    if result != 0:
        raise ValueError(f"the target's firmware did not boot (result {result})")
    table = banks.params_to_table(new_set)
    out: dict[str, tuple] = {"boot (factory set)": (boot, {})}
    reply, cost, flash = _fw_call(m, fw, msg.StageBegin(tag=1, length=TABLE_BYTES))
    _expect_ack(reply, "STAGE_BEGIN")
    nonce = int(reply.value)
    out["stage begin"] = (cost, flash)
    worst = None
    for k, offset in enumerate(range(0, TABLE_BYTES, CHUNK_BYTES)):
        chunk = msg.StageChunk(tag=2 + k, offset=offset, data=bytes(table[offset : offset + CHUNK_BYTES]))
        reply, cost, flash = _fw_call(m, fw, chunk)
        _expect_ack(reply, "STAGE_CHUNK")
        if worst is None or cost.instructions > worst[0].instructions:
            worst = (cost, flash)
    out["stage chunk"] = worst
    crc = table_crc(bytes(table))
    reply, cost, flash = _fw_call(m, fw, msg.StageVerify(tag=20, crc32=crc))
    _expect_ack(reply, "STAGE_VERIFY")
    out["stage verify"] = (cost, flash)
    reply, cost, flash = _fw_call(m, fw, msg.Commit(tag=21, crc32=crc, nonce=nonce, expected_generation=1))
    _expect_ack(reply, "COMMIT")
    out["commit"] = (cost, flash)
    reply, _, _ = _fw_call(m, fw, msg.ReadActive(tag=22))
    if not isinstance(reply, msg.ParamTable) or bytes(reply.table) != bytes(table):
        raise ValueError("the target's active set after COMMIT is not the uploaded table")
    return out


def _expect_ack(reply, what: str) -> None:
    from protocol import messages as msg

    if not isinstance(reply, msg.Ack):
        raise ValueError(f"the target's firmware refused {what}: {reply}")


# --------------------------------------------------------------------------------------------- the report
#: Refraction's site constants for the row (A, B of R = A tan z + B tan^3 z at sea level, 10 C [rad]).
_REFRACTION_AB_RAD = (2.9e-4, -3.0e-7)


def _refraction_cost(m: Machine, docs: dict, precision: str, n: int):
    """Refraction by addition of ``n`` directions (the vector file's first case, repeated to n) on the target."""
    m.reset_scratch()
    if precision == "fixed":
        inp = next(_cases(docs["refraction_by_addition.fixed.json"]))[0]
        r = _i64(np.resize(inp["r_q30"], (n, 3)))
        a, b = (int(v) for v in inp["ab_q56"])
        args = (r, n, _i64(inp["zenith_q30"]), _i64(inp["beta_q48"]), Arg("i32", 1), Arg("i64", a), Arg("i64", b))
        return m.call("refraction_topocentric_observed_q30", *args, np.zeros((n, 3), np.int64))[1]
    inp = next(_cases(docs["refraction_by_addition.float32.json"]))[0]
    r = _f32(np.resize(inp["r"], (n, 3)))
    a, b = (Arg("f64", v) for v in _REFRACTION_AB_RAD)
    return m.call("refraction_refract_toward_zenith", r, n, _f32(inp["zenith"]), a, b, np.zeros((n, 3), np.float32))[1]


def measure_target(tgt: Target, nominal, new_set, frames: list, progress=None, optimise: str = "O2") -> TargetReport:
    """Everything ``hostlink costs --target`` prints for one target (module docstring): ``frames`` are a replayed
    session's (x, y, r, identified) per frame, each with at least 32 identified stars."""
    say = progress or (lambda _text: None)
    say(f"{tgt.name}: building the image")
    m = Machine(tgt, optimise)
    docs = vectors.generate_vectors()
    say(f"{tgt.name}: golden vectors")
    results = run_vectors(m, docs)
    fw_bytes, _ = m.call("sil_firmware_bytes", returns="u32")
    est_bytes, _ = m.call("sil_estimator_bytes", returns="u32")
    ram = m.image.ram_bytes + fw_bytes + est_bytes  # the statics a flight image holds: its own, firmware_t, the state
    report = TargetReport(tgt, m.image.flash_bytes, ram, est_bytes, fw_bytes, m.image.ram_bytes)
    report.vectors = results
    report.optimise = optimise
    report.flash_by_origin = flash_breakdown(m.elf)
    rows: list[Row] = []
    deviations = {}
    for n in UPDATE_STARS:
        say(f"{tgt.name}: recursive updates at {n} stars")
        calls, deviation, _, differing = measure_updates(m, nominal, frames, n, tgt.precision)
        worst = max(calls, key=lambda c: c.instructions)
        rows.append(
            Row(
                "recursive update",
                n,
                tgt.precision,
                worst.instructions,
                worst.cycles,
                max(c.stack_bytes for c in calls),
            )
        )
        deviations[str(n)] = {
            "updates": len(calls),
            "estimate_vs_python_sigma": deviation,
            "frames_state_differs_from_python": differing,
        }
    say(f"{tgt.name}: an upload's commands")
    for what, (cost, flash) in measure_commands(m, nominal, new_set, tgt.precision).items():
        if what in ("stage chunk", "stage verify", "commit"):
            rows.append(Row(what, None, tgt.precision, cost.instructions, cost.cycles, cost.stack_bytes, str(flash)))
    cost = _refraction_cost(m, docs, tgt.precision, REFRACTION_STARS)
    rows.append(
        Row("refraction by addition", REFRACTION_STARS, tgt.precision, cost.instructions, cost.cycles, cost.stack_bytes)
    )
    report.rows = rows
    report.stack_bytes = max(r.stack_bytes for r in rows)
    report.session = deviations
    return report


def format_reports(reports: list[TargetReport]) -> str:
    """The table ``hostlink costs --target`` prints."""
    lines = []
    for rep in reports:
        t = rep.target
        mhz = t.clock_hz / 1e6
        lines.append(f"{t.name} (-{rep.optimise}): {t.description}")
        lines.append(
            f"  flash {rep.flash_bytes} bytes (text + rodata + data), RAM {rep.ram_bytes} bytes (data + bss + the "
            f"firmware and estimator state, of which estimator {rep.state_bytes}), deepest stack {rep.stack_bytes} "
            f"bytes; golden vectors {'all passed' if rep.vectors_passed else 'FAILED'} "
            f"({sum(v.passed for v in rep.vectors)}/{len(rep.vectors)} files)"
        )
        lines.append("  flash by origin: " + ", ".join(f"{k} {v}" for k, v in rep.flash_by_origin.items()))
        lines.append(
            f"  {'what':<24} {'stars':>5} {'precision':<9} {'instructions':>13} {'cycles':>13} {'stack':>6} "
            f"{'ms @' + format(mhz, 'g') + ' MHz*':>14} {'% of 10 Hz*':>11}"
        )
        for r in rep.rows:
            ms = (r.instructions if r.cycles is None else r.cycles) / t.clock_hz * 1e3
            lines.append(
                f"  {r.what:<24} {'-' if r.stars is None else r.stars:>5} {r.precision:<9} {r.instructions:>13} "
                f"{'-' if r.cycles is None else r.cycles:>13} {r.stack_bytes:>6} {ms:>14.2f} "
                f"{100 * ms / 1e3 / FRAME_PERIOD_S:>10.1f}%"
            )
        lines.append("")
    lines.append(
        "* from the modelled cycles where there are (Cortex-M0+: the TRM's per-instruction timing, zero wait "
        "states), else at one instruction per cycle, a lower bound (the emulator counts instructions exactly; "
        "pipelined loads, taken branches, divisions and flash wait states cost more)"
    )
    return "\n".join(lines)
