"""The firmware state machine decides every command (the single authority on every link) and runs the onboard
recursive estimator on the frames it takes, restarting it from each newly committed set."""

import numpy as np
import pytest

from hostlink.emulator.sensor import session_frames
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from onboard import banks, recursive
from onboard.firmware import Firmware, RecursiveEstimator, estimate_to_params
from onboard.params import ESTIMATE_NAMES, CameraParams
from protocol import messages as m
from protocol.crc import crc32

NOMINAL = CameraParams(
    focal_length_mm=70.0, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
)


@pytest.fixture(scope="module")
def frames():
    sim = simulate(SimConfig(camera=seed004_camera(), frames=25, noise_px=0.05, seed=5))
    return list(session_frames(sim.session))


def upload(fw, params, tag=1):
    table = banks.params_to_table(params)
    crc = crc32(table)
    replies = [fw.handle(m.StageBegin(tag=tag, length=len(table)))]
    replies += [fw.handle(m.StageChunk(tag=tag, offset=o, data=table[o : o + 20])) for o in range(0, len(table), 20)]
    replies.append(fw.handle(m.StageVerify(tag=tag, crc32=crc)))
    staged = fw.handle(m.ReadStaged(tag=tag))
    nonce = replies[0].value  # the staging session's nonce
    generation = fw.handle(m.GetStatus(tag=tag)).active_generation
    commit = fw.handle(m.Commit(tag=tag, crc32=crc, nonce=nonce, expected_generation=generation))
    return replies, staged, commit


def test_upload_cycle_over_messages_switches_the_active_set():
    fw = Firmware(banks.factory_store(NOMINAL))
    replies, staged, commit = upload(fw, seed004_camera(), tag=77)
    assert all(isinstance(r, m.Ack) and r.tag == 77 for r in replies)
    assert staged.bank == m.TableBank.STAGED and staged.table == banks.params_to_table(seed004_camera())
    assert isinstance(commit, m.Ack) and commit.value == 2
    active = fw.handle(m.ReadActive(tag=3))
    assert (active.generation, active.table) == (2, banks.params_to_table(seed004_camera()))
    status = fw.handle(m.GetStatus(tag=4))
    assert status.active_generation == 2 and status.active_crc32 == active.crc32
    assert status.stage_state == m.StageState.EMPTY


def test_a_reply_is_never_a_command_and_is_refused():
    fw = Firmware(banks.factory_store(NOMINAL))
    reply = fw.handle(m.Ack(tag=9, command=1, value=0))
    assert isinstance(reply, m.Nak) and reply.code == m.NakCode.UNKNOWN_COMMAND and reply.tag == 9


def test_stream_control_switches_streaming():
    fw = Firmware(banks.factory_store(NOMINAL))
    assert isinstance(fw.handle(m.StreamControl(tag=1, enable=True)), m.Ack) and fw.streaming
    fw.handle(m.StreamControl(tag=2, enable=False))
    assert not fw.streaming


def test_the_start_ack_carries_the_first_exposures_counter_from_the_firmware_itself(frames):
    """docs/hardware.md: the ACK of a start carries the frame counter of the stream's first exposure; a start while
    streaming carries the same value, a stop 0. The firmware knows it (last exposure + 1, or the camera's driver's
    announcement), with no help from the emulator."""
    fw = Firmware(banks.factory_store(NOMINAL))
    assert fw.handle(m.StreamControl(tag=1, enable=True)).value == 0  # after boot, before any exposure
    for item in frames[:3]:
        fw.process_frame(item.frame, None)
    assert fw.handle(m.StreamControl(tag=2, enable=True)).value == 0  # already streaming: the same start
    assert fw.handle(m.StreamControl(tag=3, enable=False)).value == 0
    assert fw.handle(m.StreamControl(tag=4, enable=True)).value == frames[2].frame.frame + 1
    fw.handle(m.StreamControl(tag=5, enable=False))
    fw.set_next_frame(2**32 + 77)  # the camera's counter, low 32 bits
    assert fw.handle(m.StreamControl(tag=6, enable=True)).value == 77
    fw.set_next_frame(90)  # announced while streaming: the running stream's start does not change
    assert fw.handle(m.StreamControl(tag=7, enable=True)).value == 77
    fw.process_frame(m.CentroidFrame(**{**frames[0].frame.__dict__, "frame": 2**32 - 1}), None)
    fw.handle(m.StreamControl(tag=8, enable=False))
    assert fw.handle(m.StreamControl(tag=9, enable=True)).value == 0  # the counter wraps as the u32 it is


def test_without_estimator_the_estimate_is_refused_with_a_reason():
    fw = Firmware(banks.factory_store(NOMINAL))
    reply = fw.handle(m.ReadEstimate(tag=1))
    assert reply.code == m.NakCode.NO_ESTIMATE and "no onboard estimator" in reply.text


def test_firmware_estimate_is_the_float32_recursive_estimator_bit_for_bit(frames):
    fw = Firmware(banks.factory_store(NOMINAL), RecursiveEstimator())
    assert fw.handle(m.ReadEstimate(tag=1)).code == m.NakCode.NO_ESTIMATE  # before any frame
    direct = recursive.create(banks.table_to_params(banks.params_to_table(NOMINAL)), ESTIMATE_NAMES, None, np.float32)
    for item in frames:
        fw.process_frame(item.frame, item.r_ref)
        ident = item.frame.star_id != 0
        recursive.update(
            direct,
            item.frame.x_px.astype(np.float32),
            item.frame.y_px.astype(np.float32),
            np.where(ident[:, None], item.r_ref, 0).astype(np.float32),
            ident,
        )
    est = fw.handle(m.ReadEstimate(tag=2))
    assert isinstance(est, m.Estimate)
    assert est.n_updates == direct.updates > 0 and est.last_frame == frames[-1].frame.frame
    assert est.estimated_mask == (1 << 10) - 1 and est.base_generation == 1
    assert np.array_equal(np.float32(est.values), recursive.current_params(direct).vector(np.float32))
    sig = recursive.sigma(direct)
    assert np.array_equal(np.float32(est.sigma), np.float32([sig[n] for n in ESTIMATE_NAMES]))
    # the estimate moved from the nominal toward the true camera (f 70.2262 mm) within 5 sigma
    assert abs(est.values[0] - 70.2262) < 5 * est.sigma[0] < abs(70.0 - 70.2262)


def test_commit_restarts_the_estimator_from_the_new_set(frames):
    fw = Firmware(banks.factory_store(NOMINAL), RecursiveEstimator())
    for item in frames[:5]:
        fw.process_frame(item.frame, item.r_ref)
    assert fw.handle(m.ReadEstimate(tag=1)).n_updates == 5
    upload(fw, seed004_camera())
    assert fw.handle(m.ReadEstimate(tag=2)).code == m.NakCode.NO_ESTIMATE  # restarted, no update yet
    fw.process_frame(frames[5].frame, frames[5].r_ref)
    est = fw.handle(m.ReadEstimate(tag=3))
    assert est.base_generation == 2 and est.n_updates == 1


def test_a_failing_estimator_is_counted_and_restarted_not_fatal(frames):
    class Exploding(RecursiveEstimator):
        def update(self, *args):
            raise np.linalg.LinAlgError("not positive definite")

    fw = Firmware(banks.factory_store(NOMINAL), Exploding())
    fw.process_frame(frames[0].frame, frames[0].r_ref)
    assert fw.counters.estimator_faults == 1 and fw.counters.frames_processed == 1
    assert isinstance(fw.handle(m.GetStatus(tag=1)), m.Telemetry)


def test_estimate_to_params_replaces_only_estimated_parameters():
    est = m.Estimate(estimated_mask=0b111, values=(70.1, 500.0, 530.0) + (9.0,) * 7)
    p = estimate_to_params(NOMINAL, est)
    assert (p.focal_length_mm, p.principal_point_px) == (70.1, (500.0, 530.0))
    assert p.distortion == NOMINAL.distortion


def _with_time(item, t_us):
    from dataclasses import replace

    return replace(item.frame, t_us=t_us), item.r_ref


def test_default_budget_gives_every_exposure_of_a_1_hz_session_to_the_estimator(frames):
    fw = Firmware(banks.factory_store(NOMINAL), RecursiveEstimator())
    ran = [fw.process_frame(item.frame, item.r_ref) for item in frames]
    # the simulator's frames are 1 s apart; the worst case of 32 stars and 10 parameters is 1.0 Mflop = 20 ms at the
    # default 50 Mflop/s
    assert all(ran) and fw.counters.estimator_runs == len(frames) and fw.counters.estimator_skipped == 0
    assert fw.handle(m.ReadEstimate(tag=1)).n_updates == len(frames)


class _FixedCost(RecursiveEstimator):
    """The recursive estimator, declaring one fixed cost per update (1 Mflop) whatever the star count."""

    def cost_flops(self, n_stars: int) -> int:
        return 1_000_000


def test_budget_skips_exactly_the_exposures_that_arrive_while_the_modelled_processor_is_busy(frames):
    from onboard.firmware import EstimatorBudget

    # 1 Mflop at 0.6 Mflop/s: an update lasts 1.67 s, so with exposures 1 s apart the processor is busy at the next
    # one and idle at the one after
    fw = Firmware(banks.factory_store(NOMINAL), _FixedCost(), EstimatorBudget(flops_per_s=0.6e6))
    ran = [fw.process_frame(*_with_time(item, 1_000_000 * k)) for k, item in enumerate(frames)]
    assert ran == [k % 2 == 0 for k in range(len(frames))]
    assert fw.counters.estimator_skipped == len(frames) // 2 and fw.counters.frames_processed == len(frames)
    assert fw.handle(m.ReadEstimate(tag=1)).last_frame == frames[-1 - (len(frames) - 1) % 2].frame.frame


def test_exposures_whose_time_does_not_advance_are_spaced_by_the_fastest_frame_period(frames):
    from onboard.firmware import EstimatorBudget

    # an update lasts 0.25 s = 2.5 minimum frame periods: of exposures all stamped with one time, every third runs
    fw = Firmware(banks.factory_store(NOMINAL), _FixedCost(), EstimatorBudget(flops_per_s=4e6, min_frame_period_s=0.1))
    ran = [fw.process_frame(*_with_time(item, 5_000_000)) for item in frames[:9]]
    assert ran == [k % 3 == 0 for k in range(9)]


def test_recursive_estimator_declares_the_documented_worst_case_cost():
    # (max_iterations + 2) (P^3/3 + P^2 (K + 1) + 6 P K^2 + 40 N K), P = 2N - 3: 32 stars, 10 states -> 1.0 Mflop
    assert RecursiveEstimator().cost_flops(32) == 6 * (61**3 // 3 + 61 * 61 * 11 + 6 * 61 * 100 + 40 * 32 * 10)
    assert RecursiveEstimator().cost_flops(40) == RecursiveEstimator().cost_flops(32)  # capped at max_stars
    assert RecursiveEstimator().cost_flops(2) == 0  # fewer than 3 stars: the update returns at once


def test_a_budget_without_a_positive_speed_is_refused():
    from onboard.firmware import EstimatorBudget

    for budget in (EstimatorBudget(flops_per_s=0.0), EstimatorBudget(min_frame_period_s=float("nan"))):
        with pytest.raises(ValueError, match="budget"):
            Firmware(banks.factory_store(NOMINAL), RecursiveEstimator(), budget)
