"""``pipeline.person_px``: a pinhole's frame is shrunk before the density model so that the
smallest person still spans that many pixels (``companion.pipeline.input_scale``).

The geometry is checked against the pinhole's own figures; the pipeline runs the shipped ONNX
model and the tests check which frame it was given. That people are still found on shrunk frames,
and that the photos' grain is not, is measured on rendered views in
``tests/sim/evidence/test_person_px.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config.schema import shipped_model
from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.density import DensityModel
from companion.pipeline.input_scale import MIN_SCALE, PERSON_M, density_scale, scaled_size, shrunk, smallest_person_px
from companion.pipeline.slz import PipelineConfig, SLZPipeline
from tests.companion.pipeline.recorded import Recorded

K = Intrinsics.from_fov(640, 480, 70.0)
HW = (480, 640)
HEAD = 1.7


def nadir(height_m: float, k: Intrinsics = K) -> PlaneProjection:
    return PlaneProjection.from_pose(k, Mount(), Pose(0.0, 5.0, -3.0, -height_m, 0.0, 0.0, 0.4), HEAD)



@pytest.fixture(scope="module")
def model() -> DensityModel:
    return DensityModel(shipped_model(), threads=1)


def test_the_smallest_person_looking_straight_down_is_the_pinholes_figure() -> None:
    # Straight down onto the head plane every pixel covers the same ground: fx * 0.4 m / range.
    for h in (5.0, 8.0, 12.0, 20.0, 60.0):
        assert smallest_person_px(nadir(h), HW) == pytest.approx(K.fx * PERSON_M / (h - HEAD), rel=1e-6)


def test_a_tilted_view_is_judged_where_it_reaches_farthest() -> None:
    # Pitched 30 degrees forward, the top edge sees ground farther than the nadir's: the smallest
    # person is smaller there than straight down from the same height.
    tilted = PlaneProjection.from_pose(K, Mount(), Pose(0.0, 0.0, 0.0, -10.0, 0.0, math.radians(-30.0), 0.0), HEAD)
    seen = smallest_person_px(tilted, HW)
    assert 0 < seen < smallest_person_px(nadir(10.0), HW)
    # Pitched so the top of the frame is above the horizon: no smallest person, never shrunk.
    skyward = PlaneProjection.from_pose(K, Mount(), Pose(0.0, 0.0, 0.0, -10.0, 0.0, math.radians(-80.0), 0.0), HEAD)
    assert smallest_person_px(skyward, HW) == 0.0
    assert density_scale(skyward, HW, 12.0) == 1.0


def test_the_scale_keeps_the_smallest_person_at_person_px_above_a_floor() -> None:
    assert density_scale(nadir(8.0), HW, 0.0) == 1.0  # off
    assert density_scale(nadir(30.0), HW, 12.0) == 1.0  # people already smaller than 12 px: the full frame
    s = density_scale(nadir(8.0), HW, 12.0)
    assert s == pytest.approx(12.0 / (K.fx * PERSON_M / (8.0 - HEAD)))
    assert s * smallest_person_px(nadir(8.0), HW) == pytest.approx(12.0)
    assert density_scale(nadir(2.5), HW, 12.0) == MIN_SCALE  # the floor on the map's resolution
    # The shrunk frame: whole stride cells, rounded up (a person never comes out smaller).
    assert scaled_size(HW, 0.41, 4) == (200, 264)
    assert scaled_size(HW, 1.0, 4) == HW and scaled_size((10, 10), 0.01, 4) == (4, 4)
    frame = np.zeros((480, 640, 3), np.uint8)
    frame[::2, ::2] = 255  # a one-pixel grain: area interpolation averages it out
    assert shrunk(frame, 1.0, 4) is frame
    small = shrunk(frame, 0.5, 4)
    assert small.shape == (240, 320, 3) and int(small.min()) == int(small.max()) == 64


@pytest.mark.parametrize("height_m, shrunk", [(8.0, True), (30.0, False)])
def test_the_pipeline_gives_the_model_the_shrunk_frame_and_keeps_the_frames_map(
        model: DensityModel, height_m: float, shrunk: bool) -> None:
    rec = Recorded(model)
    pipe = SLZPipeline(rec, PipelineConfig(person_px=12.0), intrinsics=K)
    pose = Pose(0.0, 0.0, 0.0, -height_m, 0.0, 0.0, 0.0)
    frame = np.full((480, 640, 3), 120, np.uint8)
    res = pipe.process(frame, 0.0, pose)
    want = scaled_size(HW, density_scale(pipe.projection_for(pose), HW, 12.0), 4) if shrunk else HW
    assert rec.shapes == [(*want, 3)]
    assert (want != HW) is shrunk
    assert res.occupancy.shape == HW  # the occupancy map is the frame's, whatever the model saw


def test_off_at_zero_and_through_a_fisheye(model: DensityModel) -> None:
    frame = np.full((480, 640, 3), 120, np.uint8)
    off = Recorded(model)
    SLZPipeline(off, PipelineConfig(), intrinsics=K).process(frame, 0.0, Pose(0.0, 0, 0, -8.0, 0, 0, 0))
    assert off.shapes == [(480, 640, 3)]  # person_px 0: the full frame, as every row flown before it
    fish = Recorded(model)
    lens = Intrinsics.from_fov(640, 480, 160.0, "fisheye")
    SLZPipeline(fish, PipelineConfig(person_px=12.0), intrinsics=lens).process(frame, 0.0, Pose(0.0, 0, 0, -8.0, 0, 0, 0))
    assert fish.shapes[0][0] == 480  # a fisheye's ground scale varies across the frame: not shrunk


def test_person_px_is_checked() -> None:
    for bad in (-1.0, math.nan, 2000.0):
        with pytest.raises(ValueError, match="person_px"):
            PipelineConfig(person_px=bad)


@pytest.mark.parametrize("height_m, shrunk", [(8.0, True), (30.0, False)])
def test_the_landability_model_sees_the_same_shrunk_frame(model: DensityModel, height_m: float, shrunk: bool) -> None:
    """Close up the full frame shows the landability model the paving's grain too, which it calls
    roof and wall (``sim.evidence.landability_threshold --person-px``): it is given the density
    model's shrunk frame, and its map comes back at the frame's size."""
    from companion.config.schema import SHIPPED_LANDABILITY
    from companion.pipeline.landability import LandabilityModel

    surface = LandabilityModel(SHIPPED_LANDABILITY, threads=1).unlandable()
    seen: list[tuple[int, ...]] = []

    def recorded(frame: np.ndarray) -> np.ndarray:
        seen.append(frame.shape)
        return surface(frame)

    rec = Recorded(model)
    pipe = SLZPipeline(rec, PipelineConfig(person_px=12.0, surface_threshold=0.05), intrinsics=K, surface=recorded)
    pose = Pose(0.0, 0.0, 0.0, -height_m, 0.0, 0.0, 0.0)
    res = pipe.process(np.full((480, 640, 3), 120, np.uint8), 0.0, pose)
    assert seen == rec.shapes and len(seen) == 1
    assert (seen[0][:2] != HW) is shrunk
    assert res.surface is not None and res.surface.shape == HW
