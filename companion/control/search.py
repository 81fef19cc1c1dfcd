"""The search: where to fly when no zone is in view at the SELECT/HOLD timeout.

The vehicle climbs to the ceiling over where it is and flies an ``expanding_square`` (legs 1.5
radii of the lens's footprint apart, hovering at each corner while the tracker looks), flying first over free ground
glimpsed at the edge of the view (a zone of at least r0 that may not be chosen yet, most often one
cut by the edge of the view), so the camera sees it whole; any zone that becomes eligible is
flown to (the phase machine checks the zones first on every frame). It hands back after
``search_s``, at ``search_radius_m``, or when the battery's time left
(``VehicleStatus.battery_s``) no longer covers the landing plus ``search_reserve_s``.

``Search`` keeps where the search is (waypoints left, the glimpse it hovers over, the glimpses
given up) and answers with a ``Move``; the phase machine (``companion.control.landing``) flies it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.control.planner import PlannerConfig, ZonePlanner
from companion.control.settings import LandingConfig
from companion.control.vehicle import VehicleStatus
from companion.pipeline.tracker import Track


@dataclass(frozen=True)
class Move:
    """The search's answer for this frame: fly to (``north``, ``east``) at the planned level
    (``to`` not None), hover where the vehicle is (``to`` None, ``done`` empty), or stop
    (``done``: why, for the pilot)."""

    to: tuple[float, float] | None = None
    done: str = ""


HOVER = Move()


def expanding_square(centre: tuple[float, float], spacing_m: float, radius_m: float) -> list[tuple[float, float]]:
    """The waypoints (north, east metres) of an expanding-square search around ``centre``: legs
    north, east, south, west of 1, 1, 2, 2, 3, 3, ... times ``spacing_m``, as far as
    ``radius_m`` from the centre (the last leg is cut there). The square visits the ground nearest
    the vehicle first and never crosses itself (IAMSAR's expanding square)."""
    if not (math.isfinite(spacing_m) and spacing_m > 0 and math.isfinite(radius_m) and radius_m >= 0):
        raise ValueError(f"expanding_square needs spacing > 0 and radius >= 0, not {spacing_m!r}, {radius_m!r}")
    n, e = centre
    points: list[tuple[float, float]] = []
    heading = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))
    k = 0
    while True:
        length = (k // 2 + 1) * spacing_m
        dn, de = heading[k % 4]
        nn, ne = n + dn * length, e + de * length
        if max(abs(nn - centre[0]), abs(ne - centre[1])) > radius_m:
            return points
        points.append((nn, ne))
        n, e = nn, ne
        k += 1


def spacing(level: float, s: VehicleStatus, view_ratio: float, radius_m: float = math.inf) -> float:
    """Metres between the search's legs at the planned ``level`` (m above home): 1.5 times the
    ground radius the camera sees there along its narrower side. Ground between two legs is then
    within 0.75 of that radius of one of them, so a free circle there shows enough of itself from
    a corner to be a glimpse worth flying over (``Search.lead``); at 1.0 a circle just beyond the
    first corner showed a strip too thin to be one, and the search flew away from it (at least
    4 m). ``view_ratio``: the lens's footprint (``LandingConfig.view_ratio``). At most the
    search's ``radius_m``: a wide lens's legs (pinhole:110 from 28.5 m: 43 m) would otherwise leave
    the square no waypoint inside it, and the search would end where it starts."""
    height = level - (s.alt - s.height)
    return max(4.0, min(1.5 * view_ratio * max(0.0, height - 1.7), radius_m))


def dwell_s(p: PlannerConfig) -> float:
    """Seconds to hover at each search waypoint: a zone's track must be born and grow old enough
    to be chosen (``min_track_age_s``), plus a second for the tracker's first frames."""
    return p.min_track_age_s + 1.0


class Search:
    """Where the search is; see the module docstring. Times are the controller's (s)."""

    def __init__(self, config: LandingConfig, planner: ZonePlanner) -> None:
        self.config = config
        self.planner = planner
        self.waypoints: list[tuple[float, float]] = []  # left to fly (north, east)
        self.started_t = math.nan
        self.dwell_until = -math.inf  # hovering at a reached waypoint until then
        self.investigated: set[int] = set()  # zones flown over that never qualified
        self.over_lead: tuple[int, float] | None = None  # (zone id, since when) hovered over

    def start(self, now: float) -> None:
        """The search's clock starts at ``now`` (its time limit counts from here)."""
        self.started_t = now

    def fly_square(self, centre: tuple[float, float], level: float, s: VehicleStatus) -> None:
        """The square's waypoints around ``centre``, spaced for the view at ``level``."""
        c = self.config
        self.waypoints = expanding_square(centre, spacing(level, s, c.view_ratio, c.search_radius_m), c.search_radius_m)

    def over(self, now: float, tracks: list[Track], s: VehicleStatus | None, to_touchdown_s: float) -> str | None:
        """Why the search must stop now, or None: its time (unless it is finishing a steady look,
        ``finishing_steady_look``), or the battery's (``to_touchdown_s``: the landing from here)."""
        c = self.config
        if now - self.started_t > c.search_s and not self.finishing_steady_look(now, tracks, s):
            return f"searched {c.search_s:g} s without a safe zone"
        if s is not None and s.battery_s is not None and math.isfinite(s.battery_s):
            need = to_touchdown_s + c.search_reserve_s
            if s.battery_s < need:
                return f"battery {s.battery_s:.0f} s left, landing needs {need:.0f} s with the reserve"
        return None

    def step(self, now: float, tracks: list[Track], s: VehicleStatus) -> Move:
        """This frame's move: toward free ground glimpsed at the edge of the view, else to the
        square's next waypoint (hovering ``dwell_s`` at each), else done."""
        c = self.config
        lead = self.lead(tracks)
        if lead is not None:
            return self.look_at(lead, now, s)
        if self.waypoints and math.hypot(self.waypoints[0][0] - s.north,
                                         self.waypoints[0][1] - s.east) <= 2 * c.arrive_radius_m:
            # Hover there long enough for a zone in view to become a track and be old enough to
            # choose (mu_2 frames, then min_track_age_s): flying on, the view slides past a
            # zone before the tracker can confirm it.
            self.dwell_until = now + dwell_s(c.planner)
            self.waypoints.pop(0)
        if now < self.dwell_until:
            return HOVER
        if not self.waypoints:
            return Move(done=f"searched {c.search_radius_m:g} m around without a safe zone")
        return Move(to=self.waypoints[0])

    def lead(self, tracks: list[Track]) -> Track | None:
        """The largest zone the latest frame confirmed that may not be chosen yet (smaller than
        ``r0_m + radius_margin_m``, or young) and has not been looked at already, or None."""
        return self.planner.largest_glimpse(tracks, self.investigated)

    def look_at(self, lead: Track, now: float, s: VehicleStatus) -> Move:
        """Free ground seen, too little of it to choose (cut by the edge of the view, or too
        young): fly over it so the camera sees it whole, and let the tracker confirm it; looked
        at without becoming a zone for as long as ``looked_long_enough`` allows, it is given up."""
        if math.hypot(lead.x - s.north, lead.y - s.east) > 2 * self.config.arrive_radius_m:
            self.over_lead = None
            return Move(to=(lead.x, lead.y))
        if self.over_lead is None or self.over_lead[0] != lead.id:
            self.over_lead = (lead.id, now)
        elif self.looked_long_enough(lead, now - self.over_lead[1]):
            self.investigated.add(lead.id)  # looked at long enough: it is no zone
        return HOVER

    def looked_long_enough(self, lead: Track, over_s: float) -> bool:
        """Whether free ground hovered over for ``over_s`` seconds without becoming a zone is to
        be given up: after the waypoints' dwell; or, for a glimpse that keeps r0 plus the steady
        margin free (``PlannerConfig.steady_r_m``), once the time over it not covered by its
        present steady watch (``Track.steady_s``) passes ``steady_s`` plus a second. The watch
        counts the same ground, so it starts once the zone's centre stops moving as the view
        comes to hold all of it (seconds after the vehicle arrived); a watch that keeps breaking,
        or never starts, is given up as soon as before, and none is looked at for longer than
        twice ``steady_s`` plus a second (one steady the planner still refuses must not hold the
        search)."""
        p = self.config.planner
        if p.is_steady_sized(lead):
            watched = lead.steady_s if math.isfinite(lead.steady_s) else 0.0
            dwell = max(dwell_s(p), p.steady_s + 1.0)
            return over_s - watched >= dwell or over_s >= dwell + p.steady_s
        return over_s >= dwell_s(p)

    def finishing_steady_look(self, now: float, tracks: list[Track], s: VehicleStatus | None) -> bool:
        """Whether the search is over a steady-sized glimpse (``looked_long_enough``) whose
        steady watch runs and has not yet reached ``steady_s``, with at most ``steady_s`` past
        the search's time: that look is finished rather than the vehicle handed back over the
        crowd a few seconds before the zone could be chosen. ``max_takeover_s`` and the battery
        still bound it."""
        p, c = self.config.planner, self.config
        if p.steady_s <= 0 or self.over_lead is None or now - self.started_t > c.search_s + p.steady_s:
            return False
        lead = next((t for t in tracks if t.id == self.over_lead[0] and t.misses == 0
                     and t.id not in self.investigated), None)
        return (lead is not None and s is not None and p.is_steady_sized(lead) and math.isfinite(lead.steady_s)
                and 0.0 < lead.steady_s < p.steady_s
                and math.hypot(lead.x - s.north, lead.y - s.east) <= 2 * c.arrive_radius_m)
