"""Recorded upload traffic can never activate anything (issue 15): a COMMIT counts only inside the staging session
whose nonce it carries and against the generation it expects. Every recorded upload is replayed after it completed,
whole, every prefix, and in seeded random orders and subsets, on the in-process loopback (the real codecs and
firmware); the same bytes over a serial line against the emulator process are in tests/test_emulator_flash.py."""

import random

import pytest

from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.sensor import EmulatedSensor
from hostlink.errors import LinkError
from hostlink.links.base import CommandRefused
from hostlink.links.operations import read_active_params, safe_upload
from hostlink.sky.simulate import seed004_camera
from onboard import banks
from onboard.firmware import Firmware
from onboard.params import CameraParams, Distortion
from protocol import messages as m
from protocol.crc import crc32
from protocol.framing import FrameSplitter, FramingError, decode_frame, encode_frame
from protocol.param_table import TABLE_BYTES

NOMINAL = CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024))
CAMERA = seed004_camera()
OTHER = CameraParams(70.1, 12.0, (505.0, 520.0), (1024, 1024), Distortion(k1=-1e-10))


def recording_sensor():
    return EmulatedSensor(Firmware(banks.factory_store(NOMINAL)), iter(()))


def record_upload(sensor, params, drop=None):
    """The command bytes a host sent for one safe upload of ``params`` (``drop``: a MsgType whose command is
    recorded but lost before it reaches the sensor)."""
    sent = []

    def tap(data):
        sent.append(data)
        return None if drop is not None and data[0] == drop else data

    link = LoopbackLink(sensor, timeout_s=0.05, tamper=tap)
    try:
        safe_upload(link, params)
    except LinkError:
        assert drop is not None  # the dropped command's reply never came
    return sent


def replay(sensor, recording):
    """Send recorded command bytes to the sensor as they are; the replies (decoded)."""
    return [sensor.handle(m.decode(data)) for data in recording]


def active(sensor):
    return banks.active_set(sensor.firmware.store)


def committed(replies):
    return [r for r in replies if isinstance(r, m.Ack) and r.command == m.MsgType.COMMIT]


def test_a_recorded_upload_commits_exactly_once_when_it_happens():
    sensor = recording_sensor()
    recording = record_upload(sensor, CAMERA)
    assert active(sensor)[:2] == (2, banks.params_to_table(CAMERA))
    kinds = [m.MsgType(d[0]).name for d in recording]
    assert kinds[0] == "READ_ACTIVE" and kinds[1] == "STAGE_BEGIN" and "COMMIT" in kinds


def test_replaying_the_whole_upload_or_any_prefix_activates_nothing():
    sensor = recording_sensor()
    recording = record_upload(sensor, CAMERA)
    record_upload(sensor, NOMINAL)  # generation 3: the recorded set (CAMERA) is no longer active
    before = active(sensor)
    for k in range(1, len(recording) + 1):
        replies = replay(sensor, recording[:k])
        assert committed(replies) == [] and active(sensor) == before, k
    stale = [r for r in replay(sensor, recording) if isinstance(r, m.Nak) and r.command == m.MsgType.COMMIT]
    assert stale[0].code == m.NakCode.STALE_SESSION


@pytest.mark.parametrize("seed", range(4))
def test_replaying_recorded_pieces_in_random_orders_activates_nothing(seed):
    """300 random permutations and 300 random subsets (random order) of two recorded uploads' commands, per seed."""
    rng = random.Random(seed)
    sensor = recording_sensor()
    pool = record_upload(sensor, CAMERA) + record_upload(sensor, OTHER)
    before = active(sensor)
    refused = 0
    for _ in range(300):
        shuffled = rng.sample(pool, len(pool))
        subset = rng.sample(pool, rng.randrange(1, len(pool)))
        replies = replay(sensor, shuffled) + replay(sensor, subset)
        assert committed(replies) == [] and active(sensor) == before
        refused += sum(isinstance(r, m.Nak) and r.command == m.MsgType.COMMIT for r in replies)
    assert refused >= 300  # every shuffle holds two COMMITs: the sensor saw and refused them


def test_an_upload_whose_commit_was_lost_cannot_be_completed_by_replaying_it_even_after_a_reboot():
    sensor = recording_sensor()
    recording = record_upload(sensor, CAMERA, drop=m.MsgType.COMMIT)  # the COMMIT bytes were sent, never arrived
    assert active(sensor)[0] == 1
    assert committed(replay(sensor, recording)) == [] and active(sensor)[0] == 1
    store = sensor.firmware.store  # power cycle: RAM lost, flash (with its session counter) kept
    flash = banks.RamFlash(store.flash.image.copy())
    rebooted = EmulatedSensor(Firmware(banks.boot(flash, store.limits, store.identity)), iter(()))
    assert committed(replay(rebooted, recording)) == [] and active(rebooted)[0] == 1


def test_a_host_that_read_an_older_generation_is_refused_and_told_why():
    sensor = recording_sensor()
    link = LoopbackLink(sensor)
    nonce = link.stage_begin(TABLE_BYTES)
    table = banks.params_to_table(CAMERA)
    link.stage_chunk(0, table[:16])
    for off in range(16, len(table), 16):
        link.stage_chunk(off, table[off : off + 16])
    crc = crc32(table)
    link.stage_verify(crc)
    with pytest.raises(CommandRefused, match="STALE_SESSION.*expected generation 7 but generation 1"):
        link.commit(crc, nonce=nonce, expected_generation=7)
    assert link.commit(crc, nonce=nonce, expected_generation=1) == 2
    assert read_active_params(link).generation == 2


def serial_bytes(recording):
    """The recorded commands as they crossed a serial line: COBS frames with sequence numbers and CRC-32."""
    return b"".join(encode_frame(seq, data) for seq, data in enumerate(recording))


def replay_serial(sensor, line):
    """Feed raw line bytes through the sensor's serial receive path (split at 0x00, check, decode, handle)."""
    replies = []
    for raw in FrameSplitter().feed(line):
        try:
            replies.append(sensor.handle(m.decode(decode_frame(raw).payload)))
        except (FramingError, m.DecodeError):
            continue  # a cut or corrupt frame is never answered
    return replies


def test_every_byte_prefix_of_a_recorded_serial_upload_activates_nothing():
    sensor = recording_sensor()
    line = serial_bytes(record_upload(sensor, CAMERA))
    record_upload(sensor, NOMINAL)
    before = active(sensor)
    stale = 0
    for n in range(1, len(line) + 1):
        replies = replay_serial(sensor, line[:n])
        assert committed(replies) == [] and active(sensor) == before, n
        stale += sum(isinstance(r, m.Nak) and r.code == m.NakCode.STALE_SESSION for r in replies)
    assert stale == 12  # the prefixes that reach the end of the COMMIT frame: each refused as stale
    assert (
        len(line) > 200
    )  # the whole upload, every byte of it (measured: 260 bytes, 12 prefixes hold the whole COMMIT)


def fresh_sensor(identity):
    """A new unit (or a wiped flash): nothing committed, no session record, the device's own identity."""
    return EmulatedSensor(Firmware(banks.erased_store(banks.PlausibilityLimits(70.0), identity)), iter(()))


def test_a_recorded_first_upload_commits_nothing_on_another_fresh_sensor_nor_on_the_same_one_wiped():
    """Issue 33: the first upload of a fresh flash used to carry nonce 1 on every device. Now the nonce is keyed by
    the device's unique ID and the flash epoch drawn at its first record: 200 other fresh sensors, and the recording
    sensor itself with its flash wiped, refuse the replayed COMMIT as stale."""
    original = fresh_sensor(banks.seeded_identity(1000))
    recording = record_upload(original, CAMERA)
    assert active(original)[:2] == (1, banks.params_to_table(CAMERA))
    twin = fresh_sensor(banks.seeded_identity(1000))  # control: the same device and draws accept the same bytes
    assert len(committed(replay(twin, recording))) == 1
    for seed in range(200):
        other = fresh_sensor(banks.seeded_identity(seed))
        replies = replay(other, recording)
        assert committed(replies) == [] and active(other) is None, seed
        stale = [r for r in replies if isinstance(r, m.Nak) and r.command == m.MsgType.COMMIT]
        assert [r.code for r in stale] == [m.NakCode.STALE_SESSION], seed
    wiped = fresh_sensor(original.firmware.store.identity)  # same uid, its random source drawn on: a new epoch
    assert committed(replay(wiped, recording)) == [] and active(wiped) is None
    assert committed(replay(original, recording)) == [] and active(original)[0] == 1  # and the sensor itself
