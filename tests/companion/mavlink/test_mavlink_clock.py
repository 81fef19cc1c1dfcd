"""The autopilot's clock on ours: late and backwards samples, TIMESYNC, reboots, wrap-around."""

from __future__ import annotations

import pytest

from companion.mavlink.clock import AutopilotClock, Verdict

#: The autopilot booted at our monotonic time 1000 s: its boot time b is our 1000 + b.
BOOT_AT = 1000.0


def feed(clock: AutopilotClock, stream: str, boots: list[float], latency: float) -> None:
    for b in boots:
        assert clock.stamp(stream, b, BOOT_AT + b + latency).verdict is Verdict.OK


def test_samples_are_placed_at_their_sampling_time_not_their_arrival() -> None:
    clock = AutopilotClock()
    # Jitter: the least-delayed packet (2 ms) bounds the offset.
    for k, delay in enumerate([0.030, 0.002, 0.015, 0.040, 0.008]):
        b = 5.0 + 0.04 * k
        clock.stamp("ATTITUDE", b, BOOT_AT + b + delay)
    assert clock.offset == pytest.approx(BOOT_AT + 0.002)
    s = clock.stamp("ATTITUDE", 5.2, BOOT_AT + 5.2 + 0.030)
    assert s.verdict is Verdict.OK and s.t == pytest.approx(BOOT_AT + 5.202) and s.lag_s == pytest.approx(0.028)
    assert clock.source == "arrivals"


def test_a_three_second_old_sample_is_late_and_rejected() -> None:
    """The audit: a packet held 3 s in a buffer became the current pose (a 50 m jump)."""
    clock = AutopilotClock(max_lag_s=0.5)
    feed(clock, "GLOBAL_POSITION_INT", [10.0 + 0.1 * k for k in range(20)], latency=0.01)
    # The link stalls; the next sample (sampled at 12.0) arrives 3 s later.
    s = clock.stamp("GLOBAL_POSITION_INT", 12.0, BOOT_AT + 15.0)
    assert s.verdict is Verdict.LATE and s.lag_s == pytest.approx(3.0, abs=0.02)
    assert clock.stats.late == 1
    # The stream did not move on: a fresh sample is still accepted.
    assert clock.stamp("GLOBAL_POSITION_INT", 15.0, BOOT_AT + 15.01).verdict is Verdict.OK


def test_backwards_and_repeated_samples_are_rejected_per_stream() -> None:
    clock = AutopilotClock()
    feed(clock, "ATTITUDE", [1.0, 1.04, 1.08], latency=0.01)
    assert clock.stamp("ATTITUDE", 1.08, BOOT_AT + 1.10).verdict is Verdict.BACKWARDS  # a duplicate
    assert clock.stamp("ATTITUDE", 1.00, BOOT_AT + 1.11).verdict is Verdict.BACKWARDS  # out of order
    assert clock.stats.backwards == 2
    # Another stream has its own order.
    assert clock.stamp("GLOBAL_POSITION_INT", 1.05, BOOT_AT + 1.06).verdict is Verdict.OK


def test_timesync_takes_a_constant_latency_out() -> None:
    """With 200 ms each way, arrival times alone place every sample 200 ms late; TIMESYNC's
    round trip measures it, and the lag of each sample then shows the latency."""
    latency = 0.2
    clock = AutopilotClock(max_lag_s=0.5)
    feed(clock, "ATTITUDE", [2.0 + 0.04 * k for k in range(10)], latency)
    assert clock.to_local(2.0) == pytest.approx(BOOT_AT + 2.0 + latency)  # biased by the latency
    sent = BOOT_AT + 2.5
    ts1 = clock.request(sent)
    their_boot_at_receipt = sent + latency - BOOT_AT
    assert clock.on_timesync(int(their_boot_at_receipt * 1e9), ts1, sent + 2 * latency)
    assert clock.source == "timesync"
    assert clock.latency_s == pytest.approx(latency)
    assert clock.to_local(2.0) == pytest.approx(BOOT_AT + 2.0, abs=1e-6)
    s = clock.stamp("ATTITUDE", 2.6, BOOT_AT + 2.6 + latency)
    assert s.t == pytest.approx(BOOT_AT + 2.6) and s.lag_s == pytest.approx(latency)


def test_timesync_answers_we_did_not_ask_for_or_from_another_clock_are_not_used() -> None:
    clock = AutopilotClock(max_lag_s=0.5)
    feed(clock, "ATTITUDE", [30.0, 30.04], latency=0.01)
    bound = clock.offset
    assert not clock.on_timesync(int(30.0e9), 123456789, BOOT_AT + 30.05)  # a ts1 we never sent
    ts1 = clock.request(BOOT_AT + 30.1)
    assert not clock.on_timesync(int(30.0e9), ts1, BOOT_AT + 30.1 + 0.9)  # round trip past 0.5 s
    # Clocks 10 s behind or ahead of time_boot_ms's: packets would have arrived before they were
    # sent, or every one of them 10 s late.
    for skew in (-10.0, 10.0):
        sent = BOOT_AT + 30.2 + skew / 100
        ts1 = clock.request(sent)
        assert clock.on_timesync(int((sent - BOOT_AT + skew) * 1e9), ts1, sent + 0.002)
        assert clock.offset == bound and clock.source == "arrivals"
    assert clock.stats.timesync_ignored == 2


def test_an_autopilot_reboot_restarts_the_clock_once_confirmed() -> None:
    clock = AutopilotClock(reboot_s=5.0, reboot_confirm=3)
    feed(clock, "ATTITUDE", [600.0, 600.04], latency=0.01)
    # Rebooted: its clock restarts at 0.5 s. One packet going back is not enough (a forgery, a
    # stray): the third in a row that agrees on the new offset restarts the estimate.
    now = BOOT_AT + 601.0
    verdicts = [clock.stamp("ATTITUDE", 0.5 + 0.04 * k, now + 0.04 * k).verdict for k in range(3)]
    assert verdicts == [Verdict.BACKWARDS, Verdict.BACKWARDS, Verdict.REBOOT]
    assert clock.stats.reboots == 1
    assert clock.to_local(0.6) == pytest.approx(now + 0.1)
    assert clock.stamp("ATTITUDE", 0.62, now + 0.125).verdict is Verdict.OK


def test_time_boot_ms_wrapping_after_49_days_is_not_a_step_back() -> None:
    clock = AutopilotClock()
    top = 2**32 / 1000.0
    feed(clock, "ATTITUDE", [top - 0.08, top - 0.04], latency=0.01)
    s = clock.stamp("ATTITUDE", 0.0, BOOT_AT + top + 0.01)
    assert s.verdict is Verdict.OK and s.boot_s == pytest.approx(top)


def test_the_latency_follows_the_link_while_the_offset_keeps_the_best_exchange() -> None:
    clock = AutopilotClock()
    feed(clock, "ATTITUDE", [1.0, 1.04], latency=0.001)
    for k, latency in enumerate([0.001, 0.001, 0.2, 0.2, 0.2]):  # the link slows down
        sent = BOOT_AT + 2.0 + k
        ts1 = clock.request(sent)
        assert clock.on_timesync(int((sent + latency - BOOT_AT) * 1e9), ts1, sent + 2 * latency)
    assert clock.latency_s == pytest.approx(0.2)
    assert clock.to_local(3.0) == pytest.approx(BOOT_AT + 3.0, abs=1e-6)
