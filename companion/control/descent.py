"""The descent: the planned level, the ceiling, the last metres by the rangefinder.

Every target altitude comes from the altitude at the trigger and the descent plan, never from
"where the vehicle is now minus a step" (against the real PX4 such targets, read a few metres too
high, ratcheted the vehicle up to 220 m). The plan keeps one planned altitude, the *level*: the
altitude at the trigger (lower if the vehicle came down before the companion took over, never
below ``descend_alt_m`` above the ground). The vehicle first flies level to the zone, then
descends one ``descend_step_m`` at a time: the level moves one step down only when the vehicle
has reached it over the zone, re-checking the zone at every frame, so a lost zone stops the
descent within one step.

At the *judging height* (``descend_alt_m`` above the ground, or the trust height below which the
density model sees people reliably, ``person_trust_height``) the zone is judged (calm ground)
and, with ``land_alt_m`` set below it, the same stepped descent goes on over the judged zone to
``land_alt_m``; there the autopilot's LAND is commanded (Copter's LAND and PX4's AUTO.LAND both
descend vertically where the vehicle is). The same sequence serves both autopilots, so that the
descent down to the judging height is always re-checked.

With ``land_agl_m`` and a fresh downward rangefinder, that LAND is first the companion's own
descent, straight down at the descent's speed, to ``land_agl_m`` above the ground the rangefinder
measures, and the autopilot's LAND only there (at once if the rangefinder goes stale or out of
range, or the ground comes first): the same committed end, flown three times faster than
ArduPilot's LAND.

Never fly away: no target is ever above the *ceiling* less ``ceiling_margin_m``; the ceiling is
the altitude at the trigger plus ``search_climb_m``, and never above ``max_alt_m`` above home.

Altitudes are metres above home, heights metres above the ground below (``VehicleStatus.height``).
These functions answer; the phase machine (``companion.control.landing``) keeps the level and acts.
"""

from __future__ import annotations

import math
from dataclasses import replace

from companion.control.settings import LAND_AGL_REACHED_M, LandingConfig
from companion.control.touchdown import DescentProfile, by_rangefinder
from companion.control.vehicle import VehicleStatus


def ceiling(trigger_alt: float, c: LandingConfig) -> float:
    """The ceiling (m above home) for a takeover that began at ``trigger_alt``."""
    return min(trigger_alt + c.search_climb_m, c.max_alt_m)


def raised(level: float, alt: float, cap: float) -> float:
    """The planned level, at least ``alt`` (m above home; a terrain floor or the hold height) and
    never above ``cap``, the highest a target may have."""
    return min(cap, max(level, alt))


#: The head plane (m above the ground) the camera's footprint is measured on.
HEAD_M = 1.7


def judging_height(c: LandingConfig) -> float:
    """The height (m above the ground) at which a zone is judged: ``descend_alt_m``, or higher
    where the lens's footprint (``view_ratio``) would not hold r0 plus ``radius_margin_m`` all
    round there (the 70-degree pinhole holds 4.4 m at 10 m, over the 4 m it needs: 10 m; a
    narrower lens judges higher), and never above the trust height."""
    need = c.planner.large_r_m / c.view_ratio + HEAD_M
    return min(max(c.descend_alt_m, need), c.trust_height_m)


def land_height(c: LandingConfig, judge: float) -> float:
    """The height (m above the ground) down to which a judged zone is descended before the LAND."""
    return min(c.land_alt_m, judge) if c.land_alt_m > 0 else judge


def approach_level(level: float, s: VehicleStatus, c: LandingConfig, cap: float) -> float:
    """The level to fly to a newly chosen zone at: no higher than the vehicle (it came down before
    the companion took over: do not climb back for nothing), no higher than the trust height
    above the ground (above it, what the model calls free is not trusted), never lower than
    ``descend_alt_m`` above the ground below, never above ``cap``."""
    if s.alt < level - c.alt_tolerance_m:
        level = s.alt
    level = min(level, s.alt - s.height + c.trust_height_m)
    return raised(level, s.alt - s.height + c.descend_alt_m, cap)


def next_level(level: float, s: VehicleStatus, dist: float, floor: float, c: LandingConfig, cap: float) -> float:
    """The plan's next level over the zone: at least ``floor`` (m above home: the judging or the
    LAND height over the ground under the vehicle, from terrain, not from the vehicle's
    altitude), one step down once the vehicle has reached the present level within
    ``2 * arrive_radius_m`` (``dist``, m) of the landing point."""
    level = raised(level, floor, cap)
    if dist <= 2 * c.arrive_radius_m and s.alt <= level + c.alt_tolerance_m:
        level = max(level - c.descend_step_m, floor)
    return level


def low_target(c: LandingConfig, s: VehicleStatus, agl_m: float | None = None) -> float | None:
    """Where the companion's own descent to ``land_agl_m`` goes (m above home: the ground the
    rangefinder measures under the vehicle, plus ``land_agl_m``), or None when the LAND is to be
    commanded now: the setting off, no fresh rangefinder, or already that low. The target is
    fixed once, from one reading at the LAND height (a few metres at most), so no later reading
    can move it. ``agl_m``: that height when not ``land_agl_m`` (a committed landing's, ``commit``)."""
    agl, to = s.measured_agl, c.land_agl_m if agl_m is None else agl_m
    if to <= 0 or agl is None or agl <= to + LAND_AGL_REACHED_M:
        return None
    return s.alt - agl + to


def low_land_reason(c: LandingConfig, s: VehicleStatus, target_alt: float, agl_m: float | None = None) -> str | None:
    """Why the companion's low descent (to ``target_alt``, m above home) ends now and the
    autopilot's LAND takes over, or None to fly on: the rangefinder says the vehicle is there,
    or no longer gives a height (stale or out of range). ``agl_m`` as for ``low_target``."""
    agl = s.measured_agl
    if agl is None:
        return f"no rangefinder height at {s.height:.1f} m above home"
    if agl <= (c.land_agl_m if agl_m is None else agl_m) + LAND_AGL_REACHED_M or s.alt <= target_alt + LAND_AGL_REACHED_M:
        return f"{agl:.1f} m above the ground by the rangefinder"
    return None


def profile_now(profile: DescentProfile, s: VehicleStatus | None, land_agl_m: float) -> DescentProfile:
    """The descent the vehicle will fly from here: with a fresh rangefinder the companion's own
    descent goes on down to ``land_agl_m`` and the autopilot's LAND is that much shorter."""
    if s is None or s.measured_agl is None:
        return profile  # no rangefinder height: the LAND at land_alt_m, as low_target says
    return by_rangefinder(profile, land_agl_m)


def with_speeds(profile: DescentProfile, speeds: dict[str, float]) -> DescentProfile | None:
    """``profile`` with the autopilot's own descent speeds (m/s by ``DescentProfile`` field, read
    from its parameters; a value that is not a positive number is ignored); None when none is
    known."""
    known = {k: v for k, v in speeds.items()
             if k in ("descend_speed_mps", "land_speed_mps") and math.isfinite(v) and v > 0}
    return replace(profile, **known) if known else None


def touchdown_clearance(profile: DescentProfile, s: VehicleStatus | None, r: float) -> float | None:
    """The least clearance (m) a zone of radius ``r`` can have at touchdown if the vehicle came
    down over it now from its present height, every walker heading for it; None without a
    vehicle position."""
    if s is None:
        return None
    value = profile.clearance_at_touchdown(r, s.height)
    return round(value, 2) if math.isfinite(value) else None


def person_trust_height(fx_px: float, min_person_px: float | None, person_m: float = 0.4,
                        head_m: float = 1.7) -> float:
    """The height above the ground (m) below which a person of ``person_m`` across (seen from
    above: 0.4 m, a little under an adult's shoulder breadth, so children count too) appears at
    least ``min_person_px`` pixels wide to a camera of focal length ``fx_px`` looking straight down
    at the head plane ``head_m`` above the ground; inf when ``min_person_px`` is None."""
    if min_person_px is None:
        return math.inf
    if not (math.isfinite(fx_px) and fx_px > 0 and math.isfinite(min_person_px) and min_person_px > 0):
        raise ValueError(f"person_trust_height needs fx > 0 and min_person_px > 0, not {fx_px!r}, {min_person_px!r}")
    return head_m + fx_px * person_m / min_person_px
