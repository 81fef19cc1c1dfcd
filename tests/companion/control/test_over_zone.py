"""The descent over a zone, one frame at a time (``over_zone.decide``): every decision it can give,
from real settings and descent profiles. The controller's acting on them is tested through
``LandingController`` (test_landing_controller, test_commit)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from companion.control import commit, over_zone
from companion.control import descent as plan
from companion.control.aim import Aimed
from companion.control.over_zone import CommitLand, GiveUp, Hover, LowDescent, StepDown, decide
from companion.control.planner import PlannerConfig
from companion.control.settings import LandingConfig
from companion.control.touchdown import DescentProfile, by_rangefinder
from companion.control.vehicle import VehicleStatus
from companion.geometry.camera import Intrinsics
from companion.geometry.geodesy import GeoPoint
from companion.pipeline.circles import GroundBelow
from companion.pipeline.tracker import Track

HOME = GeoPoint(47.397742, 8.545594, 488.0)
#: The simulator's PX4: descent 1.5 m/s, LAND from 4 m at 1.0 m/s, walkers at 1.5 m/s.
SIM = DescentProfile(descend_speed_mps=1.5, land_alt_m=4.0, land_speed_mps=1.0, walk_speed_mps=1.5)
#: The 70-degree pinhole: judged at 10 m, the LAND at 4 m, calm for 5 s, at most 15 s waited for it.
NARROW = LandingConfig(planner=PlannerConfig(r0_m=2.0, radius_margin_m=1.0, min_calm_s=5.0),
                       descend_alt_m=10.0, land_alt_m=4.0, calm_wait_s=15.0, descent=SIM,
                       view_ratio=Intrinsics.from_fov(640, 480, 70.0).seen_ratio())
#: The same with a downward rangefinder: the LAND's last metres flown by the companion to 1 m.
AGL = dataclasses.replace(NARROW, land_agl_m=1.0)
#: A 160-degree fisheye: with a rangefinder it commits from 8.9 m (``commit.commit_height``).
WIDE = dataclasses.replace(AGL, view_ratio=Intrinsics.from_fov(640, 480, 160.0, "fisheye").seen_ratio())


def zone(r: float = 4.1, steady_s: float = math.nan) -> Track:
    """Zone 1, centred at 10 m north."""
    return Track(id=1, x=10.0, y=0.0, r=r, r_filtered=r, age=20, hits=20, misses=0, born_t=0.0, last_t=10.0,
                 steady_s=steady_s)


def over(north: float = 10.0, track: Track | None = None) -> Aimed:
    """The zone's centre as the landing point, the vehicle at ``north`` (east 0)."""
    track = track or zone()
    return Aimed(track, (track.x, track.y), abs(track.x - north))


def vehicle(alt: float, north: float = 10.0, agl: float | None = None, on_ground: bool | None = False) -> VehicleStatus:
    return VehicleStatus(10.0, north, 0.0, -alt, HOME, mode="GUIDED", on_ground=on_ground, agl=agl)


def below(calm_s: float = math.nan, free_m: float = 6.0, view_m: float = 6.0) -> GroundBelow:
    """The frame's ground under the camera, over the landing point."""
    return GroundBelow(10.0, 0.0, free_m, view_m, calm_s=calm_s)


def decide_for(s: VehicleStatus, c: LandingConfig = NARROW, *, aimed: Aimed | None = None,
               ground: GroundBelow | None = None, steady: bool = False, judged: bool = False,
               calm_waited_s: float = 0.0, reach_waited_s: float = 0.0) -> over_zone.Decision:
    return decide(s, c, c.descent, aimed or over(s.north), ground, steady, judged, calm_waited_s, reach_waited_s)


def test_on_the_way_down_to_the_judging_height_the_plan_steps_down_no_lower_than_it():
    assert plan.judging_height(NARROW) == 10.0
    assert decide_for(vehicle(18.0)) == StepDown(10.0)
    # Off the point (2 m, over arrive_radius_m) at the judging height: not yet reached, no judging.
    assert decide_for(vehicle(10.0, north=8.0), ground=below(calm_s=0.0)) == StepDown(10.0)


def test_the_floor_is_the_height_over_the_ground_below_not_over_home():
    # The rangefinder says 9.0 m over ground 3 m above home: the judging height is 13 m above home.
    assert decide_for(vehicle(12.0, north=7.0, agl=9.0)) == StepDown(13.0)


def test_at_the_judging_height_ground_not_yet_calm_is_waited_for():
    move = decide_for(vehicle(9.8), ground=below(calm_s=2.0))
    assert move == Hover("calm", "ground around the landing point watched free for 2.0 s, not 5 s: "
                                 "waiting before the LAND")
    assert decide_for(vehicle(9.8), ground=None) == Hover(
        "calm", "ground around the landing point watched free for not yet, not 5 s: waiting before the LAND")


def test_the_wait_for_calm_lasts_calm_wait_s_then_the_zone_is_given_up():
    s, ground = vehicle(9.8), below(calm_s=2.0)
    assert isinstance(decide_for(s, ground=ground, calm_waited_s=15.0), Hover)  # not past it yet
    assert decide_for(s, ground=ground, calm_waited_s=15.1) == GiveUp(
        "not calm after 15 s over it: people keep passing near it")


def test_calm_ground_is_judged_once_and_the_descent_goes_on_to_the_land_height():
    move = decide_for(vehicle(9.8), ground=below(calm_s=6.3))
    assert move == StepDown(4.0, judged="zone 1 judged at 9.8 m (calm 6.3 s): descending over it to 4 m before the LAND")
    # Judged already: calm is not asked again (the view no longer holds the calm disc), no new words.
    assert decide_for(vehicle(7.0), ground=below(calm_s=math.nan), judged=True) == StepDown(4.0)
    # Judged, off the point: the plan re-centres, still down to the LAND height.
    assert decide_for(vehicle(7.0, north=8.0), judged=True) == StepDown(4.0)


def test_a_steady_zones_watch_counts_as_calm_and_is_told():
    track = zone(r=2.6, steady_s=10.0)
    move = decide_for(vehicle(9.8), aimed=over(track=track), ground=below(calm_s=math.nan), steady=True)
    assert move == StepDown(4.0, judged="zone 1 judged at 9.8 m (steady 10.0 s): descending over it to 4 m "
                                        "before the LAND")
    # Not over it as a steady zone: its watch does not count.
    assert isinstance(decide_for(vehicle(9.8), aimed=over(track=track), ground=below(calm_s=math.nan)), Hover)


def test_at_the_land_height_the_land_is_commanded_with_its_figures():
    s = vehicle(4.2)
    move = decide_for(s, ground=below(calm_s=7.26), judged=True)
    clearance = plan.touchdown_clearance(SIM, s, 4.1)
    assert clearance is not None
    assert move == CommitLand("LAND over zone 1 at 4.2 m, radius 4.1 m", None, clearance, 7.3)
    # The calm not measured is no figure.
    assert decide_for(s, ground=None, judged=True) == CommitLand("LAND over zone 1 at 4.2 m, radius 4.1 m", None,
                                                                 clearance, None)


def test_with_a_rangefinder_the_land_is_first_the_companions_own_descent_over_the_point():
    # Over ground 1.5 m above home: down to 1 m by the rangefinder, 2.5 m above home.
    s = vehicle(5.7, agl=4.2)
    move = decide_for(s, AGL, judged=True)
    assert isinstance(move, CommitLand)
    assert move.text == "LAND over zone 1 at 4.2 m, radius 4.1 m, first down to 1 m by the rangefinder"
    assert move.low == LowDescent(10.0, 0.0, pytest.approx(2.5), 1.0)
    assert move.touchdown_clearance_m == plan.touchdown_clearance(by_rangefinder(SIM, 1.0), s, 4.1)
    # Already that low by the rangefinder: the autopilot's LAND now.
    low = decide_for(vehicle(1.1, agl=1.1), AGL, judged=True)
    assert isinstance(low, CommitLand) and low.low is None


def test_ground_come_early_is_a_land_wherever_the_vehicle_is():
    # On the ground at 6 m by its altitude (a slope), off the point: the autopilot's LAND finishes.
    move = decide_for(vehicle(6.0, north=7.0, agl=3.0, on_ground=True), AGL)
    assert isinstance(move, CommitLand) and move.low is None
    assert move.text == "LAND over zone 1 at 3.0 m, radius 4.1 m"


def test_a_fisheye_commits_at_its_commit_height_fast_by_the_rangefinder():
    h = commit.commit_height(WIDE, by_rangefinder(SIM, 1.0), 4.0, 10.0)
    assert h == pytest.approx(8.9, abs=0.1)
    s = vehicle(h, agl=h)
    move = decide_for(s, WIDE, ground=below(calm_s=6.3, free_m=14.0, view_m=15.0), judged=True)
    assert isinstance(move, CommitLand)
    assert move.text == f"LAND over zone 1 at {h:.1f} m, radius 4.1 m, first down to 1 m by the rangefinder"
    assert move.low == LowDescent(10.0, 0.0, pytest.approx(1.0), 1.0)
    # Above the commit height, judged: on down to it.
    assert decide_for(vehicle(9.8, agl=9.8), WIDE, judged=True) == StepDown(pytest.approx(h))


def test_a_fisheye_holds_the_land_while_someone_seen_could_reach_the_point():
    h = commit.commit_height(WIDE, by_rangefinder(SIM, 1.0), 4.0, 10.0)
    assert h is not None
    s, ground = vehicle(h, agl=h), below(free_m=6.0, view_m=15.0)
    reach = commit.reach_m(by_rangefinder(SIM, 1.0), h)
    assert decide_for(s, WIDE, ground=ground, judged=True) == Hover(
        "reach", f"free around the vehicle 6.0 m, not r0 plus the {reach:.1f} m a walker covers before "
                 f"touchdown ({2.0 + reach:.1f} m): holding the LAND")
    # Held as long as touchdown would take from there: then on down to 4 m, as the narrow camera lands.
    to_touchdown = by_rangefinder(SIM, 1.0).time_to_touchdown(h)
    assert decide_for(s, WIDE, ground=ground, judged=True, reach_waited_s=to_touchdown + 0.1) == StepDown(4.0)


def test_the_decisions_are_frozen_data():
    move = StepDown(4.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        move.floor_alt_m = 3.0  # type: ignore[misc]
