"""The landing controller's settings (``LandingConfig``): metres above home, seconds, counts.

Each field says what it sets and why; the module each serves says how it is used (``planner``
which zone, ``ground`` whether the ground under the vehicle is fit, ``aim`` where in the zone,
``descent`` the levels and the last metres, ``search`` the search, ``obedience`` the watch over
the vehicle). The settings are checked here, once, when they are made.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from companion.control.obedience import ObedienceConfig
from companion.control.planner import PlannerConfig
from companion.control.touchdown import DescentProfile
from companion.invariant import NO_VALUE, require

#: ``place_lookback_s``: the landing point moves to the farthest point from where people were
#: seen only when that is this much farther from them (m) than the present point: a point that
#: moves for every tenth of a metre is a vehicle that never settles over it.
PLACE_GAIN_M = 0.5
#: ``land_agl_m`` may not be lower than this (m): downward rangefinders read from 0.2-0.3 m, and
#: the autopilot's LAND needs a little height to settle its descent before the ground.
LAND_AGL_MIN_M = 0.5
#: The rangefinder's height within this of ``land_agl_m`` (m) counts as there: the LAND then.
LAND_AGL_REACHED_M = 0.2


@dataclass(frozen=True)
class LandingConfig:
    """Controller settings: metres above home, seconds, counts. See the module docstring."""

    planner: PlannerConfig = field(default_factory=PlannerConfig)
    select_timeout_s: float = 10.0
    #: With nothing in view that could become a zone (no confirmed zone of at least ``r0_m``) on
    #: any frame since the trigger, the search starts this long after the trigger (s) instead of
    #: at ``select_timeout_s`` (0 = not earlier). Meanwhile the autopilot's failsafe is in charge
    #: and, landing, takes the vehicle down over the crowd: each second of waiting costs about a
    #: metre of height and of view, which the search then climbs back.
    select_empty_s: float = 0.0
    hold_timeout_s: float = 15.0
    arrive_radius_m: float = 1.0
    descend_alt_m: float = 10.0
    descend_step_m: float = 3.0
    alt_tolerance_m: float = 0.5
    land_abort_above_m: float = 3.5
    hold_height_m: float = 15.0
    max_takeover_s: float = 90.0
    max_pose_age_s: float = 0.25
    state_timeout_s: float = 1.0
    pose_timeout_s: float = 2.0
    max_refusals: int = 3
    lose_after_frames: int = 2
    handback_action: str = "LAND"
    external_modes: tuple[str, ...] = ("GUIDED", "OFFBOARD")
    retarget_min_move_m: float = 0.3
    refresh_s: float = 1.0
    search_climb_m: float = 5.0
    max_alt_m: float = 120.0
    ceiling_margin_m: float = 1.0
    obedience: ObedienceConfig = field(default_factory=ObedienceConfig)
    #: How fast the vehicle will come down (the configured speeds until the autopilot's own
    #: parameters are read, ``LandingController.use_autopilot_speeds``).
    descent: DescentProfile = field(default_factory=DescentProfile)
    #: Above this height over the ground (m) people would look smaller than the density model
    #: reliably sees (``person_trust_height``): there the vehicle approaches its candidate at this
    #: height at most, and judges it (LAND) only below it. inf: no limit known.
    trust_height_m: float = math.inf
    #: Search (see the module docstring): at most this long (s; 0 = no search, hand back at the
    #: SELECT/HOLD timeouts), no further than ``search_radius_m`` from where it starts, and only
    #: while the battery (when it says) has ``search_reserve_s`` more than the landing needs.
    search_s: float = 45.0
    search_radius_m: float = 40.0
    search_reserve_s: float = 30.0
    #: The camera's footprint: ground radius it sees all round per metre of height above the head
    #: plane (``Intrinsics.seen_ratio``, through the lens and its trusted cone; 0.524 for the
    #: 70-degree pinhole). It spaces the search's legs, raises the judging height of a narrow lens
    #: and gives a wide one its commit height (``descent.judging_height``, ``commit``).
    view_ratio: float = 0.5
    #: With ``planner.min_calm_s`` > 0: over the zone, low enough to LAND, the vehicle waits at
    #: most this long (s) for the ground under it to be calm; then the zone is given up for the
    #: rest of the takeover (people keep passing near it) and another is chosen.
    calm_wait_s: float = 15.0
    #: The height (m above the ground) at which the autopilot's LAND takes over. 0: at
    #: ``descend_alt_m``, as the paper's sequence does. Lower: once the zone is judged at
    #: ``descend_alt_m`` (calm, the walkers), the companion's own stepped descent goes on over it
    #: down to this height, every frame re-checking the ground under the vehicle and sending it
    #: back to HOLD when somebody is seen within r0; only then the LAND. The autopilot's LAND is
    #: slow (ArduPilot 0.5 m/s, PX4 0.7 m/s) against its guided descent (1.5 m/s), and the time
    #: to touchdown is what a walker has to reach the landing point (``touchdown``).
    land_alt_m: float = 0.0
    #: With a fresh downward rangefinder (``VehicleStatus.agl``), the LAND commanded at
    #: ``land_alt_m`` is first the companion's own descent (GUIDED/OFFBOARD, the descent's speed,
    #: straight down over the landing point) to this height above the ground the rangefinder
    #: measures, and the autopilot's LAND only there (m; 0 = off: the LAND at ``land_alt_m``, as
    #: without a rangefinder). It is the same committed end, flown three times faster than
    #: ArduPilot's LAND (1.5 against 0.5 m/s): the time a walker has to reach the point is shorter
    #: (docs/design.md, "The last metres by the rangefinder"). Without a fresh rangefinder, or
    #: when it goes stale or out of range on the way, the LAND is commanded at once.
    land_agl_m: float = 0.0
    #: Place the landing point inside the zone where the ground is farthest from anybody the
    #: risk map saw within this many seconds (0 = off: the zone's centre when chosen), and move it
    #: there again while approaching and before the zone is judged, whenever the farthest point
    #: lies ``PLACE_GAIN_M`` farther from them than the present one. A zone's centre is the point
    #: farthest from the people of one frame: a circle spanning a lawn and a momentary gap of the
    #: crowd beside it has its centre at the lawn's edge, where walkers go round; what the map
    #: saw over the last seconds shows where they go (docs/design.md, "Where people walked").
    place_lookback_s: float = 0.0

    def __post_init__(self) -> None:
        # The one place these rules live: the settings (companion.config) build this object to
        # check a configuration, and name the key of a field refused here (FieldError).
        def need(ok: bool, name: str, problem: str, refs: tuple[str, ...] = (), show: bool = True) -> None:
            require(ok, "controller", name, problem, getattr(self, name) if show else NO_VALUE, refs)

        need(self.handback_action in ("LAND", "RTL"), "handback_action", "must be 'LAND' or 'RTL'")
        for name in ("select_timeout_s", "hold_timeout_s", "arrive_radius_m", "descend_alt_m", "descend_step_m",
                     "hold_height_m", "max_takeover_s", "max_alt_m", "calm_wait_s",
                     "max_pose_age_s", "state_timeout_s", "pose_timeout_s"):
            value = getattr(self, name)
            need(math.isfinite(value) and value > 0, name, "must be > 0")
        for name in ("search_s", "search_radius_m", "search_reserve_s", "land_alt_m", "select_empty_s",
                     "place_lookback_s"):
            value = getattr(self, name)
            need(math.isfinite(value) and value >= 0, name, "must be >= 0")
        need(math.isfinite(self.land_agl_m) and self.land_agl_m >= 0, "land_agl_m", "must be >= 0 (0: off)")
        need(self.land_alt_m <= self.descend_alt_m, "land_alt_m",
             f"({self.land_alt_m:g} m) must not be above {{descend_alt_m}} ({self.descend_alt_m:g} m), where the "
             "zone is judged before it; set it at or below that (0: the LAND at {descend_alt_m})",
             refs=("descend_alt_m",), show=False)
        lands_at = self.land_alt_m or self.descend_alt_m
        need(not self.land_agl_m or LAND_AGL_MIN_M <= self.land_agl_m < lands_at, "land_agl_m",
             f"({self.land_agl_m:g} m) must be 0 (off) or from {LAND_AGL_MIN_M:g} m up to below the height "
             f"where the LAND is commanded ({{land_alt_m}}, {lands_at:g} m): the companion's descent goes on "
             "below that, by the rangefinder, to it", refs=("land_alt_m",), show=False)
        need(math.isfinite(self.view_ratio) and self.view_ratio > 0, "view_ratio", "must be > 0")
        need(self.trust_height_m > 0, "trust_height_m", "must be > 0 m (inf: no limit)")  # NaN too
        need(self.max_refusals >= 1, "max_refusals", "must be >= 1")
        need(self.lose_after_frames >= 1, "lose_after_frames", "must be >= 1")
        need(math.isfinite(self.ceiling_margin_m) and self.ceiling_margin_m >= 0, "ceiling_margin_m", "must be >= 0")
        need(math.isfinite(self.search_climb_m) and self.search_climb_m >= self.ceiling_margin_m, "search_climb_m",
             f"must be >= {{ceiling_margin_m}} ({self.ceiling_margin_m:g} m)", refs=("ceiling_margin_m",))
