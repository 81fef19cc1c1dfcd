"""Through a fisheye, the density model runs on the part of the frame the landing rules can use.

The grid through a lens that is not a pinhole ends at the seen disk (``LensView.seen_radius``);
``headplane.lens_crop_box`` is that disk's image plus a margin, and ``SLZPipeline`` runs the
density model on it alone. These tests run the shipped ONNX model on a rendered crowd and check
that the zones' ground is the same as with the whole frame, that what was not looked at is unseen,
and that nothing is cropped where the model or the lens would not give the same map.
"""

from __future__ import annotations

import numpy as np
import pytest

from companion import bench
from companion.config.schema import shipped_model
from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.density import DensityModel
from companion.pipeline.headplane import CROP_MARGIN_PX, GridParams, grid_for_view, lens_crop_box, sample_with_view
from companion.pipeline.occupancy import OccupancyParams
from companion.pipeline.slz import PipelineConfig, SLZPipeline
from tests.companion.pipeline.recorded import Recorded

FISHEYE = Intrinsics.from_fov(640, 480, 160.0, "fisheye")



@pytest.fixture(scope="module")
def model() -> DensityModel:
    return DensityModel(shipped_model(), threads=1)


def test_the_box_is_the_seen_disks_image_with_its_margin() -> None:
    # Looking straight down from 20 m, the seen disk (60 degrees off the axis, tan 60 = 1.724)
    # touches the image's short sides: 240 px round the centre, so the box is 480 columns plus
    # the margins, on whole stride cells.
    proj = PlaneProjection.from_pose(FISHEYE, Mount(), Pose(0.0, 3.0, 4.0, -20.0, 0.0, 0.0, 0.0), 1.7)
    box = lens_crop_box(proj, (480, 640), 4, GridParams().max_extent)
    assert box is not None
    x0, y0, x1, y1 = box
    assert (y0, y1) == (0, 480)
    assert x0 % 4 == 0 and x1 % 4 == 0
    assert 319.5 - 240 - CROP_MARGIN_PX - 4 <= x0 <= 319.5 - 240 - CROP_MARGIN_PX
    assert 319.5 + 240 + CROP_MARGIN_PX <= x1 <= 319.5 + 240 + CROP_MARGIN_PX + 5
    # A tilted vehicle moves the disk's image; the box follows it.
    tilted = PlaneProjection.from_pose(FISHEYE, Mount(), Pose(0.0, 3.0, 4.0, -20.0, 0.15, 0.0, 0.0), 1.7)
    tbox = lens_crop_box(tilted, (480, 640), 4, GridParams().max_extent)
    assert tbox is not None and tbox != box
    # A pinhole's frame is always looked at whole (its grid is its whole image).
    pin = PlaneProjection.from_pose(Intrinsics.from_fov(640, 480, 70.0), Mount(),
                                    Pose(0.0, 3.0, 4.0, -20.0, 0.0, 0.0, 0.0), 1.7)
    assert lens_crop_box(pin, (480, 640), 4) is None


def test_the_fisheyes_zones_ground_is_the_whole_frames(model: DensityModel) -> None:
    frame, _ = bench.bench_frame(640, 480, 0)
    rec = Recorded(model)
    cropped = SLZPipeline(rec, PipelineConfig(), intrinsics=FISHEYE, mount=Mount())
    # The same model behind a plain function carries no size rule: the pipeline looks at the
    # whole frame, as it did before the crop (given the model's threshold, which a plain function
    # does not carry either).
    config = PipelineConfig(occupancy=OccupancyParams(threshold=model.spec.occupancy_threshold))
    whole = SLZPipeline(lambda f: model(f), config, intrinsics=FISHEYE, mount=Mount())
    for t in (0.0, 1.0, 4.0):
        pose = bench.drifting_pose(t)
        a, b = cropped.process(frame, t, pose), whole.process(frame, t, pose)
        box = lens_crop_box(a.projection, (480, 640), model.spec.stride, GridParams().max_extent)
        assert box is not None
        x0, y0, x1, y1 = box
        assert rec.shapes[-1] == (y1 - y0, x1 - x0, 3) and (x1 - x0) * (y1 - y0) < 0.9 * 640 * 480
        assert a.grid == b.grid
        # Every cell of the seen disk is judged as from the whole frame.
        g = a.grid
        x, y = g.to_plane(*np.meshgrid(np.arange(g.rows), np.arange(g.cols), indexing="ij"))
        assert a.projection.lens is not None and a.projection.camera_xy is not None
        cx, cy = a.projection.camera_xy
        disk = np.hypot(x - cx, y - cy) <= a.projection.lens.seen_radius()
        assert disk.sum() > 100_000
        np.testing.assert_array_equal(a.free_grid[disk], b.free_grid[disk])
        # Nothing is free that the whole frame did not find free, anywhere.
        assert not ((a.free_grid > 0) & (b.free_grid == 0)).any()
        # Pixels outside the box were not looked at: not free in the image.
        assert not a.occupancy[:, :x0].any() and not a.occupancy[:, x1:].any()
        assert [(tr.x, tr.y, tr.r) for tr in a.tracks] == [(tr.x, tr.y, tr.r) for tr in b.tracks]
    assert [s for s in rec.shapes] and all(s[1] < 640 for s in rec.shapes)


def test_ground_whose_pixels_were_not_looked_at_is_unseen() -> None:
    # Only the box's pixels were looked at: a cell whose pixel lies outside it is unknown (view
    # 0, never free), not seen and occupied, though the free map there says free.
    proj = PlaneProjection.from_pose(FISHEYE, Mount(), Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0), 1.7)
    grid = grid_for_view(proj, (480, 640), GridParams())
    free = np.full((480, 640), 255, np.uint8)
    box = (160, 0, 480, 480)
    out, view = sample_with_view(free, proj, grid, box)
    whole_out, whole_view = sample_with_view(free, proj, grid)
    x, y = grid.to_plane(*np.meshgrid(np.arange(grid.rows), np.arange(grid.cols), indexing="ij"))
    uv = proj.plane_to_image(np.column_stack([x.ravel(), y.ravel()])).reshape(grid.rows, grid.cols, 2)
    u = uv[..., 0]
    outside = whole_view.astype(bool) & ((u < box[0] - 3) | (u > box[2] + 3))
    inside = whole_view.astype(bool) & (u > box[0] + 8) & (u < box[2] - 8)
    assert outside.sum() > 10_000 and inside.sum() > 10_000
    assert not view[outside].any() and not out[outside].any()
    assert view[inside].all() and out[inside].all()
    # A pinhole's frame is never cropped: a box there is a caller's bug.
    pin = PlaneProjection.from_pose(Intrinsics.from_fov(640, 480, 70.0), Mount(),
                                    Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0), 1.7)
    with pytest.raises(ValueError, match="pinhole"):
        sample_with_view(free, pin, grid_for_view(pin, (480, 640), GridParams()), box)


def test_no_crop_where_the_model_resizes_every_frame(model: DensityModel) -> None:
    # A model with a fixed input size resizes each frame to it: a crop would change its scale.
    frame, _ = bench.bench_frame(640, 480, 0)

    class Fixed(Recorded):
        @property
        def any_size(self) -> bool:
            return False

    rec = Fixed(model)
    SLZPipeline(rec, PipelineConfig(), intrinsics=FISHEYE, mount=Mount()).process(
        frame, 0.0, bench.drifting_pose(0.0))
    assert rec.shapes == [(480, 640, 3)]
    assert model.any_size


def test_the_pilots_view_dims_what_the_model_did_not_look_at(model: DensityModel) -> None:
    # Outside the crop the occupancy is 0 because unseen: the live view and the replay dim it
    # instead of tinting it red as people.
    from companion.replay import draw
    from companion.replay.live_figure import live_figure

    frame = np.full((480, 640, 3), 120, np.uint8)
    pipe = SLZPipeline(Recorded(model), PipelineConfig(), intrinsics=FISHEYE, mount=Mount())
    res = pipe.process(frame, 0.0, Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0))
    assert res.looked_at is not None
    x0, _, x1, _ = res.looked_at
    assert not res.occupancy[:, :x0].any()
    view = draw.overlay_people(frame, res.occupancy, looked_at=res.looked_at)
    outside = view[:, : x0 - 1].reshape(-1, 3)
    assert (outside == int(120 * draw.UNSEEN_DIM)).all()  # grey, dimmed: no red tint
    red = draw.overlay_people(frame, res.occupancy)[:, : x0 - 1].reshape(-1, 3)
    assert (red[:, 2] > red[:, 1]).all()  # without the box it would read as people
    # The live view's figure carries the same: its left strip is the dimmed grey.
    fig = live_figure(frame, res, None, "MONITOR")
    strip = fig[-200:, : x0 - 1].reshape(-1, 3)
    assert (strip == int(120 * draw.UNSEEN_DIM)).all()
    # A pinhole's frame is looked at whole.
    pin = SLZPipeline(Recorded(model), PipelineConfig(), intrinsics=Intrinsics.from_fov(640, 480, 70.0),
                      mount=Mount())
    assert pin.process(frame, 0.0, Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0)).looked_at is None
