"""Where the landing is committed: the camera's footprint against how far a walker gets.

Looking straight down, the camera sees ``view_ratio * (h - head)`` metres all round the point
below it (``LandingConfig.view_ratio``: the footprint of the configured lens, ``Intrinsics.
seen_ratio``, its trusted cone included). A walker at ``walk_speed_mps`` covers ``walk_speed *
T(h)`` before touchdown, ``T`` the descent flown from ``h`` (``touchdown.DescentProfile``, the
autopilot's own speeds once read). Where the footprint reaches past that reach plus ``r0``,

    view_ratio * (h - head) - walk_speed * T(h) >= r0,

nobody out of view can reach r0 of the point before touchdown, and the camera sees everybody who
could: the landing can be committed there once everything seen within ``r0 + walk_speed * T(h)``
of the vehicle is free, and held (the vehicle hovering over the point) while it is not. The
*commit height* is the lowest height from the LAND height up to the judging height where the
footprint guarantees this; the narrow 70-degree pinhole (0.525) never does (docs/design.md, "The
physics of the last metres"), and its landing keeps the LAND at ``land_alt_m``, committed below
``land_abort_above_m`` whatever comes in unseen.

From the commit height the last metres are flown at the autopilot's faster descent where the
vehicle allows it: with a fresh downward rangefinder the companion's own descent (``WPNAV_SPEED_DN``
/ ``MPC_Z_VEL_MAX_DN``) goes on straight down to ``land_agl_m`` (``FAST_AGL_M`` when that setting
is off) and the autopilot's LAND only there; without one the stepped descent goes on to
``land_alt_m`` and the LAND, as the guarantee's ``T`` assumed.

Pure: heights in metres above the ground, speeds in m/s, times in s.
"""

from __future__ import annotations

import math

from companion.control.descent import HEAD_M, land_height
from companion.control.ground import below_here
from companion.control.settings import LandingConfig
from companion.control.touchdown import DescentProfile, by_rangefinder
from companion.control.vehicle import VehicleStatus
from companion.pipeline.circles import GroundBelow

#: Where the committed fast descent hands over to the autopilot's LAND when ``land_agl_m`` is 0
#: (m above the ground by the rangefinder): the value measured for that setting.
FAST_AGL_M = 1.0
#: The commit height is searched in steps of this (m), upward from the LAND height.
STEP_M = 0.1
#: The footprint must reach this much (m) past r0 plus the walker's reach at the commit height:
#: the frame measures the free ground on its grid, to the view's edge less its cells, from where
#: the vehicle is (up to ``arrive_radius_m``, 1 m, off the landing point), so a footprint just
#: covering the reach would never be seen free that far.
MARGIN_M = 1.0


def fast_agl(c: LandingConfig) -> float:
    """The height (m, by the rangefinder) down to which a committed landing flies fast."""
    return c.land_agl_m or FAST_AGL_M


def committed_profile(c: LandingConfig, profile: DescentProfile, s: VehicleStatus | None) -> DescentProfile:
    """The descent flown once committed: with a fresh rangefinder fast down to ``fast_agl``,
    else ``profile`` (the stepped descent to ``land_alt_m``, then the LAND)."""
    if s is None or s.measured_agl is None:
        return profile
    return by_rangefinder(profile, fast_agl(c))


def reach_m(profile: DescentProfile, height_m: float) -> float:
    """How far (m) a walker at ``profile.walk_speed_mps`` gets before touchdown from ``height_m``."""
    return profile.walk_speed_mps * profile.time_to_touchdown(height_m)


def guarantees(c: LandingConfig, profile: DescentProfile, height_m: float) -> bool:
    """Whether the footprint at ``height_m`` reaches ``MARGIN_M`` past r0 plus a walker's reach to
    touchdown."""
    seen = c.view_ratio * max(0.0, height_m - HEAD_M)
    return seen - reach_m(profile, height_m) >= c.planner.r0_m + MARGIN_M


def commit_height(c: LandingConfig, profile: DescentProfile, land_at: float, judge: float) -> float | None:
    """The lowest height (m) from ``land_at`` up to ``judge`` (every ``STEP_M``) at which the
    footprint guarantees (``guarantees``) against the descent ``profile``; None where none does.
    ``land_at`` itself when it does: then the LAND height is already safe to commit at."""
    if not (math.isfinite(land_at) and math.isfinite(judge)) or judge < land_at:
        return None
    n = int(math.floor((judge - land_at) / STEP_M + 1e-9))
    for i in range(n + 1):
        h = land_at + i * STEP_M
        if guarantees(c, profile, h):
            return round(h, 3)
    return None


def reach_wait(c: LandingConfig, profile: DescentProfile, s: VehicleStatus, below: GroundBelow | None) -> str | None:
    """Why the committed landing waits at the commit height, or None to commit now: the frame
    must have seen r0 plus a walker's reach to touchdown free around the vehicle (anybody seen
    nearer could reach r0 of the point before it touches down; ground not seen, or no frame
    measure, is not free)."""
    need = c.planner.r0_m + reach_m(profile, s.height)
    here = below_here(s, below)
    free = -math.inf if here is None else here.free
    if free >= need:
        return None
    seen = "not measured" if here is None else f"{free:.1f} m"
    return (f"free around the vehicle {seen}, not r0 plus the {reach_m(profile, s.height):.1f} m a walker covers "
            f"before touchdown ({need:.1f} m): holding the LAND")


def land_plan(c: LandingConfig, profile: DescentProfile, s: VehicleStatus, judge: float,
              held_s: float) -> tuple[float, DescentProfile | None]:
    """The height (m) of the LAND over a zone judged at ``judge``, and the descent committed there
    (``committed_profile``) where the footprint guarantees at that height, else None: the LAND at
    ``descent.land_height``, as for a narrow camera. ``held_s``: how long the LAND has been held
    at the commit height for people within reach (``reach_wait``). Past the time to touchdown from
    there (at most ``calm_wait_s``), the landing goes on as a narrow camera's would: anybody seen
    within reach who headed for the point has come within r0 by then (and the zone is lost), and
    people who stay near, a crowd round a small lawn, are no reason to give up a zone the narrow
    camera lands in: they do not all head for it."""
    base = land_height(c, judge)
    fast = committed_profile(c, profile, s)
    h = commit_height(c, fast, base, judge)
    if h is None or held_s > min(c.calm_wait_s, fast.time_to_touchdown(h)):
        return base, None
    return h, fast


class Waits:
    """How long the vehicle has waited over a zone before its LAND, for each reason (``calm``,
    ``reach``): the wait for one zone runs on while the reason lasts, and restarts for another zone
    (a zone flown to again keeps its wait, so people passing near it keep counting)."""

    def __init__(self) -> None:
        self._since: dict[str, tuple[int, float]] = {}  # reason: (zone id, since when, s)

    def begin(self, kind: str, zone_id: int, now: float) -> bool:
        """Whether a wait for ``kind`` over ``zone_id`` begins at ``now`` (none was running for it)."""
        since = self._since.get(kind)
        if since is not None and since[0] == zone_id:
            return False
        self._since[kind] = (zone_id, now)
        return True

    def waited(self, kind: str, zone_id: int, now: float) -> float:
        """Seconds the wait for ``kind`` over ``zone_id`` has run at ``now`` (0 when none runs for it)."""
        since = self._since.get(kind)
        return 0.0 if since is None or since[0] != zone_id else now - since[1]
