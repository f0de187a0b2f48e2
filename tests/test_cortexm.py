"""The C firmware core on emulated Cortex-M processors (issue 28; hostlink/portkit/cortexm.py, target_costs.py,
``hostlink costs --target``): built with -Werror for both targets, every golden vector passing there with the host's
checks, instruction counts exact run to run, the target's estimator bit-identical to the host build's, an upload
through firmware.c acknowledged with the flash writes onboard.banks makes.

Needs the optional ``cortexm`` extra (ziglang, unicorn): without it these tests skip, saying so."""

from __future__ import annotations

import ctypes
import json
import shutil
import sys

import numpy as np
import pytest

from hostlink.errors import UserError
from hostlink.portkit import cortexm
from hostlink.portkit.cortexm import TARGETS, Machine, thumb_instructions

needs_tools = pytest.mark.skipif(
    not cortexm.tools_available(),
    reason="the cortexm extra (ziglang, unicorn) is not installed: pip install '.[cortexm]'",
)


def test_thumb_instruction_lengths_follow_the_encoding():
    # movs r0, #1 and bx lr (16-bit); bl, ldr.w and vadd.f32 (32-bit: first halfword 0b11110, 0b11111, 0b11101)
    code = bytes.fromhex("0120704700f000f8d0f8000030ee200a")
    assert thumb_instructions(code) == 5
    assert thumb_instructions(bytes.fromhex("01207047")) == 2


def test_m0plus_cycle_table_follows_the_trm():
    from hostlink.portkit.cortexm import m0plus_cycles

    # Cortex-M0+ TRM table 3-1: ADDS 1, LDR 2, PUSH {r4-r7, lr} 1 + 5, POP {r4, pc} 3 + 1, BEQ 1 (+1 taken), B 2,
    # BX LR 2, MOV PC, r0 2, MULS 1 (single-cycle multiplier), BL 3
    assert m0plus_cycles(0x1840) == (1, False)
    assert m0plus_cycles(0x6800) == (2, False)
    assert m0plus_cycles(0xB5F0) == (6, False)
    assert m0plus_cycles(0xBD10) == (4, False)
    assert m0plus_cycles(0xD000) == (1, True)
    assert m0plus_cycles(0xE7FE) == (2, False)
    assert m0plus_cycles(0x4770) == (2, False)
    assert m0plus_cycles(0x4687) == (2, False)
    assert m0plus_cycles(0x4348) == (1, False)
    assert m0plus_cycles(0xF000, 0xF800) == (3, False)


def test_missing_tools_are_a_one_line_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "unicorn", None)  # import unicorn raises ImportError
    with pytest.raises(UserError, match=r"pip install 'startracker-companion\[cortexm\]'"):
        cortexm.Machine(TARGETS["cortex-m4f"])
    with pytest.raises(UserError, match="unknown target"):
        cortexm.target("cortex-m7")


@pytest.fixture(scope="module", params=list(TARGETS))
def machine(request):
    if not cortexm.tools_available():
        pytest.skip("the cortexm extra (ziglang, unicorn) is not installed: pip install '.[cortexm]'")
    return Machine(TARGETS[request.param])


@needs_tools
def test_every_golden_vector_passes_on_the_emulated_processor(machine):
    from hostlink.portkit.target_costs import VECTOR_CHECKS, run_vectors

    results = run_vectors(machine)
    assert [r.file for r in results] == list(VECTOR_CHECKS)
    for r in results:
        if ".fixed." in r.file or ".bytes." in r.file:
            assert r.worst_ratio == 0.0, r  # integers and bytes: bit-exact, as on the host
        else:
            assert r.worst_ratio <= 1.0, r  # float32: within each output's stated tolerance
    # the image holds the whole core and fits the mapped memories
    assert machine.image.flash_bytes > 50_000 and machine.image.sections[".text"] < cortexm.FLASH_MAP_BYTES


@needs_tools
def test_a_hand_counted_call_has_its_instructions_and_cycles(machine):
    # cortexm_random32 is `ldr r0, [pc, #0]; bx lr` on the M0+ (2 instructions, 2 + 2 cycles by the TRM) and
    # `movw r0, #0xf491; movt r0, #0x2545; bx lr` on the M4F (3); the return trap is not counted
    value, cost = machine.call("cortexm_random32", 0, returns="u32")
    assert value == 0x2545F491 and cost.instructions == (2 if machine.target.name == "cortex-m0plus" else 3)
    assert cost.cycles == (4 if machine.models_cycles else None)
    assert machine.models_cycles == (machine.target.name == "cortex-m0plus")


def _frames(n_frames: int):
    from hostlink.sky.references import session_references
    from hostlink.sky.simulate import SimConfig, seed004_camera, simulate

    cfg = SimConfig(
        camera=seed004_camera(), frames=n_frames, noise_px=0.05, min_stars=32, max_stars=40, maglim=8.0, seed=28
    )
    session = simulate(cfg).session
    refs = session_references(session)
    return [(session.x_px[r], session.y_px[r], refs.r[r], refs.usable[r]) for r in session.frame_slices()]


def _nominal():
    from hostlink.files.params import BUILTIN_PREFIX, load_params

    return load_params(BUILTIN_PREFIX + "seed004_nominal")


@needs_tools
def test_instruction_counts_are_exact_run_to_run():
    from hostlink.portkit.target_costs import _refraction_cost, measure_updates
    from hostlink.portkit.vectors import generate_vectors

    docs = generate_vectors()
    frames = _frames(2)
    for name in TARGETS:
        counts = []
        for _ in range(2):  # two fresh emulators: nothing carried over, nothing timed
            m = Machine(TARGETS[name])
            calls, _, _, _ = measure_updates(m, _nominal(), frames, 8, TARGETS[name].precision)
            refraction = _refraction_cost(m, docs, TARGETS[name].precision, 32)
            counts.append(([(c.instructions, c.cycles) for c in calls], [c.stack_bytes for c in calls], refraction))
        assert counts[0] == counts[1]
        assert len(counts[0][0]) == 2 and min(n for n, _ in counts[0][0]) > 10_000
        if name == "cortex-m0plus":  # every instruction takes at least one cycle
            assert all(cycles >= n for n, cycles in counts[0][0])


@needs_tools
@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) for the host build")
def test_target_estimator_is_bit_identical_to_the_host_build():
    # the same C, IEEE float32 on the M4F's FPU and in the M0+'s soft float, no FMA on either: the estimate after a
    # replayed session is the host build's to the bit, and the target's saved state is the Python model's after
    # every frame (the host build is proven against the Python model by tests/test_c_recursive.py and
    # test_c_estimator_seam.py)
    from hostlink.portkit import estimator_c
    from hostlink.portkit.estimator_c import SeamConfig, ptr, ref
    from hostlink.portkit.target_costs import _frame_rows, measure_updates
    from onboard import banks
    from protocol.param_table import decode_table

    lib = estimator_c.load()
    frames = _frames(3)
    nominal = _nominal()
    for name, n_stars in (("cortex-m4f", 16), ("cortex-m0plus", 8)):
        tgt = TARGETS[name]
        calls, deviation, (values, sigma), differing = measure_updates(
            Machine(tgt), nominal, frames, n_stars, tgt.precision
        )
        assert len(calls) == 3 and differing == 0  # bit-exact with the Python sensor after each of the 3 frames
        table = banks.params_to_table(nominal, np.full(10, np.nan))
        state = ctypes.create_string_buffer(int(lib.estimator_seam_state_bytes()) + 16)
        cfg = SeamConfig(0x3FF, int(tgt.precision == "fixed"), 0.05)
        assert (
            lib.estimator_seam_start(state, ref(cfg), ptr(np.ascontiguousarray(decode_table(table), np.float32))) == 0
        )
        for frame in frames:
            x, y, r, ident = _frame_rows(frame, n_stars)
            assert lib.estimator_seam_update(state, n_stars, ptr(x), ptr(y), ptr(r), ptr(ident)) == 0
        v, s = np.zeros(10, np.float32), np.zeros(10, np.float32)
        mask, count = ctypes.c_uint32(), ctypes.c_uint32()
        lib.estimator_seam_estimate(state, ptr(v), ptr(s), ctypes.byref(mask), ctypes.byref(count))
        assert count.value == 3
        assert np.array_equal(values, v) and np.array_equal(sigma, s)
        assert deviation == 0.0  # so the estimate is the Python sensor's too, to the bit


@needs_tools
def test_an_upload_on_the_target_is_acknowledged_and_writes_one_bank_record(machine):
    from hostlink.portkit.target_costs import measure_commands
    from hostlink.sky.simulate import seed004_camera
    from onboard import banks

    out = measure_commands(machine, _nominal(), seed004_camera(), machine.target.precision)  # raises on any NAK
    # onboard.banks: STAGE_BEGIN persists one stage record, a chunk only fills RAM, COMMIT erases the inactive sector
    # and programs one bank record
    assert out["stage begin"][1] == {"sector_erases": 0, "programmed_bytes": banks.STAGE_RECORD_BYTES}
    assert out["stage chunk"][1] == {"sector_erases": 0, "programmed_bytes": 0}
    assert out["commit"][1] == {"sector_erases": 1, "programmed_bytes": banks.BANK_RECORD_BYTES}
    assert out["stage verify"][0].instructions > out["stage chunk"][0].instructions  # the CRC and plausibility


@needs_tools
@pytest.mark.parametrize("name", list(TARGETS))
def test_costs_target_json_reports_the_issue_fields(capsys, name):
    from hostlink.cli import main

    assert main(["costs", "--target", name, "--frames", "1", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rep = doc["targets"][name]
    precision = TARGETS[name].precision
    assert rep["vectors_passed"] is True
    assert rep["flash_bytes"] > 0 and rep["ram_bytes"] > rep["estimator_state_bytes"] > 0 and rep["stack_bytes"] > 0
    assert rep["ram_bytes"] == sum(rep["ram_parts"].values())
    rows = {(r["what"], r["stars"]) for r in rep["rows"]}
    assert {("recursive update", n) for n in (8, 16, 32)} <= rows
    assert {("stage chunk", None), ("stage verify", None), ("commit", None), ("refraction by addition", 32)} <= rows
    for r in rep["rows"]:
        assert set(r) >= {"what", "stars", "precision", "instructions", "cycles"}
        assert r["precision"] == precision and r["instructions"] > 0
        # cycles modelled on the M0+ (at least one per instruction), null on the M4F
        assert r["cycles"] is None if name == "cortex-m4f" else r["cycles"] >= r["instructions"]
    by_stars = {r["stars"]: r["instructions"] for r in rep["rows"] if r["what"] == "recursive update"}
    assert by_stars[8] < by_stars[16] < by_stars[32]  # the work grows with the pairs (P^3 at large N)
