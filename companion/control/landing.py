"""The landing controller: a phase machine driven by explicit inputs, returning commands to execute.

The phases and which may follow which are in ``companion.control.phases``. The questions the
machine asks on its way each have their module, which answers and changes nothing: which zone
(``planner``: zones are lost there too), is the ground under the vehicle fit now (``ground``:
and when a LAND is committed), where in the zone (``aim``), the levels and the last metres
(``descent``), what the descent over the zone does on a frame, down to the LAND (``over_zone``),
where to search (``search``), what the vehicle and the clock say (``watch``), and whether the
vehicle obeys (``obedience``). Only this machine acts: it emits the commands and the
events and changes the phase, with one handler per phase for each frame. HOLD is a position
target at the vehicle's own position (climbing to ``hold_height_m`` above the ground), so the
autopilot stays in GUIDED/OFFBOARD and can resume.

Inputs (times are monotonic seconds):

- ``on_trigger(trigger)``: a failsafe ``Trigger``; the only way out of MONITOR.
- ``on_frame(t, tracks, pose, below, view)``: the zone tracks after the frame captured at ``t``,
  the pose the pipeline used for it, and optionally the ground it saw under the camera
  (``GroundBelow``) and its ground view, which says where the risk map puts the landing point
  (``aim.SpotSource``; asked only while the point may move). A frame whose pose is missing, not
  finite or further than ``max_pose_age_s`` from ``t``, or older than ``zone_max_age_s``, is
  ignored: no decision is ever made on a zone that was not seen with a fresh pose.
- ``on_state(status)``: where the vehicle is now (``VehicleStatus``), its mode, armed, on ground.
- ``tick(now)``: timeouts.
- ``on_command_result(command, error)``: what became of a command the runner executed.

Each returns the list of ``Command``s to execute now; ``pop_events()`` gives the typed events
(``companion.control.events``: every phase change, target, hold and handback, with its time); the
service records them and sends their text as STATUSTEXT.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from companion.control import aim as aiming
from companion.control import commit, ground, over_zone, watch
from companion.control import descent as plan
from companion.control.aim import Aimed
from companion.control.commands import Command, Goto, GotoSender, Handback, Land
from companion.control.events import HandedBack, Holding, Phase, TargetChosen
from companion.control.obedience import ObedienceMonitor, Sample
from companion.control.phases import ACTIVE, FLYING, PhaseMachine
from companion.control.planner import ZoneCheck, ZonePlanner
from companion.control.search import Search, expanding_square
from companion.control.settings import LAND_AGL_MIN_M, LandingConfig
from companion.control.touchdown import DescentProfile
from companion.control.trigger import Trigger
from companion.control.vehicle import VehicleStatus, pose_usable
from companion.geometry.camera import Pose
from companion.pipeline.circles import GroundBelow
from companion.pipeline.riskmap import Spot
from companion.pipeline.tracker import Track

person_trust_height = plan.person_trust_height


class LandingController(PhaseMachine):
    """See the module docstring. Pure: no I/O, no clock; every time comes in through an input."""

    def __init__(self, config: LandingConfig | None = None) -> None:
        super().__init__()
        self.config = config or LandingConfig()
        self.planner = ZonePlanner(self.config.planner)
        self.search = Search(self.config, self.planner)
        self.trigger: Trigger | None = None
        self.target: Track | None = None
        self.status: VehicleStatus | None = None
        self.tracks: list[Track] = []
        self.below: GroundBelow | None = None  # under the camera on the latest usable frame, if it said
        self.spot: Spot | None = None  # where the latest frame's map puts the landing point, if asked
        self.last_valid_frame_t: float | None = None
        self.frames_ignored = 0
        self.refusals = 0
        self.placements = 0  # landing points moved away from people
        self.moves = aiming.MoveNews({})  # which of those moves were told
        self.failures_tolerated = 0  # single failing frames that did not lose a zone, since start
        self.trigger_alt: float | None = None  # metres above home at the trigger
        self.ceiling_m: float | None = None  # metres above home (``descent``)
        self.obedience = ObedienceMonitor(self.config.obedience)
        self.descent = self.config.descent
        self.sender = GotoSender(self.config.retarget_min_move_m, self.config.refresh_s, self.obedience)
        self._mode_confirmed = False
        self._level = math.nan  # the planned altitude (m above home; ``descent``)
        self._aim: tuple[float, float] | None = None  # landing point, north/east metres
        self._blind = False  # in LAND, the zone went out of view: committed
        self._low_to: over_zone.LowDescent | None = None  # in LAND, the companion's own descent, if any
        self._restless: set[int] = set()  # zones given up because they never became calm
        self._waits = commit.Waits()  # over the zone before the LAND: for calm, for nobody within reach
        # The zone judged at the judging height: below it the calm disc no longer fits in the
        # view, so the judgement is kept down to land_alt_m, not asked again.
        self._judged: int | None = None
        self._steady_target: int | None = None  # the target chosen as a steady zone (``_approach``)
        self._failing = 0  # consecutive frames on which the target failed its check (``_confirmed``)
        self._candidate_seen = False  # a zone of at least r0 seen since the trigger (select_empty_s)
        # One handler per phase for each usable frame.
        self._on_frame_in: dict[Phase, Callable[[], list[Command]]] = {
            Phase.SELECT: self._select, Phase.HOLD: self._select, Phase.SEARCH: self._frame_search,
            Phase.APPROACH: self._frame_approach, Phase.DESCEND: self._frame_descend, Phase.LAND: self._frame_land,
        }

    # -- inputs ------------------------------------------------------------------------------

    def on_trigger(self, trigger: Trigger) -> list[Command]:
        self._advance(trigger.t)
        if self.phase != Phase.MONITOR:
            return []
        self.trigger = trigger
        self._candidate_seen = self.planner.could_become_zone(self.tracks)
        self._set_phase(Phase.SELECT, f"trigger: {trigger.reason}; looking for a landing zone", warning=True)
        if self._status_fresh() and (refused := self._set_ceiling()):
            return refused
        return self._select()

    def on_state(self, status: VehicleStatus) -> list[Command]:
        if not all(math.isfinite(v) for v in (status.t, status.north, status.east, status.down)):
            return []  # a NaN position is no position
        self._advance(status.t)
        self.status = status
        if self.phase not in ACTIVE:
            return []
        if self.ceiling_m is None and (refused := self._set_ceiling()):
            return refused
        if news := watch.vehicle_news(status, self.phase, self._low_to is not None, self.ceiling_m, self._zone_id()):
            return self._on_news(news)
        why = self.obedience.watch(Sample.of(status), watch.obeying_watched(
            self.phase, self._low_to is not None, status.mode, self.config, self.sender.last is not None))
        if why is not None:
            return self._handback(why, action="LAND")
        if self.phase in FLYING and status.mode is not None:
            if watch.ours(status.mode, self.config):
                self._mode_confirmed = True
            elif self._mode_confirmed:  # someone else took over: stop at once
                self._set_phase(Phase.HANDBACK, f"mode changed to {status.mode} by someone else: companion stops",
                                warning=True, event=HandedBack, reason=f"mode changed to {status.mode}")
                return []
        if self.phase == Phase.LAND and (low := self._low_to) is not None:
            why = plan.low_land_reason(self.config, status, low.alt_m, low.agl_m)
            if why is not None:
                return self._low_land(why)
            return self._goto(low.north, low.east, low.alt_m, self._zone_id_or_none())
        return []

    def on_frame(self, t: float, tracks: Sequence[Track], pose: Pose | None,
                 below: GroundBelow | None = None, view: aiming.SpotSource | None = None) -> list[Command]:
        self._advance(t)
        if not (pose_usable(pose, t, self.config.max_pose_age_s) and self.now - t <= self.config.planner.zone_max_age_s):
            self.frames_ignored += 1
            return []
        self.last_valid_frame_t = t
        self.tracks = list(tracks)
        self.below = ground.usable_below(below)
        # Asked before the frame changes anything, while the landing point may move (``_placing``).
        target = self.target
        request = (aiming.request_for(target.id, tracks, self.planner, self.config.place_lookback_s, self._aim)
                   if view is not None and target is not None and self._placing(target.id) else None)
        self.spot = aiming.usable_spot(None if view is None or request is None else view.spot(request))
        if self.phase == Phase.SELECT and not self._candidate_seen:
            self._candidate_seen = self.planner.could_become_zone(self.tracks)
        handler = self._on_frame_in.get(self.phase)
        return [] if handler is None else handler()

    def tick(self, now: float) -> list[Command]:
        self._advance(now)
        if self.phase not in ACTIVE:
            return []
        due = watch.timeout(self.phase, self.now, self._phase_t, self.config, self._candidate_seen,
                            self._search_over() if self.phase == Phase.SEARCH else None,
                            None if self.trigger is None else self.trigger.t,
                            None if self.status is None else self.status.t, self.last_valid_frame_t)
        if due is None:
            return []
        if due.search:
            return self._start_search(due.why)
        return self._handback(due.why)

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
            self.sender.forget()  # re-send at the next frame
        return []

    def use_autopilot_speeds(self, speeds: dict[str, float], source: str) -> None:
        """Take the autopilot's own descent speeds for the time to touchdown (``descent.with_speeds``)."""
        d = plan.with_speeds(self.descent, speeds)
        if d is not None:
            self.descent = d
            self._event(f"descent {d.descend_speed_mps:.1f} m/s, LAND {d.land_speed_mps:.1f} m/s ({source})")

    # -- answers for the service -------------------------------------------------------------

    def touchdown_clearance(self, track: Track) -> float | None:
        """The least clearance (m) ``track`` can have at touchdown (``descent.touchdown_clearance``)."""
        return plan.touchdown_clearance(self._descent_now(), self.status, track.r)

    def zone_target(self) -> Track | None:
        """The zone the vehicle flies to (after a trigger), or would fly to now (before one); none
        after the flight: what the recording, the status line and the ground station call the target."""
        if self.phase in ACTIVE:
            return self.target
        return self.planner.choose(self.tracks, self.now) if self.phase == Phase.MONITOR else None

    # -- SELECT, HOLD, SEARCH: choosing a zone ------------------------------------------------

    def _select(self) -> list[Command]:
        """SELECT and HOLD: fly to the best eligible zone (``ZonePlanner.choose``), else wait."""
        if not self._status_fresh() or self.ceiling_m is None:
            return []
        zone = self.planner.choose(self.tracks, self.now, exclude=tuple(self._restless))
        return [] if zone is None else self._approach(zone, "landing at")

    def _frame_search(self) -> list[Command]:
        """SEARCH: a zone if one is eligible, else the search's next move (``search``)."""
        found = self._select()
        if found or self.phase != Phase.SEARCH:
            return found
        s = self.status
        if s is None or not self._status_fresh():
            return []
        move = self.search.step(self.now, self.tracks, s)
        if move.done:
            return self._handback(move.done)
        return [] if move.to is None else self._goto(move.to[0], move.to[1], self._level, None)

    def _start_search(self, why: str) -> list[Command]:
        """SELECT/HOLD timed out: search, or hand back when searching is off or out of time."""
        c, s = self.config, self.status
        if c.search_s <= 0 or s is None or not self._status_fresh() or self.ceiling_m is None:
            return self._handback(why)
        self.search.start(self.now)
        if (over := self._search_over()) is not None:
            return self._handback(f"{why}; {over}")
        # Climb to the ceiling first, over where the vehicle is: a wider view for free.
        self._level = plan.raised(self._level, self._cap(), self._cap())
        self.search.fly_square((s.north, s.east), self._level, s)
        self._aim = None
        self.sender.forget()
        self._set_phase(Phase.SEARCH, f"{why}; searching {c.search_radius_m:g} m around for "
                        f"{c.search_s:g} s", warning=True)
        return self._goto(s.north, s.east, self._level, None)

    def _search_over(self) -> str | None:
        s = self.status
        to_touchdown = math.nan if s is None else self._descent_now().time_to_touchdown(s.height)
        return self.search.over(self.now, self.tracks, s, to_touchdown)

    # -- APPROACH, DESCEND, LAND: flying to the target ----------------------------------------

    def _approach(self, zone: Track, verb: str, lost_id: int | None = None) -> list[Command]:
        s, c = self.status, self.config
        assert s is not None
        self.target = zone
        self._failing = 0
        self._aim = (zone.x, zone.y)
        # Chosen too small for the radius margin, so for its steadiness (``ground.over_steady``).
        self._steady_target = zone.id if zone.r < c.planner.large_r_m else None
        self._level = plan.approach_level(self._level, s, c, self._cap())
        dist = math.hypot(zone.x - s.north, zone.y - s.east)
        self._set_phase(Phase.APPROACH, f"{verb} zone {zone.id}, {dist:.1f} m away, radius {zone.r:.1f} m",
                        event=TargetChosen, zone_id=zone.id, north=zone.x, east=zone.y, r=zone.r,
                        lost_zone_id=lost_id, touchdown_clearance_m=self.touchdown_clearance(zone),
                        edge=zone.edge or None)
        self.sender.forget()
        return self._goto(zone.x, zone.y, self._level, zone.id)

    def _frame_approach(self) -> list[Command]:
        """APPROACH: level flight to the landing point; over it, the descent begins."""
        over = self._confirmed()
        if not isinstance(over, Aimed):
            return over
        if over.dist > self.config.arrive_radius_m:
            return self._goto(over.aim[0], over.aim[1], self._level, over.track.id)
        assert self.status is not None
        self._set_phase(Phase.DESCEND, f"over zone {over.track.id}, descending from {self.status.alt:.1f} m",
                        zone_id=over.track.id)
        return self._descend(over)

    def _frame_descend(self) -> list[Command]:
        over = self._confirmed()
        if not isinstance(over, Aimed):
            return over
        return self._descend(over)

    def _frame_land(self) -> list[Command]:
        """LAND: the autopilot lands; the zone is still checked (``_confirmed``) above the commit height."""
        over = self._confirmed()
        if not isinstance(over, Aimed):
            return over
        return []  # confirmed: the LAND goes on

    def _confirmed(self) -> Aimed | list[Command]:
        """APPROACH, DESCEND, LAND: the target as this frame confirms it, with its landing point
        (``Aimed``); else the commands for a zone lost or unconfirmed (none, another zone, HOLD)."""
        assert self.target is not None
        s, c, aim = self.status, self.config, self._aim
        over_target = self.phase in (Phase.DESCEND, Phase.LAND)
        under_aim = (over_target and s is not None and aim is not None and self._status_fresh()
                     and ground.holds_under_aim(s, aim, self.below, c.planner, c.arrive_radius_m))
        verdict, track, why = ground.target_check(self.planner, self.target, self.tracks, self.now, s, self.below,
                                                  over_target, under_aim)
        if verdict == ZoneCheck.LOST:  # gone from the tracks, or unconfirmed for zone_max_age_s
            if not self._out_of_view(track):
                return self._lost(why)
            if self.phase == Phase.LAND or s is None or aim is None or not self._status_fresh():
                return []
            return Aimed(self.target, aim, math.hypot(aim[0] - s.north, aim[1] - s.east))  # the judged descent goes on
        if verdict == ZoneCheck.UNCONFIRMED or track is None or s is None or not self._status_fresh():
            return []  # no new command toward a zone this frame did not confirm
        if verdict == ZoneCheck.SMALL:  # lost once lose_after_frames frames in a row say so (``planner``)
            self._failing += 1
            if self._failing < c.lose_after_frames:
                self.failures_tolerated += 1
                return []
            return self._lost(why)
        self._failing = 0
        self.target = track
        room = self.planner.room(track)
        aim = self._aim = aiming.aim_for(self._aim, track, room)
        spot = self.spot
        if spot is not None and self._placing(track.id) and aiming.worth_moving(spot, track, room):
            self.placements += 1
            if news := self.moves.tell(track.id, aim, aiming.was_clear(spot), spot, self.now):
                self._event(f"zone {track.id}: landing point moved {news[0]:.1f} m, {spot.clear_m:.1f} m from where "
                            f"people were seen in the last {c.place_lookback_s:g} s (was {news[1]:.1f} m)")
            aim = self._aim = (spot.x, spot.y)
        return Aimed(track, aim, math.hypot(aim[0] - s.north, aim[1] - s.east))

    def _descend(self, over: Aimed) -> list[Command]:
        """DESCEND: step down over the landing point to the judging height, judge the zone there
        (calm), step on down to the LAND height, and command the LAND: ``over_zone.decide`` says
        which on this frame; this acts on it."""
        s = self.status
        assert s is not None
        aim, zone_id = over.aim, over.track.id
        move = over_zone.decide(s, self.config, self.descent, over, self.below, self._over_steady(over.track),
                                judged=self._judged == zone_id,
                                calm_waited_s=self._waits.waited("calm", zone_id, self.now),
                                reach_waited_s=self._waits.waited("reach", zone_id, self.now))
        if isinstance(move, over_zone.GiveUp):
            self._restless.add(zone_id)
            return self._lost(move.why)
        if isinstance(move, over_zone.Hover):
            if self._waits.begin(move.wait, zone_id, self.now):
                self._event(f"zone {zone_id}: {move.why}")
            return self._goto(aim[0], aim[1], self._level, zone_id)
        if isinstance(move, over_zone.CommitLand):
            return self._command_land(move, zone_id)
        if move.judged is not None:
            self._judged = zone_id  # kept down to the LAND height, not asked again
            self._event(move.judged)
        self._level = plan.next_level(self._level, s, over.dist, move.floor_alt_m, self.config, self._cap())
        return self._goto(aim[0], aim[1], self._level, zone_id)

    def _command_land(self, move: over_zone.CommitLand, zone_id: int) -> list[Command]:
        """LAND over the zone: the autopilot's LAND now, or first the companion's own descent."""
        self._set_phase(Phase.LAND, move.text, zone_id=zone_id, touchdown_clearance_m=move.touchdown_clearance_m,
                        calm_s=move.calm_s)
        low = self._low_to = move.low
        if low is None:
            return [Land()]
        self.sender.forget()
        return self._goto(low.north, low.east, low.alt_m, zone_id)

    def _on_news(self, news: watch.News) -> list[Command]:
        """Act on what the vehicle's status says happened (``watch.vehicle_news``)."""
        if news.seen == watch.Seen.GROUND_EARLY:
            return self._low_land(news.text)
        if news.seen == watch.Seen.ABOVE_CEILING:
            return self._handback(news.text, action="LAND")
        if news.seen == watch.Seen.DISARMED_IN_AIR:
            self.target = None
            self._set_phase(Phase.HANDBACK, f"{news.text}: companion stops", warning=True, event=HandedBack,
                            reason=news.text)
        else:
            self._set_phase(Phase.LANDED, news.text, zone_id=self._zone_id_or_none())
        return []

    def _low_land(self, why: str) -> list[Command]:
        """End the companion's low descent (``descent.low_target``): the autopilot's LAND from here."""
        self._low_to = None
        self.sender.forget()
        self._event(f"zone {self._zone_id()}: LAND now, {why}")
        return [Land()]

    def _lost(self, why: str) -> list[Command]:
        """Give up the target (``why``: the reason, for the pilot): another eligible zone, else HOLD."""
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
        self.sender.forget()
        # Low over a lost zone the camera sees too little to confirm any zone: climb to where it does.
        self._aim = None
        self._level = plan.raised(self._level, s.alt - s.height + self.config.hold_height_m, self._cap())
        return self._goto(s.north, s.east, self._level, None)

    def _out_of_view(self, track: Track | None) -> bool:
        """In LAND, or descending over the judged zone (too low to confirm it), whether the target left the
        tracks with nobody seen within r0 of the vehicle (``ground.left_view``): the landing is committed."""
        last = self.target
        if last is None or not (self.phase == Phase.LAND or self._judged == last.id):
            return False
        if not ground.left_view(track, self.now, self.status, self.below, self.config.planner):
            return False  # seen occupied, or somebody seen within r0 of the vehicle: lost
        if not self._blind:
            self._blind = True
            h = "?" if self.status is None else f"{self.status.height:.1f}"
            self._event(f"zone {last.id} out of view at {h} m, nobody seen within r0: landing committed")
        return True

    # -- questions asked of the parts with this machine's state ---------------------------------

    def _placing(self, zone_id: int) -> bool:
        """Whether the landing point may move (``aim``): approaching or descending to judge it."""
        return (self.config.place_lookback_s > 0 and self.phase in (Phase.APPROACH, Phase.DESCEND)
                and self._judged != zone_id)

    def _over_steady(self, track: Track) -> bool:
        return ground.over_steady(track, self.status, self._steady_target, self.config.planner)

    def _descent_now(self) -> DescentProfile:
        return plan.profile_now(self.descent, self.status, self.config.land_agl_m)

    def _status_fresh(self) -> bool:
        return self.status is not None and self.now - self.status.t <= self.config.state_timeout_s

    def _set_ceiling(self) -> list[Command]:
        """Fix the altitude at the trigger and the ceiling from the first status after it."""
        s, c = self.status, self.config
        if s is None or self.trigger is None or self.ceiling_m is not None:
            return []
        self.trigger_alt = s.alt
        self._level = s.alt
        self.ceiling_m = plan.ceiling(s.alt, c)
        if s.alt > c.max_alt_m:
            return self._handback(f"vehicle at {s.alt:.1f} m, above the {c.max_alt_m:g} m ceiling: "
                                  "not taking over", action="LAND")
        return []

    def _cap(self) -> float:
        """The highest altitude a target may have (m above home)."""
        assert self.ceiling_m is not None
        return self.ceiling_m - self.config.ceiling_margin_m

    # -- acting: commands, phases, events ---------------------------------------------------------

    def _goto(self, north: float, east: float, alt: float, zone_id: int | None) -> list[Command]:
        assert self.status is not None  # never a target above the ceiling, whatever asked for it:
        return self.sender.goto(self.status, north, east, min(alt, self._cap()), zone_id, self.now)

    def _handback(self, why: str, action: str | None = None) -> list[Command]:
        """Give the vehicle back: ``action`` LAND or RTL (default: the configured one)."""
        action = action or self.config.handback_action
        self.target = None
        self._set_phase(Phase.HANDBACK, f"{why}: handing back to the autopilot ({action})", warning=True,
                        event=HandedBack, action=action, reason=why)
        return [Handback(action, why)]

    def _zone_id(self) -> str:
        return "?" if self.target is None else str(self.target.id)

    def _zone_id_or_none(self) -> int | None:
        return None if self.target is None else self.target.id

    def _entering(self, phase: Phase) -> None:
        if phase not in (Phase.DESCEND, Phase.LAND):
            self._judged = None  # a zone flown to again is judged again
        if phase != Phase.LAND:
            self._low_to = None


# Re-exported: a runner drives the controller with this module alone.
__all__ = ["ACTIVE", "FLYING", "LAND_AGL_MIN_M", "LandingConfig", "LandingController", "VehicleStatus",
           "expanding_square", "person_trust_height", "Command", "Goto", "Handback", "Land", "Phase"]
