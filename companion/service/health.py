"""Per-stage timings, frame counters and the health verdict the service logs and reports to systemd.

:func:`assess` tells internal faults (the process is broken: stop feeding the watchdog, let
systemd restart it) from external ones (camera, autopilot link, frames that cannot be decided
with: report them, keep feeding the watchdog, the service recovers by itself); :class:`FaultLog`
keeps the log lines about them few. Why frames cannot be used comes from
:mod:`companion.service.frame_use`.
"""

from __future__ import annotations

import logging
import math
from collections import defaultdict, deque
from dataclasses import dataclass, field

import numpy as np

from companion.service.frame_use import NO_POSE, STALE_POSE, STANDBY_REASONS


@dataclass
class StageTimings:
    """Rolling window of per-stage durations in milliseconds (the last ``window`` frames)."""

    window: int = 200
    _samples: dict[str, deque[float]] = field(default_factory=lambda: defaultdict(deque))

    def add(self, timings_ms: dict[str, float]) -> None:
        for name, ms in timings_ms.items():
            buf = self._samples[name]
            buf.append(float(ms))
            while len(buf) > self.window:
                buf.popleft()

    def summary(self) -> dict[str, tuple[float, float]]:
        """stage -> (median, 95th percentile) milliseconds over the window."""
        out = {}
        for name, buf in self._samples.items():
            if buf:
                a = np.fromiter(buf, float)
                out[name] = (float(np.median(a)), float(np.percentile(a, 95)))
        return out

    def format(self) -> str:
        return " ".join(f"{k}={med:.1f}/{p95:.1f}ms" for k, (med, p95) in self.summary().items())


@dataclass
class FrameCounters:
    """What happened to camera frames in the service, since start.

    processed: went through the pipeline and reached the controller. no_pose: had no pose fresh
    enough at their capture time (not used for decisions). bad: rejected by the pipeline (corrupt
    shape, geometry that cannot be projected) and dropped. errors: the pipeline failed otherwise.
    """

    processed: int = 0
    no_pose: int = 0
    superseded: int = 0  # paired with a pose, but a newer frame was ready at the same moment
    bad: int = 0
    errors: int = 0


# ---- health verdict: what is wrong, and whether a restart could cure it ------------------------

#: A pipeline call running longer than this counts as stuck: an internal fault.
PIPELINE_STUCK_S = 5.0


@dataclass(frozen=True)
class Fault:
    """One thing wrong. key: what (``link``, ``camera``, ``pipeline``), stable while it lasts;
    text: for people; internal: the process itself is broken, so a restart may cure it."""

    key: str
    text: str
    internal: bool
    standby: bool = False  # not a fault: the vehicle is where the companion cannot work (on the ground)


@dataclass(frozen=True)
class Health:
    """The service's health at one moment, and what it tells systemd.

    External faults (no autopilot heartbeat, camera not delivering) are outside the process: a
    restart cannot plug a camera back in, and the service reconnects both by itself, so they are
    reported (``STATUS=``, log) while the watchdog keeps being fed. Only an internal fault (the
    pipeline stuck beyond :data:`PIPELINE_STUCK_S`; an event loop too blocked to run the health
    loop stops the pings by itself) stops the watchdog, and systemd restarts the process.
    """

    faults: tuple[Fault, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.faults

    @property
    def feed_watchdog(self) -> bool:
        return not any(f.internal for f in self.faults)

    @property
    def standby(self) -> bool:
        """Only standby states hold (on the ground): nothing is wrong, but nothing is watched."""
        return bool(self.faults) and all(f.standby for f in self.faults)

    @property
    def reason(self) -> str:
        return "; ".join(f.text for f in self.faults) or "ok"

    def status(self, normal: str) -> str:
        """The ``STATUS=`` line: ``normal`` when healthy, ``standby: <state>; normal`` on the
        ground, ``degraded: <external faults>; normal`` while only external faults hold,
        ``unhealthy: <faults>`` on an internal one."""
        if self.ok:
            return normal
        if self.standby:
            return f"standby: {self.reason}; {normal}"
        if self.feed_watchdog:
            return f"degraded: {self.reason}; {normal}"
        return f"unhealthy: {self.reason}"


def assess(*, link_connected: bool, camera_delivering: bool, busy_s: float | None,
           stuck_after_s: float = PIPELINE_STUCK_S, camera_frozen: bool = False,
           frames: str | None = None) -> Health:
    """The health verdict from the service's state. busy_s: how long the pipeline call now
    running has been running (None when idle). camera_frozen: not delivering because every frame
    is stale. frames: why the frames that arrive cannot be used (:class:`FrameUse`), or None; a
    missing pose is not told again while the link is down (that is why). Internal faults first."""
    faults: list[Fault] = []
    if busy_s is not None and busy_s > stuck_after_s:
        faults.append(Fault("pipeline", f"pipeline stuck for {busy_s:.1f} s", internal=True))
    if not link_connected:
        faults.append(Fault("link", "no autopilot heartbeat", internal=False))
    if not camera_delivering:
        faults.append(Fault("camera", "camera frozen" if camera_frozen else "camera not delivering", internal=False))
    elif frames is not None and not (not link_connected and frames in (NO_POSE, STALE_POSE)):
        faults.append(Fault("frames", frames, internal=False, standby=frames in STANDBY_REASONS))
    return Health(tuple(faults))


@dataclass
class FaultLog:
    """Turns successive :class:`Health` verdicts into a few log lines, however long a fault lasts
    or however often it comes and goes: a line when a fault begins and when it clears, a reminder
    every ``remind_s`` while it lasts, and for a fault that flaps, at most one begin line per
    ``min_gap_s`` (the flaps in between are counted and told with the next one). Internal faults
    are errors, external ones warnings, standby states (on the ground) and recoveries info.
    """

    remind_s: float = 60.0
    min_gap_s: float = 10.0
    _since: dict[str, float] = field(default_factory=dict)   # active fault -> when it began
    _told: dict[str, float] = field(default_factory=dict)    # fault -> last line about it
    _flaps: dict[str, int] = field(default_factory=dict)     # begins not told since the last line

    def update(self, health: Health, now: float) -> list[tuple[int, str]]:
        """(logging level, message) lines for this verdict; usually none."""
        out: list[tuple[int, str]] = []
        current = {f.key: f for f in health.faults}
        for key, since in list(self._since.items()):
            if key not in current:
                del self._since[key]
                if not self._flaps.get(key):  # its beginning was told: so is its end
                    out.append((logging.INFO, f"{key} ok again after {now - since:.1f} s"))
        for key, fault in current.items():
            if key not in self._since:
                self._since[key] = now
                self._flaps[key] = self._flaps.get(key, 0) + 1
            level = logging.ERROR if fault.internal else logging.INFO if fault.standby else logging.WARNING
            kind = ("internal fault: watchdog no longer fed" if fault.internal
                    else "standby: frames not used" if fault.standby
                    else "external fault: reported, watchdog still fed")
            last = self._told.get(key, -math.inf)
            if self._flaps.get(key) and now - last >= self.min_gap_s:
                began = self._flaps.pop(key)
                again = f"; began {began} times since the last line" if began > 1 else ""
                out.append((level, f"{fault.text} ({kind}{again})"))
                self._told[key] = now
            elif not self._flaps.get(key) and now - last >= self.remind_s:
                out.append((level, f"{fault.text} for {now - self._since[key]:.0f} s ({kind})"))
                self._told[key] = now
        return out
