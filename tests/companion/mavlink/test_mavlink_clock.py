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
    for k, sent in enumerate((BOOT_AT + 2.5, BOOT_AT + 3.5)):
        ts1 = clock.request(sent)
        their_boot_at_receipt = sent + latency - BOOT_AT
        # The first exchange alone moves nothing (issue 61): the second one, agreeing, confirms it.
        assert clock.on_timesync(int(their_boot_at_receipt * 1e9), ts1, sent + 2 * latency) is (k == 1)
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
        for k in range(2):  # confirmed by a second exchange: the same clock, consistently
            sent = BOOT_AT + 30.2 + skew / 100 + 0.01 * k
            ts1 = clock.request(sent)
            assert clock.on_timesync(int((sent - BOOT_AT + skew) * 1e9), ts1, sent + 0.002) is (k == 1)
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
        assert clock.on_timesync(int((sent + latency - BOOT_AT) * 1e9), ts1, sent + 2 * latency) is (k > 0)
    assert clock.latency_s == pytest.approx(0.2)
    assert clock.to_local(3.0) == pytest.approx(BOOT_AT + 3.0, abs=1e-6)


# -- issue 61: no single unauthenticated packet moves the clock -------------------------------


def genuine(clock: AutopilotClock, start: float, n: int, latency: float = 0.01) -> list[Verdict]:
    """Both pose streams at 20 Hz from autopilot time ``start`` (s); their verdicts."""
    out = []
    for k in range(n):
        b = start + 0.05 * k
        out.append(clock.stamp("ATTITUDE", b, BOOT_AT + b + latency).verdict)
        out.append(clock.stamp("GLOBAL_POSITION_INT", b + 0.01, BOOT_AT + b + 0.01 + latency).verdict)
    return out


@pytest.mark.parametrize("lead_s", [0.6, 5.0, 3600.0])
@pytest.mark.parametrize("stream", ["ATTITUDE", "GLOBAL_POSITION_INT"])
def test_one_sample_ahead_of_the_clock_is_dropped_and_genuine_samples_go_on(lead_s: float, stream: str) -> None:
    """The audit: one ATTITUDE with time_boot_ms an hour ahead became the arrival bound, and
    every genuine sample after it was late or backwards for that hour (0.6-5 s ahead: ~30 s)."""
    clock = AutopilotClock()
    assert set(genuine(clock, 100.0, 40)) == {Verdict.OK}
    offset = clock.offset
    now = 102.0
    s = clock.stamp(stream, now + lead_s, BOOT_AT + now + 0.01)
    assert s.verdict is Verdict.AHEAD and clock.stats.ahead == 1
    assert clock.offset == offset
    assert set(genuine(clock, now + 0.02, 40)) == {Verdict.OK}  # the very next sample, and all after
    assert clock.offset == offset and clock.stats.jumps == 0


def test_a_forger_repeating_the_jump_is_refused_while_the_autopilot_talks() -> None:
    clock = AutopilotClock()
    genuine(clock, 100.0, 20)
    for k in range(100):  # a forged sample 1 h ahead between every genuine pair, 5 s long
        b = 101.0 + 0.05 * k
        assert clock.stamp("ATTITUDE", 3600.0 + b, BOOT_AT + b + 0.005).verdict is Verdict.AHEAD
        assert set(genuine(clock, b, 1)) == {Verdict.OK}
    assert clock.stats.ahead == 100 and clock.stats.jumps == 0


def test_a_real_jump_ahead_is_taken_once_the_streams_confirm_it() -> None:
    """A link whose latency falls from 300 ms to 10 ms: every sample is then ahead of the old
    bound. No sample on the old estimate comes between them, so after 0.2 s the estimate follows."""
    clock = AutopilotClock()
    genuine(clock, 100.0, 40, latency=0.3)
    verdicts = genuine(clock, 102.0, 20, latency=0.01)
    assert verdicts[0] is Verdict.AHEAD and verdicts[-1] is Verdict.OK
    assert verdicts.count(Verdict.AHEAD) <= 10  # dropped for at most ~0.25 s
    assert clock.stats.jumps == 1 and clock.offset == pytest.approx(BOOT_AT + 0.01)


def test_replayed_old_samples_are_no_reboot_while_the_autopilot_talks() -> None:
    """The audit: a flood of ATTITUDEs more than 5 s old counted as 195 reboots in 10 s."""
    clock = AutopilotClock()
    genuine(clock, 600.0, 20)
    for k in range(200):  # ten replayed samples (60 s old) between each genuine pair
        b = 601.0 + 0.05 * k
        for j in range(10):
            assert clock.stamp("ATTITUDE", 540.0 + 0.001 * j, BOOT_AT + b + 0.001 * j).verdict is Verdict.BACKWARDS
        assert set(genuine(clock, b, 1)) == {Verdict.OK}
    assert clock.stats.reboots == 0


def test_a_reboot_after_a_silence_is_still_a_reboot() -> None:
    clock = AutopilotClock()
    genuine(clock, 600.0, 20)
    # Silent 20 s (rebooting), then its clock reads 15 s: it started after it was last heard.
    now = BOOT_AT + 621.0
    verdicts = [clock.stamp("ATTITUDE", 15.0 + 0.05 * k, now + 0.05 * k).verdict for k in range(3)]
    assert verdicts[-1] is Verdict.REBOOT and clock.stats.reboots == 1


def exchange(clock: AutopilotClock, sent: float, offset: float, rtt: float) -> bool:
    """One TIMESYNC exchange sent at local ``sent`` with the autopilot's clock at ``local - offset``."""
    ts1 = clock.request(sent)
    return clock.on_timesync(int((sent + rtt / 2 - offset) * 1e9), ts1, sent + rtt)


def test_one_forged_timesync_answer_does_not_move_the_offset() -> None:
    """The audit: one forged answer (fast, 0.39 s off) moved the offset silently."""
    clock = AutopilotClock()
    genuine(clock, 100.0, 20, latency=0.01)
    for k in range(3):
        exchange(clock, BOOT_AT + 101.0 + k, BOOT_AT, rtt=0.02)
    assert clock.source == "timesync" and clock.offset == pytest.approx(BOOT_AT, abs=1e-6)
    assert not exchange(clock, BOOT_AT + 104.0, BOOT_AT - 0.39, rtt=0.001)  # the forgery
    assert clock.offset == pytest.approx(BOOT_AT, abs=1e-6)
    assert clock.stats.timesync_unconfirmed == 2  # the first exchange (unconfirmed then) and the forgery
    assert exchange(clock, BOOT_AT + 105.0, BOOT_AT, rtt=0.02)  # the genuine one goes on
    assert clock.offset == pytest.approx(BOOT_AT, abs=1e-6) and clock.stats.timesync_shifts == 1


def test_a_timesync_change_confirmed_by_the_next_exchanges_is_taken_and_said(caplog) -> None:
    clock = AutopilotClock()
    genuine(clock, 100.0, 20, latency=0.1)
    for k in range(2):
        exchange(clock, BOOT_AT + 101.0 + k, BOOT_AT, rtt=0.2)
    assert exchange(clock, BOOT_AT + 103.0, BOOT_AT - 0.15, rtt=0.02) is False
    with caplog.at_level("WARNING"):
        assert exchange(clock, BOOT_AT + 104.0, BOOT_AT - 0.15, rtt=0.02)
    assert clock.offset == pytest.approx(BOOT_AT - 0.15, abs=1e-6) and clock.stats.timesync_shifts == 2
    assert "offset moved by -150 ms" in caplog.text


def test_a_forger_answering_every_request_first_is_caught_by_the_autopilots_second_answers() -> None:
    """A forger who sees our requests answers each first; the autopilot's answer comes second
    (its request is no longer pending). The two disagree: the forged change is never confirmed."""
    clock = AutopilotClock()
    genuine(clock, 100.0, 20, latency=0.01)
    for k in range(2):
        exchange(clock, BOOT_AT + 101.0 + k, BOOT_AT, rtt=0.02)
    for k in range(10):
        sent = BOOT_AT + 103.0 + k
        ts1 = clock.request(sent)
        forged = clock.on_timesync(int((sent + 0.0005 - (BOOT_AT - 0.3)) * 1e9), ts1, sent + 0.001)
        assert not forged
        assert not clock.on_timesync(int((sent + 0.01 - BOOT_AT) * 1e9), ts1, sent + 0.02)  # second
    assert clock.offset == pytest.approx(BOOT_AT, abs=1e-6) and clock.stats.timesync_conflicts == 10


def test_a_forged_first_sample_ahead_gives_way_to_the_streams_that_follow() -> None:
    """A forger who speaks before the autopilot's first pose sample sets the first estimate; the
    genuine samples, all late against it, agree on another and replace it within 0.25 s."""
    clock = AutopilotClock()
    assert clock.stamp("ATTITUDE", 3700.0, BOOT_AT + 99.99).verdict is Verdict.OK  # the forgery
    verdicts = genuine(clock, 100.0, 20)
    assert verdicts.count(Verdict.RESET) == 1 and verdicts[-10:] == [Verdict.OK] * 10
    assert verdicts.index(Verdict.RESET) <= 10  # within 0.25 s
    assert clock.offset == pytest.approx(BOOT_AT + 0.01) and clock.stats.jumps == 1
    # Once established, late samples are late: a slow link does not move the estimate.
    genuine(clock, 101.0, 10)
    assert set(genuine(clock, 102.0, 10, latency=0.9)) == {Verdict.LATE}
