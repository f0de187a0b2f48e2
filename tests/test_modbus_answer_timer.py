"""The Modbus link's answer wait and read size (hostlink.links.modbus_link.AnswerTimer): RFC 6298's retransmission
timeout from timed answers, backoff only after timeouts in a row, the line time on a serial line, and the read size
that minimises the expected time per register at a measured byte fault rate (checked against a numerical minimum)."""

import math

import pytest

from hostlink.links import modbus_link as ml


def test_the_wait_follows_rfc6298_from_timed_answers_between_its_floor_and_the_devices_response_time():
    t = ml.AnswerTimer(response_s=0.2)
    assert t.wait_s(10) == 0.2  # before any answer: the device's longest response time
    t.answered(0.010, 10)
    # RFC 6298 2.2: SRTT = R, RTTVAR = R/2, RTO = SRTT + 4 RTTVAR = 3 R
    assert t.rto_s == pytest.approx(0.030)
    t.answered(0.010, 10)
    # 2.3: RTTVAR = 3/4 RTTVAR + 1/4 |SRTT - R'|, SRTT = 7/8 SRTT + 1/8 R'
    assert t.rto_s == pytest.approx(0.010 + 4 * 0.75 * 0.005)
    for _ in range(200):
        t.answered(0.0005, 10)
    assert t.rto_s == ml._MIN_WAIT_S  # a fast device: the floor
    for _ in range(200):
        t.answered(1.0, 10)
    assert t.rto_s == 0.2  # a slow one: never more than its declared response time


def test_the_wait_doubles_only_after_timeouts_in_a_row_and_an_answer_resets_the_count():
    t = ml.AnswerTimer(response_s=0.2)
    for _ in range(50):
        t.answered(0.001, 10)
    base = t.rto_s
    t.timed_out()
    assert t.rto_s == base  # one lost answer on a noisy line: no backoff
    t.timed_out()
    assert t.rto_s == 2 * base
    t.answered(0.001, 10)
    t.timed_out()
    assert t.rto_s == pytest.approx(ml._MIN_WAIT_S)  # counted afresh after an answer


def test_the_line_time_on_a_serial_line_is_that_of_11_bit_characters():
    t = ml.AnswerTimer(response_s=0.1, baud=19200)
    # a read of 125 registers: 8-byte request (9 bytes counted with the request's register data, 0 here) + 5 + 250
    assert t.line_s(125) == pytest.approx((9 + 5 + 250) * 11 / 19200)
    assert t.wait_s(125) == pytest.approx(t.line_s(125) + 0.1)
    assert ml.AnswerTimer(baud=None).line_s(125) == 0.0  # TCP: no line time


def _fed(e: float) -> ml.AnswerTimer:
    """A timer that has seen a long run of 40-register exchanges failing at the rate a byte fault rate e gives."""
    t = ml.AnswerTimer(response_s=0.2)
    for _ in range(300):
        t.answered(0.001, 40)
    b = ml._EXCHANGE_OVERHEAD_BYTES + 80
    fail = e * b  # expected failures per exchange (small e)
    acc = 0.0
    for _ in range(2000):
        acc += fail
        ok = acc < 1.0
        acc = acc - 1.0 if not ok else acc
        t.exchanged(40, ok=ok)
    return t


def test_the_read_size_is_the_largest_on_a_clean_line_and_shrinks_as_faults_grow():
    clean = ml.AnswerTimer()
    for _ in range(100):
        clean.exchanged(125, ok=True)
    assert clean.read_registers() == 125
    sizes = [_fed(e).read_registers() for e in (0.001, 0.003, 0.01, 0.03)]
    assert sizes == sorted(sizes, reverse=True) and sizes[0] > sizes[-1]


def test_the_read_size_minimises_the_expected_time_per_register():
    scipy_optimize = pytest.importorskip("scipy.optimize")
    t = _fed(0.01)
    e = t.byte_fault_rate()
    assert e == pytest.approx(0.01, rel=0.05)  # the estimate recovers the rate fed in
    t_answer, t_wait = t.srtt_s, t.rto_s + ml._RETRY_PAUSE_S

    def cost(n: float) -> float:
        p = (1 - e) ** (ml._EXCHANGE_OVERHEAD_BYTES + 2 * n)
        return (t_answer + (1 / p - 1) * t_wait) / n

    best = scipy_optimize.minimize_scalar(cost, bounds=(ml._MIN_CHUNK, 125), method="bounded").x
    n = t.read_registers()
    assert abs(n - best) <= 1.0  # integer optimum next to the continuous one
    assert math.isfinite(cost(n)) and cost(n) <= cost(best) * 1.001
