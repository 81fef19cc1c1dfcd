"""The landing controller: a state machine driven by explicit inputs, returning commands to execute.

Phases::

    MONITOR --trigger--> SELECT --eligible zone--> APPROACH --over it--> DESCEND --low enough--> LAND
       LAND --on ground / disarmed--> LANDED
    APPROACH/DESCEND/LAND --zone lost--> APPROACH (another eligible zone) or HOLD
    HOLD/SEARCH --eligible zone--> APPROACH
    SELECT/HOLD timeout --> SEARCH (with ``search_s`` 0: HANDBACK)
    SEARCH out of time, radius or battery, stale pose, repeated refusals --> HANDBACK (the
        autopilot's LAND or RTL)
    APPROACH/DESCEND/HOLD/LAND/SEARCH --pilot changes mode--> HANDBACK (without a command)

Inputs (times are monotonic seconds):

- ``on_trigger(trigger)``: a failsafe ``Trigger``; the only way out of MONITOR.
- ``on_frame(t, tracks, pose, below, spot)``: the zone tracks after the frame captured at ``t``,
  the pose the pipeline used for it, and optionally the ground it saw under the camera
  (``GroundBelow``) and where the risk map puts the landing point (``spot_request``). A frame
  whose pose is missing, not finite or further than
  ``max_pose_age_s`` from ``t``, or a frame older than ``zone_max_age_s``, is ignored: no decision
  is ever made on a zone that was not seen with a fresh pose.
- ``on_state(status)``: where the vehicle is now (``VehicleStatus``), its mode, armed, on ground.
- ``tick(now)``: timeouts.
- ``on_command_result(command, error)``: what became of a command the runner executed.

Each returns the list of ``Command``s to execute now; ``pop_events()`` gives the typed events
(``companion.control.events``: every phase change, target, hold and handback, with its time); the
service records them and sends their text as STATUSTEXT.

Flying: every target altitude comes from the altitude at the trigger and the descent plan, never
from "where the vehicle is now minus a step" (against the real PX4 such targets, read a few metres
too high, ratcheted the vehicle up to 220 m). The plan keeps one planned altitude, the *level*:
the altitude at the trigger (lower if the vehicle came down before the companion took over, never
below ``descend_alt_m`` above the ground). The vehicle first flies level to the zone, then descends
one ``descend_step_m`` at a time: the level moves one step down only when the vehicle has reached
it over the zone, re-checking the zone at every frame, so a lost zone stops the descent within one
step. The landing point (the *aim*) is the zone's centre when chosen, and it stays put while the
zone still holds ``r0_m + radius_margin_m`` around it (a zone bounded by the view: while the view
still shows ``MIN_VIEW_M`` around it): such a zone moves with the camera, and following its centre
would chase it across uniform free ground for ever. At ``descend_alt_m`` above home over the zone
the zone is judged (calm ground) and, with ``land_alt_m`` set below it,
the same stepped descent goes on over the judged zone to ``land_alt_m``, every frame re-checking
the ground under the vehicle as above (a lost zone: HOLD). There it
commands the autopilot's LAND (Copter's LAND and PX4's AUTO.LAND both descend vertically where the vehicle is). The same
sequence is used for both autopilots so that the descent down to ``descend_alt_m`` is always
re-checked. With ``land_agl_m`` and a fresh downward rangefinder, that LAND is first the
companion's own descent, straight down at the descent's speed, to ``land_agl_m`` above the ground
the rangefinder measures, and the autopilot's LAND only there (at once if the rangefinder goes
stale or out of range, or the ground comes first). During LAND the zone is still watched: above ``land_abort_above_m`` a lost zone sends
the vehicle back to HOLD; below it the landing is committed. It is committed too when the zone,
last seen all free in a view smaller than ``BLIND_VIEW_M``, drops out of the tracks: the camera
has come too low to confirm anything (seen occupied, it is lost as before). HOLD is a position
target at the vehicle's own position, so the autopilot stays in GUIDED/OFFBOARD and can resume.
A zone seen with less than ``r0_m`` free is lost only once ``lose_after_frames`` frames in a row
see it so (one frame's false detection must not throw a landing away); gone from the tracks or
stale, it is lost at once.

Search: with no zone in view at the SELECT/HOLD timeout, the vehicle climbs to the ceiling over
where it is and flies an ``expanding_square`` (legs 1.5 view radii apart, hovering at each corner
while the tracker looks), flying first over free ground glimpsed at the edge of the view; any zone that becomes eligible is
flown to. It hands back after ``search_s``, at ``search_radius_m``, or
when the battery's time left (``VehicleStatus.battery_s``) no longer covers the landing plus
``search_reserve_s``.

Never fly away: no target is ever above the *ceiling* less ``ceiling_margin_m``; the ceiling is the
altitude at the trigger plus ``search_climb_m``, and never above ``max_alt_m`` above home. While the
vehicle is in GUIDED/OFFBOARD an ``ObedienceMonitor`` checks that it goes where it is told; a vehicle
that climbs against its target, sinks below it, moves away from it, or rises above the ceiling is
handed back to the autopilot's LAND at once, with the reason as an event.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

from companion.control.commands import Command, Goto, Handback, Land, PositionTarget
from companion.control.events import Event, HandedBack, Holding, Note, Phase, PhaseChanged, TargetChosen
from companion.control.obedience import ObedienceConfig, ObedienceMonitor, Sample
from companion.control.planner import MIN_VIEW_M, PlannerConfig, ZoneCheck, ZonePlanner, seen_all_free
from companion.control.touchdown import DescentProfile, by_rangefinder
from companion.control.trigger import Trigger
from companion.geometry.camera import Pose
from companion.geometry.geodesy import GeoPoint, geo_from_ned
from companion.pipeline.circles import GroundBelow
from companion.pipeline.riskmap import Spot, SpotRequest
from companion.pipeline.tracker import Track

log = logging.getLogger(__name__)


#: A view radius (m) under which a zone that drops out of view during LAND commits the landing.
BLIND_VIEW_M = 2 * MIN_VIEW_M
#: ``place_lookback_s``: the landing point moves to the farthest point from where people were
#: seen only when that is this much farther from them (m) than the present point: a point that
#: moves for every tenth of a metre is a vehicle that never settles over it.
PLACE_GAIN_M = 0.5
#: ``land_agl_m`` may not be lower than this (m): downward rangefinders read from 0.2-0.3 m, and
#: the autopilot's LAND needs a little height to settle its descent before the ground.
LAND_AGL_MIN_M = 0.5
#: The rangefinder's height within this of ``land_agl_m`` (m) counts as there: the LAND then.
LAND_AGL_REACHED_M = 0.2

ACTIVE = frozenset({Phase.SELECT, Phase.APPROACH, Phase.DESCEND, Phase.LAND, Phase.HOLD, Phase.SEARCH})
FLYING = frozenset({Phase.APPROACH, Phase.DESCEND, Phase.LAND, Phase.HOLD, Phase.SEARCH})


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
    #: Ground radius the camera sees per metre of height above the head plane (the tangent of half
    #: its narrower field of view): the search's legs are spaced so that their views overlap.
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
        if self.handback_action not in ("LAND", "RTL"):
            raise ValueError(f"controller handback_action must be LAND or RTL, not {self.handback_action!r}")
        for name in ("select_timeout_s", "hold_timeout_s", "arrive_radius_m", "descend_alt_m", "descend_step_m",
                     "hold_height_m", "max_takeover_s", "max_alt_m", "calm_wait_s",
                     "max_pose_age_s", "state_timeout_s", "pose_timeout_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"controller {name} must be a positive number, not {value!r}")
        for name in ("search_s", "search_radius_m", "search_reserve_s", "land_alt_m", "select_empty_s",
                     "place_lookback_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"controller {name} must be a number >= 0, not {value!r}")
        if not (math.isfinite(self.land_agl_m) and (self.land_agl_m == 0 or LAND_AGL_MIN_M <= self.land_agl_m)):
            raise ValueError(f"controller land_agl_m must be 0 (off) or at least {LAND_AGL_MIN_M:g} m, "
                             f"not {self.land_agl_m!r}")
        if self.land_agl_m > 0 and self.land_agl_m >= (self.land_alt_m or self.descend_alt_m):
            raise ValueError(f"controller land_agl_m ({self.land_agl_m:g} m) must be below the height where the "
                             f"LAND is commanded ({self.land_alt_m or self.descend_alt_m:g} m)")
        if self.land_alt_m > self.descend_alt_m:
            raise ValueError(f"controller land_alt_m ({self.land_alt_m:g} m) must not be above "
                             f"descend_alt_m ({self.descend_alt_m:g} m): the zone is judged there first")
        if not (math.isfinite(self.view_ratio) and self.view_ratio > 0):
            raise ValueError(f"controller view_ratio must be > 0, not {self.view_ratio!r}")
        if not (self.trust_height_m > 0):  # NaN too
            raise ValueError(f"controller trust_height_m must be > 0 m (inf: no limit), not {self.trust_height_m!r}")
        if self.max_refusals < 1:
            raise ValueError("controller max_refusals must be >= 1")
        if self.lose_after_frames < 1:
            raise ValueError(f"controller lose_after_frames must be >= 1, not {self.lose_after_frames!r}")
        if not (math.isfinite(self.ceiling_margin_m) and self.ceiling_margin_m >= 0):
            raise ValueError(f"controller ceiling_margin_m must be >= 0, not {self.ceiling_margin_m!r}")
        if not (math.isfinite(self.search_climb_m) and self.search_climb_m >= self.ceiling_margin_m):
            raise ValueError(f"controller search_climb_m must be >= ceiling_margin_m "
                             f"({self.ceiling_margin_m:g} m), not {self.search_climb_m!r}")


@dataclass(frozen=True)
class VehicleStatus:
    """The vehicle now: ``t`` when its position was sampled (our monotonic s); NED metres from
    home; ``home`` WGS84.

    ``mode`` is the flavour's mode name; ``on_ground``/``armed`` None when unknown; ``agl`` metres
    above ground from a fresh rangefinder, None without one (then heights are above home);
    ``vn``/``ve``/``vd`` velocity in NED m/s; ``latency_s`` the link's one-way latency as measured
    (TIMESYNC), 0 when not measured; ``battery_s`` the flight time the battery has left as the
    autopilot estimates it (s), None when it does not say.
    """

    t: float
    north: float
    east: float
    down: float
    home: GeoPoint
    mode: str | None = None
    armed: bool | None = None
    on_ground: bool | None = None
    agl: float | None = None
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    latency_s: float = 0.0
    battery_s: float | None = None

    @property
    def alt(self) -> float:
        """Metres above home."""
        return -self.down

    @property
    def measured_agl(self) -> float | None:
        """Metres above the ground below as the rangefinder measures it; None without a usable
        reading (none fresh, or not a number)."""
        return self.agl if self.agl is not None and math.isfinite(self.agl) else None

    @property
    def height(self) -> float:
        """Metres above the ground below: a fresh downward rangefinder if any, else above home."""
        agl = self.measured_agl
        return self.alt if agl is None else agl


class LandingController:
    """See the module docstring. Pure: no I/O, no clock; every time comes in through an input."""

    def __init__(self, config: LandingConfig | None = None) -> None:
        self.config = config or LandingConfig()
        self.planner = ZonePlanner(self.config.planner)
        self.phase = Phase.MONITOR
        self.trigger: Trigger | None = None
        self.target: Track | None = None
        self.now = -math.inf
        self.status: VehicleStatus | None = None
        self.tracks: list[Track] = []
        #: The ground under the camera on the latest usable frame (None: the frame did not say).
        self.below: GroundBelow | None = None
        self.last_valid_frame_t: float | None = None
        self.frames_ignored = 0
        self.refusals = 0
        self._phase_t = 0.0
        self._last_goto: Goto | None = None
        self._last_goto_t = -math.inf
        self._mode_confirmed = False
        self._events: list[Event] = []
        self.trigger_alt: float | None = None  # metres above home at the trigger
        self.ceiling_m: float | None = None  # metres above home; see the module docstring
        self._level = math.nan  # the planned altitude (m above home)
        self._aim: tuple[float, float] | None = None  # landing point, north/east metres
        self._blind = False  # in LAND, the zone went out of view: committed
        # In LAND, the companion's own descent to land_agl_m by the rangefinder: its target
        # (north, east, m above home; fixed when it starts) until the autopilot's LAND is
        # commanded; else None.
        self._low_to: tuple[float, float, float] | None = None
        self._search: list[tuple[float, float]] = []  # waypoints left (north, east)
        self._search_t = math.nan  # when the search started
        self._dwell_until = -math.inf  # hovering at a reached search waypoint until then
        self._investigated: set[int] = set()  # zones the search flew over that never qualified
        self._restless: set[int] = set()  # zones given up because they never became calm
        self._calm_wait: tuple[int, float] | None = None  # (zone id, since when) waiting for calm
        # The zone judged at the judging height (calm, walkers) whose descent goes on below it,
        # under the companion's control, to land_alt_m: below the judging height the calm disc no
        # longer fits in the view, so the judgement is kept, not asked again.
        self._judged: int | None = None
        # The target chosen as a steady zone (``_approach``), or None.
        self._steady_target: int | None = None
        self._over_lead: tuple[int, float] | None = None  # (zone id, since when) the search hovers over
        self._failing = 0  # consecutive frames on which the target failed its check (see _follow)
        #: Where the risk map would put the landing point (latest frame's ``spot``; ``place_lookback_s``).
        self.spot: Spot | None = None
        self.placements = 0  # landing points moved away from where people were seen (place_lookback_s)
        self._candidate_seen = False  # a zone of at least r0 seen since the trigger (select_empty_s)
        self.failures_tolerated = 0  # single failing frames that did not lose a zone, since start
        self.obedience = ObedienceMonitor(self.config.obedience)
        self.descent = self.config.descent

    # -- inputs ------------------------------------------------------------------------------

    def on_trigger(self, trigger: Trigger) -> list[Command]:
        self._advance(trigger.t)
        if self.phase != Phase.MONITOR:
            return []
        self.trigger = trigger
        self._candidate_seen = self._candidate_in(self.tracks)
        self._set_phase(Phase.SELECT, f"trigger: {trigger.reason}; looking for a landing zone", warning=True)
        if self._status_fresh():
            refused = self._set_ceiling()
            if refused:
                return refused
        return self._select()

    def on_state(self, status: VehicleStatus) -> list[Command]:
        if not all(math.isfinite(v) for v in (status.t, status.north, status.east, status.down)):
            return []  # a NaN position is no position
        self._advance(status.t)
        self.status = status
        if self.phase not in ACTIVE:
            return []
        if self.ceiling_m is None:
            refused = self._set_ceiling()
            if refused:
                return refused
        if self.phase == Phase.LAND and self._low_to is not None and status.on_ground and status.armed is not False:
            # The ground came before land_agl_m (a slope, a rangefinder reading long): in
            # GUIDED/OFFBOARD the autopilot would sit on it armed; its LAND finishes and disarms.
            return self._low_land(f"on the ground at {status.height:.1f} m by the rangefinder")
        if self.phase == Phase.LAND and (status.on_ground or status.armed is False):
            self._set_phase(Phase.LANDED, f"landed in zone {self._zone_id()}",
                            zone_id=self._zone_id_or_none())
            return []
        if self.phase in FLYING and status.armed is False:
            # Disarmed outside our LAND: PX4's land detector disarms in OFFBOARD too (its heartbeat
            # still says OFFBOARD). Nothing more to command to a vehicle with its motors off.
            if status.on_ground:
                self._set_phase(Phase.LANDED, f"vehicle on the ground and disarmed (zone {self._zone_id()})",
                                zone_id=self._zone_id_or_none())
            else:
                self.target = None
                self._set_phase(Phase.HANDBACK, "vehicle disarmed in the air: companion stops", warning=True,
                                event=HandedBack, reason="vehicle disarmed in the air")
            return []
        if self.phase in FLYING and self.ceiling_m is not None and status.alt > self.ceiling_m:
            return self._handback(f"vehicle at {status.alt:.1f} m, above the {self.ceiling_m:.1f} m ceiling",
                                  action="LAND")
        obeying = self._check_obedience(status)
        if obeying:
            return obeying
        if self.phase in FLYING and status.mode is not None:
            allowed = (*self.config.external_modes, "LAND")
            if status.mode in allowed:
                self._mode_confirmed = True
            elif self._mode_confirmed:
                # Someone else (pilot, GCS, the autopilot's own failsafe) took over: stop at once.
                self._set_phase(Phase.HANDBACK, f"mode changed to {status.mode} by someone else: companion stops",
                                warning=True, event=HandedBack, reason=f"mode changed to {status.mode}")
                return []
        if self.phase == Phase.LAND and self._low_to is not None:
            return self._low_step(status)
        return []

    def on_frame(self, t: float, tracks: Sequence[Track], pose: Pose | None,
                 below: GroundBelow | None = None, spot: Spot | None = None) -> list[Command]:
        self._advance(t)
        if not self._frame_usable(t, pose):
            self.frames_ignored += 1
            return []
        self.last_valid_frame_t = t
        self.tracks = list(tracks)
        ok = below is not None and all(math.isfinite(v) for v in (below.x, below.y, below.r, below.r_view))
        self.below = below if ok else None
        ok = spot is not None and all(math.isfinite(v) for v in (spot.x, spot.y, spot.clear_m))
        self.spot = spot if ok else None
        if self.phase == Phase.SELECT and not self._candidate_seen:
            self._candidate_seen = self._candidate_in(self.tracks)
        if self.phase in (Phase.SELECT, Phase.HOLD, Phase.SEARCH):
            found = self._select()
            if found or self.phase == Phase.SELECT:
                return found
            if self.phase == Phase.HOLD:
                return []  # hover where the hold began until a zone or the timeout
            return self._search_step()
        if self.phase in (Phase.APPROACH, Phase.DESCEND, Phase.LAND):
            return self._follow()
        return []

    def _candidate_in(self, tracks: Sequence[Track]) -> bool:
        """Whether any zone confirmed by the latest frame is at least ``r0_m`` across (``select_empty_s``):
        something that may still become a landing zone, worth the SELECT's wait."""
        r0 = self.config.planner.r0_m
        return any(t.misses == 0 and math.isfinite(t.r) and t.r >= r0 for t in tracks)

    def spot_request(self, tracks: Sequence[Track]) -> SpotRequest | None:
        """Where the landing point may go on this frame (``place_lookback_s``), for the pipeline's
        ``landing_spot``, asked with the frame's ``tracks`` before ``on_frame``: while approaching
        the target or descending to judge it (not once judged, nor in LAND), within the part of
        the zone whose landing points keep the room the zone must hold around them. None
        otherwise."""
        if self.target is None or not self._placing(self.target.id):
            return None
        track = next((t for t in tracks if t.id == self.target.id and t.misses == 0), None)
        if track is None or not all(math.isfinite(v) for v in (track.x, track.y, track.r)):
            return None
        radius = track.r - self._room(track)
        if radius <= 0:
            return None
        return SpotRequest(track.x, track.y, radius, self.config.place_lookback_s, self._aim_for(track))

    def _placing(self, zone_id: int) -> bool:
        """Whether the landing point over zone ``zone_id`` may still move (``place_lookback_s``):
        approaching it or descending to judge it, not once judged, nor in LAND."""
        return (self.config.place_lookback_s > 0 and self.phase in (Phase.APPROACH, Phase.DESCEND)
                and self._judged != zone_id)

    def _room(self, track: Track) -> float:
        """How much of the zone (m) must stay free around its landing point for the point to stay
        put: r0 plus the margin, or ``MIN_VIEW_M`` for a zone bounded by the view (see ``_follow``)."""
        p = self.config.planner
        return MIN_VIEW_M if seen_all_free(track) else p.large_r_m

    def _aim_for(self, track: Track) -> tuple[float, float]:
        """The landing point over ``track`` now: the present one while the zone holds ``_room``
        around it, else the zone's centre."""
        aim = self._aim
        if aim is None or track.r - math.hypot(aim[0] - track.x, aim[1] - track.y) < self._room(track):
            return (track.x, track.y)
        return aim

    def _place(self, track: Track, aim: tuple[float, float]) -> tuple[float, float]:
        """With ``place_lookback_s``: the risk map's spot (``self.spot``) instead of ``aim`` when it
        is ``PLACE_GAIN_M`` farther from where people were seen and inside the part of ``track``
        that keeps its room around it; says so (a Note). Else ``aim``."""
        spot = self.spot
        if spot is None or not self._placing(track.id):
            return aim
        was = spot.aim_clear_m if math.isfinite(spot.aim_clear_m) else 0.0
        if spot.clear_m < was + PLACE_GAIN_M:
            return aim
        if track.r - math.hypot(spot.x - track.x, spot.y - track.y) < self._room(track) - 1e-6:
            return aim  # another frame's zone: not this one's room
        moved = math.hypot(spot.x - aim[0], spot.y - aim[1])
        self.placements += 1
        self._event(f"zone {track.id}: landing point moved {moved:.1f} m, {spot.clear_m:.1f} m from where people "
                    f"were seen in the last {self.config.place_lookback_s:g} s (was {was:.1f} m)")
        return (spot.x, spot.y)

    def tick(self, now: float) -> list[Command]:
        self._advance(now)
        c = self.config
        if self.phase not in ACTIVE:
            return []
        if self.phase == Phase.SELECT and c.select_empty_s > 0 and not self._candidate_seen \
                and self.now - self._phase_t > c.select_empty_s:
            return self._start_search(f"nothing in view within {c.select_empty_s:g} s could be a safe zone")
        if self.phase == Phase.SELECT and self.now - self._phase_t > c.select_timeout_s:
            return self._start_search(f"no safe zone confirmed within {c.select_timeout_s:g} s")
        if self.phase == Phase.HOLD and self.now - self._phase_t > c.hold_timeout_s:
            return self._start_search(f"held {c.hold_timeout_s:g} s without a safe zone")
        if self.phase == Phase.SEARCH:
            why = self._search_over()
            if why is not None:
                return self._handback(why)
        # Zones that keep being lost and re-targeted must not keep a vehicle with a failing
        # battery in the air: past this budget the autopilot's own failsafe lands it. In LAND the
        # autopilot is already landing over a confirmed zone; handing back would change nothing
        # but the zone checks (a lost zone still sends it to HOLD, where the budget applies).
        if self.trigger is not None and self.phase != Phase.LAND and \
                self.now - self.trigger.t > c.max_takeover_s:
            return self._handback(f"not landed within {c.max_takeover_s:g} s of the trigger")
        if self.phase in FLYING:
            if self.status is None or self.now - self.status.t > c.pose_timeout_s:
                return self._handback("vehicle position stale")
            seen = self.last_valid_frame_t
            if self.phase != Phase.LAND and (seen is None or self.now - seen > c.pose_timeout_s):
                return self._handback("no frame with a fresh pose")
        return []

    def on_command_result(self, command: Command, error: Exception | None) -> list[Command]:
        if error is None:
            self.refusals = 0
            return []
        self.refusals += 1
        self._event(f"command {type(command).__name__} failed: {error}", warning=True)
        if isinstance(command, Handback):
            return []  # nothing more to try: the autopilot's own failsafe is still armed
        if self.phase in ACTIVE and self.refusals >= self.config.max_refusals:
            return self._handback(f"{self.refusals} commands failed in a row")
        if isinstance(command, Goto):
            self._last_goto = None  # re-send at the next frame
        return []

    def use_autopilot_speeds(self, speeds: dict[str, float], source: str) -> None:
        """Take the autopilot's own descent speeds (m/s by ``DescentProfile`` field, read from its
        parameters) for the time to touchdown; a value that is not a positive number is ignored."""
        known = {k: v for k, v in speeds.items()
                 if k in ("descend_speed_mps", "land_speed_mps") and math.isfinite(v) and v > 0}
        if not known:
            return
        self.descent = replace(self.descent, **known)
        d = self.descent
        self._event(f"descent {d.descend_speed_mps:.1f} m/s, LAND {d.land_speed_mps:.1f} m/s ({source})")

    def _descent_now(self) -> DescentProfile:
        """The descent the vehicle will fly from here: with ``land_agl_m`` and a fresh rangefinder,
        the companion's own descent goes on down to ``land_agl_m`` and the autopilot's LAND is
        that much shorter."""
        s = self.status
        if s is None or s.measured_agl is None:
            return self.descent  # no rangefinder height: the LAND at land_alt_m, as _low_target says
        return by_rangefinder(self.descent, self.config.land_agl_m)

    def touchdown_clearance(self, track: Track) -> float | None:
        """The least clearance (m) ``track`` can have at touchdown if the vehicle came down over it
        now from its present height, with every walker heading for it (``DescentProfile``); None
        without a vehicle position."""
        if self.status is None:
            return None
        value = self._descent_now().clearance_at_touchdown(track.r, self.status.height)
        return round(value, 2) if math.isfinite(value) else None

    def zone_target(self) -> Track | None:
        """The zone the vehicle flies to (after a trigger), or would fly to now (before one): what
        the flight recording, the status line and the ground station call "the target". After
        the flight (LANDED, HANDBACK) there is none."""
        if self.phase in ACTIVE:
            return self.target
        if self.phase != Phase.MONITOR:
            return None
        return self.planner.choose(self.tracks, self.now)

    def pop_events(self) -> list[Event]:
        events, self._events = self._events, []
        return events

    # -- decisions ---------------------------------------------------------------------------

    def _frame_usable(self, t: float, pose: Pose | None) -> bool:
        if pose is None:
            return False
        values = (pose.t, pose.north, pose.east, pose.down, pose.roll, pose.pitch, pose.yaw)
        if not all(math.isfinite(v) for v in values) or abs(pose.t - t) > self.config.max_pose_age_s:
            return False
        return self.now - t <= self.config.planner.zone_max_age_s

    def _status_fresh(self) -> bool:
        return self.status is not None and self.now - self.status.t <= self.config.state_timeout_s

    def _set_ceiling(self) -> list[Command]:
        """Fix the altitude at the trigger and the ceiling from the first status after it."""
        s, c = self.status, self.config
        if s is None or self.trigger is None or self.ceiling_m is not None:
            return []
        self.trigger_alt = s.alt
        self._level = s.alt
        self.ceiling_m = min(s.alt + c.search_climb_m, c.max_alt_m)
        if s.alt > c.max_alt_m:
            return self._handback(f"vehicle at {s.alt:.1f} m, above the {c.max_alt_m:g} m ceiling: "
                                  "not taking over", action="LAND")
        return []

    def _check_obedience(self, status: VehicleStatus) -> list[Command]:
        """Hand back to LAND when the vehicle does not follow our targets (see ``obedience``)."""
        ours = ((self.phase in (Phase.APPROACH, Phase.DESCEND, Phase.HOLD, Phase.SEARCH)
                 or (self.phase == Phase.LAND and self._low_to is not None))
                and status.mode in self.config.external_modes and self._last_goto is not None)
        if not ours:
            self.obedience.disengage()
            return []
        sample = Sample(status.north, status.east, status.alt, status.vn, status.ve, status.vd, status.t)
        if not self.obedience.engaged:
            self.obedience.engage(sample)
            return []
        why = self.obedience.check(sample)
        return [] if why is None else self._handback(why, action="LAND")

    def _cap(self) -> float:
        """The highest altitude a target may have (m above home)."""
        assert self.ceiling_m is not None
        return self.ceiling_m - self.config.ceiling_margin_m

    def _raise_level(self, alt: float) -> None:
        """The planned level, at least ``alt`` (m above home; a terrain floor or the hold height)
        and never above the ceiling's cap."""
        self._level = min(self._cap(), max(self._level, alt))

    def _select(self) -> list[Command]:
        if not self._status_fresh() or self.ceiling_m is None:
            return []
        zone = self.planner.choose(self.tracks, self.now, exclude=tuple(self._restless))
        if zone is None:
            return []
        return self._approach(zone, "landing at")

    def _approach(self, zone: Track, verb: str, lost_id: int | None = None) -> list[Command]:
        s, c = self.status, self.config
        assert s is not None
        self.target = zone
        self._failing = 0
        self._aim = (zone.x, zone.y)
        # Chosen too small for the radius margin, so for its steadiness: its steady watch will
        # stand for the calm disc that does not fit in it (``_over_steady``).
        self._steady_target = zone.id if zone.r < c.planner.large_r_m else None
        if s.alt < self._level - c.alt_tolerance_m:
            self._level = s.alt  # it came down before we took over: do not climb back for nothing
        # Above the height where people look as large as the model reliably sees them, what it
        # calls free is not trusted: approach the candidate no higher than that, and judge it there.
        self._level = min(self._level, s.alt - s.height + c.trust_height_m)
        # Level flight, but never lower than descend_alt_m above the ground below.
        self._raise_level(s.alt - s.height + c.descend_alt_m)
        dist = math.hypot(zone.x - s.north, zone.y - s.east)
        self._set_phase(Phase.APPROACH, f"{verb} zone {zone.id}, {dist:.1f} m away, radius {zone.r:.1f} m",
                        event=TargetChosen, zone_id=zone.id, north=zone.x, east=zone.y, r=zone.r,
                        lost_zone_id=lost_id, touchdown_clearance_m=self.touchdown_clearance(zone),
                        edge=zone.edge or None)
        self._last_goto = None
        return self._goto(zone.x, zone.y, self._level, zone.id)

    def _below_here(self) -> tuple[float, bool] | None:
        """The frame's measure under the camera (``GroundBelow``), carried to where the vehicle is
        now: how far the ground around it is free (m, less how far it moved since the frame), and
        whether everything the camera saw there is free with ``MIN_VIEW_M`` in view. None without
        a measure or a vehicle position."""
        s, below = self.status, self.below
        if s is None or below is None:
            return None
        moved = math.hypot(below.x - s.north, below.y - s.east)
        return below.r - moved, below.view_limited and below.r_view - moved >= MIN_VIEW_M

    def _ground_below_holds(self) -> bool:
        """Over the zone (DESCEND, or LAND above the commit height), whether this frame saw r0
        free around the vehicle, or everything it saw there free (``_below_here``)."""
        s, aim, here = self.status, self._aim, self._below_here()
        if self.phase not in (Phase.DESCEND, Phase.LAND) or s is None or here is None or aim is None \
                or not self._status_fresh():
            return False
        if math.hypot(aim[0] - s.north, aim[1] - s.east) > self.config.arrive_radius_m:
            return False  # not over the landing point: the zone's own track must say
        free, all_free = here
        return free >= self.config.planner.r0_m or all_free

    def _free_below(self, track: Track) -> tuple[float, bool]:
        """How far the ground around the vehicle is free (m), and whether everything the camera
        sees around it is free (the view, not a person, bounds it, and it shows ``MIN_VIEW_M``).

        Two measures, the larger wins (both are lower bounds of the same thing): the zone's radius
        less the vehicle's offset from its centre, and the frame's own measure under the camera
        (``_below_here``). The first alone threw landings away low over view-bounded zones: at
        10 m the view shows about 4 m around the vehicle, the zone's centre sits 1-2 m off it,
        away from the people at one side, and ``r - offset`` came out at 1.6-1.9 m with the
        nearest person 4 m away."""
        s = self.status
        assert s is not None
        free = track.r - math.hypot(track.x - s.north, track.y - s.east)
        here = self._below_here()
        if here is None:
            return free, False
        return max(free, here[0]), here[1]

    def _follow(self) -> list[Command]:
        assert self.target is not None
        verdict, track, why = self.planner.check_target(self.target.id, self.tracks, self.now)
        if verdict == ZoneCheck.LOST and track is None and self._ground_below_holds():
            # Low over the zone the tracker may drop it (the view, smaller than r0 plus the
            # margin, makes no proposal of it), while this frame sees r0 free straight under the
            # vehicle: that ground, not the zone's track, is where it comes down.
            verdict, track, why = ZoneCheck.OK, self.target, ""
        if verdict == ZoneCheck.LOST:
            # Gone from the tracks, or unconfirmed for zone_max_age_s: that already took time.
            if self._out_of_view(track):
                return []
            return self._lost(why)
        if verdict == ZoneCheck.UNCONFIRMED or track is None or not self._status_fresh():
            return []  # no new command toward a zone this frame did not confirm
        s = self.status
        assert s is not None
        c = self.config
        if verdict == ZoneCheck.OK and self.phase in (Phase.DESCEND, Phase.LAND) and not seen_all_free(track):
            # Over the zone the vehicle lands where it is, not at the zone's centre: what must be
            # free is r0 around the vehicle.
            free, all_free = self._free_below(track)
            if free < c.planner.r0_m and not all_free:
                verdict, why = ZoneCheck.SMALL, f"{free:.1f} m free around the vehicle < r0 {c.planner.r0_m:g} m"
        if verdict == ZoneCheck.SMALL:
            # A zone seen too small is lost only when ``lose_after_frames`` frames in a row say so:
            # the network marks a patch of ground as a person in one frame now and then (at 10 m
            # about one frame in thirty, on the simulator's ground), and one such frame used to
            # throw a LAND over a free circle back to HOLD every few seconds. A person who walks
            # in is seen on every frame: the reaction comes one frame later (0.1 s at 10 Hz, 0.15
            # m at walking pace). No command goes toward the zone meanwhile.
            self._failing += 1
            if self._failing < c.lose_after_frames:
                self.failures_tolerated += 1
                return []
            return self._lost(why)
        self._failing = 0
        self.target = track
        # The landing point stays where it is while the zone still holds r0 plus the margin around
        # it; only then does it move to the zone's new centre (see the module docstring). A zone
        # bounded by the view (everything seen is free) keeps it while the view still shows
        # MIN_VIEW_M around it: low down the view is smaller than r0 plus the margin.
        aim = self._aim = self._aim_for(track)
        aim = self._aim = self._place(track, aim)
        dist = math.hypot(aim[0] - s.north, aim[1] - s.east)
        if self.phase == Phase.APPROACH:
            if dist > c.arrive_radius_m:
                return self._goto(aim[0], aim[1], self._level, track.id)
            self._set_phase(Phase.DESCEND, f"over zone {track.id}, descending from {s.alt:.1f} m", zone_id=track.id)
        if self.phase == Phase.DESCEND:
            judge = min(c.descend_alt_m, c.trust_height_m)
            low = s.height <= judge + c.alt_tolerance_m
            over = dist <= c.arrive_radius_m and low
            judged = self._judged == track.id
            if over and not s.on_ground and not judged and not self._calm_below(track):
                if self._calm_wait is not None and self.now - self._calm_wait[1] > c.calm_wait_s:
                    self._restless.add(track.id)
                    return self._lost(f"not calm after {c.calm_wait_s:g} s over it: people keep passing near it")
                return self._goto(aim[0], aim[1], self._level, track.id)
            land_at = min(c.land_alt_m, judge) if c.land_alt_m > 0 else judge
            if not s.on_ground and over and s.height > land_at + c.alt_tolerance_m:
                # Judged (calm): the companion's own descent goes on to land_at by the plan's
                # steps below, the ground under the vehicle re-checked every frame above (a person
                # within r0 sends it back to HOLD).
                if not judged:
                    judged, self._judged = True, track.id
                    calm = self._calm_here()
                    measured = [f"calm {calm:.1f} s"] if math.isfinite(calm) else []
                    if self._over_steady(track):
                        measured.append(f"steady {track.steady_s:.1f} s")
                    self._event(f"zone {track.id} judged at {s.height:.1f} m"
                                + (f" ({', '.join(measured)})" if measured else "")
                                + f": descending over it to {land_at:g} m before the LAND")
            elif s.on_ground or over:
                # on_ground: the ground came early (a slope); the autopilot's LAND finishes and disarms.
                calm = self._calm_here()
                low_alt = None if s.on_ground else self._low_target(s)
                how = "" if low_alt is None else f", first down to {c.land_agl_m:g} m by the rangefinder"
                self._set_phase(Phase.LAND, f"LAND over zone {track.id} at {s.height:.1f} m, radius {track.r:.1f} m"
                                + how, zone_id=track.id, touchdown_clearance_m=self.touchdown_clearance(track),
                                calm_s=round(calm, 1) if math.isfinite(calm) else None)
                if low_alt is None:
                    return [Land()]
                # Straight down over the landing point as it is now: a zone bounded by the view
                # moves with the camera, and the committed descent must not chase it.
                self._low_to = (aim[0], aim[1], low_alt)
                self._last_goto = None
                return self._goto(aim[0], aim[1], low_alt, track.id)
            # The plan's next step: one step down once the vehicle has reached the current level
            # over the zone, so a lost zone never leaves the vehicle committed to a long descent.
            # Never below descend_alt_m above the ground under the vehicle (a rangefinder may show
            # the ground rising): the plan's floor, from terrain, not from the vehicle's altitude;
            # once the zone is judged, land_at (off the point, it re-centres without climbing).
            floor = s.alt - s.height + (land_at if judged else judge)
            self._raise_level(floor)
            if dist <= 2 * c.arrive_radius_m and s.alt <= self._level + c.alt_tolerance_m:
                self._level = max(self._level - c.descend_step_m, floor)
            return self._goto(aim[0], aim[1], self._level, track.id)
        return []

    def _low_target(self, s: VehicleStatus) -> float | None:
        """Where the companion's own descent to ``land_agl_m`` goes (m above home: the ground the
        rangefinder measures under the vehicle, plus ``land_agl_m``), or None when the LAND is to
        be commanded now: the setting off, no fresh rangefinder, or already that low. The target
        is fixed here, once, from one reading at the LAND height (a few metres at most), so no
        later reading can move it."""
        c, agl = self.config, s.measured_agl
        if c.land_agl_m <= 0 or agl is None or agl <= c.land_agl_m + LAND_AGL_REACHED_M:
            return None
        return s.alt - agl + c.land_agl_m

    def _low_step(self, s: VehicleStatus) -> list[Command]:
        """The companion's own committed descent to ``land_agl_m``, on every vehicle status: the
        autopilot's LAND once the rangefinder says the vehicle is there, or at once when it no
        longer gives a height (stale or out of range); meanwhile the target, re-sent as any other."""
        assert self._low_to is not None
        agl = s.measured_agl
        if agl is None:
            return self._low_land(f"no rangefinder height at {s.height:.1f} m above home")
        north, east, alt = self._low_to
        if agl <= self.config.land_agl_m + LAND_AGL_REACHED_M or s.alt <= alt + LAND_AGL_REACHED_M:
            return self._low_land(f"{agl:.1f} m above the ground by the rangefinder")
        return self._goto(north, east, alt, self._zone_id_or_none())

    def _low_land(self, why: str) -> list[Command]:
        """End the companion's low descent: the autopilot's LAND from here."""
        self._low_to = None
        self._last_goto = None
        self._event(f"zone {self._zone_id()}: LAND now, {why}")
        return [Land()]

    def _zone_id_or_none(self) -> int | None:
        return None if self.target is None else self.target.id

    def _calm_below(self, track: Track) -> bool:
        """Whether the ground under the vehicle (the latest frame's ``GroundBelow``) has been
        watched and seen free for ``planner.min_calm_s``; when not, says once per zone that the
        LAND waits for it (a Note) and starts that zone's wait."""
        p = self.config.planner
        calm = self._calm_here()
        if self._over_steady(track):
            # A steady zone's watch is the calm of its disc, r0 plus its margin, and the vehicle's
            # own r0 lies within that disc: the calm disc (r0 plus calm_margin_m round the
            # vehicle) may not fit inside a zone that small, however long it has been free.
            calm = max(calm, track.steady_s) if math.isfinite(calm) else track.steady_s
        if p.is_calm(calm):
            return True
        if self._calm_wait is None or self._calm_wait[0] != track.id:
            self._calm_wait = (track.id, self.now)
            seen = f"{calm:.1f} s" if math.isfinite(calm) else "not yet"
            why = f"ground around the landing point watched free for {seen}, not {p.min_calm_s:g} s"
            self._event(f"zone {track.id}: {why}: waiting before the LAND")
        return False

    def _over_steady(self, track: Track) -> bool:
        """Whether ``track`` was chosen as a steady zone (too small, when chosen, for
        ``r0_m + radius_margin_m``), is steady still (``PlannerConfig.is_steady``) and the vehicle
        within ``steady_margin_m`` of its centre, so that r0 round the vehicle lies inside the
        disc the zone has kept free. A zone chosen larger has room for the calm disc, and calm
        judges it, also once the view at the judging height bounds it under that size."""
        s, p = self.status, self.config.planner
        return (s is not None and self._steady_target == track.id and p.is_steady(track)
                and math.hypot(s.north - track.x, s.east - track.y) <= p.steady_margin_m)

    def _calm_here(self) -> float:
        """The latest frame's calm under the camera (s; NaN when not measured)."""
        return self.below.calm_s if self.below is not None else math.nan

    def _out_of_view(self, track: Track | None) -> bool:
        """In LAND, a zone last seen all free with a view of under ``BLIND_VIEW_M`` that then
        drops out of the tracks (rather than being seen occupied) has gone below what the camera
        can confirm: the landing is committed, as below ``land_abort_above_m``. Over uniform free
        ground this happens a little above the commit height; sending the vehicle back up to HOLD
        there only to come down again churned for a minute."""
        last = self.target
        gone = track is None or self.now - track.last_t > self.config.planner.zone_max_age_s
        if self.phase != Phase.LAND or last is None or not gone or not last.view_limited or \
                last.r_view >= BLIND_VIEW_M:
            return False
        here = self._below_here()
        if here is not None and here[0] < self.config.planner.r0_m and not here[1]:
            # This frame sees somebody within r0 of the vehicle: the zone is lost, not out of
            # view. "All free" was said of the track's centre, which drifts to the edge of the
            # view while the vehicle comes down over the aim: ArduPilot seed 6 committed so at
            # 7.5 m and landed 0.8 m from a person (a starved flight, 2026-11-25).
            return False
        if not self._blind:
            self._blind = True
            h = "?" if self.status is None else f"{self.status.height:.1f}"
            self._event(f"zone {last.id} out of view at {h} m, last seen all free: landing committed")
        return True

    def _lost(self, why: str) -> list[Command]:
        """Give up the target (``why``: the reason, for the pilot): another eligible zone, else
        HOLD."""
        assert self.target is not None
        lost = self.target
        s = self.status
        if self.phase == Phase.LAND and s is not None and s.height <= self.config.land_abort_above_m:
            return []  # committed: too low to fly away safely; the autopilot finishes the landing
        other = (self.planner.choose(self.tracks, self.now, exclude=(lost.id, *self._restless))
                 if self._status_fresh() else None)
        if other is not None:
            return self._approach(other, f"zone {lost.id} lost ({why}); re-targeting", lost_id=lost.id)
        self.target = None
        self._set_phase(Phase.HOLD, f"zone {lost.id} lost ({why}); holding", warning=True,
                        event=Holding, lost_zone_id=lost.id, reason=why)
        if s is None or not self._status_fresh():
            return []
        self._last_goto = None
        # Low over a lost zone the camera sees too little to confirm any zone of r0 plus margin:
        # climb back to where it sees enough (never above the ceiling), rather than hover blind
        # until the handback.
        self._aim = None
        self._raise_level(s.alt - s.height + self.config.hold_height_m)
        return self._goto(s.north, s.east, self._level, None)

    # -- search ------------------------------------------------------------------------------

    def _start_search(self, why: str) -> list[Command]:
        """No zone in view for the SELECT/HOLD timeout: search, or hand back when searching is off
        or there is no time left for it."""
        c, s = self.config, self.status
        if c.search_s <= 0 or s is None or not self._status_fresh() or self.ceiling_m is None:
            return self._handback(why)
        self._search_t = self.now
        over = self._search_over()
        if over is not None:
            return self._handback(f"{why}; {over}")
        # Climb to the ceiling first, over where the vehicle is: a wider view for free.
        self._raise_level(self._cap())
        self._search = expanding_square((s.north, s.east), self._search_spacing(), c.search_radius_m)
        self._aim = None
        self._last_goto = None
        self._set_phase(Phase.SEARCH, f"{why}; searching {c.search_radius_m:g} m around for "
                        f"{c.search_s:g} s", warning=True)
        return self._goto(s.north, s.east, self._level, None)

    def _search_spacing(self) -> float:
        """Metres between the search's legs: 1.5 times the ground radius the camera sees at the
        planned level along its narrower side. Ground between two legs is then within 0.75 of
        that radius of one of them, so a free circle there shows enough of itself from a corner
        to be a glimpse worth flying over (``_search_lead``); at 1.0 a circle just beyond the
        first corner showed a strip too thin to be one, and the search flew away from it (at
        least 4 m)."""
        s, c = self.status, self.config
        assert s is not None
        height = self._level - (s.alt - s.height)
        return max(4.0, 1.5 * c.view_ratio * max(0.0, height - 1.7))

    def _search_over(self) -> str | None:
        """Why the search must stop now, or None: its time, or the battery's."""
        c, s = self.config, self.status
        if self.now - self._search_t > c.search_s and not self._finishing_steady_look():
            return f"searched {c.search_s:g} s without a safe zone"
        if s is not None and s.battery_s is not None and math.isfinite(s.battery_s):
            need = self._descent_now().time_to_touchdown(s.height) + c.search_reserve_s
            if s.battery_s < need:
                return f"battery {s.battery_s:.0f} s left, landing needs {need:.0f} s with the reserve"
        return None

    def _search_step(self) -> list[Command]:
        """Fly the search on (every frame re-checks the zones first, in ``on_frame``): toward free
        ground glimpsed at the edge of the view, else to the square's next waypoint."""
        s, c = self.status, self.config
        if s is None or not self._status_fresh():
            return []
        lead = self._search_lead()
        if lead is not None:
            return self._look_at(lead)
        if self._search and math.hypot(self._search[0][0] - s.north,
                                        self._search[0][1] - s.east) <= 2 * c.arrive_radius_m:
            # Hover there long enough for a zone in view to become a track and be old enough to
            # choose (mu_2 frames, then min_track_age_s): flying on, the view slides past a
            # zone before the tracker can confirm it.
            self._dwell_until = self.now + self._search_dwell_s()
            self._search.pop(0)
        if self.now < self._dwell_until:
            return []
        if not self._search:
            return self._handback(f"searched {c.search_radius_m:g} m around without a safe zone")
        north, east = self._search[0]
        return self._goto(north, east, self._level, None)

    def _search_lead(self) -> Track | None:
        """The largest zone the latest frame confirmed that may not be chosen yet (smaller than
        ``r0_m + radius_margin_m``, or young) and has not been looked at already, or None."""
        leads = [t for t in self.tracks if t.misses == 0 and t.id not in self._investigated
                 and math.isfinite(t.x) and math.isfinite(t.y) and t.r >= self.config.planner.r0_m]
        return max(leads, key=lambda t: t.r, default=None)

    def _look_at(self, lead: Track) -> list[Command]:
        """Free ground seen, too little of it to choose (cut by the edge of the view, or too
        young): fly over it at the planned level so the camera sees it whole, and let the tracker
        confirm it; looked at without becoming a zone for as long as ``_looked_long_enough``
        allows, it is given up."""
        s, c = self.status, self.config
        assert s is not None
        if math.hypot(lead.x - s.north, lead.y - s.east) > 2 * c.arrive_radius_m:
            self._over_lead = None
            return self._goto(lead.x, lead.y, self._level, None)
        if self._over_lead is None or self._over_lead[0] != lead.id:
            self._over_lead = (lead.id, self.now)
        elif self._looked_long_enough(lead, self.now - self._over_lead[1]):
            self._investigated.add(lead.id)  # looked at long enough: it is no zone
        return []

    def _looked_long_enough(self, lead: Track, over_s: float) -> bool:
        """Whether free ground hovered over for ``over_s`` seconds without becoming a zone is to
        be given up: after the waypoints' dwell; or, for a glimpse that keeps r0 plus the steady
        margin free (``PlannerConfig.steady_r_m``), once the time over it not covered by its
        present steady watch (``Track.steady_s``) passes ``steady_s`` plus a second. The watch
        counts the same ground, so it starts once the zone's centre stops moving as the view
        comes to hold all of it (dense-beyond seed 43: 4.5 s after the vehicle arrived); a
        watch that keeps breaking, or never starts, is given up as soon as before, and none is
        looked at for longer than twice ``steady_s`` plus a second (one steady the planner
        still refuses, near a point to avoid, must not hold the search)."""
        p = self.config.planner
        if p.is_steady_sized(lead):
            watched = lead.steady_s if math.isfinite(lead.steady_s) else 0.0
            dwell = max(self._search_dwell_s(), p.steady_s + 1.0)
            return over_s - watched >= dwell or over_s >= dwell + p.steady_s
        return over_s >= self._search_dwell_s()

    def _finishing_steady_look(self) -> bool:
        """Whether the search is over a steady-sized glimpse (``_looked_long_enough``) whose
        steady watch runs and has not yet reached ``steady_s``, with at most ``steady_s`` past
        the search's time: that look is finished rather than the vehicle handed back over the
        crowd a few seconds before the zone could be chosen. ``max_takeover_s`` and the battery
        still bound it."""
        p, c = self.config.planner, self.config
        if p.steady_s <= 0 or self._over_lead is None or self.now - self._search_t > c.search_s + p.steady_s:
            return False
        lead = next((t for t in self.tracks if t.id == self._over_lead[0] and t.misses == 0
                     and t.id not in self._investigated), None)
        s = self.status
        return (lead is not None and s is not None and p.is_steady_sized(lead) and math.isfinite(lead.steady_s)
                and 0.0 < lead.steady_s < p.steady_s
                and math.hypot(lead.x - s.north, lead.y - s.east) <= 2 * c.arrive_radius_m)

    def _search_dwell_s(self) -> float:
        """Seconds to hover at each search waypoint: a zone's track must be born and grow old
        enough to be chosen (``min_track_age_s``), plus a second for the tracker's first frames."""
        return self.config.planner.min_track_age_s + 1.0

    def _goto(self, north: float, east: float, alt: float, zone_id: int | None) -> list[Command]:
        assert self.status is not None
        alt = min(alt, self._cap())  # never a target above the ceiling, whatever asked for it
        last = self._last_goto
        if (
            last is not None
            and last.zone_id == zone_id
            and math.hypot(last.north - north, last.east - east) < self.config.retarget_min_move_m
            and abs(last.target.rel_alt_m - alt) < self.config.retarget_min_move_m
            and self.now - self._last_goto_t < self.config.refresh_s
        ):
            return []  # the vehicle already has this target; do not flood the link
        point = geo_from_ned(self.status.home, north, east, -alt)
        cmd = Goto(PositionTarget(point.lat_deg, point.lon_deg, alt, point.alt_m), zone_id, north, east)
        self._last_goto, self._last_goto_t = cmd, self.now
        s = self.status
        # The vehicle flies on with its old target from the status's sample time until this one
        # reaches it: the status's age plus the link's latency out.
        unheard = max(0.0, self.now - s.t) + max(0.0, s.latency_s)
        self.obedience.target(north, east, alt, Sample(s.north, s.east, s.alt, s.vn, s.ve, s.vd, s.t), unheard)
        return [cmd]

    def _handback(self, why: str, action: str | None = None) -> list[Command]:
        """Give the vehicle back: ``action`` LAND or RTL (default: the configured one)."""
        action = action or self.config.handback_action
        self.target = None
        self._set_phase(Phase.HANDBACK, f"{why}: handing back to the autopilot ({action})", warning=True,
                        event=HandedBack, action=action, reason=why)
        return [Handback(action, why)]

    # -- bookkeeping -------------------------------------------------------------------------

    def _advance(self, t: float) -> None:
        if math.isfinite(t):
            self.now = max(self.now, t)

    def _zone_id(self) -> str:
        return "?" if self.target is None else str(self.target.id)

    def _set_phase(self, phase: Phase, text: str, warning: bool = False, event: type[Event] = PhaseChanged,
                   **fields: object) -> None:
        """Enter ``phase`` (or stay in it), reporting it as one ``event`` of the given type: the
        only way the phase changes, so no change goes unreported."""
        old = self.phase
        if phase not in (Phase.DESCEND, Phase.LAND):
            self._judged = None  # a zone flown to again is judged again
        if phase != Phase.LAND:
            self._low_to = None
        if phase != old:
            log.info("landing: %s -> %s", old.value, phase.value)
            self.phase = phase
            self._phase_t = self.now
        self._emit(event(self.now, old, phase, f"SLZ: {text}", warning, **fields))

    def _event(self, text: str, warning: bool = False) -> None:
        self._emit(Note(self.now, self.phase, self.phase, f"SLZ: {text}", warning))

    def _emit(self, event: Event) -> None:
        (log.warning if event.warning else log.info)("%s", event.text)
        self._events.append(event)


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


# The commands the controller returns and its phases are re-exported: a runner drives the
# controller with this module alone.
__all__ = [
    "ACTIVE", "BLIND_VIEW_M", "FLYING", "LandingConfig", "LandingController", "VehicleStatus",
    "expanding_square", "person_trust_height",
    "Command", "Goto", "Handback", "Land", "Phase",
]
