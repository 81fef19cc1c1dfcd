"""The whole per-frame pipeline on synthetic frames with known free circles."""

import math

import numpy as np
import pytest

from companion import synthetic
from companion.control.planner import PlannerConfig, ZonePlanner
from companion.geometry.camera import GeometryError, Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.occupancy import OCCUPIED
from companion.pipeline.slz import PipelineConfig, SLZPipeline


def _target(res, r0_m: float = 1.0):
    """The zone the landing controller would fly to (the planner decides, not the pipeline), with
    the age, hit and margin checks off so that only "confirmed and r >= r0" is left."""
    planner = ZonePlanner(PlannerConfig(r0_m=r0_m, radius_margin_m=0.0, min_track_age_s=0.0, min_track_hits=1))
    return planner.choose(res.tracks, res.t)


def _pipeline_for(scene, **kw):
    density = synthetic.point_density(scene)
    return SLZPipeline(lambda frame: density, **kw)


def test_nadir_pipeline_finds_the_known_free_circle():
    scene = synthetic.crowd_scene(free=((250.0, 240.0, 100.0),), n_people=400)
    gsd = 0.05
    pipe = _pipeline_for(scene, config=PipelineConfig(r0_m=1.0),
                         projection=PlaneProjection.nadir(gsd))
    frame = synthetic.render(scene)
    for k in range(4):
        res = pipe.process(frame, 0.1 * k)
    best = res.proposals[0]
    # The free disc shrinks by the occupancy dilation (4 px) and the density stride (< 4 px).
    assert math.hypot(best.x / gsd - 250.0, best.y / gsd - 240.0) < 12
    assert 100 - 12 <= best.r / gsd <= 100
    target = _target(res)
    assert target is not None and target.r >= 1.0
    assert math.hypot(target.x / gsd - 250, target.y / gsd - 240) < 12
    assert set(res.timings_ms) >= {"density", "occupancy", "projection", "proposals", "tracking",
                                   "post_density", "total"}
    # No proposal covers a person.
    for c in res.proposals:
        d = np.hypot(scene.people[:, 0] * gsd - c.x, scene.people[:, 1] * gsd - c.y)
        assert d.min() > c.r


def test_posed_pipeline_places_zones_in_world_metres():
    K = Intrinsics.from_fov(640, 480, 70.0)
    alt = 25.0
    pose = Pose(0.0, 100.0, -50.0, -alt, 0.0, 0.0, 0.0)
    scene = synthetic.crowd_scene(free=((420.0, 150.0, 80.0),), n_people=300, seed=3)
    # The paper's circle (the first largest): this checks where it lands in the world, and a
    # near-tie nearer the camera (proposal_tie_m) would move it toward the vehicle.
    pipe = _pipeline_for(scene, config=PipelineConfig(r0_m=1.0, proposal_tie_m=0.0), intrinsics=K, mount=Mount())
    res = pipe.process(synthetic.render(scene), 0.0, pose)
    # Where the free circle's centre pixel lands on the head plane, in world NED.
    expect = res.projection.image_to_plane(np.array([[420.0, 150.0]]))[0]
    best = res.proposals[0]
    gsd = (alt - 1.7) / K.fx
    assert math.hypot(best.x - expect[0], best.y - expect[1]) < 12 * gsd
    assert best.x > pose.north and best.y > pose.east  # up-right of centre = north-east


def test_cells_outside_the_view_are_never_free():
    K = Intrinsics.from_fov(640, 480, 70.0)
    pipe = SLZPipeline(lambda f: np.zeros((120, 160), np.float32), intrinsics=K, mount=Mount())
    # Oblique camera that sees the horizon: the grid is bounded and what lies outside the view
    # (above the horizon, behind the camera, beyond the corners) is unknown.
    pose = Pose(0.0, 0.0, 0.0, -15.0, 0.0, 0.0, 0.0)
    pipe.mount = Mount.from_degrees(0, -30, 0)
    res = pipe.process(np.zeros((480, 640, 3), np.uint8), 0.0, pose)
    assert res.free_grid.shape[0] <= 2 * 40 / 0.1 + 2
    rows, cols = np.nonzero(res.free_grid)
    xs, ys = res.grid.to_plane(rows, cols)
    uv = res.projection.plane_to_image(np.column_stack([xs, ys]))
    assert np.isfinite(uv).all()
    assert (uv[:, 0] >= -1).all() and (uv[:, 0] <= 640).all()
    assert (uv[:, 1] >= -1).all() and (uv[:, 1] <= 480).all()
    for c in res.proposals:
        uvc = res.projection.plane_to_image(np.array([[c.x, c.y]]))
        assert np.isfinite(uvc).all()


def test_all_occupied_frame_gives_no_proposals_not_an_error():
    pipe = SLZPipeline(lambda f: np.random.default_rng(0).random((120, 160)).astype(np.float32),
                       projection=PlaneProjection.nadir(0.05))
    res = pipe.process(np.zeros((480, 640, 3), np.uint8), 0.0)
    assert (res.occupancy == OCCUPIED).mean() > 0.99
    assert res.proposals == [] and res.tracks == [] and _target(res) is None


def test_bad_inputs_are_clear_errors():
    K = Intrinsics.from_fov(640, 480, 70.0)
    pipe = SLZPipeline(lambda f: np.zeros((120, 160), np.float32), intrinsics=K)
    frame = np.zeros((480, 640, 3), np.uint8)
    with pytest.raises(GeometryError, match="NaN"):
        pipe.process(frame, 0.0, Pose(0.0, 0.0, 0.0, float("nan"), 0.0, 0.0, 0.0))
    with pytest.raises(GeometryError, match="no pose and no fixed projection"):
        pipe.process(frame, 0.0, None)
    with pytest.raises(GeometryError, match="640x480"):
        pipe.process(np.zeros((240, 320, 3), np.uint8), 0.0, Pose(0.0, 0, 0, -20, 0, 0, 0))
    with pytest.raises(ValueError, match="image"):
        pipe.process(np.zeros((0, 0, 3), np.uint8), 0.0, Pose(0.0, 0, 0, -20, 0, 0, 0))
    with pytest.raises(GeometryError, match="not invertible"):
        SLZPipeline(lambda f: f, projection=PlaneProjection.from_image_to_plane(np.ones((3, 3))))


def test_threshold_defaults_to_the_models_own_and_an_explicit_one_wins():
    from companion.pipeline.occupancy import OccupancyParams

    class Model:
        class spec:
            occupancy_threshold = 0.25

        def __call__(self, frame):
            return np.zeros((120, 160), np.float32)

    nadir = PlaneProjection.nadir(0.05)
    assert SLZPipeline(Model(), projection=nadir).config.occupancy.threshold == 0.25
    explicit = PipelineConfig(occupancy=OccupancyParams(threshold=0.0))
    assert SLZPipeline(Model(), explicit, projection=nadir).config.occupancy.threshold == 0.0
    assert SLZPipeline(lambda f: f, projection=nadir).config.occupancy.threshold == 0.0


def test_ground_all_free_up_to_the_view_edge_is_view_limited():
    K = Intrinsics.from_fov(640, 480, 70.0)
    pipe = SLZPipeline(lambda f: np.zeros((120, 160), np.float32),
                       PipelineConfig(r0_m=1.0), intrinsics=K, mount=Mount())
    pose = Pose(0.0, 0.0, 0.0, -6.0, 0.0, 0.0, 0.0)  # low: the view is ~6 x 4.5 m
    for k in range(4):
        res = pipe.process(np.zeros((480, 640, 3), np.uint8), 0.1 * k, pose)
    t = res.tracks[0]
    assert t.view_limited and t.r == pytest.approx(t.r_view, abs=1e-6)
    assert 1.5 < t.r_view < 2.5


def test_the_ground_under_the_camera_is_measured_on_every_posed_frame():
    """What the controller checks under the vehicle: the free radius around the camera's ground
    point, people included and the view's edge too (unseen is never free)."""
    K = Intrinsics.from_fov(640, 480, 70.0)
    alt = 12.0
    pose = Pose(0.0, 20.0, -5.0, -alt, 0.0, 0.0, 0.0)
    gsd = (alt - 1.7) / K.fx
    # One person 60 px right of the image centre: about 60 gsd east of the vehicle.
    density = np.zeros((120, 160), np.float32)
    density[60, 80 + 15] = 1.0  # stride 4: column 95 is pixel 380, 60 px right of 320
    pipe = SLZPipeline(lambda f: density, PipelineConfig(r0_m=1.0), intrinsics=K, mount=Mount())
    res = pipe.process(np.zeros((480, 640, 3), np.uint8), 0.0, pose)
    below = res.below
    assert below is not None and (below.x, below.y) == pytest.approx((20.0, -5.0), abs=1e-6)
    assert not below.view_limited and 0.5 < below.r < 60 * gsd  # the person (dilated) bounds it
    assert below.r_view == pytest.approx(240 * gsd, rel=0.1)  # the narrower half of the view
    empty = SLZPipeline(lambda f: np.zeros((120, 160), np.float32), PipelineConfig(r0_m=1.0), intrinsics=K,
                        mount=Mount()).process(np.zeros((480, 640, 3), np.uint8), 0.0, pose).below
    assert empty is not None and empty.view_limited and empty.r == pytest.approx(empty.r_view, abs=1e-6)
    # A fixed projection that does not say where the camera is: no measure, not a guess.
    assert SLZPipeline(lambda f: density, projection=PlaneProjection.nadir(0.05)).process(
        np.zeros((480, 640, 3), np.uint8), 0.0).below is None
