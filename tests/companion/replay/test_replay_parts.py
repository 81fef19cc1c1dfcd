"""The parts of replay on their own: homography files, pixel circles, drawing, the summary."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.control.planner import PlannerConfig, ZonePlanner
from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.circles import Circle
from companion.pipeline.headplane import GridSpec
from companion.pipeline.tracker import Track
from companion.replay import draw
from companion.replay.homography import HomographyFileError, projection_from_file, read_homography
from companion.replay.records import circle_in_image, frame_record
from companion.replay.sources import ReplayInputError, open_folder, open_input
from companion.replay.summary import SummaryBuilder, format_summary

H = np.array([[0.05, 0.01, -3.0], [-0.02, 0.06, 4.0], [1e-5, 2e-5, 1.0]])


@pytest.mark.parametrize("form", ["npy", "npy9", "txt", "csv", "json_list", "json_flat", "json_obj"])
def test_homography_file_forms(form: str, tmp_path: Path) -> None:
    if form.startswith("npy"):
        p = tmp_path / "h.npy"
        np.save(p, H if form == "npy" else H.ravel())
    elif form == "txt":
        p = tmp_path / "h.txt"
        p.write_text("\n".join(" ".join(repr(float(v)) for v in row) for row in H) + "\n")
    elif form == "csv":
        p = tmp_path / "h.csv"
        p.write_text("\n".join(",".join(repr(float(v)) for v in row) for row in H))
    else:
        p = tmp_path / "h.json"
        body = {"json_list": H.tolist(), "json_flat": H.ravel().tolist(),
                "json_obj": {"image_to_plane": H.tolist(), "note": "survey 3"}}[form]
        p.write_text(json.dumps(body))
    np.testing.assert_array_equal(read_homography(p), H)
    np.testing.assert_allclose(projection_from_file(p).H_inv, H)


@pytest.mark.parametrize("text,message", [("1 2 3\n4 5 6\n", "3x3"), ("1 2 x\n", "cannot read"),
                                          ("", "3x3")])
def test_bad_homography_text_names_the_file(text: str, message: str, tmp_path: Path) -> None:
    p = tmp_path / "h.txt"
    p.write_text(text)
    with pytest.raises(HomographyFileError, match=message) as exc:
        read_homography(p)
    assert str(p) in str(exc.value)


def test_json_without_matrix_key(tmp_path: Path) -> None:
    p = tmp_path / "h.json"
    p.write_text('{"matrix": [1, 0, 0, 0, 1, 0, 0, 0, 1]}')
    with pytest.raises(HomographyFileError, match="none of the keys"):
        read_homography(p)


def test_nan_homography_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "h.npy"
    np.save(p, np.array([[1, 0, 0], [0, np.nan, 0], [0, 0, 1]], float))
    with pytest.raises(HomographyFileError, match="NaN"):
        projection_from_file(p)


def test_r_px_of_a_similarity_is_exact() -> None:
    # Image-to-plane: rotate 30 deg, 0.04 m/px, shift. Every plane direction scales by 1/0.04.
    a = math.radians(30)
    s = 0.04
    Hi = np.array([[s * math.cos(a), -s * math.sin(a), 5.0], [s * math.sin(a), s * math.cos(a), -2.0],
                   [0, 0, 1]])
    proj = PlaneProjection.from_image_to_plane(Hi)
    u, v, r_px = circle_in_image(proj, 10.0, 3.0, 2.0)
    np.testing.assert_allclose(proj.image_to_plane(np.array([[u, v]]))[0], [10.0, 3.0], atol=1e-9)
    assert r_px == pytest.approx(2.0 / s, rel=1e-9)


def test_r_px_is_the_ellipse_extent_along_image_x_under_an_oblique_view() -> None:
    K = Intrinsics.from_fov(640, 480, 70.0)
    proj = PlaneProjection.from_pose(K, Mount.from_degrees(pitch_deg=-50), Pose(0, 0, 0, -20, 0, 0, 0.3))
    centre = proj.image_to_plane(np.array([[320.0, 300.0]]))[0]
    r = 1.5
    u, v, r_px = circle_in_image(proj, *centre, r)
    # Sample the projected circle finely; its half-width along the image row through the centre.
    pts = proj.plane_to_image(draw.circle_polygon(*centre, r, n=20000))
    row = np.abs(pts[:, 1] - v) < 0.05
    half_width = (pts[row, 0].max() - pts[row, 0].min()) / 2
    assert r_px == pytest.approx(half_width, rel=0.02)
    assert r_px != pytest.approx(r * K.fx / 20, rel=0.02)  # not a nadir scale in disguise


def test_centre_behind_the_camera_is_null_not_nan() -> None:
    K = Intrinsics.from_fov(640, 480, 70.0)
    proj = PlaneProjection.from_pose(K, Mount.from_degrees(pitch_deg=-20), Pose(0, 0, 0, -10, 0, 0, 0))
    assert circle_in_image(proj, -30.0, 0.0, 2.0) == (None, None, None)


class _Result:
    """The fields of FrameResult that a record reads."""

    def __init__(self, proj: PlaneProjection) -> None:
        self.t = 1.5
        self.projection = proj
        self.proposals = [Circle(float("nan"), 1.0, 2.0), Circle(3.0, 4.0, 1.0)]
        self.tracks = [Track(7, 3.0, 4.0, 1.0, 1.1, 4, 5, 0, 0.0, 1.5),
                       Track(8, 9.0, 9.0, 3.0, 3.0, 9, 9, 1, 0.0, 1.4)]
        self.timings_ms = {"density": 1.0, "occupancy": 0.1, "projection": 0.2, "proposals": 0.3,
                           "tracking": 0.4, "total": float("nan")}


def _planner(r0_m: float) -> ZonePlanner:
    """The landing controller's target rule, its margin off (these tracks are 1 m and 3 m wide)."""
    return ZonePlanner(PlannerConfig(r0_m=r0_m, radius_margin_m=0.0))


def test_record_is_valid_json_with_nulls_and_stability() -> None:
    rec = frame_record(4, _Result(PlaneProjection.nadir(0.1)), _planner(0.5))  # type: ignore[arg-type]
    text = json.dumps(rec, allow_nan=False)
    back = json.loads(text)
    assert back["frame"] == 4 and back["target"] == 7
    assert back["proposals"][0]["x"] is None and back["proposals"][0]["u"] is None
    assert back["proposals"][1]["u"] == pytest.approx(30.0)
    assert back["timing_ms"]["total"] is None
    # Stable needs misses == 0 and r >= r_0: track 8 was missed this frame.
    assert [t["stable"] for t in back["tracks"]] == [True, False]
    assert frame_record(0, _Result(PlaneProjection.nadir(0.1)), _planner(2.0))["tracks"][0]["stable"] is False  # type: ignore[arg-type]


def test_summary_counts_target_switches_per_minute() -> None:
    s = SummaryBuilder()
    timings = {"density": 2.0, "occupancy": 1.0, "projection": 1.0, "proposals": 1.0,
               "tracking": 1.0, "total": 6.0}
    # Target 1, lost, 1 again (no switch), then 2 (switch), then 3 (switch), over 30 s.
    for k, target in enumerate([1, None, 1, 2, 2, 3, None]):
        s.add_frame(5.0 * k, timings, target)
    s.add_skip("unreadable frame")
    out = s.build(wall_s=2.0, tracks_born=3, tracks_ended=1)
    assert out["target_switches"] == 2
    assert out["target_switches_per_min"] == pytest.approx(2 / 0.5)
    assert out["frames"] == 7 and out["frames_skipped"] == 1 and out["frames_per_s"] == 3.5
    assert out["latency_ms"]["density"] == {"median": 2.0, "p99": 2.0}
    assert out["frames_with_target"] == 5
    text = format_summary(out)
    assert "7 processed, 1 skipped" in text and "3 born, 1 ended" in text


def test_image_view_draws_circles_as_projected_polygons() -> None:
    frame = np.full((200, 300, 3), 100, np.uint8)
    free = np.full((200, 300), 255, np.uint8)
    free[:20, :20] = 0
    proj = PlaneProjection.nadir(0.1)
    tr = Track(3, 15.0, 10.0, 4.0, 4.0, 7, 8, 0, 0.0, 1.0)
    img = draw.draw_image_view(frame, free, proj, [Circle(5.0, 5.0, 2.0)], [tr], target_id=3)
    assert img.shape == frame.shape and (frame == 100).all()  # input untouched
    assert img[5, 5, 2] > 150 and img[5, 5, 0] < 100  # occupied tinted red
    assert (img[100, 100] == 100).all()  # free ground untouched
    # Green proposal ring of radius 20 px about (50, 50); yellow target ring of 40 px about (150, 100).
    assert img[50, 70, 1] > 150 and img[50, 50, 1] == 100
    assert img[100, 190, 2] > 200 and img[100, 190, 1] > 180 and img[100, 190, 0] < 90


def test_plane_view_is_north_up() -> None:
    grid = GridSpec(x0=0.0, y0=0.0, cell=1.0, rows=50, cols=100)  # x (north) 0..99, y (east) 0..49
    free = np.zeros(grid.shape, np.uint8)
    free[10:20, 80:90] = 255  # east 10-19, north 80-89: a free patch far north
    view = draw.draw_plane_view(free, grid, [], [], None, size=200)
    assert view.shape == (200, 200, 3)
    # 2 px per metre: 100 m of north fill the height, 50 m of east are centred (50 px margins).
    # The patch is at display rows 2 * (99 - 89) .. 2 * (99 - 80) + 1, columns 50 + 20 .. 50 + 39.
    white = (view == 255).all(axis=2)
    assert white[22:38, 72:88].all()
    assert not white[162:178, 72:88].any()  # mirrored north-south
    assert not white[22:38, 112:128].any()  # mirrored east-west
    assert not white[52:150, 50:150].any()


def test_figure_adds_the_plane_panel_only_with_a_grid() -> None:
    frame = np.zeros((120, 160, 3), np.uint8)
    free = np.full((120, 160), 255, np.uint8)
    proj = PlaneProjection.nadir(0.1)
    assert draw.figure(frame, free, proj, [], [], None).shape == (120, 160, 3)
    grid = GridSpec(0.0, 0.0, 0.1, 30, 40)
    fig = draw.figure(frame, free, proj, [], [], None, np.full(grid.shape, 255, np.uint8), grid)
    assert fig.shape == (120, 160 + 4 + 120, 3)


def test_folder_source_sorts_by_name_and_times_by_fps(tmp_path: Path) -> None:
    for name in ("b.png", "a.png", "c.jpg"):
        cv2.imwrite(str(tmp_path / name), np.full((8, 8, 3), ord(name[0]), np.uint8))
    (tmp_path / "notes.txt").write_text("not a frame")
    src = open_folder(tmp_path, fps=4.0)
    frames = list(src.frames)
    assert [f.name for f in frames] == ["a.png", "b.png", "c.jpg"]
    assert [f.t for f in frames] == [0.0, 0.25, 0.5]
    assert src.total == 3 and src.fps == 4.0
    with pytest.raises(ReplayInputError, match="fps"):
        open_folder(tmp_path, fps=0.0)


def test_video_that_opencv_cannot_open(tmp_path: Path) -> None:
    p = tmp_path / "clip.mp4"
    p.write_bytes(b"\x00" * 100)
    with pytest.raises(ReplayInputError, match="not a video") as exc:
        open_input(p)
    assert str(p) in str(exc.value)


def test_folder_that_is_not_a_recording(tmp_path: Path) -> None:
    (tmp_path / "meta.json").write_text("{broken")
    with pytest.raises(ReplayInputError, match="meta.json"):
        open_input(tmp_path)


def test_skipped_frames_are_logged_a_few_times_per_reason_then_only_counted(caplog):
    import logging

    from companion.replay.runner import LOGGED_SKIPS, _log_skip

    counts: dict[str, int] = {}
    with caplog.at_level(logging.WARNING, logger="companion.replay.runner"):
        for i in range(LOGGED_SKIPS + 10):
            _log_skip(counts, "geometry", i, "camera below the head plane")
        _log_skip(counts, "unreadable", 99, "truncated JPEG")
    lines = [r.getMessage() for r in caplog.records]
    assert sum("camera below the head plane" in m for m in lines) == LOGGED_SKIPS
    assert any("counted in the summary only" in m for m in lines)
    assert any("frame 99 skipped: truncated JPEG" in m for m in lines)
    assert counts == {"geometry": LOGGED_SKIPS + 10, "unreadable": 1}


def test_each_track_is_labelled_with_its_predicted_clearance_at_touchdown() -> None:
    # Issue 11, item 6: the video shows what the controller judges, a zone's clearance at touchdown.
    tr = Track(3, 15.0, 10.0, 4.0, 4.0, 7, 8, 0, 0.0, 1.0)
    assert draw._track_text(tr) == "#3 age 7"
    assert draw._track_text(tr, 1.44) == "#3 age 7, 4.0 / +1.4 m"  # free now / at touchdown
    assert draw._track_text(tr, -12.0) == "#3 age 7, 4.0 / -12.0 m"  # a walker could be there first
    assert draw._track_text(tr, float("nan")) == "#3 age 7"
    frame = np.full((200, 300, 3), 100, np.uint8)
    free = np.full((200, 300), 255, np.uint8)
    proj = PlaneProjection.nadir(0.1)
    plain = draw.draw_image_view(frame, free, proj, [], [tr], target_id=None)
    labelled = draw.draw_image_view(frame, free, proj, [], [tr], target_id=None, clearances={3: 1.4})
    # The longer label writes further right of the zone's centre (150, 100) than the plain one.
    right = (slice(80, 100), slice(230, 300))
    assert (labelled[right] != 100).any() and not (plain[right] != 100).any()


def test_frames_from_the_ground_are_said_once_at_info_not_warned_about(caplog):
    # Issue 62: the demo's evidence replay printed six WARNING lines for the frames after the
    # landing, which every recording of a flight ends with.
    import logging

    from companion.replay.runner import LOGGED_SKIPS, _log_skip

    why = "camera at down=-1.41 m is not above the head plane (z = -1.70 m)"
    counts: dict[str, int] = {}
    with caplog.at_level(logging.INFO, logger="companion.replay.runner"):
        for i in range(LOGGED_SKIPS + 10):
            _log_skip(counts, "no valid head-plane projection for the frame", i, why)
        # A frame recorded before the first pose: the flight did not use it either.
        for i in range(3):
            _log_skip(counts, "no valid head-plane projection for the frame", 100 + i,
                      "no pose and no fixed projection: cannot place the frame on the head plane")
    assert [r.levelno for r in caplog.records] == [logging.INFO, logging.INFO]
    assert "(on the ground)" in caplog.records[0].getMessage()
    assert "the flight did not use it either" in caplog.records[1].getMessage()


def test_a_frame_from_head_plane_height_is_said_once_at_info_with_why(caplog):
    # The demo's replay warned "homography is not invertible" at the frame before touchdown where
    # the camera passes the head plane: the real message of that frame's projection, 1 mm above
    # the plane 50 m from home, is an expected skip, said once at INFO with the reason.
    import logging

    from companion.geometry.camera import GeometryError, Intrinsics, Mount, PlaneProjection, Pose
    from companion.replay.runner import SKIP_GEOMETRY, _log_skip

    lens = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    with pytest.raises(GeometryError) as exc:
        PlaneProjection.from_pose(lens, Mount(), Pose(0.0, 30.0, 40.0, -1.701, 0.01, 0.02, 0.3), 1.7)
    why = str(exc.value)
    assert "homography is not invertible" in why
    counts: dict[str, int] = {}
    with caplog.at_level(logging.INFO, logger="companion.replay.runner"):
        for i in range(3):
            _log_skip(counts, SKIP_GEOMETRY, i, why)
    assert [r.levelno for r in caplog.records] == [logging.INFO]
    assert "head-plane height" in caplog.records[0].getMessage()
    assert "touchdown" in caplog.records[0].getMessage()
