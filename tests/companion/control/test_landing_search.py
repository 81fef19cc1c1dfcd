"""Search instead of giving up (issue 11, item 4): with no zone in view, climb to the ceiling,
fly an expanding square, take the first zone that becomes eligible on the way, and hand back only
when the search's time, its radius or the battery runs out. The pure controller, driven by
explicit inputs; the closed-loop flight is in tests/flights/test_sitl.py."""

from __future__ import annotations

import dataclasses
import math

import pytest

from companion.control.events import Phase
from companion.control.landing import Goto, Handback, LandingController, expanding_square
from tests.companion.control.test_landing_controller import CFG, pose, status, texts, trigger, zone

SEARCH = dataclasses.replace(CFG, search_s=30.0, search_radius_m=25.0, search_reserve_s=20.0, view_ratio=0.525,
                             select_timeout_s=2.0)


def test_the_expanding_square_visits_the_nearest_ground_first_and_stays_within_its_radius():
    pts = expanding_square((100.0, 50.0), 10.0, 25.0)
    # North 10, east 10, south 20, west 20, north 30, east 30, south 40, west 40; north 50 would
    # leave the 25 m square.
    assert pts == [(110.0, 50.0), (110.0, 60.0), (90.0, 60.0), (90.0, 40.0), (120.0, 40.0), (120.0, 70.0),
                   (80.0, 70.0), (80.0, 30.0)]
    assert all(max(abs(n - 100.0), abs(e - 50.0)) <= 25.0 for n, e in pts)
    assert len(set(pts)) == len(pts)  # nothing visited twice
    assert expanding_square((0.0, 0.0), 10.0, 5.0) == []
    with pytest.raises(ValueError):
        expanding_square((0.0, 0.0), 0.0, 10.0)


def _to_search(ctl: LandingController, alt: float = 20.0, battery_s: float | None = None) -> float:
    """Trigger with nothing in view and wait out the SELECT timeout; returns the time."""
    ctl.on_state(status(0.0, alt=alt, mode="RTL", battery_s=battery_s))
    ctl.on_trigger(trigger(0.0))
    t = 0.0
    while ctl.phase == Phase.SELECT and t < 5.0:
        t += 0.1
        ctl.on_state(status(t, alt=alt, mode="RTL", battery_s=battery_s))
        ctl.on_frame(t, [], pose(t, alt=alt))
        ctl.tick(t)
    return t


def test_no_zone_in_view_climbs_to_the_ceiling_then_flies_the_square_and_lands_on_what_it_finds():
    ctl = LandingController(SEARCH)
    ctl.on_state(status(0.0, alt=20.0, mode="RTL"))
    ctl.on_trigger(trigger(0.0))
    t, first = 0.0, []
    while ctl.phase == Phase.SELECT:
        t += 0.1
        ctl.on_state(status(t, alt=20.0, mode="RTL"))
        ctl.on_frame(t, [], pose(t, alt=20.0))
        first = ctl.tick(t)
    assert ctl.phase == Phase.SEARCH and t == pytest.approx(2.0, abs=0.11)
    assert any("no safe zone confirmed within 2 s; searching 25 m around for 30 s" in x for x in texts(ctl))
    # First: climb where it is, to the ceiling less its margin (20 + 5 - 1 m).
    assert len(first) == 1 and isinstance(first[0], Goto) and first[0].zone_id is None
    assert (first[0].north, first[0].east, first[0].target.rel_alt_m) == pytest.approx((0.0, 0.0, 24.0))
    # Then the square: legs of 1.5 times the ground radius seen at 24 m (0.525 x 22.3 m): 17.6 m.
    spacing = 1.5 * 0.525 * (24.0 - 1.7)
    north, east, visited, sent_t = 0.0, 0.0, [], []
    while len(visited) < 3:
        t += 0.1
        ctl.on_state(status(t, north, east, 24.0, mode="GUIDED"))
        for goto in (c for c in ctl.on_frame(t, [], pose(t, north, east, 24.0)) if isinstance(c, Goto)):
            assert goto.zone_id is None and goto.target.rel_alt_m == pytest.approx(24.0)
            if (round(goto.north, 3), round(goto.east, 3)) not in visited[-1:]:
                visited.append((round(goto.north, 3), round(goto.east, 3)))
                sent_t.append(t)
            north, east = goto.north, goto.east  # the vehicle gets there at once
    # It hovers at each waypoint for min_track_age_s + 1 s (2 s), time for a zone to be tracked:
    # there one frame after it was sent, 2 s of hovering, on at the next frame.
    assert sent_t[2] - sent_t[1] == pytest.approx(0.1 + 2.0 + 0.1, abs=0.05)
    s = round(spacing, 3)
    assert visited == [(s, 0.0), (s, s), (-s, s)]  # north 1, east 1, south 2 legs
    # A zone comes into view and stays eligible: it is flown to as after any SELECT.
    t += 0.1
    ctl.on_state(status(t, north, east, 24.0, mode="GUIDED"))
    cmds = ctl.on_frame(t, [zone(9, north + 3.0, east, t)], pose(t, north, east, 24.0))
    assert ctl.phase == Phase.APPROACH and cmds[0].zone_id == 9
    assert any("landing at zone 9" in x for x in texts(ctl))


def _fly_search(ctl: LandingController, t: float, battery=None, period: float = 0.5) -> tuple[float, list]:
    """Follow the search: every ``period`` s the vehicle is where it was last sent (a frame with
    no zone, a status, a tick). ``battery(t)``: the battery's time left. Returns (t, last commands)."""
    north = east = 0.0
    alt, cmds = 24.0, []
    while ctl.phase == Phase.SEARCH and t < 200.0:
        t += period
        left = None if battery is None else battery(t)
        ctl.on_state(status(t, north, east, alt, mode="GUIDED", battery_s=left))
        cmds = ctl.on_frame(t, [], pose(t, north, east, alt)) + ctl.tick(t)
        for c in cmds:
            if isinstance(c, Goto):
                north, east, alt = c.north, c.east, c.target.rel_alt_m
    return t, cmds


def test_the_search_hands_back_when_its_time_runs_out():
    ctl = LandingController(dataclasses.replace(SEARCH, search_radius_m=500.0))
    start = _to_search(ctl)
    assert ctl.phase == Phase.SEARCH
    t, cmds = _fly_search(ctl, start)
    assert ctl.phase == Phase.HANDBACK and t - start == pytest.approx(30.0, abs=0.51)
    assert cmds[-1] == Handback("LAND", "searched 30 s without a safe zone")


def test_the_search_hands_back_at_the_end_of_its_square():
    ctl = LandingController(SEARCH)
    t = _to_search(ctl)
    north = east = 0.0
    for _ in range(300):
        t += 0.1
        ctl.on_state(status(t, north, east, 24.0, mode="GUIDED"))
        cmds = ctl.on_frame(t, [], pose(t, north, east, 24.0))
        if ctl.phase != Phase.SEARCH:
            break
        for goto in (c for c in cmds if isinstance(c, Goto)):
            north, east = goto.north, goto.east
            assert max(abs(north), abs(east)) <= 25.0
    assert ctl.phase == Phase.HANDBACK
    assert cmds == [Handback("LAND", "searched 25 m around without a safe zone")]


def test_no_search_when_the_battery_cannot_pay_for_it_and_none_past_its_reserve():
    # 20 m at 1.5 m/s to 10 m, then 0.5 m/s: 26.7 s to land, plus the 20 s reserve: 46.7 s.
    ctl = LandingController(SEARCH)
    _to_search(ctl, battery_s=40.0)
    assert ctl.phase == Phase.HANDBACK
    assert any("battery 40 s left, landing needs 47 s with the reserve" in x for x in texts(ctl))
    ctl = LandingController(dataclasses.replace(SEARCH, search_radius_m=500.0))
    start = _to_search(ctl, battery_s=60.0)
    assert ctl.phase == Phase.SEARCH
    t, cmds = _fly_search(ctl, start, battery=lambda t: 60.0 - (t - start))
    assert ctl.phase == Phase.HANDBACK and "battery" in cmds[-1].reason
    # From 24 m: 14 m at 1.5 m/s and 10 m at 0.5 m/s, plus the 20 s reserve: 49.3 s.
    assert 60.0 - (t - start) == pytest.approx(14.0 / 1.5 + 20.0 + 20.0, abs=0.51)


def test_search_off_hands_back_at_the_timeout_as_before():
    ctl = LandingController(dataclasses.replace(SEARCH, search_s=0.0))
    _to_search(ctl)
    assert ctl.phase == Phase.HANDBACK


def test_a_zone_lost_with_nothing_else_holds_then_searches_from_there():
    ctl = LandingController(dataclasses.replace(SEARCH, hold_timeout_s=1.0))
    ctl.on_state(status(0.0, 10.0, 0.0, 20.0))
    ctl.on_frame(0.0, [zone(1, 10.0, 0.0, 0.0)], pose(0.0, 10.0, 0.0, 20.0))
    ctl.on_trigger(trigger(0.0))
    t = 0.0
    for _ in range(2):  # someone walks in: lost, nothing else eligible
        t += 0.1
        ctl.on_state(status(t, 10.0, 0.0, 20.0, mode="GUIDED"))
        ctl.on_frame(t, [zone(1, 10.0, 0.0, t, r=0.5)], pose(t, 10.0, 0.0, 20.0))
    assert ctl.phase == Phase.HOLD
    while ctl.phase == Phase.HOLD:
        t += 0.1
        ctl.on_state(status(t, 10.0, 0.0, 20.0, mode="GUIDED"))
        ctl.on_frame(t, [], pose(t, 10.0, 0.0, 20.0))
        ctl.tick(t)
    assert ctl.phase == Phase.SEARCH
    assert any("held 1 s without a safe zone; searching" in x for x in texts(ctl))


def test_bad_search_settings_are_refused():
    for field, value in (("search_s", -1.0), ("search_radius_m", math.nan), ("view_ratio", 0.0)):
        with pytest.raises(ValueError, match=field):
            dataclasses.replace(SEARCH, **{field: value})


def test_free_ground_glimpsed_at_the_edge_of_the_view_is_flown_over_first():
    ctl = LandingController(SEARCH)
    t = _to_search(ctl)
    # A free patch at the edge of the view: 2.5 m, too small to choose (r0 + margin is 3 m).
    t += 0.1
    ctl.on_state(status(t, 0.0, 0.0, 24.0, mode="GUIDED"))
    cmds = ctl.on_frame(t, [zone(5, -9.0, 6.0, t, r=2.5)], pose(t, 0.0, 0.0, 24.0))
    assert [(c.north, c.east, c.zone_id) for c in cmds if isinstance(c, Goto)] == [(-9.0, 6.0, None)]
    # Over it, it hovers while the tracker looks; seen whole now, it qualifies and is flown to.
    t += 0.1
    ctl.on_state(status(t, -9.0, 6.0, 24.0, mode="GUIDED"))
    assert ctl.on_frame(t, [zone(5, -9.0, 6.0, t, r=2.5)], pose(t, -9.0, 6.0, 24.0)) == []
    t += 0.1
    ctl.on_state(status(t, -9.0, 6.0, 24.0, mode="GUIDED"))
    cmds = ctl.on_frame(t, [zone(5, -9.0, 6.0, t, r=4.5)], pose(t, -9.0, 6.0, 24.0))
    assert ctl.phase == Phase.APPROACH and cmds[0].zone_id == 5


def test_a_glimpse_that_never_qualifies_is_looked_at_once_then_the_square_goes_on():
    ctl = LandingController(SEARCH)
    t = _to_search(ctl)
    north, east, targets = 0.0, 0.0, []
    for _ in range(60):  # 6 s; the patch stays 2.5 m wherever the vehicle is
        t += 0.1
        ctl.on_state(status(t, north, east, 24.0, mode="GUIDED"))
        for c in ctl.on_frame(t, [zone(5, -9.0, 6.0, t, r=2.5)], pose(t, north, east, 24.0)):
            if isinstance(c, Goto):
                targets.append((round(c.north, 1), round(c.east, 1)))
                north, east = c.north, c.east
    assert targets[0] == (-9.0, 6.0)  # first the patch,
    assert ctl.phase == Phase.SEARCH and (-9.0, 6.0) not in targets[1:]  # then the square, never back
    assert targets[1] == (round(1.5 * 0.525 * 22.3, 1), 0.0)


def test_nothing_in_view_that_could_be_a_zone_starts_the_search_early():
    """select_empty_s: with no zone of r0 or more on any frame since the trigger, the search starts
    then, not at select_timeout_s; a candidate seen once (a 2.5 m gap that may grow) keeps the
    full wait; off (0), the wait is select_timeout_s as before."""
    cfg = dataclasses.replace(SEARCH, select_timeout_s=10.0, select_empty_s=3.0)

    def until_search(ctl: LandingController, tracks=lambda t: []) -> float:
        ctl.on_state(status(0.0, alt=20.0, mode="LAND"))
        ctl.on_trigger(trigger(0.0))
        t = 0.0
        while ctl.phase == Phase.SELECT and t < 20.0:
            t += 0.1
            ctl.on_state(status(t, alt=20.0, mode="LAND"))
            ctl.on_frame(t, tracks(t), pose(t, alt=20.0))
            ctl.tick(t)
        return t

    early = LandingController(cfg)
    assert until_search(early) == pytest.approx(3.0, abs=0.11) and early.phase == Phase.SEARCH
    assert any("nothing in view within 3 s could be a safe zone; searching" in x for x in texts(early))
    gap = LandingController(cfg)  # a gap too small to choose, but at least r0: wait the full time
    assert until_search(gap, lambda t: [zone(4, 5.0, 0.0, t, r=2.5)] if t < 0.5 else []) == \
        pytest.approx(10.0, abs=0.11)
    off = LandingController(dataclasses.replace(cfg, select_empty_s=0.0))
    assert until_search(off) == pytest.approx(10.0, abs=0.11)
    with pytest.raises(ValueError, match="select_empty_s"):
        dataclasses.replace(cfg, select_empty_s=math.nan)


def test_holding_hovers_where_it_began_beside_a_glimpse_until_the_timeout():
    """A zone lost, nothing else eligible, a lawn's rim at the edge of the view (2.5 m, too small
    to choose): the hold hovers where it began until it times out into the search."""
    def fly(cfg) -> tuple[LandingController, list]:
        ctl = LandingController(cfg)
        ctl.on_state(status(0.0, 10.0, 0.0, 20.0))
        ctl.on_frame(0.0, [zone(1, 10.0, 0.0, 0.0)], pose(0.0, 10.0, 0.0, 20.0))
        ctl.on_trigger(trigger(0.0))
        t, north, east, sent = 0.0, 10.0, 0.0, []
        for k in range(60):
            t += 0.1
            ctl.on_state(status(t, north, east, 20.0, mode="GUIDED"))
            if k < 2:  # someone walks in: lost, nothing else eligible
                tracks = [zone(1, 10.0, 0.0, t, r=0.5)]
            elif math.hypot(north - 16.0, east - 7.0) < 2.0:
                tracks = [zone(5, 16.0, 7.0, t, r=4.5)]  # over it: seen whole
            else:
                tracks = [zone(5, 16.0, 7.0, t, r=2.5)]  # the rim at the view's edge
            for c in ctl.on_frame(t, tracks, pose(t, north, east, 20.0)):
                if isinstance(c, Goto):
                    sent.append((round(c.north, 1), round(c.east, 1), c.zone_id))
                    north, east = c.north, c.east
            ctl.tick(t)
            if ctl.phase not in (Phase.HOLD, Phase.APPROACH) or ctl.phase == Phase.APPROACH and k > 2:
                break
        return ctl, sent

    plain, sent = fly(dataclasses.replace(SEARCH, hold_timeout_s=4.0))
    assert plain.phase == Phase.SEARCH and all(n == 10.0 and e == 0.0 for n, e, _ in sent)
