"""Does the vehicle obey its position target? A pure check that catches a fly-away within seconds.

Against the real PX4 a target frame that the autopilot converted wrongly made the vehicle climb
from 20 m to about 220 m while the companion kept sending targets (issue 19, ``docs/autopilot.md``).
Whatever the cause (a frame bug, a wrong home, a misconfigured autopilot, wind beyond its limits),
the companion must notice that the vehicle does not go where it is told, and give the vehicle back
to the autopilot's own landing at once instead of at the end of its takeover budget.

The rule, in world NED metres from home (altitudes above home), per axis:

- After each new target, the error the vehicle *could* still reach is its error at the point where
  it would stop if it braked now at ``brake_accel_mss`` (a multicopter cannot stop instantly, so a
  target behind it or below a climb is approached after an overshoot). The least such error since
  the target was set is the best the vehicle has shown it can do.
- When the target moves by ``d`` metres, that best error may grow by at most ``d`` (triangle
  inequality), and is at most the error the vehicle's stopping point has once it has heard the
  target. So targets that creep with a zone's filtered centre never look like disobedience, while
  a vehicle drifting away from a target re-sent every second still adds up.
- A target is heard the status's age plus the link's one-way latency after it was sent. Until
  then the vehicle flies the last target it heard, and may still speed up toward it: its samples
  lower the best error only by their error to that target plus the distance between the two
  targets (the triangle again). With 200 ms of latency each way, a hold sent while the vehicle
  sped toward a zone otherwise took the best from a sample 0.4 s before the vehicle heard it, and
  the overshoot that followed read as moving away: a handback, and the autopilot's LAND wherever
  the vehicle was.
- The vehicle disobeys when that error, now, exceeds the best by more than the tolerance:
  ``tolerance_z_m`` vertically (climbing while told to hold or descend, or sinking below the
  target), ``tolerance_xy_m`` horizontally (moving away from the target).
- A vehicle that stops short (an autopilot ignoring or misreading its targets) is caught too: off
  its target by more than the tolerance, and no closer by ``progress_m`` for ``stall_s``.

Nothing here knows about MAVLink or clocks: ``engage``/``target``/``check`` take what the landing
controller knows, and ``check`` returns the reason to hand back, or None.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from companion.control.vehicle import VehicleStatus
from companion.invariant import require


@dataclass(frozen=True)
class ObedienceConfig:
    """Tolerances in metres, deceleration in m/s^2 (the least a multicopter brakes with)."""

    tolerance_z_m: float = 1.0
    tolerance_xy_m: float = 2.0
    brake_accel_mss: float = 2.0
    stall_s: float = 3.0
    progress_m: float = 0.3

    def __post_init__(self) -> None:
        for name in ("tolerance_z_m", "tolerance_xy_m", "brake_accel_mss", "stall_s", "progress_m"):
            value = getattr(self, name)
            require(math.isfinite(value) and value > 0, "controller", name, "must be > 0", value)


@dataclass(frozen=True)
class Sample:
    """Where the vehicle is and how fast it moves: NED metres from home, metres above home, m/s;
    ``t`` when (monotonic s; NaN: no stall check)."""

    north: float
    east: float
    alt: float
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    t: float = math.nan

    @classmethod
    def of(cls, s: VehicleStatus) -> Sample:
        """The sample a vehicle status gives."""
        return cls(s.north, s.east, s.alt, s.vn, s.ve, s.vd, s.t)


class ObedienceMonitor:
    """See the module docstring. ``engaged`` only while the vehicle is in the companion's mode."""

    def __init__(self, config: ObedienceConfig | None = None) -> None:
        self.config = config or ObedienceConfig()
        self.engaged = False
        self._target: tuple[float, float, float] | None = None  # north, east, alt
        self._best_xy = math.inf
        self._best_z = math.inf
        self._progress_t = math.nan  # when the vehicle last got closer (or was there)
        self._progress_best = (math.inf, math.inf)
        self._heard: tuple[float, float, float] | None = None  # the last target the vehicle heard
        #: Targets sent and not heard yet: (sample time from which the vehicle has it, target).
        self._unheard: deque[tuple[float, tuple[float, float, float]]] = deque()

    def disengage(self) -> None:
        """The autopilot flies by itself (its LAND, a mode change): nothing to judge."""
        self.engaged = False

    def target(self, north: float, east: float, alt: float, now: Sample | None = None,
               unheard_s: float = 0.0) -> None:
        """A new position target was commanded (metres; alt above home); ``now`` the vehicle then.

        ``unheard_s``: how long the vehicle goes on with its old target before it can act on this
        one (the age of ``now`` plus the link's one-way latency, s): samples taken before
        ``now.t + unheard_s`` are judged as the module docstring says. Without a sample time
        (``now.t`` NaN), ``now`` carried on at its velocity for ``unheard_s`` bounds the best.
        """
        if self._target is not None:
            n0, e0, a0 = self._target
            # The best error reachable grows by at most what the target moved.
            self._best_xy += math.hypot(north - n0, east - e0)
            self._best_z += abs(alt - a0)
            if max(abs(alt - a0), math.hypot(north - n0, east - e0)) >= self.config.progress_m:
                self._progress_t = math.nan  # a new target: a new chance to make progress
        self._target = (north, east, alt)
        if now is not None and self.engaged and math.isfinite(now.t) and math.isfinite(unheard_s):
            self._unheard.append((now.t + max(0.0, unheard_s), self._target))
            self._update_best(now)  # as far as what it heard says (``_update_best``)
        elif now is not None and self.engaged:
            self._update_best(now)  # and is at most what the vehicle can reach from where it is
            if math.isfinite(unheard_s) and unheard_s > 0:
                speed_xy = math.hypot(now.vn, now.ve)
                if math.isfinite(speed_xy) and math.isfinite(now.vd):
                    self._best_xy += speed_xy * unheard_s
                    self._best_z += abs(now.vd) * unheard_s

    def engage(self, s: Sample) -> None:
        """The vehicle is now in the mode that follows our targets: judge from here on."""
        self.engaged = True
        self._best_xy = self._best_z = math.inf
        self._progress_t = math.nan
        self._heard, self._unheard = self._target, deque()  # in its mode now: it flies this target
        self._update_best(s)

    def watch(self, s: Sample, ours: bool) -> str | None:
        """On every vehicle status: while ``ours`` (the vehicle in the companion's mode, flying to
        a target it was sent) engage and check it; otherwise disengage. Why it disobeys, or None."""
        if not ours:
            self.disengage()
            return None
        if not self.engaged:
            self.engage(s)
            return None
        return self.check(s)

    def check(self, s: Sample) -> str | None:
        """Why the vehicle does not obey its target, or None. Call with every fresh position."""
        if not self.engaged or self._target is None:
            return None
        if not all(math.isfinite(v) for v in (s.north, s.east, s.alt, s.vn, s.ve, s.vd)):
            return None
        n, e, alt = self._target
        c = self.config
        err_z, err_xy = self._stop_errors(s)
        why = None
        if abs(err_z) > self._best_z + c.tolerance_z_m:
            if err_z > 0:
                why = (f"vehicle climbing against its target: {s.alt:.1f} m, "
                       f"{s.alt - alt:.1f} m above the {alt:.1f} m commanded")
            else:
                why = (f"vehicle sinking below its target: {s.alt:.1f} m, "
                       f"{alt - s.alt:.1f} m below the {alt:.1f} m commanded")
        elif err_xy > self._best_xy + c.tolerance_xy_m:
            why = (f"vehicle moving away from its target: {math.hypot(s.north - n, s.east - e):.1f} m "
                   f"off and heading {err_xy:.1f} m off, had been heading within {self._best_xy:.1f} m")
        self._update_best(s)
        if self._unheard:
            return why  # still flying an older target: no progress to judge toward this one
        return why or self._stalled(s, err_z, err_xy)

    def _stalled(self, s: Sample, err_z: float, err_xy: float) -> str | None:
        """A vehicle that stops short of its target (an autopilot that ignores or misreads it) makes
        no progress: neither error improves by ``progress_m`` within ``stall_s``."""
        c = self.config
        if not math.isfinite(s.t):
            return None
        there = abs(err_z) <= c.tolerance_z_m and err_xy <= c.tolerance_xy_m
        best = (self._best_z, self._best_xy)
        if there or not math.isfinite(self._progress_t) or \
                best[0] <= self._progress_best[0] - c.progress_m or best[1] <= self._progress_best[1] - c.progress_m:
            self._progress_t, self._progress_best = s.t, best
            return None
        if s.t - self._progress_t <= c.stall_s:
            return None
        n, e, alt = self._target  # type: ignore[misc]
        return (f"vehicle not reaching its target: {s.alt - alt:+.1f} m vertically and "
                f"{math.hypot(s.north - n, s.east - e):.1f} m horizontally off for {c.stall_s:g} s")

    def _stop_errors(self, s: Sample, target: tuple[float, float, float] | None = None) -> tuple[float, float]:
        """(vertical, horizontal) error of the point where the vehicle would stop if it braked now
        (``v|v| / 2a`` further along each axis) from ``target`` (the present one when None).
        Actual and best errors are always compared through this same estimate, so a vehicle
        speeding up toward its target never looks like one falling behind."""
        assert self._target is not None
        n, e, alt = self._target if target is None else target
        a = self.config.brake_accel_mss
        stop_n = s.north + s.vn * abs(s.vn) / (2 * a)
        stop_e = s.east + s.ve * abs(s.ve) / (2 * a)
        stop_alt = s.alt - s.vd * abs(s.vd) / (2 * a)
        return stop_alt - alt, math.hypot(stop_n - n, stop_e - e)

    def _update_best(self, s: Sample) -> None:
        """Lower the best errors by what sample ``s`` shows the vehicle can reach: its stopping
        point's error, or, before it has heard the present target, its error to the target it
        heard last plus the distance between the two (the module docstring)."""
        if self._target is None:
            return
        t = s.t if math.isfinite(s.t) else math.inf
        while self._unheard and self._unheard[0][0] <= t:
            self._heard = self._unheard.popleft()[1]
        err_z, err_xy = self._stop_errors(s)
        if self._unheard:
            if self._heard is None:
                return  # nothing heard since it was engaged: nothing it does bounds these targets
            (n0, e0, a0), (n, e, alt) = self._heard, self._target
            heard_z, heard_xy = self._stop_errors(s, self._heard)
            err_z, err_xy = abs(heard_z) + abs(alt - a0), heard_xy + math.hypot(n - n0, e - e0)
        self._best_xy = min(self._best_xy, err_xy)
        self._best_z = min(self._best_z, abs(err_z))
