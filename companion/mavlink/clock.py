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
  autopilot reboot: the estimate starts again (``reboots`` counts them).

Pure: times are passed in (seconds; ``local`` on ``time.monotonic()``, ``boot`` on the
autopilot's clock). The offset drifts with the two crystals (tens of ppm, well under a millisecond
in the ``window_s`` the bound is kept over), so the window lets it follow.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum

#: ``time_boot_ms`` is a uint32: it wraps after 49.7 days.
_WRAP_S = 2**32 / 1000.0


class Verdict(str, Enum):
    """What became of one stamped sample."""

    OK = "ok"
    LATE = "late"  # arrived more than max_lag_s after it was sent
    BACKWARDS = "backwards"  # not newer than the stream's last sample
    REBOOT = "reboot"  # the sample that confirmed a reboot: the estimate restarted on it


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


#: Pose telemetry arriving later than this after the autopilot sampled it (its time_boot_ms) is
#: dropped, and a frame waits this long for the sample after its capture (s): a companion wired to
#: its autopilot hears it within milliseconds; half a second is a link in trouble.
MAX_TELEMETRY_LAG_S = 0.5


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
        self._pending: dict[int, float] = {}  # TIMESYNC ts1 (ns) we sent -> local send time (s)

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
        self._pending.clear()

    # -- input -------------------------------------------------------------------------------

    def stamp(self, stream: str, boot_s: float, arrival_s: float) -> Stamp:
        """Judge one sample of ``stream`` sent at autopilot time ``boot_s`` and received at local
        ``arrival_s``; an OK or REBOOT verdict moves the stream on, the others leave it as it was."""
        last = self._last_boot.get(stream)
        if last is not None and boot_s <= last and last - boot_s > _WRAP_S / 2:
            boot_s += _WRAP_S * round((last - boot_s) / _WRAP_S)  # uint32 wrap, not a step back
        if last is not None and boot_s <= last:
            if last - boot_s > self.reboot_s and self._vote_reboot(arrival_s - boot_s):
                self.reset()
                self.stats.reboots += 1
                self._observe(boot_s, arrival_s)
                self._last_boot[stream] = boot_s
                return Stamp(Verdict.REBOOT, arrival_s, 0.0, boot_s)
            self.stats.backwards += 1
            off = self.offset
            t_back = boot_s + (off if off is not None else arrival_s - boot_s)
            return Stamp(Verdict.BACKWARDS, t_back, arrival_s - t_back, boot_s)
        self._reboot_votes.clear()
        self._observe(boot_s, arrival_s)
        off = self.offset
        assert off is not None  # _observe just gave a bound
        t = boot_s + off
        lag = arrival_s - t
        if lag > self.max_lag_s:
            self.stats.late += 1
            return Stamp(Verdict.LATE, t, lag, boot_s)
        self._last_boot[stream] = boot_s
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
        rtt = None if sent is None else received_s - sent
        if sent is None or tc1_ns <= 0 or rtt is None or not 0.0 <= rtt <= self.max_rtt_s:
            self.stats.timesync_ignored += 1
            return False
        offset = (sent + received_s) / 2.0 - tc1_ns * 1e-9
        self._syncs.append((received_s, rtt, offset))
        while self._syncs and received_s - self._syncs[0][0] > self.window_s:
            self._syncs.popleft()
        self.stats.timesync_used += 1
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

    def _vote_reboot(self, implied_offset: float) -> bool:
        """True once ``reboot_confirm`` jumps back in a row agree on one new offset (to 1 s)."""
        votes = self._reboot_votes
        if votes and abs(implied_offset - votes[0]) > 1.0:
            votes.clear()
        votes.append(implied_offset)
        return len(votes) >= self.reboot_confirm
