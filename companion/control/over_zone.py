"""Over the zone: what the descent does on one frame, from over the landing point to the LAND.

In DESCEND the vehicle is over a zone the frame has just confirmed (``aim.Aimed``). Each frame
the descent does one of four things (``decide``):

- ``Hover`` over the landing point while a named wait lasts: ``calm`` at the judging height
  until the ground under the vehicle has been watched free for ``min_calm_s`` (``ground.
  calm_verdict``), or ``reach`` at the commit height until the frame has seen r0 plus a walker's
  reach free around the vehicle (``commit.reach_wait``);
- ``GiveUp`` the zone: not calm after ``calm_wait_s`` of waiting over it;
- ``StepDown``: the plan's next level, never below the judging height, or once the zone is judged
  (calm, at the judging height: ``judged_text`` says so on that frame) never below the LAND
  height (``commit.land_plan``);
- ``CommitLand``: reached the LAND height (or on the ground early, a slope), the LAND is
  commanded: the autopilot's LAND now, or first the companion's own descent straight down to a
  height by the rangefinder (``descent.low_target``; fast from a commit height, ``commit``).

Pure: it reads the vehicle, the settings, the descent profile, the frame's ground below and how
long the waits have lasted, and changes nothing; the phase machine (``companion.control.landing``)
turns the decision into commands and events and keeps the waits, the level and the judgement.
Heights in metres above the ground below (``VehicleStatus.height``), altitudes in metres above
home, times in seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, TypeAlias

from companion.control import commit, ground
from companion.control import descent as plan
from companion.control.aim import Aimed
from companion.control.settings import LandingConfig
from companion.control.touchdown import DescentProfile
from companion.control.vehicle import VehicleStatus
from companion.pipeline.circles import GroundBelow

#: The waits over a zone before its LAND (``commit.Waits``' kinds).
Wait = Literal["calm", "reach"]


@dataclass(frozen=True)
class Hover:
    """Hover over the landing point at the present level while ``wait`` lasts; ``why`` its words
    for the pilot (told once, when the wait begins)."""

    wait: Wait
    why: str


@dataclass(frozen=True)
class GiveUp:
    """Give the zone up (it never became calm): ``why`` for the pilot."""

    why: str


@dataclass(frozen=True)
class StepDown:
    """Fly the plan's next level (``descent.next_level``), never below ``floor_alt_m`` (m above
    home). ``judged``: the zone was judged on this frame, the words of that event; None otherwise."""

    floor_alt_m: float
    judged: str | None = None


@dataclass(frozen=True)
class LowDescent:
    """The companion's own descent in LAND, straight down over the landing point as it was when
    the LAND was commanded (``north``, ``east``: m from home; the committed descent chases no
    zone) to ``alt_m`` (m above home), ``agl_m`` above the ground by the rangefinder; there, or
    once the rangefinder stops giving a height, the autopilot's LAND (``descent.low_land_reason``)."""

    north: float
    east: float
    alt_m: float
    agl_m: float


@dataclass(frozen=True)
class CommitLand:
    """Command the LAND: ``text`` the LAND event's words, with its ``touchdown_clearance_m`` (m;
    None without a figure) and ``calm_s`` (s, one decimal; None when not measured). ``low``
    None: the autopilot's LAND now; else first the companion's own descent (``LowDescent``)."""

    text: str
    low: LowDescent | None
    touchdown_clearance_m: float | None
    calm_s: float | None


Decision: TypeAlias = Hover | GiveUp | StepDown | CommitLand


def decide(s: VehicleStatus, c: LandingConfig, profile: DescentProfile, over: Aimed, below: GroundBelow | None,
           steady: bool, judged: bool, calm_waited_s: float, reach_waited_s: float) -> Decision:
    """What the descent over ``over`` (the zone, its landing point and the vehicle's distance to
    it, m) does on this frame, with the vehicle at ``s`` and the ``profile`` it will descend by.
    ``below``: the frame's ground under the camera (``GroundBelow``), if usable; ``steady``: the
    vehicle is over a steady zone whose watch counts as calm (``ground.over_steady``);
    ``judged``: the zone was judged already (its descent goes on to the LAND height);
    ``calm_waited_s``/``reach_waited_s``: how long the vehicle has hovered over this zone for
    calm and for people within reach (0 when not waiting, ``commit.Waits.waited``)."""
    track, zone_id = over.track, over.track.id
    judge = plan.judging_height(c)
    reached = over.dist <= c.arrive_radius_m and s.height <= judge + c.alt_tolerance_m
    in_air = not s.on_ground

    if reached and in_air and not judged:
        calm = ground.calm_verdict(track, below, steady, c.planner)
        if not calm.ok:
            # A wait that runs past calm_wait_s has begun earlier: the zone is given up.
            if calm_waited_s > c.calm_wait_s:
                return GiveUp(f"not calm after {c.calm_wait_s:g} s over it: people keep passing near it")
            return Hover("calm", f"{calm.why}: waiting before the LAND")

    # fast: the footprint guarantees, and the landing is committed from land_at (``commit``).
    land_at, fast = commit.land_plan(c, profile, s, judge, reach_waited_s)
    ground_alt = s.alt - s.height  # m above home, under the vehicle

    if in_air and reached and s.height > land_at + c.alt_tolerance_m:
        # Over the point, above the LAND height: judged (calm) now if not yet, the companion's own
        # descent goes on to land_at by the plan's steps, the ground under the vehicle re-checked
        # every frame (the controller's ``_confirmed``).
        steady_s = track.steady_s if steady else None
        text = None if judged else ground.judged_text(zone_id, s.height, ground.calm_s(below), steady_s, land_at)
        return StepDown(ground_alt + land_at, judged=text)

    if not (s.on_ground or reached):
        # On the way down to the judging height (judged: to the LAND height); off the point it re-centres.
        return StepDown(ground_alt + (land_at if judged else judge))

    if fast and in_air:
        why = commit.reach_wait(c, fast, s, below)
        if why:
            return Hover("reach", why)  # no longer than calm_wait_s: land_plan
    return _land(s, c, profile, over, below, commit.fast_agl(c) if fast else c.land_agl_m)


def _land(s: VehicleStatus, c: LandingConfig, profile: DescentProfile, over: Aimed, below: GroundBelow | None,
          agl: float) -> CommitLand:
    """The LAND over ``over`` at the vehicle's height now: on the ground (the ground came early, a
    slope) the autopilot's LAND finishes and disarms; in the air, with a fresh rangefinder, first
    straight down to ``agl`` (m) above the ground it measures."""
    track = over.track
    low_alt = None if s.on_ground else plan.low_target(c, s, agl)
    low = None if low_alt is None else LowDescent(over.aim[0], over.aim[1], low_alt, agl)
    how = "" if low is None else f", first down to {agl:g} m by the rangefinder"
    calm_s = ground.calm_s(below)
    return CommitLand(
        text=f"LAND over zone {track.id} at {s.height:.1f} m, radius {track.r:.1f} m" + how,
        low=low,
        touchdown_clearance_m=plan.touchdown_clearance(plan.profile_now(profile, s, c.land_agl_m), s, track.r),
        calm_s=round(calm_s, 1) if math.isfinite(calm_s) else None,
    )
