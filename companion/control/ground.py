"""Is the ground under the vehicle fit now: free below, calm, steady.

Over the zone the vehicle lands where it is, not at the zone's centre, so what must be free is r0
around the vehicle. Two measures say how far the ground around it is free, and the larger wins
(both are lower bounds of the same thing): the zone's radius less the vehicle's offset from its
centre, and the frame's own measure under the camera (``GroundBelow``), carried to where the
vehicle is now. The first alone threw landings away low over view-bounded zones: at 10 m the
view shows about 4 m around the vehicle, the zone's centre sits 1-2 m off it, away from the
people at one side, and ``r - offset`` came out at 1.6-1.9 m with the nearest person 4 m away.

Low over a zone the view is smaller than r0; then everything the camera sees there must be free,
with at least ``MIN_VIEW_M`` of view (``planner.seen_all_free``).

Calm: at the judging height the ground under the vehicle must have been watched and seen free
for ``PlannerConfig.min_calm_s`` before the LAND. A zone chosen for its steadiness (too small,
when chosen, for r0 plus the radius margin) stands for the calm disc that does not fit in it: its
steady watch (``Track.steady_s``) counts as calm while the vehicle is within ``steady_margin_m``
of its centre.

During LAND the zone is still watched: above ``land_abort_above_m`` a zone seen occupied sends
the vehicle back to HOLD; below it the landing is committed. A zone that merely drops out of the
tracks (``gone``) commits the landing too, unless the frame sees somebody within r0 of the
vehicle: low over it the view is too small for the tracker to keep the zone, and that is no
reason to climb (the real PX4 1.15.4 SIH climbed back to 10-12 m from 3-4 m three times so, its
altitude reading up to 1.8 m off; issue 62).

Every function here answers a question and changes nothing; the phase machine
(``companion.control.landing``) acts on the answers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.control.planner import MIN_VIEW_M, PlannerConfig, ZoneCheck, ZonePlanner, seen_all_free
from companion.control.vehicle import VehicleStatus
from companion.pipeline.circles import GroundBelow
from companion.pipeline.tracker import Track


@dataclass(frozen=True)
class Below:
    """The frame's measure under the camera carried to where the vehicle is now: ``free`` how far
    the ground around it is free (m, less how far it moved since the frame), ``all_free`` whether
    everything the camera saw there is free with ``MIN_VIEW_M`` in view."""

    free: float
    all_free: bool


@dataclass(frozen=True)
class CalmVerdict:
    """Whether the ground under the vehicle is calm enough to LAND on (``ok``); ``calm_s`` the
    calm that counted (s; NaN when not measured) and, when not ok, ``why`` (for the pilot)."""

    ok: bool
    calm_s: float
    why: str = ""


def usable_below(below: GroundBelow | None) -> GroundBelow | None:
    """``below`` when every measure of it that places it is finite, else None."""
    ok = below is not None and all(math.isfinite(v) for v in (below.x, below.y, below.r, below.r_view))
    return below if ok else None


def below_here(status: VehicleStatus | None, below: GroundBelow | None) -> Below | None:
    """The frame's measure under the camera (``GroundBelow``), carried to where the vehicle is
    now; None without a measure or a vehicle position."""
    if status is None or below is None:
        return None
    moved = math.hypot(below.x - status.north, below.y - status.east)
    return Below(below.r - moved, below.view_limited and below.r_view - moved >= MIN_VIEW_M)


def free_below(track: Track, status: VehicleStatus, below: GroundBelow | None) -> Below:
    """How far the ground around the vehicle is free (m), and whether everything the camera sees
    around it is free: the larger of the zone's radius less the vehicle's offset from its centre
    and the frame's own measure (``below_here``; see the module docstring)."""
    free = track.r - math.hypot(track.x - status.north, track.y - status.east)
    here = below_here(status, below)
    if here is None:
        return Below(free, False)
    return Below(max(free, here.free), here.all_free)


def someone_within_r0(status: VehicleStatus | None, below: GroundBelow | None, planner: PlannerConfig) -> bool:
    """Whether this frame saw somebody (not the end of the view) within r0 of the vehicle. A view
    that saw only free ground saw nobody, however far the vehicle has moved from its centre since
    (carried to the vehicle, its free radius shrinks by that much, which is no person)."""
    here = below_here(status, below)
    return here is not None and below is not None and not below.view_limited and \
        not planner.holds_r0(here.free, here.all_free)


def holds_under_aim(status: VehicleStatus, aim: tuple[float, float], below: GroundBelow | None,
                    planner: PlannerConfig, arrive_radius_m: float) -> bool:
    """Over the landing point ``aim`` (within ``arrive_radius_m``), whether this frame saw r0
    free around the vehicle, or everything it saw there free: low over the zone the tracker may
    drop it (the view, smaller than r0 plus the margin, makes no proposal of it) while the ground
    under the vehicle, where it comes down, is free. Off the point the zone's own track must say."""
    here = below_here(status, below)
    if here is None or math.hypot(aim[0] - status.north, aim[1] - status.east) > arrive_radius_m:
        return False
    return planner.holds_r0(here.free, here.all_free)


def over_steady(track: Track, status: VehicleStatus | None, steady_target: int | None,
                planner: PlannerConfig) -> bool:
    """Whether ``track`` was chosen as a steady zone (``steady_target``: too small, when chosen,
    for ``r0_m + radius_margin_m``), is steady still (``PlannerConfig.is_steady``) and the
    vehicle within ``steady_margin_m`` of its centre, so that r0 round the vehicle lies inside the
    disc the zone has kept free. A zone chosen larger has room for the calm disc, and calm judges
    it, also once the view at the judging height bounds it under that size."""
    return (status is not None and steady_target == track.id and planner.is_steady(track)
            and math.hypot(status.north - track.x, status.east - track.y) <= planner.steady_margin_m)


def calm_s(below: GroundBelow | None) -> float:
    """The frame's calm under the camera (s; NaN when not measured)."""
    return below.calm_s if below is not None else math.nan


def calm_verdict(track: Track, below: GroundBelow | None, steady: bool, planner: PlannerConfig) -> CalmVerdict:
    """Whether the ground under the vehicle has been watched and seen free for
    ``planner.min_calm_s``; ``steady``: the vehicle is over a steady zone (``over_steady``),
    whose watch counts as calm (see the module docstring)."""
    calm = calm_s(below)
    if steady:
        calm = max(calm, track.steady_s) if math.isfinite(calm) else track.steady_s
    if planner.is_calm(calm):
        return CalmVerdict(True, calm)
    seen = f"{calm:.1f} s" if math.isfinite(calm) else "not yet"
    return CalmVerdict(False, calm, f"ground around the landing point watched free for {seen}, "
                                    f"not {planner.min_calm_s:g} s")


def gone(track: Track | None, now: float, zone_max_age_s: float) -> bool:
    """Whether the target has dropped out of the tracks (``track``: its snapshot on this frame,
    None when gone, or not confirmed for ``zone_max_age_s``) rather than being seen occupied. In
    LAND that commits the landing unless the frame sees somebody within r0 of the vehicle
    (``someone_within_r0``): whether the view was small by the height the pose gives or by the
    true one (the real PX4 SIH's altitude reads up to 1.8 m high), the camera low over the zone
    cannot confirm it, and the vehicle must not climb away for that."""
    return track is None or now - track.last_t > zone_max_age_s


def left_view(track: Track | None, now: float, status: VehicleStatus | None, below: GroundBelow | None,
              planner: PlannerConfig) -> bool:
    """Whether the target merely left the view (``gone``) with nobody seen within r0 of the vehicle
    (``someone_within_r0``): low over the zone, no reason to give it up."""
    return gone(track, now, planner.zone_max_age_s) and not someone_within_r0(status, below, planner)


def target_check(planner: ZonePlanner, target: Track, tracks: list[Track], now: float, s: VehicleStatus | None,
                 below: GroundBelow | None, over_zone: bool, free_under_aim: bool) -> tuple[ZoneCheck, Track | None, str]:
    """Whether the zone flown to still holds on this frame: ``ZonePlanner.check_target``, and
    over the zone (``over_zone``: DESCEND, LAND) r0 free around the vehicle, where it lands
    (``free_below``); a zone the tracker dropped low over it still holds while the ground under
    the landing point is free (``free_under_aim``, ``holds_under_aim``). (verdict, its snapshot,
    the reason)."""
    verdict, track, why = planner.check_target(target.id, tracks, now)
    if verdict == ZoneCheck.LOST and track is None and free_under_aim:
        verdict, track, why = ZoneCheck.OK, target, ""
    if verdict == ZoneCheck.OK and over_zone and s is not None and track is not None and not seen_all_free(track):
        here = free_below(track, s, below)
        if not planner.config.holds_r0(here.free, here.all_free):
            return ZoneCheck.SMALL, track, f"{here.free:.1f} m free around the vehicle < r0 {planner.config.r0_m:g} m"
    return verdict, track, why


def judged_text(zone_id: int, height_m: float, calm: float, steady_s: float | None, land_at_m: float) -> str:
    """The words for a zone judged at ``height_m`` (m) with its ``calm`` (s; NaN: not measured)
    and, over a steady zone, its ``steady_s``, the descent going on to ``land_at_m``."""
    measured = [f"calm {calm:.1f} s"] if math.isfinite(calm) else []
    if steady_s is not None:
        measured.append(f"steady {steady_s:.1f} s")
    return (f"zone {zone_id} judged at {height_m:.1f} m" + (f" ({', '.join(measured)})" if measured else "")
            + f": descending over it to {land_at_m:g} m before the LAND")
