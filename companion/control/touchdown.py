"""How long until touchdown, and how clear a zone will be then: walking speed x blind time.

Once the companion commits to a zone, the vehicle comes down in two parts: the companion's own
stepped descent (GUIDED/OFFBOARD, about ``descend_speed_mps``) to ``land_alt_m``, then the
autopilot's LAND at ``land_speed_mps`` (ArduPilot's ``LAND_SPEED``, 50 cm/s by default; PX4's
``MPC_LAND_SPEED``, 0.7 m/s). Nobody walks faster than ``walk_speed_mps`` (1.5 m/s by default,
``pipeline.walk_speed_mps``), so a zone whose clearance is ``c`` metres now has at least
``c - walk_speed * t`` at touchdown ``t`` seconds later, and no margin can do better than that
floor: from 10 m at 0.5 m/s, 20 s of LAND let a walker cover 30 m. Pure: heights in metres above
the ground under the zone (above home when nothing better is known), speeds in m/s, times in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from companion.invariant import require


@dataclass(frozen=True)
class DescentProfile:
    """See the module docstring."""

    descend_speed_mps: float = 1.5
    land_alt_m: float = 10.0
    land_speed_mps: float = 0.5
    walk_speed_mps: float = 1.5

    def __post_init__(self) -> None:
        for name in ("descend_speed_mps", "land_speed_mps", "walk_speed_mps"):
            v = getattr(self, name)
            require(math.isfinite(v) and v > 0, "descent", name, "must be > 0 (a speed)", v)
        require(math.isfinite(self.land_alt_m) and self.land_alt_m >= 0, "descent", "land_alt_m", "must be >= 0",
                self.land_alt_m)

    def time_to_touchdown(self, height_m: float) -> float:
        """Seconds from ``height_m`` above the ground to touchdown (NaN for a NaN height)."""
        if not math.isfinite(height_m):
            return math.nan
        h = max(0.0, height_m)
        upper = max(0.0, h - self.land_alt_m)
        return upper / self.descend_speed_mps + min(h, self.land_alt_m) / self.land_speed_mps

    def clearance_at_touchdown(self, clearance_now_m: float, height_m: float) -> float:
        """The least clearance (m) a zone of ``clearance_now_m`` can have at touchdown from
        ``height_m``: less the distance a walker covers meanwhile (negative: somebody may be there)."""
        return clearance_now_m - self.walk_speed_mps * self.time_to_touchdown(height_m)


def by_rangefinder(profile: DescentProfile, land_agl_m: float) -> DescentProfile:
    """The descent when a fresh downward rangefinder measures the height (``controller.land_agl_m``,
    docs/design.md, "The last metres by the rangefinder"): the companion's own descent goes on
    down to ``land_agl_m`` above the ground and the autopilot's LAND flies only that. ``profile``
    itself when ``land_agl_m`` is 0 (off) or not below the profile's LAND height. One rule for the
    controller and for replay's ``clearance_m``."""
    if not 0 < land_agl_m < profile.land_alt_m:
        return profile
    return replace(profile, land_alt_m=land_agl_m)


def touchdown_basis(alt_m: float | None, agl_m: float | None, profile: DescentProfile,
                    land_agl_m: float) -> tuple[float | None, DescentProfile]:
    """The height a touchdown time is figured from and the descent flown from it, as the landing
    controller figures them (``VehicleStatus.height``, ``LandingController._descent_now``): a
    fresh downward rangefinder's height ``agl_m`` and the descent by it (``by_rangefinder``),
    else the height above home ``alt_m`` (None: unknown) and ``profile`` as it is. For replay,
    which reads both from a recording."""
    if agl_m is not None and math.isfinite(agl_m):
        return agl_m, by_rangefinder(profile, land_agl_m)
    return alt_m, profile


def guaranteed_clearance(profile: DescentProfile, height_m: float, view_ratio: float, head_m: float = 1.7,
                         step_m: float = 0.1) -> float:
    """The clearance (m) a vertical descent from ``height_m`` can guarantee at touchdown against
    walkers at ``profile.walk_speed_mps`` heading for it from just beyond what the camera sees:
    ``max over h <= height_m of view_ratio * (h - head_m) - walk_speed * time_to_touchdown(h)``,
    evaluated every ``step_m``. ``view_ratio``: ground radius seen per metre of height above the
    head plane (the tangent of half the narrower field of view). See the module docstring."""
    if not (math.isfinite(height_m) and math.isfinite(view_ratio) and view_ratio >= 0 and step_m > 0):
        raise ValueError("guaranteed_clearance needs a finite height, a view ratio >= 0 and a step > 0")
    best = -math.inf
    n = max(0, int(math.floor(max(0.0, height_m - head_m) / step_m)))
    for i in range(n + 1):
        h = min(height_m, head_m + i * step_m)
        seen = view_ratio * max(0.0, h - head_m)
        best = max(best, seen - profile.walk_speed_mps * profile.time_to_touchdown(h))
    return best
