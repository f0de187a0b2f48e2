"""The C firmware core (onboard/c) against the Python reference model: it compiles with the flight-code warnings as
errors, its refusal texts format numbers as Python does, and the same command sequences give the same replies and
the same flash images byte for byte (random sequences drawn by hypothesis, power cuts and reboots among them, a
recorded upload, flash images written by one firmware booted by the other).

``HOSTLINK_FWC_EXAMPLES=10000`` runs 10^4 random sequences (the acceptance run; ``scripts/firmware_c_proof.py`` does
the same with a seeded generator and prints the figures); the default is a CI-sized run."""

import math
import os
import random
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from firmware_twins import LIMITS, N_FIELDS, NOMINAL, SPECIAL_VALUES, TABLES, Twins, aged_image, with_field
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.sensor import EmulatedSensor
from hostlink.links.operations import safe_upload
from hostlink.portkit import firmware_c
from hostlink.portkit.export_c import generate_c
from hostlink.sky.simulate import seed004_camera
from onboard import banks
from onboard.firmware import Firmware
from protocol import messages as m
from protocol.param_table import TABLE_BYTES

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC") or "cc") is None, reason="no C compiler")

#: Random sequences per run: every command kind and NAK code many times, a few seconds of CI.
EXAMPLES = int(os.environ.get("HOSTLINK_FWC_EXAMPLES", "300"))
STEP = st.tuples(st.integers(0, 16), st.integers(0, 2**32 - 1), st.integers(0, 2**16 - 1), st.integers(0, 255))


@pytest.fixture(scope="module", autouse=True)
def library():
    """Built once (or found in the user's cache, keyed by the sources' hash) and loaded."""
    return firmware_c.load_library()


def test_the_core_and_the_codec_compile_with_the_flight_code_warnings_as_errors(tmp_path):
    for name, text in {**firmware_c.core_sources(), **generate_c()}.items():
        (tmp_path / name).write_text(text)
    for source in sorted(tmp_path.glob("*.c")):
        cmd = [firmware_c.find_compiler(), *firmware_c.WARNING_FLAGS, "-ffp-contract=off", "-c", str(source)]
        run = subprocess.run([*cmd, "-o", str(tmp_path / "x.o")], capture_output=True, text=True)
        assert run.returncode == 0 and run.stderr == "", f"{source.name}:\n{run.stderr}"


def test_numbers_are_formatted_as_python_formats_them():
    """repr, .3g, .6g, .0f and .0% of 20000 doubles: float32 values of every magnitude, random bit patterns
    (subnormals, infinities, NaN included), halves (ties of .0f) and powers of two (repr's uneven neighbours)."""
    rng = random.Random(7)
    xs = [0.0, -0.0, math.inf, -math.inf, math.nan, 0.5, 1.5, 2.5, -0.5, 1023.5, 99.95, 999.5, 1e16, 1e-5, 5e-324]
    for _ in range(20000):
        k = rng.random()
        if k < 0.35:
            xs.append(float(np.float32(rng.uniform(-1, 1) * 10 ** rng.uniform(-45, 38))))
        elif k < 0.6:
            xs.append(struct.unpack("<d", rng.getrandbits(64).to_bytes(8, "little"))[0])
        elif k < 0.8:
            xs.append(rng.randint(-(10**7), 10**7) / rng.choice([1, 2, 4, 8, 1000]))
        else:
            xs.append(math.ldexp(rng.choice([1.0, -1.0]), rng.randint(-1074, 1023)))
    for x in xs:
        for spec in firmware_c.FORMATS:
            want = repr(x) if spec == "r" else format(x, spec)
            assert firmware_c.format_c(spec, x) == want[:120], (x, spec)


def _on_the_wire(refusal: banks.Refusal | None) -> str | None:
    """A refusal's text as a NAK carries it (cut at NAK_TEXT_MAX bytes), None for no refusal."""
    return None if refusal is None else m.nak_text_bytes(refusal.text).decode()


def test_the_sensor_checks_give_the_same_verdict_and_text_for_every_field_at_every_edge():
    """Each of the 23 table fields of four good sets set to each edge value (NaN, infinities, zero, signs, half
    pixels, the image-size bound, huge and tiny): the reference's check_table and the C core's, text for text."""
    refused = 0
    for base in TABLES[:4]:
        for index in range(N_FIELDS):
            for value in SPECIAL_VALUES:
                table = with_field(base, index, value)
                refusal = banks.check_table(table, LIMITS)
                assert firmware_c.check_table_c(table, LIMITS) == _on_the_wire(refusal)
                refused += refusal is not None
    assert refused > 1000  # most edges break a rule: the texts were compared, not only the acceptances


def test_the_checks_agree_on_random_distortions_near_the_bounds():
    """Random distortion coefficients scaled around the monotonicity and displacement bounds (float32 arithmetic,
    the same operation order: the same verdict and the same printed numbers)."""
    rng = np.random.default_rng(3)
    scales = np.array([1e-9, 1e-15, 1e-21, 1e-5, 1e-5, 1e-5, 1e-5])
    for _ in range(400):
        table = TABLES[0]
        for k in range(7):
            table = with_field(table, 6 + k, float(rng.normal() * scales[k] * 10 ** rng.uniform(-1, 2.5)))
        refusal = banks.check_table(table, None)
        assert firmware_c.check_table_c(table, None) == _on_the_wire(refusal)


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(seed=st.integers(0, 2**16), steps=st.lists(STEP, min_size=3, max_size=60))
def test_random_command_sequences_give_the_same_replies_and_flash_bytes(seed, steps):
    twins = Twins(seed)
    for step in steps:
        twins.step(*step)


def test_the_sequences_exercise_every_refusal_and_commits():
    """A seeded run of the same generator: every NAK code the banks and the state machine give appears, and sets are
    committed (so the equality above covers them)."""
    rng = random.Random(11)
    refusals, commits = {}, 0
    for seed in range(40):
        twins = Twins(seed)
        for _ in range(60):
            twins.step(rng.randrange(17), rng.getrandbits(32), rng.getrandbits(16), rng.getrandbits(8))
        for code, count in twins.refusals.items():
            refusals[code] = refusals.get(code, 0) + count
        commits += twins.commits
    expected = {c for c in m.NakCode if c not in (m.NakCode.BUSY, m.NakCode.BANK_WRITE_FAILED)}
    assert set(refusals) >= expected and commits > 20, (refusals, commits)


@pytest.mark.parametrize("sessions", [0, 246, 247, 248, 250, 2 * 248 + 3])
def test_a_session_area_rewrite_and_power_cuts_through_it_agree(sessions):
    """Sequences started on a flash near or past a session-area rewrite (248 stage records per sector), including a
    power cut at every 97th byte of a STAGE_BEGIN that rewrites the active set."""
    image = aged_image(5, sessions)
    twins = Twins(5, image)
    rng = random.Random(sessions)
    for _ in range(30):
        twins.step(
            rng.choice([2, 2, 6, 8, 12, 13, 14, 15]), rng.getrandbits(32), rng.getrandbits(16), rng.getrandbits(8)
        )
    for budget in range(0, banks.SECTOR_BYTES + banks.BANK_RECORD_BYTES + 16, 97):
        twins = Twins(5, aged_image(5, banks.STAGE_SLOTS))
        twins.power_cut(budget, m.StageBegin(tag=1, length=TABLE_BYTES))
        twins.step(14, 0, 2, 0)


def _active(firmware) -> bytes:
    return firmware.handle_bytes(m.encode(m.ReadActive(tag=9)))


def test_a_flash_image_written_by_one_firmware_boots_in_the_other_to_the_same_active_set():
    """Python's image in a C sensor, C's image in a Python sensor: the same active set and status, and the next
    session gets the same nonce (counter and epoch recovered alike) and the same flash bytes."""
    rng = random.Random(2)
    generations = []
    for seed in range(30):
        twins = Twins(seed)
        for _ in range(25):
            twins.step(rng.choice([2, 3, 6, 8, 12, 13, 14, 14, 15]), rng.getrandbits(32), rng.getrandbits(16), 0)
        generations.append(twins.cross_boot(seed))
    assert max(generations) > 2  # images with committed sets were crossed, not only factory ones


def _recorded_upload(seed: int, image: np.ndarray | None = None) -> list[bytes]:
    """The command bytes of a bench upload (safe_upload of the seed-004 camera over the loopback link) to a Python
    sensor of identity ``seed`` (fresh from the factory, or booted from a copy of ``image``)."""
    identity = banks.seeded_identity(seed)
    if image is None:
        store = banks.factory_store(NOMINAL, banks.RamFlash(), LIMITS, identity)
    else:
        store = banks.boot(banks.RamFlash(image.copy()), LIMITS, identity)
    sensor = EmulatedSensor(Firmware(store), iter(()))
    sent = []

    def tap(data):
        sent.append(data)
        return data

    safe_upload(LoopbackLink(sensor, timeout_s=0.5, tamper=tap), seed004_camera())
    return sent


def test_a_recorded_upload_gives_the_same_replies_and_flash_bytes_and_replayed_commits_nothing():
    recording = _recorded_upload(21)
    twins = Twins(21)  # the recording device: the upload commits, in both firmwares alike
    for data in recording:
        twins.send(data)
    assert twins.commits == 1 and twins.generation() == 2
    for data in recording:  # replayed to the same sensor: nothing more
        twins.send(data)
    assert twins.commits == 1 and twins.generation() == 2
    twins.reboot()  # the same device (the same uid) after a power cycle: its session counter comes back from flash
    for data in recording:
        twins.send(data)
    assert twins.commits == 1 and twins.generation() == 2
    other = Twins(22)  # another sensor, fresh from the factory: nothing in either firmware
    for data in recording:
        other.send(data)
    assert other.commits == 0 and other.generation() == 1
    twins.check_flash()
    other.check_flash()


def test_successive_recorded_uploads_with_and_without_a_sigma_agree_and_their_replays_commit_nothing():
    """What the bench does, twice on one unit: an upload of a calibrated set with its 1-sigma prior (the bench's, issue
    29), then one without; recorded on the line of a Python sensor, played to both firmwares of the same unit (both
    commit, generation 3, the same replies and flash bytes), then replayed whole, each upload alone and in reverse
    order to that unit and to a unit with the same factory image: nothing more is committed."""
    sigma = np.array([0.02, 1.5, 1.5, 1e-10, 1e-16, np.nan, 0, 0, 0, 0])
    store = banks.factory_store(NOMINAL, banks.RamFlash(), LIMITS, banks.seeded_identity(41))
    image = store.flash.image.copy()
    sensor = EmulatedSensor(Firmware(store), iter(()))
    uploads: list[list[bytes]] = [[], []]
    for k, (params, prior) in enumerate(((seed004_camera(), sigma), (NOMINAL, None))):
        tap = uploads[k].append
        safe_upload(LoopbackLink(sensor, timeout_s=0.5, tamper=lambda d, tap=tap: (tap(d), d)[1]), params, sigma=prior)
    unit = Twins(41, image)
    for data in uploads[0] + uploads[1]:
        unit.send(data)
    assert unit.commits == 2 and unit.generation() == 3
    clone = Twins(42, image)
    for replay in (uploads[0] + uploads[1], uploads[0], uploads[1], uploads[1] + uploads[0]):
        for twins in (unit, clone):
            for data in replay:
                twins.send(data)
    assert unit.commits == 2 and unit.generation() == 3 and clone.commits == 0 and clone.generation() == 1
    unit.check_flash()
    clone.check_flash()


def test_a_recorded_upload_replayed_to_a_unit_programmed_with_the_same_factory_image_commits_nothing():
    """The hardest fresh sensor: a second unit whose flash is a byte copy of the recording unit's before the upload
    (a factory programming one image into every unit: the same epoch, the same session counter, so the same
    counter-based session as the recording). Only the device's uid tells the sessions apart; the nonce is keyed by
    it, so the recorded COMMIT is stale there, in both firmwares alike, and every reply and flash byte agree."""
    for sessions in (0, 5, banks.STAGE_SLOTS - 1):  # a new image, a used one, one whose next session rewrites
        image = aged_image(31, sessions)
        recording = _recorded_upload(31, image)
        recording_unit = Twins(31, image)  # the recording is a good upload for the unit it was made on
        for data in recording:
            recording_unit.send(data)
        assert recording_unit.commits == 1 and recording_unit.generation() == 2
        clone = Twins(32, image)  # another uid, the same flash bytes
        assert clone.py.store.epoch == recording_unit.py.store.epoch != 0
        for data in recording:
            clone.send(data)
        assert clone.commits == 0 and clone.generation() == 1, sessions
        clone.check_flash()


def test_the_message_handler_gives_the_same_verdict_on_fuzzed_bytes():
    """10^5 inputs (valid commands with bytes changed, cut or appended; random bytes after a real type byte), about
    4 s: the C handler never crashes and answers exactly when and what the Python one answers.
    ``scripts/firmware_c_proof.py --sequences 0 --fuzz 1000000`` is the 10^6 run."""
    rng = random.Random(4)
    twins = Twins(4)
    answered = 0
    for _ in range(100_000):
        answered += twins.send(fuzz_input(rng, twins)) is not None
    assert 10_000 < answered < 100_000  # both verdicts occur


PROOF_SCRIPT = Path(__file__).parents[1] / "scripts" / "firmware_c_proof.py"


def test_the_handler_fuzzed_from_python_under_address_and_undefined_behaviour_sanitizers():
    """The acceptance's fuzz run with the C core built with -fsanitize=address,undefined -fno-sanitize-recover=all
    and loaded into Python (the ASan runtime preloaded): 10^5 mutated or random messages and 300 command sequences,
    the same verdict and bytes as the Python firmware, no sanitizer report (one would abort the run)."""
    if firmware_c.sanitizer_preload() is None:
        pytest.skip("the compiler has no AddressSanitizer runtime")
    run = subprocess.run(
        [sys.executable, str(PROOF_SCRIPT), "--sequences", "300", "--fuzz", "100000", "--seed", "8", "--sanitize"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    assert "Sanitizer" not in run.stderr and "runtime error" not in run.stderr, run.stderr[-3000:]
    assert "100000 fuzz inputs" in run.stdout and "ASan+UBSan, no finding" in run.stdout, run.stdout


def fuzz_input(rng: random.Random, twins: Twins) -> bytes:
    """A mutated command: a real one with 1-3 bytes changed, cut short, extended, or random bytes after a type."""
    seeds = [
        m.GetStatus(tag=1), m.StreamControl(tag=2, enable=True), m.StageBegin(tag=3, length=TABLE_BYTES),
        m.StageChunk(tag=4, offset=8, data=TABLES[0][8:40]), m.StageVerify(tag=5, crc32=7), m.ReadStaged(tag=6),
        m.Commit(tag=7, crc32=1, nonce=twins.nonce, expected_generation=1), m.ReadActive(tag=8),
        m.ReadEstimate(tag=9),
    ]  # fmt: skip
    raw = bytearray(m.encode(rng.choice(seeds)))
    how = rng.randrange(4)
    if how == 0:
        for _ in range(rng.randint(1, 3)):
            raw[rng.randrange(len(raw))] = rng.getrandbits(8)
    elif how == 1:
        raw = raw[: rng.randrange(len(raw))]
    elif how == 2:
        raw += bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 8)))
    else:
        raw = bytearray([rng.choice([s.type_id for s in m.MESSAGES])]) + bytes(
            rng.getrandbits(8) for _ in range(rng.randint(0, 110))
        )
    return bytes(raw)


SIL_HARNESS = Path(__file__).with_name("c") / "sil_harness.c"


def test_the_sil_harness_runs_clean_under_address_and_undefined_behaviour_sanitizers(tmp_path):
    """A standalone C program (tests/c/sil_harness.c: a RAM flash HAL with power cuts, 20000 commands drawn from a
    seeded generator, a seventh of them mutated, reboots; then 100000 all mutated or random) built with
    -fsanitize=address,undefined: no sanitizer report, every reply decodes (10^6 of each by hand: 932270 and 297562
    answered, 4739 and 3 commits, 0 findings)."""
    for name, text in {**firmware_c.core_sources(), **generate_c()}.items():
        (tmp_path / name).write_text(text)
    shutil.copy(SIL_HARNESS, tmp_path / SIL_HARNESS.name)
    exe = tmp_path / "sil"
    sources = sorted(str(p) for p in tmp_path.glob("*.c"))
    flags = [*firmware_c.WARNING_FLAGS, "-ffp-contract=off", "-O1", *firmware_c.SANITIZE_FLAGS]
    build = subprocess.run(
        [
            firmware_c.find_compiler(),
            *flags,
            f"-I{tmp_path}",
            *sources,
            "-o",
            str(exe),
            "-lm",
        ],
        capture_output=True,
        text=True,
    )
    if build.returncode != 0 and "sanitize" in build.stderr and "cannot" in build.stderr:
        pytest.skip("the compiler has no sanitizer runtime")
    assert build.returncode == 0, build.stderr
    for mode in ([], ["fuzz"]):  # commands a seventh of them mutated; then every one mutated or random
        run = subprocess.run([str(exe), "100000", *mode], capture_output=True, text=True, timeout=300)
        assert run.returncode == 0 and "runtime error" not in run.stderr and "Sanitizer" not in run.stderr, run.stderr
        assert "commands 100000" in run.stdout and "replies 0 undecodable" in run.stdout, run.stdout


def test_the_cached_build_is_keyed_by_the_code_alone():
    """The library's cache key hashes what is compiled: the core's README ships with it (export-c writes it) but is
    not a build source, so editing it does not rebuild every cached library (the sanitized one takes ~20 s)."""
    assert "README.md" in firmware_c.core_sources()
    built = firmware_c.build_sources()
    assert built and all(name.endswith((".c", ".h")) for name in built)
    assert {n for n in firmware_c.core_sources() if n.endswith((".c", ".h"))} <= set(built)


def test_hostlink_export_c_writes_the_core_beside_the_codec_and_the_tree_compiles_stand_alone(tmp_path):
    """``hostlink export-c DIR``: the codec and the firmware core in one folder, every .c compiled with the flight-code
    flags and linked into one object (no undefined symbol but the C library's)."""
    run = subprocess.run(
        [sys.executable, "-m", "hostlink.cli", "export-c", str(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    written = {Path(line).name for line in run.stdout.split()}
    assert {"st_protocol.c", "firmware.c", "firmware.h", "banks.c", "params.c", "estimator_seam.h"} <= written
    sources = sorted(str(p) for p in tmp_path.glob("*.c"))
    out = tmp_path / "core.so"
    cmd = [firmware_c.find_compiler(), *firmware_c.WARNING_FLAGS, "-ffp-contract=off", "-fPIC", "-shared", *sources]
    build = subprocess.run([*cmd, "-o", str(out), "-Wl,--no-undefined", "-lm"], capture_output=True, text=True)
    assert build.returncode == 0 and build.stderr == "", build.stderr


def _fenced(text: str, after: str, language: str) -> str:
    """The first fenced ``language`` block of a Markdown text after the line containing ``after``."""
    start = text.index(f"```{language}\n", text.index(after)) + len(language) + 4
    return text[start : text.index("```", start)]


def test_the_exported_readmes_build_lines_and_minimal_main_work_stand_alone_with_plain_cc(tmp_path):
    """What a firmware engineer does with ``hostlink export-c DIR``: the README's main.c beside the core, then the
    README's two build lines run as written (every .c with the flight-code flags, linked with -lm), in a folder that
    holds nothing else; the program boots on an erased flash (RAM HAL of ram_flash.c, the estimator state reserved
    statically through estimator_seam_state.h) and answers GET_STATUS as the README says."""
    run = subprocess.run(
        [sys.executable, "-m", "hostlink.cli", "export-c", str(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    readme = (tmp_path / "README.md").read_text()
    (tmp_path / "main.c").write_text(_fenced(readme, "<!-- main.c", "c"))
    build = _fenced(readme, "## Build", "sh")
    assert build.count("\ncc ") + build.startswith("cc ") == 2, build  # the two commands the README promises
    env = dict(os.environ, PATH=f"{Path(firmware_c.find_compiler()).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    made = subprocess.run(["sh", "-e", "-c", build], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert made.returncode == 0 and made.stderr == "", made.stderr
    sensor = subprocess.run([str(tmp_path / "sensor")], capture_output=True, text=True, timeout=60)
    assert sensor.returncode == 0 and sensor.stdout == "tag 7, active generation 0, stage state 0\n", sensor


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_with_the_estimator_the_c_sensor_schedules_updates_and_estimates_as_the_python_one(precision):
    """300 simulated exposures (seed-004 camera, 0.05 px) through both firmwares with their estimators, an upload of a
    set with a sigma half-way (the estimators restart from it) and a slow modelled processor (frames skipped): the
    same frames estimated, skipped and counted, the same status replies byte for byte, and the Python sensor's
    estimate to the bit (the float32 filter is bit-exact, its configuration's centroid noise a double in both)."""
    from hostlink.emulator.sensor import session_frames
    from hostlink.emulator.setup import DEFAULT_NOMINAL
    from hostlink.files.params import load_params
    from hostlink.sky.simulate import SimConfig, simulate
    from onboard.firmware import EstimatorBudget, RecursiveEstimator
    from onboard.params import ESTIMATE_NAMES, PlausibilityLimits
    from onboard.recursive import RecursiveConfig

    if not firmware_c.estimator_available():
        pytest.skip("this build has no estimator implementation (estimator_seam.c)")
    nominal = load_params(DEFAULT_NOMINAL)
    limits = PlausibilityLimits(nominal.focal_length_mm)
    budget = EstimatorBudget(flops_per_s=1e6)  # 30 stars take ~0.86 s, more than some of the 0.8-1.2 s gaps
    seam = RecursiveEstimator(ESTIMATE_NAMES, RecursiveConfig(centroid_noise_px=0.05), precision=precision)
    py = Firmware(banks.factory_store(nominal, banks.RamFlash(), limits, banks.seeded_identity(1)), seam, budget)
    c = firmware_c.CFirmware(banks.RamFlash(), banks.seeded_identity(1), limits, nominal, budget, 1023, precision, 0.05)
    sim = simulate(SimConfig(camera=seed004_camera(), frames=300, noise_px=0.05, seed=3))
    sigma = np.array([0.02, 1.5, 1.5, 1e-10, 1e-16, np.nan, 0, 0, 0, 0])
    table = banks.params_to_table(nominal, sigma)
    for k, item in enumerate(session_frames(sim.session)):
        frame = m.CentroidFrame(**{**item.frame.__dict__, "t_us": item.frame.t_us + (k % 7) * 60_000})
        assert py.process_frame(frame, item.r_ref) == c.process_frame(frame, item.r_ref), k
        if k == 150:  # an upload: both estimators restart from the new set and its sigma
            for command in (
                m.StageBegin(tag=1, length=TABLE_BYTES), m.StageChunk(tag=2, offset=0, data=table),
                m.StageVerify(tag=3, crc32=banks.crc32(table)),
            ):  # fmt: skip
                assert c.handle_bytes(m.encode(command)) == m.encode(py.handle(command))
            commit = m.Commit(tag=4, crc32=banks.crc32(table), nonce=py.store.stage_nonce, expected_generation=1)
            assert c.handle_bytes(m.encode(commit)) == m.encode(py.handle(commit))
        status = m.GetStatus(tag=k)
        assert c.handle_bytes(m.encode(status)) == m.encode(py.handle(status))
    assert c.counters == py.counters and py.counters.estimator_skipped > 0 and py.counters.estimator_runs > 100
    expected, got = py.handle(m.ReadEstimate(tag=9)), c.handle(m.ReadEstimate(tag=9))
    same = ("estimated_mask", "base_generation", "n_updates", "last_frame", "status")
    assert [getattr(got, f) for f in same] == [getattr(expected, f) for f in same] and got.base_generation == 2
    # the seam inside the firmware is bit-exact with the Python one (tests/test_c_estimator_seam.py): the same float32
    # estimate; its 1-sigma, a double sum in two orders rounded to float32, within 1 float32 ulp
    assert np.array_equal(np.array(got.values, np.float32), np.array(expected.values, np.float32))
    ulps = np.array(got.sigma, np.float32).view(np.int32) - np.array(expected.sigma, np.float32).view(np.int32)
    assert np.all(np.abs(ulps) <= 1), ulps


def test_a_power_cut_anywhere_in_a_commit_leaves_the_same_flash_in_both_and_boots_alike():
    """A COMMIT cut after every 7th byte of its flash writes (the erase of the inactive sector and the 120-byte bank
    record: 4216 bytes; 7 is prime to the 8-byte write unit, so cuts fall at every offset within a unit): both
    firmwares stop at the same byte with the same image, and both reboot to the same active set and status."""
    table = TABLES[1]
    outcomes = []
    for budget in range(0, banks.SECTOR_BYTES + banks.BANK_RECORD_BYTES + 8, 7):
        twins = Twins(9)
        twins.table = table
        twins.command(m.StageBegin(tag=1, length=TABLE_BYTES))
        twins.command(m.StageChunk(tag=2, offset=0, data=table))
        twins.command(m.StageVerify(tag=3, crc32=banks.crc32(table)))
        commit = m.Commit(tag=4, crc32=banks.crc32(table), nonce=twins.nonce, expected_generation=1)
        twins.power_cut(budget, commit)  # compares the images, then reboots both
        for command in (m.ReadActive(tag=5), m.GetStatus(tag=6)):
            twins.command(command)
        outcomes.append(twins.generation())
    assert set(outcomes) == {1, 2} and outcomes.count(2) == 1  # old until the record's last byte, then new
