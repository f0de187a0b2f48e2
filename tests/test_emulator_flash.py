"""``hostlink emulate --flash FILE``: the sensor's banks and counters live in a NOR-flash image file; a restart on the
same file boots the last committed set; a kill -9 at any point of an upload leaves the complete old or complete new
set; recorded serial upload bytes replayed after a restart activate nothing; bad --flash use is a one-line error."""

import signal

import numpy as np
import pytest
from emulator_fixtures import hostlink
from scripts_loader import load_script

from hostlink.emulator.flash import FileFlash
from hostlink.emulator.process import EmulatorProcess
from hostlink.errors import UserError
from hostlink.links import open_link
from hostlink.links.operations import read_active_params, safe_upload
from hostlink.sky.simulate import seed004_camera
from onboard import banks
from onboard.params import CameraParams

NOMINAL = CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024))
CAMERA = seed004_camera()
FAST = ("--no-estimator", "--sim-frames", "5")  # the banks matter here, not the frames


def test_a_file_flash_mirrors_every_write_and_boots_what_was_committed(tmp_path):
    path = tmp_path / "f.img"
    flash = FileFlash(path)
    identity = banks.seeded_identity(3)
    store = banks.factory_store(NOMINAL, flash=flash, identity=identity)
    nonce = banks.stage_begin(store, banks.TABLE_BYTES)
    table = banks.params_to_table(CAMERA)
    assert banks.stage_chunk(store, 0, table) is None and banks.stage_verify(store, banks.crc32(table)) is None
    assert banks.commit(store, banks.crc32(table), nonce, 1) == 2
    flash.close()
    on_disk = np.fromfile(path, dtype=np.uint8)
    assert np.array_equal(on_disk, flash.image)  # every erase and program reached the file
    again = FileFlash(path)
    rebooted = banks.boot(again, identity=identity)
    assert banks.active_set(rebooted)[:2] == (2, table) and rebooted.nonce_counter == store.nonce_counter == 1
    next_nonce = banks.session_nonce(identity.uid, store.epoch, 2)
    assert banks.stage_begin(rebooted, banks.TABLE_BYTES) == next_nonce  # the counter and epoch survived too
    again.close()


def test_a_flash_file_of_the_wrong_size_or_in_use_is_a_one_line_error(tmp_path):
    bad = tmp_path / "bad.img"
    bad.write_bytes(b"\xff" * 100)
    with pytest.raises(UserError, match=f"100 bytes is not a flash image \\({banks.FLASH_BYTES} bytes\\)"):
        FileFlash(bad)
    first = FileFlash(tmp_path / "f.img")
    with pytest.raises(UserError, match="in use by another emulated sensor"):
        FileFlash(tmp_path / "f.img")
    first.close()
    run = hostlink("emulate", "--transport", "serial", "--flash", str(bad))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1 and "not a flash image" in run.stderr
    run = hostlink("emulate", "--transport", "serial", "--power-cut-after", "3")
    assert run.returncode == 2 and "--power-cut-after needs --flash" in run.stderr


def test_a_restart_on_the_same_flash_boots_the_last_committed_set(tmp_path):
    flash = tmp_path / "sensor.img"
    with EmulatorProcess("serial", FAST, flash_path=flash) as emulator:
        with open_link(emulator.link) as link:
            assert read_active_params(link).generation == 1  # a new image receives the factory set
            assert safe_upload(link, CAMERA).generation == 2
    with EmulatorProcess("serial", FAST, flash_path=flash) as emulator:  # SIGTERM above; a restart here
        with open_link(emulator.link) as link:
            active = read_active_params(link)
    assert active.generation == 2 and banks.params_to_table(active.params) == banks.params_to_table(CAMERA)


def test_recorded_serial_upload_bytes_replayed_after_a_restart_activate_nothing(tmp_path):
    flash = tmp_path / "sensor.img"
    recorded = bytearray()
    with EmulatorProcess("serial", FAST, flash_path=flash) as emulator:
        with open_link(emulator.link) as link:
            write = link._port.write
            link._port.write = lambda data: (recorded.extend(data), write(data))[1]  # tap the line
            safe_upload(link, CAMERA)
            link._port.write = write
            safe_upload(link, NOMINAL)  # generation 3: the recorded set is not active any more
    with EmulatorProcess("serial", FAST, flash_path=flash) as emulator:
        with open_link(emulator.link) as link:
            link._port.write(bytes(recorded))  # the whole recording, as another host on the line would send it
            link._port.write(bytes(recorded[: len(recorded) // 2]))  # and its first half
            active = read_active_params(link)  # replies in order: the replay has been handled by now
    assert active.generation == 3 and banks.params_to_table(active.params) == banks.params_to_table(NOMINAL)


@pytest.mark.slow  # Monte Carlo (issue 29: the fast lane is pytest -m 'not slow')
@pytest.mark.parametrize("firmware", ["python", "c"])
def test_kill_9_at_random_points_of_uploads_leaves_the_complete_old_or_new_set(tmp_path, firmware):
    """20 power cuts (seed 15): 10 from inside at an exact flash write unit, 10 kill -9 from outside at random times;
    after each restart a recorded upload (whole, a prefix or some of its frames) is replayed on the line and activates
    nothing; with the Python firmware and with the C core (``--firmware c``). The 200-point acceptance run is
    ``scripts/flash_power_cuts.py --trials 200 [--firmware c]`` (docs/hardware.md)."""
    trials = load_script("flash_power_cuts.py").run_trials(20, seed=15, workdir=tmp_path, firmware=firmware)
    assert [t.outcome for t in trials if t.outcome not in ("old", "new")] == []
    assert len(trials) == 20 and sum(t.how.startswith("inside") for t in trials) == 10
    assert [t.replay_outcome for t in trials if t.replay_outcome != "nothing activated"] == []
    # the replays were handled by the sensor (each opened a staging session), not lost on the way
    assert sum(t.replay_sessions > 0 for t in trials) >= 10


def test_the_power_cut_hook_kills_the_emulator_mid_commit(tmp_path):
    flash = tmp_path / "sensor.img"
    with EmulatorProcess("serial", FAST, flash_path=flash):
        pass  # the factory set, written once
    units = (banks.STAGE_RECORD_BYTES + banks.SECTOR_BYTES // 2) // banks.WRITE_BYTES  # half-way through the erase
    emulator = EmulatorProcess("serial", (*FAST, "--power-cut-after", str(units)), flash_path=flash)
    try:
        with open_link(emulator.link, timeout_s=5.0) as link, pytest.raises(Exception):  # noqa: B017 - link died
            safe_upload(link, CAMERA)
        assert emulator.process.wait(30) == -signal.SIGKILL
    finally:
        emulator.stop()
    image = np.fromfile(flash, dtype=np.uint8)
    assert banks.active_set(banks.boot(banks.RamFlash(image)))[0] == 1


@pytest.mark.parametrize("firmware", ["python", "c"])
def test_a_recorded_first_upload_replayed_to_another_fresh_sensor_commits_nothing(tmp_path, firmware):
    """Issue 33: two new units (fresh flash files), the first upload of one recorded on its serial line and sent to the
    other: its COMMIT is stale there (the nonce is the first sensor's), the factory set stays active."""
    recorded = bytearray()
    args = (*FAST, "--firmware", firmware)
    with EmulatorProcess("serial", args, flash_path=tmp_path / "a.img") as emulator:
        with open_link(emulator.link) as link:
            write = link._port.write
            link._port.write = lambda data: (recorded.extend(data), write(data))[1]  # tap the line
            assert safe_upload(link, CAMERA).generation == 2
    with EmulatorProcess("serial", args, flash_path=tmp_path / "b.img") as emulator:
        with open_link(emulator.link) as link:
            link._port.write(bytes(recorded))
            active = read_active_params(link)  # replies in order: the replay has been handled by now
    assert active.generation == 1 and banks.params_to_table(active.params) != banks.params_to_table(CAMERA)
    image = np.fromfile(tmp_path / "b.img", dtype=np.uint8)
    assert banks.boot(banks.RamFlash(image)).nonce_counter == 1  # the replay reached it: its STAGE_BEGIN was answered


@pytest.mark.parametrize("firmware", ["python", "c"])
@pytest.mark.parametrize("transport", ["serial", "can", "modbus"])
def test_a_recorded_upload_replayed_to_another_unit_or_the_same_restarted_commits_nothing_on_every_transport(
    tmp_path, transport, firmware
):
    """Issue 27: an upload's link calls recorded on one new unit (STAGE_BEGIN, chunks, STAGE_VERIFY, COMMIT with its
    nonce) and made again, through the transport's own command path, to another new unit and to the first restarted:
    the sensor accepts every call but the COMMIT (the replay reached its staging) and nothing is activated."""
    script = load_script("flash_power_cuts.py")
    failures, reached = script.unit_replays(1, tmp_path, transport, firmware)
    assert failures == []
    assert len(reached) == 2 and all(accepted == made - 1 and made >= 4 for accepted, made in reached), reached


@pytest.mark.parametrize("firmware", ["python", "c"])
def test_a_unit_restarted_on_its_flash_keeps_its_uid_so_its_nonces_follow_its_counter(tmp_path, firmware):
    """The emulated unit is its flash file: restarted on it, the same uid (hostlink.emulator.setup.unit_identity: an
    MCU's unique ID does not change at a reset), so each STAGE_BEGIN's nonce is the device's keyed permutation of its
    persisted counter; another file is another unit (another uid)."""
    from hostlink.emulator.setup import unit_identity

    flash = tmp_path / "unit.img"
    assert unit_identity(str(flash)).uid == unit_identity(str(flash)).uid != unit_identity(str(tmp_path / "b")).uid
    nonces = []
    for _ in range(2):
        with EmulatorProcess("serial", (*FAST, "--firmware", firmware), flash_path=flash) as emulator:
            with open_link(emulator.link) as link:
                nonces.append(link.stage_begin(banks.TABLE_BYTES))
    store = banks.boot(banks.RamFlash(np.fromfile(flash, dtype=np.uint8)))
    uid = unit_identity(str(flash)).uid
    assert store.nonce_counter == 2
    assert nonces == [banks.session_nonce(uid, store.epoch, c) for c in (1, 2)]
