"""The camera's footprint and where it commits the landing (issue 60, item 4): the 70-degree
pinhole keeps today's numbers exactly; a fisheye commits higher, once nobody seen can reach."""

from __future__ import annotations

import dataclasses
import math

import pytest

from companion.control import commit
from companion.control import descent as plan
from companion.control.landing import Goto, Land, LandingController, Phase
from companion.control.search import expanding_square, spacing
from companion.control.touchdown import DescentProfile, by_rangefinder
from companion.geometry.camera import GeometryError, Intrinsics
from companion.pipeline.circles import GroundBelow

from .test_landing_controller import LOW, _low_over_zone, pose, status, texts, zone

#: The simulator's PX4: descent 1.5 m/s, LAND from 4 m at 1.0 m/s, walkers at 1.5 m/s.
SIM = DescentProfile(descend_speed_mps=1.5, land_alt_m=4.0, land_speed_mps=1.0, walk_speed_mps=1.5)
PINHOLE_70 = Intrinsics.from_fov(640, 480, 70.0).seen_ratio()
FISHEYE_160 = Intrinsics.from_fov(640, 480, 160.0, "fisheye").seen_ratio()


def test_the_70_degree_pinholes_footprint_is_the_ratio_the_rules_were_written_for():
    k = Intrinsics.from_fov(640, 480, 70.0)
    assert PINHOLE_70 == min(k.cx / k.fx, k.cy / k.fy)  # exactly: the default rows must not move
    assert Intrinsics.from_fov(640, 480, 110.0).seen_ratio() == pytest.approx(math.tan(math.radians(55)) * 239.5 / 320)


def test_a_fisheyes_footprint_is_its_narrow_sides_angle_within_the_trusted_cone():
    # 160 degrees across 640 px: 60 degrees to the top and bottom edges, 80 to the sides (trusted to 70).
    assert FISHEYE_160 == pytest.approx(math.tan(math.radians(60.0 * 239.5 / 240)), rel=1e-3)
    # 200 across: 75 degrees to the top, wider than the model is trusted: the trusted cone bounds it.
    assert Intrinsics.from_fov(640, 480, 200.0, "fisheye").seen_ratio() == pytest.approx(math.tan(math.radians(70)))


def test_a_distorted_pinhole_walks_its_border_through_the_lens():
    plain = Intrinsics.from_fov(640, 480, 90.0)
    barrel = dataclasses.replace(plain, dist=(-0.2, 0.03, 0.0, 0.0))
    assert barrel.seen_ratio() > plain.seen_ratio()  # barrel distortion squeezes a wider view in


def test_a_lens_that_sees_none_of_its_border_is_refused():
    tiny = Intrinsics(1000.0, 1000.0, 319.5, 239.5, 640, 480, (0.0, 0.0, 0.0, 0.0), "fisheye")
    assert tiny.seen_ratio() > 0
    blind = Intrinsics(50.0, 50.0, 319.5, 239.5, 640, 480, (0.0, 0.0, 0.0, 0.0), "fisheye")
    with pytest.raises(GeometryError, match="none of its image border"):
        blind.seen_ratio()


def test_the_judging_height_and_the_searchs_spacing_are_todays_for_the_pinhole_and_wider_for_the_fisheye():
    narrow = dataclasses.replace(LOW, view_ratio=PINHOLE_70)
    assert plan.judging_height(narrow) == 10.0  # 4.4 m seen all round at 10 m, over r0 + margin
    assert plan.judging_height(dataclasses.replace(LOW, view_ratio=0.2)) == pytest.approx(3.0 / 0.2 + 1.7)
    s = status(0.0, alt=25.0)
    assert spacing(25.0, s, PINHOLE_70, 40.0) == 1.5 * PINHOLE_70 * (25.0 - 1.7)
    assert spacing(25.0, s, FISHEYE_160, 40.0) == 40.0  # 60 m legs would leave no waypoint within 40 m
    assert spacing(12.0, s, FISHEYE_160, 40.0) == pytest.approx(1.5 * FISHEYE_160 * 10.3)
    # pinhole:110 searching from 28.5 m: 43 m legs left the square no waypoint within 40 m.
    high = status(0.0, alt=28.5)
    assert expanding_square((0.0, 0.0), 1.5 * 1.0689 * (28.5 - 1.7), 40.0) == []
    assert len(expanding_square((0.0, 0.0), spacing(28.5, high, 1.0689, 40.0), 40.0)) == 4


def test_the_narrow_pinhole_never_commits_higher_the_fisheye_does_with_a_rangefinder():
    narrow = dataclasses.replace(LOW, view_ratio=PINHOLE_70)
    wide = dataclasses.replace(LOW, view_ratio=FISHEYE_160)
    fast = by_rangefinder(SIM, commit.FAST_AGL_M)
    assert commit.commit_height(narrow, fast, 4.0, 10.0) is None
    assert commit.commit_height(narrow, SIM, 4.0, 10.0) is None
    # 1.72 (h - 1.7) - 1.5 ((h - 1) / 1.5 + 1) >= r0 2 + margin 1: from 8.9 m.
    h = commit.commit_height(wide, fast, 4.0, 10.0)
    assert h == pytest.approx(8.9, abs=0.1)
    assert commit.guarantees(wide, fast, h) and not commit.guarantees(wide, fast, h - 0.1)
    # Without a rangefinder the slow LAND from 4 m is part of the walker's time: no guarantee below 10 m.
    assert commit.commit_height(wide, SIM, 4.0, 10.0) is None
    # Runners (2.4 m/s): no height guarantees.
    assert commit.commit_height(wide, dataclasses.replace(fast, walk_speed_mps=2.4), 4.0, 10.0) is None


WIDE = dataclasses.replace(LOW, view_ratio=FISHEYE_160, descent=SIM)


def _down(ctl: LandingController, free_m: float, until: float = 30.0, t: float | None = None,
          alt: float = 9.8) -> tuple[float, float, list]:
    """Follow the controller's targets down from ``alt`` over zone 1 with a rangefinder (from the
    start of its descent when ``t`` is None), the frame seeing ``free_m`` free around the vehicle
    (of a view of 15 m), calm at the top."""
    t, cmds = _low_over_zone(ctl) if t is None else t, []
    while t < until:
        ctl.on_state(status(t, 10, 0, alt, mode="GUIDED", agl=alt))
        calm = 6.3 if alt >= 9.5 else math.nan
        cmds = ctl.on_frame(t, [zone(1, 10, 0, t, born=-8)], pose(t, 10, 0, alt),
                            GroundBelow(10.0, 0.0, free_m, 15.0, calm_s=calm))
        t += 0.1
        if ctl.phase == Phase.LAND or any(isinstance(c, Land) for c in cmds):
            break
        alt = next((c.target.rel_alt_m for c in cmds if isinstance(c, Goto)), alt)
    return t, alt, cmds


def test_a_fisheye_commits_at_its_commit_height_and_flies_the_last_metres_fast():
    ctl = LandingController(WIDE)
    _t, alt, cmds = _down(ctl, free_m=14.0)
    assert ctl.phase == Phase.LAND and 8.7 <= alt <= 9.8
    goto = [c for c in cmds if isinstance(c, Goto)]
    assert goto and goto[0].target.rel_alt_m == pytest.approx(1.0)  # by the rangefinder to 1 m
    assert any("first down to 1 m by the rangefinder" in x for x in texts(ctl))


def test_a_fisheye_holds_the_land_while_someone_seen_could_reach_then_lands_as_the_pinhole():
    ctl = LandingController(WIDE)
    t, alt, cmds = _down(ctl, free_m=6.0, until=3.0)
    assert ctl.phase == Phase.DESCEND and alt >= 8.7 and not any(isinstance(c, Land) for c in cmds)
    held = [x for x in texts(ctl) if "holding the LAND" in x]
    assert len(held) == 1 and "free around the vehicle 6.0 m" in held[0]
    # After the time to touchdown from there (at most calm_wait_s, 3 s here), on down to 4 m and the LAND.
    _t, alt, cmds = _down(ctl, free_m=6.0, until=30.0, t=t, alt=alt)
    assert ctl.phase == Phase.LAND and alt == pytest.approx(4.0) and cmds == [Land()]


def test_the_narrow_pinhole_lands_as_before_whatever_it_sees():
    ctl = LandingController(dataclasses.replace(WIDE, view_ratio=PINHOLE_70))
    _t, alt, _cmds = _down(ctl, free_m=6.0)
    assert ctl.phase == Phase.LAND and alt == pytest.approx(4.0)
    assert not any("holding the LAND" in x for x in texts(ctl))


def test_the_hold_lasts_as_long_as_touchdown_would_take_from_the_commit_height():
    """Anybody seen within reach who heads for the point comes within r0 in that time (and the
    zone is lost); people who stay near do not hold the landing for all of calm_wait_s."""
    ctl = LandingController(dataclasses.replace(WIDE, calm_wait_s=15.0))
    t, alt, _cmds = _down(ctl, free_m=6.0, until=1.0)
    assert any("holding the LAND" in x for x in texts(ctl))  # held from within a second of the start
    t, alt, cmds = _down(ctl, free_m=6.0, until=30.0, t=t, alt=alt)
    assert ctl.phase == Phase.LAND and alt == pytest.approx(4.0) and cmds == [Land()]
    to_touchdown = by_rangefinder(SIM, commit.FAST_AGL_M).time_to_touchdown(8.9)  # 6.3 s
    assert to_touchdown < t - 0.2 < to_touchdown + 1.5
