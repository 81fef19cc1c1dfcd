"""The autopilot's clock on ours: ``time_boot_ms`` mapped onto ``time.monotonic()``.

Telemetry carries the autopilot's time of the sample (``time_boot_ms``, ms since its boot); a
frame carries our grab time. Pairing them by arrival time is wrong by the link's latency and by
whatever a packet spent in a buffer: a 3 s old packet was once taken for the current pose (a 50 m
jump), and 200 ms of latency alone kept the companion from ever landing. ``AutopilotClock``
estimates the offset ``local = boot + offset`` (seconds) and judges each sample by it:

- **Bound from arrivals.** A sample sent at boot time ``b`` arrives at local time ``a >= b + offset``
  (latency is never negative), so the least ``a - b`` over a recent window is an upper bound on the
  offset, reached by the least-delayed packet (a constant latency stays inside it).
- **TIMESYNC where the autopilot answers it** (ArduPilot and PX4 both do: ``tc1`` = their boot
  time in ns, ``ts1`` echoed): the midpoint of the exchange with the smallest round trip gives the
  offset with the latency taken out, to within half that round trip. A TIMESYNC estimate that
  contradicts the arrival bound (says packets arrived before they were sent, or that even the
  least-delayed one was late) is not used: its clock is not the one ``time_boot_ms`` counts.
- **Late samples are rejected**: one that arrives more than ``max_lag_s`` after its local time
  (with TIMESYNC the latency counts; without it, the delay beyond the least-delayed packet's).
- **Backwards samples are rejected**: per stream, ``time_boot_ms`` must increase. A jump back of
  more than ``reboot_s`` seen ``reboot_confirm`` times in a row with a consistent new offset is an
  autopilot reboot: the estimate starts again (``reboots`` counts them). The new clock must have
  started after the old one was last heard (a new ``time_boot_ms`` no larger than the time since
  the last accepted sample, plus ``max_lag_s``): replayed old samples while the autopilot keeps
  talking are backwards, never a reboot (issue 61: a flood of them cleared the pose 195 times).

No single unauthenticated packet moves the estimate (issue 61):

- **A sample ahead of the estimate** (sent, by its ``time_boot_ms``, more than ``AHEAD_TOL_S``
  after it arrived) is counted (``ahead``) and dropped; it becomes no bound and does not move its
  stream on. One forged ATTITUDE an hour ahead once left the service without a pose for the hour.
  A real jump ahead (a link whose latency fell) is taken once ``reboot_confirm`` samples in a row,
  over at least ``AHEAD_CONFIRM_S`` with no sample on the old estimate between them, agree on the
  new offset (``jumps`` counts them). A first estimate set by such a sample (it came first) gives
  way the same way to the late samples that follow, until ``reboot_confirm`` samples were taken.
- **A TIMESYNC exchange that disagrees with the estimate in use** (their uncertainty intervals,
  half a round trip each, do not overlap) is not used until ``TIMESYNC_CONFIRM`` exchanges in a
  row agree with it; then the estimate moves, with a warning (``timesync_shifts``). The first
  estimate needs as many. One forged answer once moved the offset by 0.39 s without a word. A
  request answered twice with answers that disagree (a forger answering before the autopilot,
  whose answer then comes second) cancels the change being confirmed (``timesync_conflicts``).

Pure: times are passed in (seconds; ``local`` on ``time.monotonic()``, ``boot`` on the
autopilot's clock). The offset drifts with the two crystals (tens of ppm, well under a millisecond
in the ``window_s`` the bound is kept over), so the window lets it follow.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from enum import Enum

log = logging.getLogger(__name__)

#: ``time_boot_ms`` is a uint32: it wraps after 49.7 days.
_WRAP_S = 2**32 / 1000.0


class Verdict(str, Enum):
    """What became of one stamped sample."""

    OK = "ok"
    LATE = "late"  # arrived more than max_lag_s after it was sent
    BACKWARDS = "backwards"  # not newer than the stream's last sample
    AHEAD = "ahead"  # sent after it arrived, by the estimate, and not (yet) confirmed
    REBOOT = "reboot"  # the sample that confirmed a reboot: the estimate restarted on it
    RESET = "reset"  # the sample that confirmed a new first estimate (the first one was an outlier)


@dataclass(frozen=True)
class Stamp:
    """A sample placed on our clock: ``t`` local time it describes, ``lag_s`` how late it came."""

    verdict: Verdict
    t: float  # local monotonic seconds of the sample (its boot time + offset)
    lag_s: float  # arrival minus t (s); with TIMESYNC it includes the link latency
    boot_s: float  # the autopilot's time of the sample (s), unwrapped past uint32 ms


@dataclass
class ClockStats:
    """Counters since start: samples stamped, rejected late or backwards, reboots, TIMESYNC
    replies used and ignored (unknown request, round trip too long, inconsistent clock)."""

    stamped: int = 0
    late: int = 0
    backwards: int = 0
    reboots: int = 0
    timesync_used: int = 0
    timesync_ignored: int = 0
    ahead: int = 0  # samples sent after they arrived, by the estimate: dropped unless confirmed
    jumps: int = 0  # jumps ahead the streams confirmed (the estimate moved on them)
    timesync_unconfirmed: int = 0  # exchanges that disagreed with the estimate, not (yet) confirmed
    timesync_shifts: int = 0  # times a confirmed TIMESYNC estimate replaced another (or the first)
    timesync_conflicts: int = 0  # requests answered twice, the answers disagreeing (a forger)


#: Pose telemetry arriving later than this after the autopilot sampled it (its time_boot_ms) is
#: dropped, and a frame waits this long for the sample after its capture (s): a companion wired to
#: its autopilot hears it within milliseconds; half a second is a link in trouble.
MAX_TELEMETRY_LAG_S = 0.5

#: How far ahead of the estimate a sample may claim to be sent (s) and still be taken: the
#: least-delayed packet sets the arrival bound, and a packet faster than all before it by jitter
#: (milliseconds on a wire, tens of ms on a radio) moves it that much. More is a forgery, or a
#: link whose latency fell, which the samples that follow confirm.
AHEAD_TOL_S = 0.05
#: A jump ahead is taken when the samples agreeing on it span at least this long (s) with none on
#: the old estimate among them: the autopilot sends the pose at 20 Hz on two streams, so a
#: forger would have to silence it for this long.
AHEAD_CONFIRM_S = 0.2
#: TIMESYNC exchanges in a row that must agree on an estimate before it is used, the first one
#: included: one answer, which anyone who sees the request can forge, moves nothing.
TIMESYNC_CONFIRM = 2
#: Slack (s) on top of half the round trips when two TIMESYNC exchanges are compared: crystal
#: drift and timer resolution over the window.
TIMESYNC_TOL_S = 0.002


class AutopilotClock:
    """Offset between the autopilot's boot clock and ``time.monotonic()``, and sample verdicts.

    ``max_lag_s``: a sample later than this is rejected. ``window_s``: how long an offset
    measurement is kept (the bound follows crystal drift and an autopilot that slowed down).
    ``max_rtt_s``: TIMESYNC exchanges slower than this are not used. ``reboot_s`` and
    ``reboot_confirm``: see the module docstring.
    """

    def __init__(
        self,
        *,
        max_lag_s: float = 0.5,
        window_s: float = 30.0,
        max_rtt_s: float = 0.5,
        reboot_s: float = 5.0,
        reboot_confirm: int = 3,
    ) -> None:
        self.max_lag_s = max_lag_s
        self.window_s = window_s
        self.max_rtt_s = max_rtt_s
        self.reboot_s = reboot_s
        self.reboot_confirm = reboot_confirm
        self.stats = ClockStats()
        self._bounds: deque[tuple[float, float]] = deque()  # (arrival, arrival - boot), minima only
        self._syncs: deque[tuple[float, float, float]] = deque()  # (received, rtt, offset)
        self._last_boot: dict[str, float] = {}
        self._reboot_votes: list[float] = []  # implied offsets of consecutive jumps back
        self._ahead_votes: list[tuple[str, float, float]] = []  # (stream, boot, arrival) ahead in a row
        self._last_ok_arrival: float | None = None  # local arrival of the newest accepted sample
        self._ok_since_reset = 0  # samples accepted since the estimate started
        self._pending: dict[int, float] = {}  # TIMESYNC ts1 (ns) we sent -> local send time (s)
        self._sync_candidates: list[tuple[float, float, float]] = []  # exchanges not yet agreed on
        #: ts1 (ns) answered -> (local send time, the exchange), for max_rtt_s: a second answer
        #: to one request shows two answerers.
        self._answered: dict[int, tuple[float, tuple[float, float, float]]] = {}

    # -- estimate ----------------------------------------------------------------------------

    @property
    def offset(self) -> float | None:
        """``local - boot`` (s): TIMESYNC's when it agrees with the arrival bound, else the bound."""
        bound = self._bounds[0][1] if self._bounds else None
        if self._syncs:
            sync = min(self._syncs, key=lambda s: s[1])[2]
            # Latency is never negative (sync <= bound) and the least-delayed packet was not
            # late (sync >= bound - max_lag_s); a TIMESYNC outside that counts another clock.
            if bound is None or bound - self.max_lag_s <= sync <= bound + 0.005:
                return sync
        return bound

    @property
    def latency_s(self) -> float | None:
        """Half the best of the last three TIMESYNC round trips (s): the one-way latency now, or
        None. The offset keeps the best exchange of the whole window (the clocks do not change
        when the link slows down); the latency must follow the link."""
        if not self._syncs:
            return None
        return min(s[1] for s in list(self._syncs)[-3:]) / 2.0

    @property
    def source(self) -> str:
        """Where the offset comes from: "timesync" (latency taken out), "arrivals" or "none"."""
        off = self.offset
        if off is None:
            return "none"
        return "timesync" if self._syncs and off == min(self._syncs, key=lambda s: s[1])[2] else "arrivals"

    def to_local(self, boot_s: float) -> float | None:
        """Our monotonic time (s) of autopilot boot time ``boot_s``, or None before any estimate."""
        off = self.offset
        return None if off is None else boot_s + off

    def to_boot(self, local_s: float) -> float | None:
        """The autopilot's boot time (s) at our monotonic time ``local_s``, or None."""
        off = self.offset
        return None if off is None else local_s - off

    def reset(self) -> None:
        """Forget the estimate and the streams (an autopilot that rebooted, a new link)."""
        self._bounds.clear()
        self._syncs.clear()
        self._last_boot.clear()
        self._reboot_votes.clear()
        self._ahead_votes.clear()
        self._last_ok_arrival = None
        self._ok_since_reset = 0
        self._pending.clear()
        self._sync_candidates.clear()
        self._answered.clear()

    # -- input -------------------------------------------------------------------------------

    def stamp(self, stream: str, boot_s: float, arrival_s: float) -> Stamp:
        """Judge one sample of ``stream`` sent at autopilot time ``boot_s`` and received at local
        ``arrival_s``; an OK or REBOOT verdict moves the stream on, the others leave it as it was."""
        last = self._last_boot.get(stream)
        if last is not None and boot_s <= last and last - boot_s > _WRAP_S / 2:
            boot_s += _WRAP_S * round((last - boot_s) / _WRAP_S)  # uint32 wrap, not a step back
        if last is not None and boot_s <= last:
            if last - boot_s > self.reboot_s and self._restarted(boot_s, arrival_s) \
                    and self._vote_reboot(arrival_s - boot_s):
                self.reset()
                self.stats.reboots += 1
                self._observe(boot_s, arrival_s)
                self._last_boot[stream] = boot_s
                self._last_ok_arrival = arrival_s
                self._ok_since_reset = 1
                return Stamp(Verdict.REBOOT, arrival_s, 0.0, boot_s)
            self.stats.backwards += 1
            off = self.offset
            t_back = boot_s + (off if off is not None else arrival_s - boot_s)
            return Stamp(Verdict.BACKWARDS, t_back, arrival_s - t_back, boot_s)
        self._reboot_votes.clear()
        off = self.offset
        if off is not None and boot_s + off - arrival_s > AHEAD_TOL_S:
            if not self._vote_ahead(stream, boot_s, arrival_s):
                self.stats.ahead += 1
                return Stamp(Verdict.AHEAD, boot_s + off, arrival_s - boot_s - off, boot_s)
            self._take_jump()
        else:
            self._observe(boot_s, arrival_s)
        off = self.offset
        assert off is not None  # _observe just gave a bound
        t = boot_s + off
        lag = arrival_s - t
        if lag > self.max_lag_s:
            # An estimate that rests on fewer than reboot_confirm samples (a forged first packet
            # ahead of the autopilot's clock) gives way to the late samples that agree on another.
            if not (self._ok_since_reset < self.reboot_confirm and self._vote_ahead(stream, boot_s, arrival_s)):
                self.stats.late += 1
                return Stamp(Verdict.LATE, t, lag, boot_s)
            # The first estimate and every stream's place on it go: the history is on a clock
            # that never was (the caller clears it, as after a reboot).
            self._last_boot.clear()
            self._take_jump()
            self._ok_since_reset = 1
            self._last_ok_arrival = arrival_s
            t = boot_s + self.offset  # type: ignore[operator]  # the votes gave a bound
            return Stamp(Verdict.RESET, t, arrival_s - t, boot_s)
        self._ahead_votes.clear()  # a sample on the estimate: the old clock still talks
        self._last_boot[stream] = boot_s
        self._last_ok_arrival = arrival_s
        self._ok_since_reset += 1
        self.stats.stamped += 1
        return Stamp(Verdict.OK, t, lag, boot_s)

    def request(self, now_s: float) -> int:
        """A TIMESYNC request's ``ts1`` (ns) for a request sent at local ``now_s``; remembered so
        that only answers to our own requests are used."""
        ts1 = int(now_s * 1e9)
        self._pending[ts1] = now_s
        for key in [k for k, sent in self._pending.items() if now_s - sent > self.max_rtt_s]:
            del self._pending[key]
        return ts1

    def on_timesync(self, tc1_ns: int, ts1_ns: int, received_s: float) -> bool:
        """Take a TIMESYNC answer (``tc1`` their boot time, ``ts1`` ours echoed); True if used."""
        sent = self._pending.pop(ts1_ns, None)
        if sent is None and ts1_ns in self._answered and tc1_ns > 0:
            # A second answer to one request: two answerers. If they disagree, one forges: the
            # change it pushes is not confirmed while the autopilot keeps answering too.
            first_sent, first = self._answered[ts1_ns]
            second = (first_sent + received_s) / 2.0 - tc1_ns * 1e-9
            if abs(second - first[2]) > received_s - first_sent + TIMESYNC_TOL_S:
                self.stats.timesync_conflicts += 1
                self._sync_candidates.clear()
        rtt = None if sent is None else received_s - sent
        if sent is None or tc1_ns <= 0 or rtt is None or not 0.0 <= rtt <= self.max_rtt_s:
            self.stats.timesync_ignored += 1
            return False
        offset = (sent + received_s) / 2.0 - tc1_ns * 1e-9
        exchange = (received_s, rtt, offset)
        self._answered[ts1_ns] = (sent, exchange)
        for key in [k for k, (t0, _e) in self._answered.items() if received_s - t0 > self.max_rtt_s]:
            del self._answered[key]
        while self._syncs and received_s - self._syncs[0][0] > self.window_s:
            self._syncs.popleft()
        best = min(self._syncs, key=lambda s: s[1]) if self._syncs else None
        if best is not None and _agree(best, exchange):
            self._syncs.append(exchange)
            self._sync_candidates.clear()
            self.stats.timesync_used += 1
            return True
        # A first estimate, or one that contradicts the estimate in use: believed only once the
        # exchanges that follow agree with it (a forged answer moves nothing on its own).
        candidates = self._sync_candidates
        if candidates and not all(_agree(c, exchange) for c in candidates):
            candidates.clear()
        candidates.append(exchange)
        if len(candidates) < TIMESYNC_CONFIRM:
            self.stats.timesync_unconfirmed += 1
            return False
        self._syncs.clear()
        self._syncs.extend(candidates)
        candidates.clear()
        self.stats.timesync_used += 1
        self.stats.timesync_shifts += 1
        new = min(self._syncs, key=lambda s: s[1])[2]
        if best is not None:
            log.warning("TIMESYNC: the autopilot's clock offset moved by %+.0f ms, confirmed by %d exchanges",
                        (new - best[2]) * 1000.0, TIMESYNC_CONFIRM)
        return True

    # -- internals ---------------------------------------------------------------------------

    def _observe(self, boot_s: float, arrival_s: float) -> None:
        """Keep the running minimum of ``arrival - boot`` over the window (a monotonic deque)."""
        bound = arrival_s - boot_s
        while self._bounds and self._bounds[-1][1] >= bound:
            self._bounds.pop()
        self._bounds.append((arrival_s, bound))
        while arrival_s - self._bounds[0][0] > self.window_s:
            self._bounds.popleft()

    def _restarted(self, boot_s: float, arrival_s: float) -> bool:
        """Whether a clock that reads ``boot_s`` at ``arrival_s`` can have started after the old
        one was last heard: a rebooted autopilot's ``time_boot_ms`` cannot exceed the time since
        its last sample before the reboot (plus the lag a sample may have)."""
        last = self._last_ok_arrival
        return last is None or boot_s <= arrival_s - last + self.max_lag_s

    def _vote_ahead(self, stream: str, boot_s: float, arrival_s: float) -> bool:
        """True once the samples ahead of the estimate, in a row, confirm a new one: at least
        ``reboot_confirm`` of them over ``AHEAD_CONFIRM_S`` or more, agreeing on the offset to
        ``max_lag_s`` (a link's jitter), each newer than its stream's last."""
        votes = self._ahead_votes
        implied = arrival_s - boot_s
        if votes and any(abs((a - b) - implied) > self.max_lag_s for _s, b, a in votes):
            votes.clear()
        if any(s == stream and b >= boot_s for s, b, _a in votes):
            return False  # not newer than its stream's last vote: a repeat proves nothing
        votes.append((stream, boot_s, arrival_s))
        return len(votes) >= self.reboot_confirm and arrival_s - votes[0][2] >= AHEAD_CONFIRM_S

    def _take_jump(self) -> None:
        """The streams confirmed a new offset (a jump ahead, or a first estimate they all contradict):
        the arrival bound starts again from the votes, and their streams move on."""
        self._bounds.clear()
        for stream, boot_s, arrival_s in self._ahead_votes:
            self._observe(boot_s, arrival_s)
            self._last_boot[stream] = max(boot_s, self._last_boot.get(stream, boot_s))
        self._ahead_votes.clear()
        self.stats.jumps += 1
        log.warning("autopilot clock: %d samples over %.2f s confirmed a new offset", self.reboot_confirm,
                    AHEAD_CONFIRM_S)

    def _vote_reboot(self, implied_offset: float) -> bool:
        """True once ``reboot_confirm`` jumps back in a row agree on one new offset (to 1 s)."""
        votes = self._reboot_votes
        if votes and abs(implied_offset - votes[0]) > 1.0:
            votes.clear()
        votes.append(implied_offset)
        return len(votes) >= self.reboot_confirm


def _agree(a: tuple[float, float, float], b: tuple[float, float, float]) -> bool:
    """Two TIMESYNC exchanges ``(received, rtt, offset)`` agree when the true offset can lie in
    both: each is within half its round trip of its midpoint estimate."""
    return abs(a[2] - b[2]) <= (a[1] + b[1]) / 2.0 + TIMESYNC_TOL_S
