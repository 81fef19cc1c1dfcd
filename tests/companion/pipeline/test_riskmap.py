"""The ground risk map (issue 11): memory of people over frames, walking growth, unknown ground."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.geometry.camera import GeometryError, Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.headplane import GridSpec
from companion.pipeline.riskmap import GroundRiskMap, RiskMapConfig, RiskMapError
from companion.pipeline.slz import PipelineConfig, SLZPipeline

CELL = 0.1
GRID = GridSpec(x0=-10.0, y0=-10.0, cell=CELL, rows=201, cols=201)  # 20 m square around (0, 0)


def frame_grids(people: list[tuple[float, float]], grid: GridSpec = GRID, radius: float = 0.4,
                seen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(free, seen) uint8 grids: everything seen and free but disks of ``radius`` m at ``people``."""
    ys, xs = np.mgrid[0:grid.rows, 0:grid.cols]
    x, y = grid.x0 + xs * grid.cell, grid.y0 + ys * grid.cell
    free = np.full(grid.shape, 255, np.uint8)
    for px, py in people:
        free[np.hypot(x - px, y - py) <= radius] = 0
    seen_grid = np.full(grid.shape, 255, np.uint8) if seen is None else seen
    free[seen_grid == 0] = 0
    return free, seen_grid


def test_ground_never_seen_or_not_seen_for_longer_than_the_memory_is_never_free():
    risk = GroundRiskMap(RiskMapConfig(memory_s=5.0, hold_s=1.0))
    half_seen = np.zeros(GRID.shape, np.uint8)
    half_seen[:, :100] = 255  # the camera sees only the west half
    free, seen = frame_grids([], seen=half_seen)
    risk.update(GRID, free, seen, 0.0)
    assert (risk.known_free(GRID, 2.0)[:, 100:] == 0).all()  # never seen: unknown
    assert (risk.known_free(GRID, 2.0)[:, :100] == 255).all()  # seen free 2 s ago
    assert (risk.known_free(GRID, 6.0) == 0).all()  # not seen for longer than the memory
    # Seen occupied at its last look: not known free, however long ago the hold ran out.
    occ_free, occ_seen = frame_grids([(-5.0, 0.0)], seen=half_seen)
    risk.update(GRID, occ_free, occ_seen, 3.0)
    assert risk.known_free(GRID, 4.5)[100, 50] == 0


def test_bad_frames_are_refused_and_counted_and_the_map_is_unchanged():
    risk = GroundRiskMap()
    free, seen = frame_grids([(1.0, 1.0)])
    risk.update(GRID, free, seen, 5.0, camera_xy=(0.0, 0.0))
    before = risk.last_occ.copy()
    empty, _ = frame_grids([(-4.0, -4.0)])
    bad = [
        dict(t=float("nan")),
        dict(t=4.0),  # time going back
        dict(t=5.1, camera_xy=(40.0, 0.0)),  # 40 m in 0.1 s: a pose jump
        dict(t=5.2, camera_xy=(float("nan"), 0.0)),
        dict(t=5.3, grid=GridSpec(-10.0, -10.0, 0.2, 101, 101)),  # another cell size
    ]
    for case in bad:
        grid = case.get("grid", GRID)
        f, s = (empty, seen) if grid is GRID else frame_grids([], grid=grid)
        with pytest.raises(RiskMapError):
            risk.update(grid, f, s, case["t"], camera_xy=case.get("camera_xy"))
    assert risk.stats.dropped == len(bad)
    assert np.array_equal(risk.last_occ, before)
    assert isinstance(RiskMapError("x"), GeometryError)  # the service counts it as a bad frame


def test_the_map_is_bounded_and_follows_the_vehicle():
    cfg = RiskMapConfig(half_extent_m=15.0)
    risk = GroundRiskMap(cfg)
    n = risk.size
    free, seen = frame_grids([(0.0, 0.0)])
    risk.update(GRID, free, seen, 0.0)
    # Fly 12 m north in steps: the map recentres, keeps what is still inside, stays the same size.
    for k in range(1, 13):
        g = GridSpec(GRID.x0 + k, GRID.y0, CELL, GRID.rows, GRID.cols)
        f, s = frame_grids([], grid=g)
        risk.update(g, f, s, 0.1 * k, camera_xy=(float(k), 0.0))
    assert risk.size == n and risk.last_seen.shape == (n, n)
    assert risk.stats.recentred >= 1
    far = GridSpec(GRID.x0 + 12, GRID.y0, CELL, GRID.rows, GRID.cols)
    assert risk.known_free(far, 1.2).any()
    # A grid larger than the whole map is clipped to it, counted, and never an exception.
    huge = GridSpec(-40.0, -40.0, CELL, 801, 801)
    f, s = frame_grids([], grid=huge)
    risk.update(huge, f, s, 2.0, camera_xy=(12.0, 0.0))
    assert risk.stats.clipped == 1


def test_calm_is_how_long_the_disc_has_been_watched_free_and_restarts_on_a_sighting():
    """A lawn nobody enters grows calm for as long as it is watched; a gap a walker has just
    crossed is calm only since the walker left it."""
    risk = GroundRiskMap(RiskMapConfig(watch_gap_s=1.0))
    empty, seen = frame_grids([])
    assert risk.calm_s(0.0, 0.0, 3.0, 0.0) == 0.0  # no frame yet: nothing watched
    for k in range(51):  # 5 s at 10 Hz, nobody anywhere
        risk.update(GRID, empty, seen, 100.0 + 0.1 * k)
    assert risk.calm_s(0.0, 0.0, 3.0, 105.0) == pytest.approx(5.0, abs=1e-3)
    # A walker passes 2.5 m from (5, 0), inside its 3 m disc, at t = 105.1; (-5, 0) stays calm.
    walker, _ = frame_grids([(5.0, 2.5)], radius=0.2)
    risk.update(GRID, walker, seen, 105.1)
    for k in range(2, 31):
        risk.update(GRID, empty, seen, 105.0 + 0.1 * k)
    assert risk.calm_s(5.0, 0.0, 3.0, 108.0) == pytest.approx(2.9, abs=1e-3)
    assert risk.calm_s(-5.0, 0.0, 3.0, 108.0) == pytest.approx(8.0, abs=1e-3)
    # Further than the radius (plus half a cell's diagonal) does not count.
    assert risk.calm_s(5.0, -1.0, 3.0, 108.0) == pytest.approx(8.0, abs=1e-3)


def test_calm_needs_the_whole_disc_in_view_now_and_an_unbroken_watch():
    risk = GroundRiskMap(RiskMapConfig(watch_gap_s=1.0))
    west = np.zeros(GRID.shape, np.uint8)
    west[:, :100] = 255  # columns are x: the camera sees x < 0 only
    empty, seen = frame_grids([])
    for k in range(30):
        risk.update(GRID, empty, seen, 0.1 * k)
    # Watched 2.9 s, then the view moves west for 3 s: the east was out of view, anybody could
    # have walked there unseen.
    free_w, seen_w = frame_grids([], seen=west)
    for k in range(30, 60):
        risk.update(GRID, free_w, seen_w, 0.1 * k)
    assert risk.calm_s(5.0, 0.0, 3.0, 5.9) == 0.0  # not in view now
    assert risk.calm_s(-0.5, 0.0, 3.0, 5.9) == 0.0  # the disc straddles the view's edge
    assert risk.calm_s(-5.0, 0.0, 3.0, 5.9) == pytest.approx(5.9, abs=1e-3)
    # Back in view: the east's watch starts again now, not at t = 0.
    for k in range(60, 71):
        risk.update(GRID, empty, seen, 0.1 * k)
    assert risk.calm_s(5.0, 0.0, 3.0, 7.0) == pytest.approx(1.0, abs=1e-3)
    # A point whose disc leaves the map is not calm; nor is a non-finite one.
    assert GroundRiskMap(RiskMapConfig(half_extent_m=5.0)).calm_s(0.0, 0.0, 3.0, 0.0) == 0.0
    assert risk.calm_s(math.nan, 0.0, 3.0, 7.0) == 0.0
    with pytest.raises(ValueError, match="watch_gap_s"):
        RiskMapConfig(watch_gap_s=0.0)


def test_unwalked_survives_looking_away_and_restarts_only_on_a_sighting():
    """Unlike calm, a disc out of view for a while keeps its unwalked time (nobody was seen
    there); a sighting restarts it; ground never seen whole is 0."""
    risk = GroundRiskMap(RiskMapConfig(watch_gap_s=1.0))
    west = np.zeros(GRID.shape, np.uint8)
    west[:, :100] = 255  # columns are x: the camera sees x < 0 only
    empty, seen = frame_grids([])
    free_w, seen_w = frame_grids([], seen=west)
    assert risk.unwalked_s(-5.0, 0.0, 3.0, 0.0) == 0.0  # no frame yet
    for k in range(20):  # 2 s seeing only the west
        risk.update(GRID, free_w, seen_w, 0.1 * k)
    assert risk.unwalked_s(5.0, 0.0, 3.0, 1.9) == 0.0  # the east never seen
    assert risk.unwalked_s(-0.5, 0.0, 3.0, 1.9) == 0.0  # part of its disc never seen
    for k in range(20, 40):  # 2 s seeing everything, a walker 2.5 m from (5, 0) at t = 3.0
        people = [(5.0, 2.5)] if k == 30 else []
        risk.update(GRID, frame_grids(people, radius=0.2)[0], seen, 0.1 * k)
    for k in range(40, 70):  # 3 s looking west again
        risk.update(GRID, free_w, seen_w, 0.1 * k)
    assert risk.calm_s(-5.0, 0.0, 3.0, 6.9) == pytest.approx(6.9, abs=1e-3)
    assert risk.calm_s(5.0, -6.0, 3.0, 6.9) == 0.0  # out of view now: not calm ...
    assert risk.unwalked_s(5.0, -6.0, 3.0, 6.9) == pytest.approx(6.9 - 2.0, abs=1e-3)  # ... unwalked since first seen
    assert risk.unwalked_s(5.0, 0.0, 3.0, 6.9) == pytest.approx(3.9, abs=1e-3)  # since the walker
    assert risk.unwalked_s(math.nan, 0.0, 3.0, 6.9) == 0.0
    assert GroundRiskMap(RiskMapConfig(half_extent_m=5.0)).unwalked_s(0.0, 0.0, 3.0, 0.0) == 0.0

    # Both from one read of the map (what the pipeline asks every frame): the same two figures.
    for x, y, t in ((-5.0, 0.0, 6.9), (5.0, -6.0, 6.9), (5.0, 0.0, 6.9), (-0.5, 0.0, 1.9), (5.0, 0.0, 1.9),
                    (math.nan, 0.0, 6.9), (0.0, 0.0, 4.0), (40.0, 0.0, 6.9)):
        assert risk.calm_and_unwalked_s(x, y, 3.0, t) == (risk.calm_s(x, y, 3.0, t), risk.unwalked_s(x, y, 3.0, t))

def test_the_frame_pipeline_measures_unwalked_only_when_asked():
    base = np.zeros((240, 320), np.float32)
    frame = np.zeros((240, 320, 3), np.uint8)
    K = Intrinsics.from_fov(320, 240, 70.0)
    pipe = SLZPipeline(lambda _f: base, PipelineConfig(unwalked=True), intrinsics=K, mount=Mount())
    plain = SLZPipeline(lambda _f: base, PipelineConfig(), intrinsics=K, mount=Mount())
    assert pipe.risk is not None and plain.risk is None
    for k in range(30):
        t = 0.1 * k
        pose = Pose(t, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0)
        res, ref = pipe.process(frame, t, pose), plain.process(frame, t, pose)
        assert res.proposals == ref.proposals
    centre = [tr for tr in res.tracks if math.hypot(tr.x, tr.y) < 0.5]
    assert centre and centre[0].unwalked_s == pytest.approx(2.9, abs=1e-3)
    assert all(math.isnan(tr.calm_s) for tr in res.tracks)  # calm not asked
    assert ref.tracks and all(math.isnan(tr.unwalked_s) for tr in ref.tracks)
    # Zones only: the ground below carries no unwalked measure (``GroundBelow`` has none).
    assert res.below is not None and not hasattr(res.below, "unwalked_s")


def test_the_frame_pipeline_measures_each_zones_calm_without_changing_its_zones():
    """The map only measures calm (when asked): the proposals
    are the frame's own, and each posed frame's tracks and ground below carry calm_s. Not asked,
    the map does not run and nothing is measured (NaN)."""
    base = np.zeros((240, 320), np.float32)
    frame = np.zeros((240, 320, 3), np.uint8)
    K = Intrinsics.from_fov(320, 240, 70.0)
    pipe = SLZPipeline(lambda _f: base, PipelineConfig(calm=True), intrinsics=K, mount=Mount())
    ref = SLZPipeline(lambda _f: base, PipelineConfig(), intrinsics=K, mount=Mount())
    for k in range(30):
        t = 0.1 * k
        pose = Pose(t, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0)
        res = pipe.process(frame, t, pose)
        plain = ref.process(frame, t, pose)
        assert res.proposals == plain.proposals
    assert res.below is not None and res.below.calm_s == pytest.approx(2.9, abs=1e-3)
    centre = [tr for tr in res.tracks if math.hypot(tr.x, tr.y) < 0.5]
    assert centre and centre[0].calm_s == pytest.approx(2.9, abs=1e-3)
    # Zones whose disc reaches past the edge of the view are not calm: part of it is unwatched.
    assert all(tr.calm_s == 0.0 for tr in res.tracks if math.hypot(tr.x, tr.y) > 4.0)
    # Without a pose (a fixed projection) nothing is measured: NaN, never "calm".
    assert ref.risk is None and plain.tracks and all(math.isnan(tr.calm_s) for tr in plain.tracks)
    assert plain.below is not None and math.isnan(plain.below.calm_s)
    calm_only = SLZPipeline(lambda _f: base, PipelineConfig(calm=True), intrinsics=K, mount=Mount())
    out = calm_only.process(frame, 0.0, Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0))
    assert out.below is not None and out.below.calm_s == 0.0
    fixed = SLZPipeline(lambda _f: base, PipelineConfig(calm=True), projection=PlaneProjection.nadir(0.05))
    for k in range(5):
        out = fixed.process(frame, 0.1 * k)
    assert out.tracks and all(math.isnan(tr.calm_s) for tr in out.tracks)


