"""The landing controller state machine and its planner, driven by explicit inputs."""

from __future__ import annotations

import dataclasses
import math

import pytest
from geographiclib.geodesic import Geodesic

from companion.control.landing import (
    Goto,
    Handback,
    Land,
    LandingConfig,
    LandingController,
    Phase,
    VehicleStatus,
    person_trust_height,
)
from companion.control.planner import PlannerConfig, ZonePlanner
from companion.control.trigger import Trigger, TriggerSource
from companion.geometry.camera import Pose
from companion.geometry.geodesy import GeoPoint
from companion.mavlink.link import CommandRefused
from companion.pipeline.circles import GroundBelow
from companion.pipeline.tracker import Track

HOME = GeoPoint(47.397742, 8.545594, 488.0)
CFG = LandingConfig(
    planner=PlannerConfig(r0_m=2.0, radius_margin_m=1.0, min_track_age_s=1.0, min_track_hits=3, zone_max_age_s=1.0),
    select_timeout_s=5.0,
    hold_timeout_s=4.0,
    arrive_radius_m=1.0,
    descend_alt_m=10.0,
    descend_step_m=3.0,
    land_abort_above_m=5.0,
    max_pose_age_s=0.25,
    pose_timeout_s=2.0,
    max_refusals=3,
    search_s=0.0,  # the search has tests of its own (test_landing_search.py)
)


def zone(id: int, x: float, y: float, t: float, *, r: float = 4.1, born: float | None = None, hits: int = 20,
         misses: int = 0, last: float | None = None) -> Track:
    born = t - 5.0 if born is None else born
    return Track(id=id, x=x, y=y, r=r, r_filtered=r, age=hits + misses, hits=hits, misses=misses, born_t=born,
                 last_t=t if last is None else last)


def pose(t: float, north: float = 0.0, east: float = 0.0, alt: float = 30.0) -> Pose:
    return Pose(t, north, east, -alt, 0.0, 0.0, 0.0)


def status(t: float, north: float = 0.0, east: float = 0.0, alt: float = 30.0, mode: str | None = "LOITER",
           **kw) -> VehicleStatus:
    return VehicleStatus(t, north, east, -alt, HOME, mode=mode, **kw)


def trigger(t: float) -> Trigger:
    return Trigger("battery 0 charge state CRITICAL", TriggerSource.BATTERY, t)


def expected_latlon(north: float, east: float) -> tuple[float, float]:
    """Independent check through geographiclib's Direct problem."""
    g = Geodesic.WGS84.Direct(HOME.lat_deg, HOME.lon_deg, math.degrees(math.atan2(east, north)), math.hypot(north, east))
    return g["lat2"], g["lon2"]


def texts(ctl: LandingController) -> list[str]:
    return [e.text for e in ctl.pop_events()]


def test_no_trigger_no_command_even_over_a_perfect_zone():
    ctl = LandingController(CFG)
    for i in range(20):
        t = i * 0.1
        assert ctl.on_state(status(t)) == []
        assert ctl.on_frame(t, [zone(3, 10, 5, t)], pose(t)) == []
        assert ctl.tick(t) == []
    assert ctl.phase == Phase.MONITOR


def test_trigger_and_confirmed_zone_fly_over_it_descend_and_land():
    ctl = LandingController(CFG)
    ctl.on_state(status(0.0, mode="RTL"))
    assert ctl.on_trigger(trigger(0.0)) == []  # no frame yet: nothing to fly to
    assert ctl.phase == Phase.SELECT
    cmds = ctl.on_frame(0.1, [zone(7, 40, 40, 0.1, r=3.5), zone(3, 12.0, 0.9, 0.1, born=-9.0)], pose(0.1))
    assert len(cmds) == 1 and isinstance(cmds[0], Goto)
    goto = cmds[0]
    assert goto.zone_id == 3  # the oldest stable zone, not the first listed
    lat, lon = expected_latlon(12.0, 0.9)
    assert goto.target.lat_deg == pytest.approx(lat, abs=1e-9) and goto.target.lon_deg == pytest.approx(lon, abs=1e-9)
    assert goto.target.rel_alt_m == pytest.approx(30.0)  # level approach at the current altitude
    assert ctl.phase == Phase.APPROACH
    events = texts(ctl)
    assert events[0].startswith("SLZ: trigger: battery 0 charge state CRITICAL")
    assert events[-1] == "SLZ: landing at zone 3, 12.0 m away, radius 4.1 m"
    # Over the zone now: descend in steps of at most 3 m, re-checking the zone at every frame.
    t, alt, alts = 0.2, 30.0, []
    while ctl.phase != Phase.LAND:
        ctl.on_state(status(t, 12.0, 0.9, alt, mode="GUIDED"))
        cmds = ctl.on_frame(t, [zone(3, 12.0, 0.9, t, born=-9.0)], pose(t, 12.0, 0.9, alt))
        for c in cmds:
            if isinstance(c, Goto):
                assert c.zone_id == 3 and alt - c.target.rel_alt_m <= 3.0 + 1e-9
                assert c.target.rel_alt_m >= 10.0
                alts.append(c.target.rel_alt_m)
                alt = c.target.rel_alt_m  # the vehicle reaches each step
        t += 0.1
        assert t < 5.0
    assert cmds == [Land()]
    assert alts == [27.0, 24.0, 21.0, 18.0, 15.0, 12.0, 10.0]
    ctl.on_state(status(t, 12.0, 0.9, 0.0, mode="LAND", on_ground=True))
    assert ctl.phase == Phase.LANDED
    assert "SLZ: landed in zone 3" in texts(ctl)


@pytest.mark.parametrize(
    "bad,why",
    [
        (dict(hits=2), "young"),
        (dict(born=-0.5), "young"),
        (dict(r=2.9), "small"),
        (dict(misses=1, last=-0.3), "not confirmed"),
        (dict(last=-1.5), "stale"),
    ],
)
def test_young_small_unconfirmed_or_stale_zones_are_never_targets(bad, why):
    now = 0.0
    track = zone(1, 5, 5, now, **{"born": -5.0, **bad})
    assert why in ZonePlanner(CFG.planner).why_not_eligible(track, now)
    ctl = LandingController(CFG)
    ctl.on_state(status(now))
    ctl.on_trigger(trigger(now))
    assert ctl.on_frame(now, [track], pose(now)) == []
    assert ctl.phase == Phase.SELECT


def test_no_zone_within_the_timeout_hands_back_to_the_autopilot():
    for action in ("LAND", "RTL"):
        ctl = LandingController(dataclasses.replace(CFG, handback_action=action))
        ctl.on_state(status(0.0))
        ctl.on_trigger(trigger(0.0))
        t, cmds = 0.0, []
        while not cmds:
            t += 0.1
            ctl.on_state(status(t))
            ctl.on_frame(t, [zone(1, 5, 5, t, r=2.5)], pose(t))  # too small
            cmds = ctl.tick(t)
        assert cmds == [Handback(action, "no safe zone confirmed within 5 s")]
        assert t == pytest.approx(5.1, abs=0.01) and ctl.phase == Phase.HANDBACK
        assert any("handing back to the autopilot" in x for x in texts(ctl))
        assert ctl.on_frame(t, [zone(2, 5, 5, t)], pose(t)) == [] and ctl.tick(t + 10) == []  # terminal


def start_descent(ctl: LandingController, zones, t: float = 0.0, alt: float = 20.0):
    ctl.on_state(status(t, 0, 0, alt))
    ctl.on_trigger(trigger(t))
    cmds = ctl.on_frame(t, zones, pose(t))
    ctl.on_state(status(t + 0.1, 10, 0, alt, mode="GUIDED"))
    ctl.on_frame(t + 0.1, [z if z.id != 1 else zone(1, 10, 0, t + 0.1, born=-8) for z in zones], pose(t + 0.1, 10, 0, alt))
    assert ctl.phase == Phase.DESCEND
    return cmds


def test_zone_lost_during_descent_retargets_to_another_stable_zone():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8), zone(2, -20, 5, 0.0, born=-4)])
    t = 0.2
    ctl.on_state(status(t, 10, 0, 18, mode="GUIDED"))
    cmds = ctl.on_frame(t, [zone(2, -20, 5, t, born=-4)], pose(t, 10, 0, 18))  # zone 1 gone: people walked in
    assert len(cmds) == 1 and cmds[0].zone_id == 2 and ctl.phase == Phase.APPROACH
    lat, lon = expected_latlon(-20, 5)
    assert (cmds[0].target.lat_deg, cmds[0].target.lon_deg) == pytest.approx((lat, lon), abs=1e-9)
    assert any("zone 1 lost (no longer tracked); re-targeting zone 2" in x for x in texts(ctl))


def test_zone_shrinking_below_r0_with_no_alternative_holds_then_hands_back():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    t = 0.1
    ctl.on_state(status(t, 10, 0, 17, mode="GUIDED"))
    # One frame that sees it too small is not enough (lose_after_frames = 2): no command, no hold.
    assert ctl.on_frame(t, [zone(1, 10, 0, t, r=1.5, born=-8)], pose(t, 10, 0, 17)) == []
    assert ctl.phase == Phase.DESCEND
    t = 0.2
    ctl.on_state(status(t, 10, 0, 17, mode="GUIDED"))
    cmds = ctl.on_frame(t, [zone(1, 10, 0, t, r=1.5, born=-8)], pose(t, 10, 0, 17))
    assert ctl.phase == Phase.HOLD
    assert len(cmds) == 1 and cmds[0].zone_id is None  # hold where it is
    lat, lon = expected_latlon(10, 0)
    assert (cmds[0].target.lat_deg, cmds[0].target.lon_deg, cmds[0].target.rel_alt_m) == pytest.approx((lat, lon, 17))
    assert any("shrank to r 1.5 m < r0 2 m" in x for x in texts(ctl))
    while ctl.phase == Phase.HOLD:
        t += 0.1
        ctl.on_state(status(t, 10, 0, 17, mode="GUIDED"))
        ctl.on_frame(t, [], pose(t, 10, 0, 17))
        cmds = ctl.tick(t)
    assert ctl.phase == Phase.HANDBACK and isinstance(cmds[0], Handback)
    assert t == pytest.approx(0.2 + 4.0, abs=0.11)


def test_hold_resumes_when_a_stable_zone_appears():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    ctl.on_state(status(0.2, 10, 0, 17, mode="GUIDED"))
    ctl.on_frame(0.2, [], pose(0.2, 10, 0, 17))
    assert ctl.phase == Phase.HOLD
    cmds = ctl.on_frame(0.3, [zone(4, 0, 30, 0.3)], pose(0.3, 10, 0, 17))
    assert ctl.phase == Phase.APPROACH and cmds[0].zone_id == 4


def test_one_frame_that_sees_the_zone_too_small_pauses_commands_and_loses_nothing():
    """The network's one-frame false detections used to throw a landing back to HOLD: a single
    frame that sees less than r0 free around the vehicle now sends nothing and changes nothing,
    and a good frame after it starts the count again. Two in a row lose the zone."""
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    texts(ctl)
    t = 0.2
    for k in range(6):  # bad, good, bad, good, ...: never two bad frames in a row
        r = 1.2 if k % 2 == 0 else 4.1
        ctl.on_state(status(t, 10, 0, 17, mode="GUIDED"))
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, r=r, born=-8)], pose(t, 10, 0, 17))
        if r < 2.0:
            assert cmds == []  # nothing toward a zone this frame saw too small
        assert ctl.phase == Phase.DESCEND
        t += 0.1
    assert ctl.failures_tolerated == 3 and texts(ctl) == []
    for _ in range(2):
        ctl.on_state(status(t, 10, 0, 17, mode="GUIDED"))
        ctl.on_frame(t, [zone(1, 10, 0, t, r=1.2, born=-8)], pose(t, 10, 0, 17))
        t += 0.1
    assert ctl.phase == Phase.HOLD
    assert any("zone 1 lost (shrank to r 1.2 m < r0 2 m); holding" in x for x in texts(ctl))


def test_lose_after_one_frame_reacts_to_the_first_frame_as_before():
    ctl = LandingController(dataclasses.replace(CFG, lose_after_frames=1))
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    ctl.on_state(status(0.2, 10, 0, 17, mode="GUIDED"))
    cmds = ctl.on_frame(0.2, [zone(1, 10, 0, 0.2, r=1.5, born=-8)], pose(0.2, 10, 0, 17))
    assert ctl.phase == Phase.HOLD and cmds[0].zone_id is None


def test_a_zone_gone_from_the_tracks_is_lost_at_once_whatever_lose_after_frames_says():
    ctl = LandingController(dataclasses.replace(CFG, lose_after_frames=5))
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    ctl.on_state(status(0.2, 10, 0, 17, mode="GUIDED"))
    ctl.on_frame(0.2, [], pose(0.2, 10, 0, 17))  # the tracker dropped it: that took mu_1 frames already
    assert ctl.phase == Phase.HOLD


def test_a_briefly_unconfirmed_zone_pauses_commands_then_is_lost():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    t = 0.2
    for _ in range(9):  # missed for 0.9 s < zone_max_age_s: no command toward it, not lost yet
        ctl.on_state(status(t, 10, 0, 17, mode="GUIDED"))
        assert ctl.on_frame(t, [zone(1, 10, 0, t, born=-8, misses=2, last=0.1)], pose(t, 10, 0, 17)) == []
        t += 0.1
    assert ctl.phase == Phase.DESCEND
    t += 0.2
    ctl.on_state(status(t, 10, 0, 17, mode="GUIDED"))
    cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8, misses=12, last=0.1)], pose(t, 10, 0, 17))
    assert ctl.phase == Phase.HOLD and cmds[0].zone_id is None


def test_stale_pose_gives_no_command():
    ctl = LandingController(CFG)
    ctl.on_state(status(0.0))
    ctl.on_trigger(trigger(0.0))
    t = 1.0
    ctl.on_state(status(t))
    good = [zone(1, 10, 0, t)]
    assert ctl.on_frame(t, good, None) == []  # no pose at all
    assert ctl.on_frame(t, good, pose(t - 0.5)) == []  # pose far from the frame's capture time
    assert ctl.on_frame(t, good, Pose(t, float("nan"), 0, -30, 0, 0, 0)) == []
    ctl.tick(t + 2.0)
    assert ctl.on_frame(t, good, pose(t)) == []  # a frame captured too long ago
    assert ctl.frames_ignored == 4 and ctl.phase == Phase.SELECT


def test_stale_vehicle_position_gives_no_command_and_then_hands_back():
    ctl = LandingController(CFG)
    ctl.on_state(status(0.0))
    ctl.on_trigger(trigger(0.0))
    assert ctl.on_frame(1.5, [zone(1, 10, 0, 1.5)], pose(1.5)) == []  # status is 1.5 s old
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    t = 0.2
    cmds = []
    while not cmds:  # frames keep coming, telemetry stopped at 0.1 s
        ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 20))
        cmds = ctl.tick(t)
        t += 0.1
    assert cmds == [Handback("LAND", "vehicle position stale")]


def test_repeated_refusals_hand_back():
    ctl = LandingController(CFG)
    ctl.on_state(status(0.0))
    ctl.on_trigger(trigger(0.0))
    t = 0.1
    goto = ctl.on_frame(t, [zone(1, 10, 0, t)], pose(t))[0]
    refused = CommandRefused(176, 2)
    assert ctl.on_command_result(goto, refused) == []
    for _ in range(2):
        t += 0.1
        ctl.on_state(status(t))
        again = ctl.on_frame(t, [zone(1, 10, 0, t)], pose(t))
        assert again and isinstance(again[0], Goto)  # re-sent after a refusal
        result = ctl.on_command_result(again[0], refused)
    assert result == [Handback("LAND", "3 commands failed in a row")]
    assert ctl.phase == Phase.HANDBACK


def test_a_success_resets_the_refusal_count():
    ctl = LandingController(CFG)
    ctl.on_state(status(0.0))
    ctl.on_trigger(trigger(0.0))
    goto = ctl.on_frame(0.1, [zone(1, 10, 0, 0.1)], pose(0.1))[0]
    ctl.on_command_result(goto, CommandRefused(176, 2))
    ctl.on_command_result(goto, CommandRefused(176, 2))
    ctl.on_command_result(goto, None)
    assert ctl.on_command_result(goto, CommandRefused(176, 2)) == [] and ctl.phase == Phase.APPROACH


def test_pilot_taking_over_stops_the_companion_without_a_command():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    assert ctl.on_state(status(0.2, 10, 0, 18, mode="POSHOLD")) == []
    assert ctl.phase == Phase.HANDBACK
    assert ctl.on_frame(0.3, [zone(1, 10, 0, 0.3, born=-8)], pose(0.3, 10, 0, 18)) == []


def test_land_is_aborted_above_the_commit_altitude_only():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=11.0)
    assert ctl.phase == Phase.DESCEND
    ctl.on_state(status(0.2, 10, 0, 10.2, mode="GUIDED"))
    assert ctl.on_frame(0.2, [zone(1, 10, 0, 0.2, born=-8)], pose(0.2, 10, 0, 10.2)) == [Land()]
    ctl.on_state(status(0.3, 10, 0, 4.0, mode="LAND"))
    assert ctl.on_frame(0.3, [], pose(0.3, 10, 0, 4.0)) == []  # committed below 5 m
    assert ctl.phase == Phase.LAND
    ctl2 = LandingController(CFG)
    start_descent(ctl2, [zone(1, 10, 0, 0.0, born=-8)], alt=11.0)
    ctl2.on_state(status(0.2, 10, 0, 10.2, mode="GUIDED"))
    ctl2.on_frame(0.2, [zone(1, 10, 0, 0.2, born=-8)], pose(0.2, 10, 0, 10.2))
    ctl2.on_state(status(0.3, 10, 0, 8.0, mode="LAND"))
    # Above the commit height, the zone gone and somebody seen 0.9 m from the vehicle: HOLD.
    cmds = ctl2.on_frame(0.3, [], pose(0.3, 10, 0, 8.0), GroundBelow(10.0, 0.0, 0.9, 4.0))
    assert ctl2.phase == Phase.HOLD and isinstance(cmds[0], Goto) and cmds[0].zone_id is None


def test_config_errors_name_the_key():
    with pytest.raises(ValueError, match="handback_action"):
        LandingConfig(handback_action="LOITER")
    with pytest.raises(ValueError, match="descend_step_m"):
        LandingConfig(descend_step_m=0)
    with pytest.raises(ValueError, match="min_track_hits"):
        PlannerConfig(min_track_hits=0)
    with pytest.raises(ValueError, match="lose_after_frames"):
        LandingConfig(lose_after_frames=0)


def test_a_rangefinder_height_decides_when_to_land_over_raised_ground():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=20.0)
    # The zone is on a 8 m rise: 20 m above home is only 12 m above the ground there.
    ctl.on_state(status(0.2, 10, 0, 20.0, mode="GUIDED", agl=12.0))
    cmds = ctl.on_frame(0.2, [zone(1, 10, 0, 0.2, born=-8)], pose(0.2, 10, 0, 20.0))
    assert cmds[0].target.rel_alt_m == pytest.approx(18.0)  # a 2 m step, not 3: stop at 10 m AGL
    ctl.on_state(status(0.3, 10, 0, 18.2, mode="GUIDED", agl=10.2))
    assert ctl.on_frame(0.3, [zone(1, 10, 0, 0.3, born=-8)], pose(0.3, 10, 0, 18.2)) == [Land()]


def test_touching_down_early_during_the_descent_hands_to_land():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=20.0)
    ctl.on_state(status(0.2, 10, 0, 14.0, mode="GUIDED", on_ground=True))
    assert ctl.on_frame(0.2, [zone(1, 10, 0, 0.2, born=-8)], pose(0.2, 10, 0, 14.0)) == [Land()]
    ctl.on_state(status(0.3, 10, 0, 14.0, mode="LAND", on_ground=True))
    assert ctl.phase == Phase.LANDED


def test_hold_low_over_a_lost_zone_climbs_back_to_see():
    ctl = LandingController(dataclasses.replace(CFG, hold_height_m=15.0))
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    for t in (0.1, 0.2):  # seen too small on two frames in a row: lost
        ctl.on_state(status(t, 10, 0, 8, mode="GUIDED"))
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, r=1.0, born=-8)], pose(t, 10, 0, 8))
    assert ctl.phase == Phase.HOLD
    assert cmds[0].zone_id is None and cmds[0].target.rel_alt_m == pytest.approx(15.0)


def test_a_takeover_that_keeps_retargeting_hands_back_within_its_budget():
    ctl = LandingController(dataclasses.replace(CFG, max_takeover_s=5.0))
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8), zone(2, -20, 5, 0.0, born=-4)])
    t, handed_back = 0.2, None
    while t < 10.0 and handed_back is None:
        # Zones come and go: each frame shows the other one only, so the controller keeps
        # re-targeting and never lands. The vehicle stays where start_descent left it: a jump of
        # 10 m in 0.1 s would (rightly) be judged a vehicle that does not obey its target.
        zid, x = (2, -20) if int(t * 10) % 2 else (1, 10)
        ctl.on_state(status(t, 10, 0, 18, mode="GUIDED"))
        ctl.on_frame(t, [zone(zid, x, 0, t, born=-8)], pose(t, 10, 0, 18))
        cmds = ctl.tick(t)
        if ctl.phase == Phase.HANDBACK:
            handed_back = t
        t += 0.1
    assert handed_back == pytest.approx(5.0, abs=0.15)
    assert isinstance(cmds[0], Handback)
    assert any("not landed within 5 s of the trigger" in x for x in texts(ctl))


def test_the_takeover_budget_does_not_interrupt_a_landing_under_way():
    ctl = LandingController(dataclasses.replace(CFG, max_takeover_s=5.0))
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    t = 0.2
    while ctl.phase != Phase.LAND and t < 3.0:
        ctl.on_state(status(t, 10, 0, 9.5, mode="GUIDED"))
        ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 9.5))
        t += 0.1
    assert ctl.phase == Phase.LAND
    for k in range(80):  # 8 s more, well past the budget, still descending over the zone
        t += 0.1
        ctl.on_state(status(t, 10, 0, 9.0 - 0.05 * k, mode="LAND"))
        ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 9.0 - 0.05 * k))
        ctl.tick(t)
    assert ctl.phase == Phase.LAND


def test_descent_needs_r0_free_around_the_vehicle_not_only_around_the_zone_centre():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)])
    # The vehicle is 0.9 m off the zone's centre; the zone is 2.5 m: only 1.6 m free around it,
    # on two frames in a row.
    for t in (0.1, 0.2):
        ctl.on_state(status(t, 10.9, 0, 17, mode="GUIDED"))
        ctl.on_frame(t, [zone(1, 10, 0, t, r=2.5, born=-8)], pose(t, 10.9, 0, 17))
    assert ctl.phase == Phase.HOLD
    assert any("1.6 m free around the vehicle < r0 2 m" in x for x in texts(ctl))


def test_the_ground_measured_under_the_camera_keeps_a_descent_over_a_view_bounded_zone():
    """Low over a zone the view bounds it: the zone's centre sits off the vehicle, away from the
    people at one side, and its radius less that offset is under r0 although the frame measured
    4 m free straight under the camera. That frame's measure keeps the descent going; seen
    occupied under the camera, the zone is lost as before."""
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    texts(ctl)
    t = 0.2
    for _ in range(10):
        ctl.on_state(status(t, 11.5, 0, 11, mode="GUIDED"))
        below = GroundBelow(11.5, 0.0, r=4.0, r_view=4.6)  # a person 4 m away; 1.6 m by r - offset
        ctl.on_frame(t, [zone(1, 10, 0, t, r=3.1, born=-8)], pose(t, 11.5, 0, 11), below)
        t += 0.1
    assert ctl.phase == Phase.DESCEND and ctl.failures_tolerated == 0 and texts(ctl) == []
    # The frame was taken 1 m from where the vehicle is now: 4.0 - 1.0 = 3.0 m is still >= r0,
    # and 2.5 - 1.0 = 1.5 m is not (one frame: tolerated, nothing lost).
    ctl.on_state(status(t, 11.5, 0, 11, mode="GUIDED"))
    ctl.on_frame(t, [zone(1, 10, 0, t, r=3.1, born=-8)], pose(t, 11.5, 0, 11), GroundBelow(10.5, 0.0, 4.0, 4.6))
    assert ctl.phase == Phase.DESCEND and ctl.failures_tolerated == 0
    t += 0.1
    ctl.on_state(status(t, 11.5, 0, 11, mode="GUIDED"))
    ctl.on_frame(t, [zone(1, 10, 0, t, r=3.1, born=-8)], pose(t, 11.5, 0, 11), GroundBelow(10.5, 0.0, 2.5, 4.6))
    assert ctl.phase == Phase.DESCEND and ctl.failures_tolerated == 1
    for _ in range(2):  # somebody 1.2 m from the vehicle, on two frames
        t += 0.1
        ctl.on_state(status(t, 11.5, 0, 11, mode="GUIDED"))
        ctl.on_frame(t, [zone(1, 10, 0, t, r=3.1, born=-8)], pose(t, 11.5, 0, 11), GroundBelow(11.5, 0.0, 1.2, 4.6))
    assert ctl.phase in (Phase.HOLD, Phase.APPROACH)  # out of the descent (HOLD, or back to a zone)
    assert any("zone 1 lost (1.6 m free around the vehicle < r0 2 m)" in x for x in texts(ctl))


def test_a_zone_the_tracker_drops_low_down_holds_while_the_ground_under_the_vehicle_is_seen_free():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    texts(ctl)
    t = 0.2
    for _ in range(5):  # no tracks at all, r0 free under the vehicle: the descent goes on
        ctl.on_state(status(t, 10, 0, 11, mode="GUIDED"))
        ctl.on_frame(t, [], pose(t, 10, 0, 11), GroundBelow(10.0, 0.0, 2.6, 3.0))
        t += 0.1
    assert ctl.phase == Phase.DESCEND and texts(ctl) == []
    # Without the measure (or with somebody within r0 of the vehicle) it is lost as before.
    ctl.on_state(status(t, 10, 0, 11, mode="GUIDED"))
    ctl.on_frame(t, [], pose(t, 10, 0, 11), GroundBelow(10.0, 0.0, 1.1, 3.0))
    assert ctl.phase == Phase.HOLD
    assert any("zone 1 lost (no longer tracked)" in x for x in texts(ctl))


def test_an_all_free_view_under_the_camera_counts_and_a_broken_measure_is_ignored():
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    t = 0.2
    for _ in range(5):  # 1.5 m seen around the vehicle, all of it free: the view bounds it
        ctl.on_state(status(t, 11.5, 0, 11, mode="GUIDED"))
        ctl.on_frame(t, [zone(1, 10, 0, t, r=3.1, born=-8)], pose(t, 11.5, 0, 11), GroundBelow(11.5, 0, 1.5, 1.5))
        t += 0.1
    assert ctl.phase in (Phase.DESCEND, Phase.LAND) and ctl.failures_tolerated == 0
    ctl2 = LandingController(CFG)
    start_descent(ctl2, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    for k in range(2):  # NaN under the camera: ignored, the zone's own measure (1.6 m) decides
        t = 0.2 + 0.1 * k
        ctl2.on_state(status(t, 11.5, 0, 11, mode="GUIDED"))
        ctl2.on_frame(t, [zone(1, 10, 0, t, r=3.1, born=-8)], pose(t, 11.5, 0, 11),
                      GroundBelow(11.5, 0, math.nan, 4.6))
    assert ctl2.phase == Phase.HOLD and ctl2.below is None


def _in_land(ctl: LandingController, r_view: float) -> float:
    """Fly ctl to LAND over a view-limited zone 1 whose last view reached ``r_view`` m."""
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    t = 0.2
    while ctl.phase != Phase.LAND and t < 3.0:
        ctl.on_state(status(t, 10, 0, 10.2, mode="GUIDED"))
        ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 10.2))
        t += 0.1
    assert ctl.phase == Phase.LAND
    ctl.on_state(status(t, 10, 0, 6.0, mode="LAND"))
    low = dataclasses.replace(zone(1, 10, 0, t, born=-8, r=r_view), view_limited=True, r_view=r_view)
    ctl.on_frame(t, [low], pose(t, 10, 0, 6.0))
    assert ctl.phase == Phase.LAND
    texts(ctl)
    return t + 0.1


def test_a_zone_dropping_out_of_a_tiny_all_free_view_in_land_commits_the_landing():
    ctl = LandingController(CFG)
    t = _in_land(ctl, r_view=1.1)
    for k in range(15):  # gone from the tracks: the view at 5.9 m is too small to confirm anything
        ctl.on_state(status(t, 10, 0, 5.9 - 0.1 * k, mode="LAND"))
        assert ctl.on_frame(t, [], pose(t, 10, 0, 5.9 - 0.1 * k)) == []
        t += 0.1
    assert ctl.phase == Phase.LAND
    assert any("out of view at 5.9 m, nobody seen within r0: landing committed" in x for x in texts(ctl))


@pytest.mark.parametrize("height, below, phase", [
    # The zone's track said "all free" around its own centre, at the edge of a small view; under
    # the vehicle this frame sees a person 0.8 m away: that is a lost zone, not a blind one.
    (7.5, GroundBelow(10.0, 0.0, 0.8, 4.0), Phase.HOLD),
    # The same with everything under the vehicle seen free: committed, as before.
    (5.9, GroundBelow(10.0, 0.0, 1.2, 1.2), Phase.LAND),
])
def test_a_zone_out_of_view_never_commits_while_the_frame_sees_someone_within_r0_of_the_vehicle(
        height, below, phase):
    ctl = LandingController(CFG)
    t = _in_land(ctl, r_view=1.1)
    for _ in range(3):
        ctl.on_state(status(t, 10, 0, height, mode="LAND"))
        ctl.on_frame(t, [], pose(t, 10, 0, height), below)
        t += 0.1
    assert ctl.phase == phase
    if phase == Phase.HOLD:
        assert not any("landing committed" in x for x in texts(ctl))


def test_a_zone_gone_from_a_large_view_in_land_commits_unless_someone_is_seen_within_r0():
    # The real PX4 SIH: its altitude reading 1.3-1.8 m off, the view the pipeline computed was
    # larger than the camera's; the zone left the tracks at 3-4 m and the vehicle climbed back to
    # 10-12 m, three times (issue 62). Leaving the tracks is no reason to climb; a person is.
    ctl = LandingController(CFG)
    t = _in_land(ctl, r_view=3.0)
    ctl.on_state(status(t, 10, 0, 5.9, mode="LAND"))
    assert ctl.on_frame(t, [], pose(t, 10, 0, 5.9)) == []
    assert ctl.phase == Phase.LAND
    assert any("nobody seen within r0: landing committed" in x for x in texts(ctl))
    ctl = LandingController(CFG)
    t = _in_land(ctl, r_view=3.0)
    ctl.on_state(status(t, 10, 0, 5.9, mode="LAND"))
    ctl.on_frame(t, [], pose(t, 10, 0, 5.9), GroundBelow(10.0, 0.0, 0.9, 4.0))  # a person 0.9 m away
    assert ctl.phase == Phase.HOLD
    ctl = LandingController(CFG)
    t = _in_land(ctl, r_view=1.1)
    for k in range(2):  # someone walked in, seen on two frames in a row
        ctl.on_state(status(t + 0.1 * k, 10, 0, 5.9, mode="LAND"))
        ctl.on_frame(t + 0.1 * k, [zone(1, 10, 0, t + 0.1 * k, born=-8, r=0.4)], pose(t + 0.1 * k, 10, 0, 5.9))
    assert ctl.phase == Phase.HOLD


def test_disarmed_by_landing_in_offboard_is_landed_and_disarmed_in_the_air_stops_the_companion():
    # PX4's land detector disarms in OFFBOARD too, and its heartbeat still says OFFBOARD.
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    assert ctl.on_state(status(0.2, 10, 0, 0.0, mode="OFFBOARD", armed=False, on_ground=True)) == []
    assert ctl.phase == Phase.LANDED
    assert ctl.on_frame(0.3, [zone(1, 10, 0, 0.3, born=-8)], pose(0.3, 10, 0, 0.0)) == []
    assert ctl.tick(5.0) == []
    ctl = LandingController(CFG)
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    assert ctl.on_state(status(0.2, 10, 0, 11.0, mode="GUIDED", armed=False, on_ground=False)) == []
    assert ctl.phase == Phase.HANDBACK  # nothing to command to a vehicle with its motors off
    assert any("disarmed in the air" in x for x in texts(ctl))


def test_the_height_where_people_look_large_enough_to_trust_free():
    fx = 320.0 / math.tan(math.radians(35.0))  # the simulator's 640 px, 70 degree camera: 457 px
    assert person_trust_height(fx, 8.0) == pytest.approx(1.7 + fx * 0.4 / 8.0)  # 24.6 m
    assert person_trust_height(fx, None) == math.inf
    with pytest.raises(ValueError, match="min_person_px"):
        person_trust_height(fx, 0.0)
    with pytest.raises(ValueError, match="trust_height_m"):
        LandingConfig(trust_height_m=math.nan)


def _fly_down(ctl: LandingController, trigger_alt: float) -> tuple[list[float], float]:
    """Trigger at ``trigger_alt`` over zone 3 (12 m north); follow every target. Returns the
    target altitudes and the height at which LAND was commanded."""
    ctl.on_state(status(0.0, alt=trigger_alt, mode="RTL"))
    ctl.on_trigger(trigger(0.0))
    t, alt, north, alts = 0.1, trigger_alt, 0.0, []
    while ctl.phase != Phase.LAND:
        ctl.on_state(status(t, north, 0.9, alt, mode="GUIDED"))
        for c in ctl.on_frame(t, [zone(3, 12.0, 0.9, t, born=-9.0)], pose(t, north, 0.9, alt)):
            if isinstance(c, Goto):
                alts.append(c.target.rel_alt_m)
                alt, north = c.target.rel_alt_m, c.north  # the vehicle gets there
        t += 0.1
        assert t < 10.0, ctl.phase
    return alts, alt


def test_above_the_trust_height_the_candidate_is_approached_at_it_and_judged_below_it():
    # No limit: level approach at 30 m, LAND at descend_alt_m (10 m).
    alts, land_alt = _fly_down(LandingController(CFG), 30.0)
    assert alts[0] == pytest.approx(30.0) and land_alt == pytest.approx(10.0)
    # People look large enough only below 18 m: the approach itself comes down to 18 m.
    alts, land_alt = _fly_down(LandingController(dataclasses.replace(CFG, trust_height_m=18.0)), 30.0)
    assert alts[0] == pytest.approx(18.0) and max(alts) <= 18.0 and land_alt == pytest.approx(10.0)
    # Only below 6 m: the descent goes on past descend_alt_m, and LAND waits until 6 m.
    alts, land_alt = _fly_down(LandingController(dataclasses.replace(CFG, trust_height_m=6.0)), 30.0)
    assert alts[0] == pytest.approx(10.0)  # never below descend_alt_m before it is over the zone
    assert land_alt == pytest.approx(6.0) and min(alts) == pytest.approx(6.0)


def _low_over_zone(ctl: LandingController) -> float:
    """Fly ctl down to the LAND height over zone 1 (at north 10, east 0) without commanding it
    yet: returns the time reached."""
    start_descent(ctl, [zone(1, 10, 0, 0.0, born=-8)], alt=12.0)
    return 0.2


#: The controller that waits for calm ground before the LAND (off by default: docs/design.md).
CALM = dataclasses.replace(CFG, planner=dataclasses.replace(CFG.planner, min_calm_s=6.0), calm_wait_s=3.0)


def below(t: float, calm: float, north: float = 10.0, east: float = 0.0) -> GroundBelow:
    return GroundBelow(north, east, 6.0, 6.0, calm_s=calm)


def test_the_land_waits_for_calm_ground_under_the_vehicle_and_says_so_once():
    """Over the zone, low enough: a gap a walker left 2 s ago is free but not calm; the vehicle
    hovers (a Note, no phase change) and commands the LAND once the ground has been watched free
    for min_calm_s, the calm it had written into the LAND event."""
    ctl = LandingController(CALM)
    t = _low_over_zone(ctl)
    texts(ctl)
    for calm in (2.0, 2.1, 2.2, math.nan):  # NaN: not measured, never calm
        ctl.on_state(status(t, 10, 0, 9.8, mode="GUIDED"))
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 9.8), below(t, calm))
        assert not any(isinstance(c, Land) for c in cmds) and ctl.phase == Phase.DESCEND
        t += 0.1
    notes = texts(ctl)
    assert len(notes) == 1 and "watched free for 2.0 s, not 6 s: waiting before the LAND" in notes[0]
    ctl.on_state(status(t, 10, 0, 9.8, mode="GUIDED"))
    assert Land() in ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 9.8), below(t, 6.3))
    land = [e for e in ctl.pop_events() if e.phase == Phase.LAND]
    assert land and land[0].as_record()["calm_s"] == 6.3


#: Judged (calm) at descend_alt_m, then the companion's own descent down to 4 m before the LAND.
LOW = dataclasses.replace(CALM, land_alt_m=4.0)


def _descend_low(ctl: LandingController, t: float, zone_r: float = 4.1, until_alt: float = 0.0,
                 calm_at_top: float = 6.3, alt: float = 9.8) -> tuple[float, float, list[float], list]:
    """From ``alt`` (9.8 m) over zone 1, follow the controller's targets down (the vehicle reaches each),
    the ground below calm at the top only (NaN below: the calm disc no longer fits in the view).
    Stops at a LAND, at a phase other than DESCEND, or below ``until_alt``. Returns the time, the
    altitude, the targets' altitudes and the last commands."""
    alts: list[float] = []
    cmds: list = []
    while t < 20.0:
        ctl.on_state(status(t, 10, 0, alt, mode="GUIDED"))
        calm = calm_at_top if alt >= 9.5 else math.nan
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8, r=zone_r)], pose(t, 10, 0, alt), below(t, calm))
        t += 0.1
        if any(isinstance(c, Land) for c in cmds) or ctl.phase != Phase.DESCEND:
            break
        for c in cmds:
            if isinstance(c, Goto):
                if not alts or c.target.rel_alt_m != alts[-1]:
                    alts.append(c.target.rel_alt_m)
                alt = c.target.rel_alt_m
        if alt < until_alt:
            break
    return t, alt, alts, cmds


def test_a_judged_zone_is_flown_down_to_land_alt_before_the_land_watched_all_the_way():
    """land_alt_m: the zone is judged calm at 9.8 m, then the companion's own stepped descent goes
    on to 4 m (no second calm wait below, where the calm disc no longer fits in the view), and
    the autopilot's LAND is commanded only there: its slow descent is 4 m long, not 10."""
    ctl = LandingController(LOW)
    t = _low_over_zone(ctl)
    texts(ctl)
    t, alt, alts, cmds = _descend_low(ctl, t)
    assert cmds == [Land()] and ctl.phase == Phase.LAND
    assert alts == [7.0, 4.0] and alt == pytest.approx(4.0)
    events = ctl.pop_events()
    said = [e.text for e in events]
    assert said[0] == "SLZ: zone 1 judged at 9.8 m (calm 6.3 s): descending over it to 4 m before the LAND"
    assert not any("waiting before the LAND" in x for x in said)
    land = [e for e in events if e.phase == Phase.LAND]
    assert land and land[0].text.startswith("SLZ: LAND over zone 1 at 4.0 m")
    # The time to touchdown that every clearance is judged against follows the new profile.
    assert LOW.descent.time_to_touchdown(10.0) == pytest.approx(10.0 / LOW.descent.land_speed_mps)
    low_profile = dataclasses.replace(LOW.descent, land_alt_m=4.0)
    assert low_profile.time_to_touchdown(10.0) == pytest.approx(6.0 / 1.5 + 4.0 / 0.5)


def test_a_judged_zone_leaving_the_tracks_low_down_is_no_reason_to_climb_a_person_is():
    """Below the judging height the view is too small to confirm the zone; the simulated PX4 with
    its altitude reading 1.3 m low lost it there on every descent and climbed back four times until
    the takeover's budget ran out (issue 62). Gone from the tracks, nobody seen within r0 under
    the vehicle: the judged descent goes on to the LAND. Somebody seen: HOLD, as before."""
    ctl = LandingController(LOW)
    t = _low_over_zone(ctl)
    t, alt, alts, _ = _descend_low(ctl, t, until_alt=7.5)
    assert alts == [7.0] and ctl.phase == Phase.DESCEND
    texts(ctl)
    cmds: list = []
    while t < 20.0 and not any(isinstance(c, Land) for c in cmds):
        ctl.on_state(status(t, 10, 0, alt, mode="GUIDED"))
        cmds = ctl.on_frame(t, [], pose(t, 10, 0, alt))  # no zone, and no measure under the vehicle
        alt = min([c.target.rel_alt_m for c in cmds if isinstance(c, Goto)] + [alt])
        t += 0.1
    assert ctl.phase == Phase.LAND and cmds == [Land()]
    said = texts(ctl)
    assert any("zone 1 out of view at 7.0 m, nobody seen within r0: landing committed" in x for x in said), said
    assert not any("lost" in x for x in said)
    ctl = LandingController(LOW)
    t = _low_over_zone(ctl)
    t, alt, _, _ = _descend_low(ctl, t, until_alt=7.5)
    ctl.on_state(status(t, 10, 0, alt, mode="GUIDED"))
    ctl.on_frame(t, [], pose(t, 10, 0, alt), GroundBelow(10, 0, 0.9, 3.0))  # somebody 0.9 m away
    assert ctl.phase == Phase.HOLD


def test_somebody_within_r0_during_the_low_descent_sends_it_back_up_and_the_zone_is_judged_again():
    ctl = LandingController(LOW)
    t = _low_over_zone(ctl)
    t, alt, alts, _ = _descend_low(ctl, t, until_alt=7.5)
    assert alts == [7.0] and ctl.phase == Phase.DESCEND
    texts(ctl)
    cmds: list = []
    for _ in range(CFG.lose_after_frames):  # a person walks in: 1.5 m free around the vehicle
        ctl.on_state(status(t, 10, 0, alt, mode="GUIDED"))
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8, r=1.5)], pose(t, 10, 0, alt),
                            GroundBelow(10, 0, 1.5, 1.5 + 0.1, calm_s=0.0))
        t += 0.1
    assert ctl.phase == Phase.HOLD and not any(isinstance(c, Land) for c in cmds)
    goto = [c for c in cmds if isinstance(c, Goto)]
    assert goto and goto[0].target.rel_alt_m >= LOW.hold_height_m  # back up to where it sees enough
    assert any("zone 1 lost" in x for x in texts(ctl))
    # The vehicle climbs back (it follows its targets), the zone is free again: down again to the
    # judging height, where it is judged again (not calm yet this time: it waits there).
    ctl.on_state(status(t, 10, 0, goto[0].target.rel_alt_m, mode="GUIDED"))
    ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, goto[0].target.rel_alt_m), below(t, 1.0))
    assert ctl.phase in (Phase.APPROACH, Phase.DESCEND)
    t, alt, alts, cmds = _descend_low(ctl, t + 0.1, calm_at_top=1.0, alt=goto[0].target.rel_alt_m)
    assert not any(isinstance(c, Land) for c in cmds) and alt == pytest.approx(10.0)
    assert any("waiting before the LAND" in x for x in texts(ctl))


def test_land_alt_m_off_or_above_the_judging_height():
    assert dataclasses.replace(CALM, land_alt_m=0.0).land_alt_m == 0.0  # 0: LAND at descend_alt_m
    with pytest.raises(ValueError, match="land_alt_m"):
        dataclasses.replace(CFG, land_alt_m=12.0)  # above descend_alt_m (10 m)
    with pytest.raises(ValueError, match="land_alt_m"):
        dataclasses.replace(CFG, land_alt_m=-1.0)


#: LOW with the last metres flown by the companion, by the rangefinder, to 1 m (land_agl_m).
AGL = dataclasses.replace(LOW, land_agl_m=1.0)


def _at_the_land(ctl: LandingController, ground: float = 0.0) -> tuple[float, list]:
    """Judge zone 1 at 9.8 m and follow the stepped descent to the LAND height with a rangefinder
    over ground ``ground`` m above home (the vehicle reaches each target). Returns the time and
    the commands of the frame that reached the LAND height."""
    t = _low_over_zone(ctl)
    alt, cmds = 9.8, []
    while t < 30.0:
        ctl.on_state(status(t, 10, 0, alt, mode="GUIDED", agl=alt - ground))
        calm = 6.3 if alt >= 9.5 else math.nan
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, alt), below(t, calm))
        t += 0.1
        if ctl.phase == Phase.LAND or any(isinstance(c, Land) for c in cmds):
            return t, cmds
        alt = next((c.target.rel_alt_m for c in cmds if isinstance(c, Goto)), alt)
    raise AssertionError("never reached the LAND")


def test_with_a_rangefinder_the_last_metres_are_the_companions_own_descent_then_the_land():
    """land_agl_m: at the LAND height (4 m) the companion does not command the autopilot's slow
    LAND yet; it flies straight down over the landing point (GUIDED) to 1 m above the ground the
    rangefinder measures, watched by the obedience check, and commands the LAND there."""
    ctl = LandingController(AGL)
    t, cmds = _at_the_land(ctl)
    assert ctl.phase == Phase.LAND and not any(isinstance(c, Land) for c in cmds)
    goto = [c for c in cmds if isinstance(c, Goto)]
    assert len(goto) == 1 and goto[0].target.rel_alt_m == pytest.approx(1.0)
    assert (goto[0].north, goto[0].east) == pytest.approx((10.0, 0.0))
    land = [e for e in ctl.pop_events() if e.phase == Phase.LAND]
    assert land[0].text == "SLZ: LAND over zone 1 at 4.0 m, radius 4.1 m, first down to 1 m by the rangefinder"
    # The time to touchdown judged from here is the shorter one: 3 m at 1.5 m/s, 1 m at 0.5 m/s.
    assert ctl._descent_now().time_to_touchdown(4.0) == pytest.approx(3.0 / 1.5 + 1.0 / 0.5)
    assert land[0].as_record()["touchdown_clearance_m"] == pytest.approx(4.1 - 1.5 * 4.0)
    for alt in (3.4, 2.5, 1.6):
        cmds = ctl.on_state(status(t, 10, 0, alt, mode="GUIDED", agl=alt, vd=1.5))
        assert not any(isinstance(c, Land) for c in cmds) and ctl.phase == Phase.LAND
        assert ctl.obedience.engaged  # it flies our target: a vehicle that climbs is handed back
        t += 0.7
    assert ctl.on_state(status(t, 10, 0, 1.15, mode="GUIDED", agl=1.15)) == [Land()]
    assert texts(ctl)[-1] == "SLZ: zone 1: LAND now, 1.1 m above the ground by the rangefinder"
    assert ctl.on_state(status(t + 0.1, 10, 0, 1.1, mode="LAND", agl=1.1)) == []  # the autopilot lands it
    assert not ctl.obedience.engaged
    ctl.on_state(status(t + 2.5, 10, 0, 0.0, mode="LAND", on_ground=True))
    assert ctl.phase == Phase.LANDED


def _low_target(ctl: LandingController) -> tuple[float, float, float]:
    """Where the companion's own descent in LAND goes: north, east (m from home), altitude (m above home)."""
    low = ctl._low_to
    assert low is not None
    return (low.north, low.east, low.alt_m)


def test_the_rangefinder_target_is_the_ground_it_measures_fixed_once():
    """Over ground 1.5 m above home the target is 2.5 m above home, and a later reading (a bump,
    a long echo) does not move it."""
    ctl = LandingController(AGL)
    _, cmds = _at_the_land(ctl, ground=1.5)
    goto = [c for c in cmds if isinstance(c, Goto)]
    assert goto and goto[0].target.rel_alt_m == pytest.approx(2.5)
    assert _low_target(ctl) == pytest.approx((10.0, 0.0, 2.5))
    ctl.on_state(status(50.0, 10, 0, 4.5, mode="GUIDED", agl=30.0))
    assert _low_target(ctl) == pytest.approx((10.0, 0.0, 2.5))


@pytest.mark.parametrize("agl", [None, math.nan])
def test_a_rangefinder_lost_on_the_way_down_commands_the_land_at_once(agl):
    ctl = LandingController(AGL)
    t, _ = _at_the_land(ctl)
    assert Land() not in ctl.on_state(status(t, 10, 0, 3.0, mode="GUIDED", agl=3.0))
    assert ctl.on_state(status(t + 0.5, 10, 0, 2.6, mode="GUIDED", agl=agl)) == [Land()]
    assert "LAND now, no rangefinder height at 2.6 m above home" in texts(ctl)[-1]
    # The time to touchdown judged from here is the autopilot's LAND's again: 2.6 m at 0.5 m/s.
    assert ctl._descent_now().time_to_touchdown(2.6) == pytest.approx(2.6 / 0.5)


def test_without_a_rangefinder_or_with_the_setting_off_the_land_is_commanded_at_land_alt():
    no_rangefinder = LandingController(AGL)
    t = _low_over_zone(no_rangefinder)
    _t, _alt, _alts, cmds = _descend_low(no_rangefinder, t)  # statuses without agl
    assert cmds == [Land()] and no_rangefinder.phase == Phase.LAND
    off = LandingController(dataclasses.replace(AGL, land_agl_m=0.0))
    _, cmds = _at_the_land(off)
    assert cmds == [Land()]


def test_the_ground_before_the_rangefinder_height_hands_to_the_land_that_disarms():
    ctl = LandingController(AGL)
    t, _ = _at_the_land(ctl)
    cmds = ctl.on_state(status(t, 10, 0, 2.0, mode="GUIDED", agl=0.3, on_ground=True, armed=True))
    assert cmds == [Land()] and ctl.phase == Phase.LAND  # in GUIDED it would sit there armed
    ctl.on_state(status(t + 0.5, 10, 0, 2.0, mode="LAND", agl=0.3, on_ground=True, armed=False))
    assert ctl.phase == Phase.LANDED


def test_the_companions_last_metres_are_committed_below_the_abort_height():
    """Below land_abort_above_m (5 m here) nothing the camera sees sends it back up: a view of
    the last metres cannot confirm r0 and a zone seen small there is the low view, not a walker
    the vehicle could still avoid (as for the autopilot's LAND)."""
    ctl = LandingController(AGL)
    t, _ = _at_the_land(ctl)
    for _ in range(3):
        ctl.on_state(status(t, 10, 0, 3.0, mode="GUIDED", agl=3.0))
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8, r=0.6)], pose(t, 10, 0, 3.0),
                            GroundBelow(10, 0, 0.6, 0.7, calm_s=0.0))
        assert not any(isinstance(c, (Handback, Land)) for c in cmds)
        t += 0.1
    assert ctl.phase == Phase.LAND and _low_target(ctl) == pytest.approx((10.0, 0.0, 1.0))
    assert ctl.on_state(status(t, 10, 0, 1.0, mode="GUIDED", agl=1.0)) == [Land()]


def test_the_last_metres_go_straight_down_where_they_started_whatever_the_zone_does():
    """A zone bounded by the view moves with the camera: its centre must not pull the committed
    descent sideways."""
    ctl = LandingController(AGL)
    t, _ = _at_the_land(ctl)
    ctl.on_state(status(t, 10, 0, 3.4, mode="GUIDED", agl=3.4))
    ctl.on_frame(t, [zone(1, 12.5, 1.5, t, born=-8, r=5.0)], pose(t, 10, 0, 3.4), below(t, math.nan))
    cmds = ctl.on_state(status(t + 1.5, 10, 0, 3.0, mode="GUIDED", agl=3.0))  # past the refresh
    goto = [c for c in cmds if isinstance(c, Goto)]
    assert goto and (goto[0].north, goto[0].east, goto[0].target.rel_alt_m) == pytest.approx((10.0, 0.0, 1.0))


def test_a_vehicle_that_climbs_in_the_companions_last_metres_is_handed_back():
    ctl = LandingController(AGL)
    t, _ = _at_the_land(ctl)
    cmds: list = []
    for i in range(20):
        alt = 4.0 + 0.2 * i
        cmds = ctl.on_state(status(t, 10, 0, alt, mode="GUIDED", agl=alt, vd=-0.5))
        t += 0.2
        if cmds:
            break
    assert cmds and isinstance(cmds[0], Handback) and cmds[0].action == "LAND"
    assert ctl.phase == Phase.HANDBACK


@pytest.mark.parametrize("bad", [0.3, -1.0, math.nan, math.inf, 4.0, 6.0])
def test_land_agl_m_is_off_or_between_its_floor_and_the_land_height(bad):
    with pytest.raises(ValueError, match="land_agl_m"):
        dataclasses.replace(LOW, land_agl_m=bad)


def test_a_zone_that_never_becomes_calm_is_given_up_for_another_and_not_chosen_again():
    ctl = LandingController(CALM)  # calm_wait_s = 3 s
    t = _low_over_zone(ctl)
    other = zone(2, -20, 5, t, born=-4)
    while t < 3.5:
        ctl.on_state(status(t, 10, 0, 9.8, mode="GUIDED"))
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8), dataclasses.replace(other, last_t=t)],
                            pose(t, 10, 0, 9.8), below(t, 1.0))
        assert not any(isinstance(c, Land) for c in cmds)
        t += 0.1
    assert ctl.phase == Phase.APPROACH and ctl.target is not None and ctl.target.id == 2
    assert any("zone 1 lost (not calm after 3 s over it: people keep passing near it); re-targeting zone 2" in x
               for x in texts(ctl))
    # Zone 2 lost in turn: zone 1, older and still free, is not chosen again; the vehicle holds.
    ctl.on_state(status(t, 10, 0, 9.8, mode="GUIDED"))
    ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 9.8), below(t, 9.0))
    assert ctl.phase == Phase.HOLD and ctl.target is None


def test_calm_off_lands_as_before_whatever_the_ground_below_says():
    ctl = LandingController(CFG)
    t = _low_over_zone(ctl)
    ctl.on_state(status(t, 10, 0, 9.8, mode="GUIDED"))
    assert Land() in ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, 9.8), below(t, 0.0))
    with pytest.raises(ValueError, match="min_calm_s"):
        PlannerConfig(min_calm_s=-1.0)
    with pytest.raises(ValueError, match="calm_wait_s"):
        LandingConfig(calm_wait_s=0.0)


def test_the_planner_chooses_calm_zones_first_then_the_oldest():
    planner = ZonePlanner(dataclasses.replace(CFG.planner, min_calm_s=5.0))
    old_gap = dataclasses.replace(zone(1, 0, 0, 10.0, born=0.0), calm_s=1.0)
    young_lawn = dataclasses.replace(zone(2, 20, 0, 10.0, born=6.0), calm_s=8.0)
    unmeasured = zone(3, 40, 0, 10.0, born=-5.0)  # calm_s NaN: not measured, not calm
    assert planner.choose([old_gap, young_lawn, unmeasured], 10.0).id == 2
    assert planner.choose([old_gap, unmeasured], 10.0).id == 3  # none calm: the oldest, as before
    assert ZonePlanner(CFG.planner).choose([old_gap, young_lawn], 10.0).id == 1  # calm off: the paper's rule


def test_prefer_unwalked_ranks_calm_zones_by_unwalked_time_before_age():
    """A gap crossed a few seconds ago and a lawn nobody has entered since it was first seen, both
    calm now: with prefer_unwalked the lawn, though younger; within the same whole second the
    oldest as before; calm still comes first; off (or not measured), the paper's oldest."""
    on = ZonePlanner(dataclasses.replace(CFG.planner, min_calm_s=5.0, prefer_unwalked=True))
    old_gap = dataclasses.replace(zone(1, 0, 0, 30.0, born=0.0), calm_s=6.0, unwalked_s=6.0)
    young_lawn = dataclasses.replace(zone(2, 20, 0, 30.0, born=12.0), calm_s=6.0, unwalked_s=25.0)
    restless = dataclasses.replace(zone(3, 40, 0, 30.0, born=14.0), calm_s=2.0, unwalked_s=40.0)
    assert on.choose([old_gap, young_lawn, restless], 30.0).id == 2
    assert on.choose([dataclasses.replace(old_gap, unwalked_s=25.4), young_lawn], 30.0).id == 1
    assert on.choose([old_gap, restless], 30.0).id == 1  # calm first
    off = ZonePlanner(dataclasses.replace(CFG.planner, min_calm_s=5.0))
    assert off.choose([old_gap, young_lawn], 30.0).id == 1
    unmeasured = dataclasses.replace(young_lawn, unwalked_s=math.nan)
    assert on.choose([old_gap, unmeasured], 30.0).id == 1


def test_a_small_all_free_view_behind_the_vehicle_is_nobody_within_r0():
    # The view saw only free ground (r = r_view = 1.5 m) around a point 1 m from where the vehicle
    # is now: carried to the vehicle only 0.5 m of it is left, which is the view's end, no person.
    # The simulated PX4 reading its altitude 1.3 m low lost its judged zone so on every descent.
    ctl = LandingController(CFG)
    t = _in_land(ctl, r_view=3.0)
    ctl.on_state(status(t, 10, 0, 5.9, mode="LAND"))
    ctl.on_frame(t, [], pose(t, 10, 0, 5.9), GroundBelow(11.0, 0.0, 1.5, 1.5))
    assert ctl.phase == Phase.LAND
    assert any("nobody seen within r0: landing committed" in x for x in texts(ctl))
