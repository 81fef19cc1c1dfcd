"""Where the landing point goes inside a zone: away from where the risk map saw people lately
(``controller.place_lookback_s``; ``GroundRiskMap.farthest_from_walkers``)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from companion.control.events import Note
from companion.control.landing import Goto, LandingConfig, LandingController, Phase
from companion.control.planner import PlannerConfig
from companion.geometry.camera import Intrinsics, Mount
from companion.pipeline.headplane import GridSpec
from companion.pipeline.riskmap import GroundRiskMap, RiskMapConfig, Spot, SpotRequest, _disc, _extremes
from companion.pipeline.slz import PipelineConfig, SLZPipeline
from companion.pipeline.tracker import Track
from tests.companion.control.test_landing_controller import pose, status, trigger, zone
from tests.companion.pipeline.test_riskmap import frame_grids

CELL = 0.1
GRID = GridSpec(x0=-15.0, y0=-15.0, cell=CELL, rows=301, cols=301)  # 30 m square around (0, 0)


def grids(people: list[tuple[float, float]], **kw: Any) -> tuple[np.ndarray, np.ndarray]:
    """``frame_grids`` over this module's 30 m GRID (plane x = north, y = east)."""
    return frame_grids(people, GRID, **kw)


def walk(risk: GroundRiskMap, path: list[tuple[float, float]], t0: float = 0.0, dt: float = 0.1) -> float:
    """One frame per point of ``path`` (a person there), ``dt`` apart; returns the last time."""
    t = t0
    for k, p in enumerate(path):
        t = t0 + k * dt
        free, seen = grids([p])
        risk.update(GRID, free, seen, t)
    return t


def test_the_point_goes_to_the_side_of_the_zone_away_from_where_a_walker_went():
    """A walker crossed the ground 3.5 m east of the zone's centre, north to south, and is gone:
    the frame alone shows an empty circle, the map remembers the path. The point goes to the
    zone's far (west) side, and its distance to the path is measured, never overstated."""
    risk = GroundRiskMap(RiskMapConfig())
    t = walk(risk, [(x, 3.5) for x in np.arange(8.0, -8.0, -0.15)])
    for k in range(1, 11):  # nobody in view for a second
        risk.update(GRID, *grids([]), t + 0.1 * k)
    t += 1.0
    spot = risk.farthest_from_walkers(0.0, 0.0, 3.0, t, lookback_s=30.0, reach_m=8.0, aim=(0.0, 0.0))
    assert isinstance(spot, Spot)
    assert spot.y < -2.5 and abs(spot.x) < 1.0  # the far side, 3 m from the centre at most
    assert math.hypot(spot.x, spot.y) <= 3.0 + 0.3
    true_clear = abs(spot.y - 3.5) - 0.4  # to the edge of the walker's disc
    assert true_clear - 0.6 <= spot.clear_m <= true_clear + 1e-9
    assert 3.5 - 0.4 - 0.6 <= spot.aim_clear_m <= 3.5 - 0.4
    # Sightings older than the lookback do not count: the centre is as good as anywhere then.
    late = risk.farthest_from_walkers(0.0, 0.0, 3.0, t, lookback_s=0.5, reach_m=8.0, aim=(0.0, 0.0))
    assert late is not None and late.clear_m == pytest.approx(8.0) and late.aim_clear_m == pytest.approx(8.0)
    assert math.hypot(late.x, late.y) < 0.3  # ties go to the point nearest the present one


def test_ground_not_looked_at_counts_as_occupied():
    """Beside the edge of the view nobody was seen because nobody looked: the point does not go
    there (it would look far from everybody)."""
    risk = GroundRiskMap(RiskMapConfig())
    seen = np.full(GRID.shape, 255, np.uint8)
    seen[:, :120] = 0  # plane x < -3 never seen
    for k in range(20):
        risk.update(GRID, *grids([(0.0, 6.0)], seen=seen), 0.1 * k)
    spot = risk.farthest_from_walkers(0.0, 0.0, 3.0, 2.0, lookback_s=30.0, reach_m=8.0, aim=(0.0, 0.0))
    assert spot is not None
    assert spot.x > 1.5  # to the east side, away from the unseen ground west of x = -3
    assert math.hypot(spot.x, spot.y - 6.0) > 5.0  # and not toward the person at y = 6


def test_coarse_cells_never_free_ground():
    """One person on a single fine cell: the measured distance never exceeds the true one."""
    risk = GroundRiskMap(RiskMapConfig())
    free, seen = grids([])
    free[150 + 13, 150 + 17] = 0  # plane (1.7, 1.3)
    risk.update(GRID, free, seen, 0.0)
    for x, y in ((0.0, 0.0), (-2.0, 1.0), (1.7, -1.0), (3.0, 3.0)):
        spot = risk.farthest_from_walkers(x, y, 0.0, 0.0, lookback_s=5.0, reach_m=8.0, aim=(x, y))
        assert spot is not None
        true = math.hypot(spot.x - 1.7, spot.y - 1.3) - CELL * math.sqrt(0.5)
        assert spot.clear_m <= true + 1e-9
        assert spot.aim_clear_m <= math.hypot(x - 1.7, y - 1.3) + 1e-9


def test_bad_arguments_give_none_or_a_clear_error():
    risk = GroundRiskMap(RiskMapConfig(half_extent_m=20.0))
    assert risk.farthest_from_walkers(0.0, 0.0, 3.0, 0.0, 10.0, 8.0) is None  # no frame yet
    risk.update(GRID, *grids([]), 0.0)
    for bad in ((math.nan, 0.0, 3.0, 0.0), (0.0, 0.0, math.inf, 0.0), (0.0, 0.0, 3.0, math.nan)):
        assert risk.farthest_from_walkers(*bad, 10.0, 8.0) is None
    assert risk.farthest_from_walkers(15.0, 0.0, 3.0, 0.0, 10.0, 8.0) is None  # past the map's edge
    with pytest.raises(ValueError, match="radius_m"):
        risk.farthest_from_walkers(0.0, 0.0, -1.0, 0.0, 10.0, 8.0)
    with pytest.raises(ValueError, match="reach_m"):
        risk.farthest_from_walkers(0.0, 0.0, 1.0, 0.0, 10.0, 0.0)
    spot = risk.farthest_from_walkers(0.0, 0.0, 1.0, 0.0, 10.0, 8.0, aim=(math.nan, 0.0))
    assert spot is not None and math.isnan(spot.aim_clear_m)


def test_a_spot_request_carries_what_the_pipeline_needs():
    request = SpotRequest(1.0, 2.0, 3.0, 30.0, (1.5, 2.0))
    assert (request.x, request.y, request.radius_m, request.lookback_s, request.aim) == (1.0, 2.0, 3.0, 30.0, (1.5, 2.0))


# -- the controller ------------------------------------------------------------------------------

PLACE = LandingConfig(
    planner=PlannerConfig(r0_m=2.0, radius_margin_m=1.0, min_track_age_s=1.0, min_track_hits=3, zone_max_age_s=1.0),
    select_timeout_s=5.0, hold_timeout_s=4.0, descend_alt_m=10.0, land_abort_above_m=5.0, search_s=0.0,
    place_lookback_s=30.0)


@dataclass
class View:
    """A frame's ground view that answers every request with ``answer`` and keeps the requests."""

    answer: Spot | None = None
    asked: list[SpotRequest] = field(default_factory=list)

    def spot(self, request: SpotRequest) -> Spot | None:
        self.asked.append(request)
        return self.answer


def track(t: float) -> Track:
    """Zone 1: centre (10, 0), radius 6 m, tracked for 8 s, confirmed at ``t``."""
    return zone(1, 10.0, 0.0, t, r=6.0, born=t - 8.0)


def fly_to_zone(cfg: LandingConfig = PLACE) -> LandingController:
    """Triggered at 20 m over (0, 0), approaching zone 1 (centre (10, 0), radius 6 m)."""
    ctl = LandingController(cfg)
    ctl.on_state(status(0.0, 0.0, 0.0, 20.0))
    ctl.on_trigger(trigger(0.0))
    ctl.on_frame(0.0, [track(0.0)], pose(0.0, 0.0, 0.0, 20.0))
    assert ctl.phase == Phase.APPROACH
    ctl.pop_events()
    return ctl


def frame(ctl: LandingController, t: float, spot: Spot | None, north: float = 5.0,
          tracks: list[Track] | None = None) -> tuple[list, View]:
    """A frame at ``t`` over zone 1 (or ``tracks``) whose ground view answers ``spot``: the
    commands, and the view (what it was asked)."""
    view = View(spot)
    ctl.on_state(status(t, north, 0.0, 20.0, mode="GUIDED"))
    return ctl.on_frame(t, [track(t)] if tracks is None else tracks, pose(t, north, 0.0, 20.0), view=view), view


def goto_ned(cmd: Goto) -> tuple[float, float]:
    return cmd.north, cmd.east


def test_the_controller_asks_within_the_zones_room_and_flies_to_a_spot_clearly_farther_from_people():
    _, view = frame(fly_to_zone(), 0.1, None, tracks=[])
    assert view.asked == []  # the target not on this frame: nothing to place
    ctl = fly_to_zone()
    # 0.3 m farther from people: not worth moving for.
    cmds, view = frame(ctl, 0.1, Spot(10.0, -2.0, 4.3, 4.0))
    (request,) = view.asked
    # Room: r0 2 m plus the margin 1 m must stay inside the 6 m zone around the point.
    assert (request.x, request.y, request.radius_m, request.lookback_s) == (10.0, 0.0, 3.0, 30.0)
    assert request.aim == (10.0, 0.0)
    assert all(goto_ned(c)[1] == pytest.approx(0.0, abs=1e-6) for c in cmds if isinstance(c, Goto))
    assert ctl.placements == 0
    # 2 m farther: the landing point moves there, and the vehicle flies to it.
    cmds, _ = frame(ctl, 0.2, Spot(10.0, -2.5, 6.0, 4.0))
    gotos = [c for c in cmds if isinstance(c, Goto)]
    assert gotos and goto_ned(gotos[-1]) == pytest.approx((10.0, -2.5), abs=1e-3)
    assert ctl.placements == 1
    notes = [e for e in ctl.pop_events() if isinstance(e, Note)]
    assert any("landing point moved 2.5 m, 6.0 m from where people were seen in the last 30 s (was 4.0 m)"
               in e.text for e in notes)
    # The next request starts from the new point.
    _, view = frame(ctl, 0.3, None)
    assert [r.aim for r in view.asked] == [(10.0, -2.5)]


def test_a_spot_outside_the_zones_room_or_not_finite_is_ignored():
    ctl = fly_to_zone()
    frame(ctl, 0.1, Spot(10.0, -3.5, 7.0, 4.0))  # 3.5 m from the centre: only 2.5 m of the zone round it
    frame(ctl, 0.2, Spot(math.nan, 0.0, 7.0, 4.0))
    frame(ctl, 0.3, Spot(10.0, 1.0, math.inf, 4.0))
    assert ctl.placements == 0
    assert ctl._aim == (10.0, 0.0)


def test_once_judged_or_in_land_the_point_stays_and_nothing_is_asked():
    ctl = fly_to_zone(dataclasses.replace(PLACE, planner=dataclasses.replace(PLACE.planner, min_calm_s=0.0)))
    t = 0.1
    # Over the zone: descend to the judging height, where the zone is judged and the LAND follows.
    alt = 20.0
    while ctl.phase != Phase.LAND and t < 20.0:
        ctl.on_state(status(t, 10.0, 0.0, alt, mode="GUIDED"))
        for c in ctl.on_frame(t, [track(t)], pose(t, 10.0, 0.0, alt)):
            if isinstance(c, Goto):
                alt = c.target.rel_alt_m
        t += 0.1
    assert ctl.phase == Phase.LAND
    ctl.on_state(status(t, 10.0, 0.0, 9.0, mode="LAND"))
    view = View(Spot(10.0, -2.5, 7.0, 3.0))
    ctl.on_frame(t, [track(t)], pose(t, 10.0, 0.0, 9.0), view=view)
    assert ctl.placements == 0 and ctl._aim == (10.0, 0.0) and view.asked == []


def test_the_point_moves_while_approaching_and_while_descending_to_judge_the_zone():
    """The point moves while the vehicle approaches, and also once it is over the zone and
    descending to judge it (the moves that carry the point into the lawn)."""

    def over(ctl: LandingController, t: float, spot: Spot | None = None) -> View:
        view = View(spot)
        ctl.on_state(status(t, 10.0, -2.5, 20.0, mode="GUIDED"))
        ctl.on_frame(t, [track(t)], pose(t, 10.0, -2.5, 20.0), view=view)
        return view

    ctl = fly_to_zone()
    frame(ctl, 0.1, Spot(10.0, -2.5, 6.0, 4.0))
    assert ctl.placements == 1 and ctl._aim == (10.0, -2.5)
    over(ctl, 0.2)
    assert ctl.phase == Phase.DESCEND
    assert len(over(ctl, 0.3, Spot(10.0, -1.5, 8.0, 3.0)).asked) == 1  # asked while descending too
    assert ctl.phase == Phase.DESCEND  # still flying it, not handed back
    assert ctl.placements == 2 and ctl._aim == (10.0, -1.5)


def test_off_by_default_no_request_and_spots_change_nothing():
    ctl = fly_to_zone(dataclasses.replace(PLACE, place_lookback_s=0.0))
    _, view = frame(ctl, 0.1, Spot(10.0, -2.5, 7.0, 3.0))
    assert ctl.placements == 0 and ctl._aim == (10.0, 0.0) and view.asked == []


# -- the pipeline --------------------------------------------------------------------------------

def test_the_frames_ground_view_answers_with_its_map_and_without_one_says_none():
    """Posed frames over a crowd-free view: the ground view of a pipeline that keeps a map (calm
    on, as by default) places the point, with nobody seen the farthest distance everywhere; one
    that keeps none (the paper's per-frame rule alone) answers None; and a view asked after the
    pipeline has taken another frame answers None (the map has moved on)."""
    base = np.zeros((240, 320), np.float32)
    image = np.zeros((240, 320, 3), np.uint8)
    K = Intrinsics.from_fov(320, 240, 70.0)
    with_map = SLZPipeline(lambda _f: base, PipelineConfig(calm=True), intrinsics=K, mount=Mount())
    without = SLZPipeline(lambda _f: base, PipelineConfig(), intrinsics=K, mount=Mount())
    request = SpotRequest(0.0, 0.0, 1.0, 30.0, (0.0, 0.0))
    for k in range(10):
        t = 0.1 * k
        at = pose(t, 0.0, 0.0, 20.0)
        mapped = with_map.process(image, t, at)
        plain = without.process(image, t, at)
    assert mapped.ground is not None and plain.ground is not None
    spot = mapped.ground.spot(request)
    assert spot is not None and math.hypot(spot.x, spot.y) <= 1.0
    # 20 m up the view reaches about 9 m: the unseen ground beyond it bounds the distance.
    assert 5.0 < spot.clear_m <= 8.0 and spot.aim_clear_m == pytest.approx(spot.clear_m, abs=0.31)
    assert plain.ground.spot(request) is None
    with_map.process(image, 1.0, pose(1.0, 0.0, 0.0, 20.0))
    assert mapped.ground.spot(request) is None  # the map has taken another frame


@pytest.mark.parametrize("seed", range(5))
def test_disc_extremes_equal_numpys_over_the_same_cells(seed):
    """The calm and unwalked measures read a disc's min and max with OpenCV under a mask: the
    same numbers as numpy over the gathered cells, NEVER (-inf) included."""
    rng = np.random.default_rng(seed)
    big = rng.uniform(-50, 50, (200, 200)).astype(np.float32)
    big[rng.random((200, 200)) < 0.05] = -np.inf
    disc = _disc(30, 3.0, 0.1)
    rows, cols = slice(40 + seed, 101 + seed), slice(70, 131)
    low, high = _extremes(big[rows, cols], disc)
    cells = big[rows, cols][disc.view(np.bool_)]
    assert (low, high) == (float(cells.min()), float(cells.max()))
