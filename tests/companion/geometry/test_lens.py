"""Lens models (issue 60): the fisheye and the distorted pinhole through the head plane, and
calibration files written by OpenCV's own FileStorage."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion import config as config_mod
from companion.cli import main as companion_main
from companion.config import ConfigError
from companion.geometry import calibration
from companion.geometry.camera import GeometryError, Intrinsics, Mount, PlaneProjection, Pose
from companion.geometry.lens import MAX_THETA
from companion.pipeline.headplane import GridParams, grid_for_view, sample_with_view

FISHEYE = Intrinsics(301.0, 299.0, 322.0, 238.0, 640, 480, (0.04, -0.012, 0.003, -0.0004), "fisheye")


def _rays(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p[:, 2] = np.abs(p[:, 2]) + 0.2  # in front, within about 80 deg of the axis
    return p


def test_the_fisheye_projects_as_opencvs_own_and_unprojects_back() -> None:
    p = _rays(300)
    ref, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), FISHEYE.K,
                                       np.array(FISHEYE.dist))
    uv = FISHEYE.project(p)
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-6
    back = FISHEYE.unproject(uv)
    assert np.abs(back - p / np.linalg.norm(p, axis=1, keepdims=True)).max() < 1e-9


def test_the_fisheye_sees_beyond_90_degrees_up_to_a_200_degree_view() -> None:
    K = Intrinsics.from_fov(640, 480, 160.0, "fisheye")
    # The ideal equidistant lens: 160 deg across, so 200 deg across the 4:3 diagonal.
    corner = K.unproject(np.array([[0.0, 0.0]]))[0]
    assert math.degrees(math.acos(corner[2])) == pytest.approx(100.0, abs=0.3)
    for deg in (95.0, 99.0):
        th = math.radians(deg)
        ray = np.array([[math.sin(th), 0.0, math.cos(th)]])
        assert np.abs(K.unproject(K.project(ray)) - ray).max() < 1e-9
    behind = np.array([[math.sin(MAX_THETA + 0.05), 0.0, math.cos(MAX_THETA + 0.05)]])
    assert np.isnan(K.project(behind)).all()
    assert np.isnan(K.unproject(np.array([[-200.0, -200.0]]))).all()  # outside the image circle


def test_a_distorted_pinhole_projects_as_opencvs_own() -> None:
    k = Intrinsics(500.0, 505.0, 320.0, 240.0, 640, 480, (-0.28, 0.07, 0.001, -0.0005, 0.0))
    p = _rays(200, 1)
    p[:, 2] += 1.5  # a pinhole's view: within ~40 deg
    ref, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k.K, np.array(k.dist))
    assert np.abs(k.project(p) - ref.reshape(-1, 2)).max() < 1e-6
    assert np.isnan(k.project(np.array([[0.0, 0.0, -1.0]]))).all()  # behind a pinhole


def test_a_fisheye_takes_four_coefficients_and_is_never_undistorted_to_a_pinhole() -> None:
    with pytest.raises(GeometryError, match="4 distortion"):
        Intrinsics(300.0, 300.0, 320.0, 240.0, 640, 480, (0.1, 0.0, 0.0, 0.0, 0.0), "fisheye")
    with pytest.raises(GeometryError, match="camera model"):
        Intrinsics(300.0, 300.0, 320.0, 240.0, 640, 480, (), "omni")
    with pytest.raises(GeometryError, match="fisheye"):
        FISHEYE.undistort_maps()


@pytest.mark.parametrize("att_deg", [(0, 0, 0), (8, -5, 40), (-15, 12, -170)])
def test_the_head_plane_through_a_fisheye_round_trips(att_deg: tuple[float, float, float]) -> None:
    roll, pitch, yaw = (math.radians(a) for a in att_deg)
    proj = PlaneProjection.from_pose(FISHEYE, Mount(), Pose(0.0, 4.0, -3.0, -12.0, roll, pitch, yaw), 1.7)
    assert proj.lens is not None
    u, v = np.meshgrid(np.linspace(0, 639, 15), np.linspace(0, 479, 15))
    xy = proj.image_to_plane(np.column_stack([u.ravel(), v.ravel()]))
    seen = np.isfinite(xy).all(axis=1)
    assert seen.sum() > 100
    back = proj.plane_to_image(proj.image_to_plane(proj.plane_to_image(xy[seen])))
    assert np.abs(back - proj.plane_to_image(xy[seen])).max() < 1e-6
    # The centre pixel of a level camera looking straight down sees the point under it.
    level = PlaneProjection.from_pose(FISHEYE, Mount(), Pose(0.0, 4.0, -3.0, -12.0, 0.0, 0.0, 0.0), 1.7)
    assert level.image_to_plane(np.array([[FISHEYE.cx, FISHEYE.cy]]))[0] == pytest.approx([4.0, -3.0], abs=1e-9)


def test_pixels_whose_rays_point_at_or_above_the_horizon_are_unseen() -> None:
    # Looking 30 deg below the horizon, nose first: a fisheye's upper half sees the sky.
    proj = PlaneProjection.from_pose(Intrinsics.from_fov(640, 480, 160.0, "fisheye"),
                                     Mount.from_degrees(0, -30, 0), Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0), 1.7)
    top, bottom = proj.image_to_plane(np.array([[319.5, 5.0], [319.5, 470.0]]))
    assert np.isnan(top).all() and np.isfinite(bottom).all()
    grid = grid_for_view(proj, (480, 640), GridParams())
    free = np.full((480, 640), 255, np.uint8)
    out, view = sample_with_view(free, proj, grid)
    # Ground behind the vehicle (south) is beyond the view: unseen and never free.
    jj, ii = np.meshgrid(np.arange(grid.cols), np.arange(grid.rows))
    x, y = grid.to_plane(ii, jj)
    assert not view[x < -25].any() and not out[x < -25].any()
    assert view[(x > 5) & (x < 20) & (np.abs(y) < 5)].all()


def test_occupied_pixels_reach_the_grid_through_the_fisheye() -> None:
    pose = Pose(0.0, 0.0, 0.0, -10.0, 0.02, -0.03, 0.6)
    proj = PlaneProjection.from_pose(FISHEYE, Mount(), pose, 1.7)
    grid = grid_for_view(proj, (480, 640), GridParams())
    free = np.full((480, 640), 255, np.uint8)
    people = np.array([[3.0, 4.0], [-6.5, 4.0], [8.0, -8.0]])  # near, far, at the edge (m)
    uv = proj.plane_to_image(people)
    assert ((uv > 10) & (uv < [630, 470])).all()
    for u, v in uv:
        cv2.circle(free, (int(round(u)), int(round(v))), 2, 0, -1)
    out, view = sample_with_view(free, proj, grid)
    for x, y in people:
        j, i = round((x - grid.x0) / grid.cell), round((y - grid.y0) / grid.cell)
        assert view[i, j] == 255 and out[i, j] == 0, (x, y)
    j, i = round((-3.0 - grid.x0) / grid.cell), round((-4.0 - grid.y0) / grid.cell)
    assert out[i, j] == 255  # open ground seen stays free


# ---- calibration files ----------------------------------------------------------------------

K_CAL = np.array([[285.3, 0.0, 318.7], [0.0, 284.9, 242.1], [0.0, 0.0, 1.0]])
D_FISHEYE = np.array([0.031, -0.007, 0.0012, -0.0002])


def _config(tmp_path: Path, model: str, cal: Path, width: int = 640, height: int = 480) -> config_mod.Config:
    f = tmp_path / "c.toml"
    f.write_text(f'[camera]\nmodel = "{model}"\ncalibration = "{cal.name}"\nwidth = {width}\nheight = {height}\n')
    return config_mod.load(f)


@pytest.mark.parametrize("suffix", [".yaml", ".xml", ".json"])
def test_a_calibration_written_by_opencv_is_the_camera(tmp_path: Path, suffix: str) -> None:
    cal = tmp_path / f"cal{suffix}"
    calibration.save(cal, K_CAL, D_FISHEYE, 640, 480, fisheye=True)
    k = config_mod.intrinsics(_config(tmp_path, "fisheye", cal))
    assert k.model == "fisheye"
    assert (k.fx, k.fy, k.cx, k.cy) == (285.3, 284.9, 318.7, 242.1)
    assert k.dist == pytest.approx(tuple(D_FISHEYE))


def test_the_calibration_samples_own_layout_and_a_plain_json_are_read(tmp_path: Path) -> None:
    # As samples/cpp/calibration.cpp writes it: more keys, a 5x1 pinhole distortion, no model flag.
    cal = tmp_path / "out_camera_data.yml"
    fs = cv2.FileStorage(str(cal), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Sun Dec  6 05:00:00 2026")
    fs.write("nframes", 25)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("board_width", 9)
    fs.write("camera_matrix", K_CAL)
    fs.write("distortion_coefficients", np.array([[-0.28], [0.07], [0.001], [-0.0005], [0.0]]))
    fs.write("avg_reprojection_error", 0.31)
    fs.release()
    k = config_mod.intrinsics(_config(tmp_path, "pinhole", cal))
    assert k.model == "pinhole" and len(k.dist) == 5 and k.fx == 285.3
    plain = tmp_path / "plain.json"
    plain.write_text('{"camera_matrix": [[285.3, 0, 318.7], [0, 284.9, 242.1], [0, 0, 1]], '
                     '"distortion_coefficients": [0.031, -0.007, 0.0012, -0.0002], '
                     '"image_width": 640, "image_height": 480}')
    assert config_mod.intrinsics(_config(tmp_path, "fisheye", plain)).dist == pytest.approx(tuple(D_FISHEYE))


def _write(path: Path, **fields: object) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in fields.items():
        fs.write(key, value)  # type: ignore[arg-type]
    fs.release()
    return path


BAD_CALIBRATIONS = [
    ({"camera_matrix": np.eye(2), "distortion_coefficients": D_FISHEYE, "image_width": 640, "image_height": 480},
     "3x3"),
    ({"camera_matrix": np.where(np.eye(3) > 0, np.nan, 0.0), "distortion_coefficients": D_FISHEYE,
      "image_width": 640, "image_height": 480}, "NaN or infinite"),
    ({"camera_matrix": K_CAL, "distortion_coefficients": np.array([0.1, np.inf, 0.0, 0.0]), "image_width": 640,
      "image_height": 480}, "NaN or infinite"),
    ({"camera_matrix": K_CAL, "distortion_coefficients": D_FISHEYE, "image_width": 1280, "image_height": 720},
     "for 1280x720 but camera.width x camera.height is 640x480"),
    ({"camera_matrix": K_CAL, "distortion_coefficients": np.zeros(5), "image_width": 640, "image_height": 480},
     "4 distortion coefficients"),
    ({"camera_matrix": K_CAL, "distortion_coefficients": D_FISHEYE, "image_width": 640, "image_height": 480,
      "fisheye_model": 0}, "pinhole calibration but camera.model is fisheye"),
    ({"camera_matrix": K_CAL * np.array([[-1], [1], [1]]), "distortion_coefficients": D_FISHEYE,
      "image_width": 640, "image_height": 480}, "focal lengths"),
    ({"distortion_coefficients": D_FISHEYE, "image_width": 640, "image_height": 480}, "no camera_matrix"),
]


@pytest.mark.parametrize(("fields", "says"), BAD_CALIBRATIONS)
def test_a_bad_calibration_is_refused_naming_the_key(tmp_path: Path, fields: dict[str, object], says: str) -> None:
    cal = _write(tmp_path / "cal.yaml", **fields)
    with pytest.raises(ConfigError, match="camera.calibration") as err:
        _config(tmp_path, "fisheye", cal)
    assert says in str(err.value)


def test_check_config_exits_2_on_a_bad_or_missing_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "c.toml"
    f.write_text('[camera]\nmodel = "fisheye"\ncalibration = "missing.yaml"\n')
    assert companion_main(["check-config", str(f)]) == 2
    assert "camera.calibration" in capsys.readouterr().err
    (tmp_path / "junk.yaml").write_text("this is no calibration: [")
    f.write_text('[camera]\nmodel = "fisheye"\ncalibration = "junk.yaml"\n')
    assert companion_main(["check-config", str(f)]) == 2
    err = capsys.readouterr().err
    assert "camera.calibration" in err and "Traceback" not in err
    calibration.save(tmp_path / "good.yaml", K_CAL, D_FISHEYE, 640, 480, fisheye=True)
    f.write_text('[camera]\nmodel = "fisheye"\ncalibration = "good.yaml"\nfx = 300.0\n')
    assert companion_main(["check-config", str(f)]) == 2
    assert "must stay unset" in capsys.readouterr().err
    f.write_text('[camera]\nmodel = "fisheye"\ncalibration = "good.yaml"\n')
    assert companion_main(["check-config", str(f)]) == 0


def test_ground_wider_than_the_trusted_angle_is_unseen_though_people_there_are_placed() -> None:
    # The shipped model's recall holds out to lens.TRUSTED_THETA (70 deg) from the axis; beyond,
    # the ground is unseen (never free), but a person found there is still on the plane.
    from companion.geometry.lens import TRUSTED_THETA

    K = Intrinsics.from_fov(640, 480, 160.0, "fisheye")
    proj = PlaneProjection.from_pose(K, Mount(), Pose(0.0, 0.0, 0.0, -11.7, 0.0, 0.0, 0.0), 1.7)
    grid = grid_for_view(proj, (480, 640), GridParams())
    _out, view = sample_with_view(np.full((480, 640), 255, np.uint8), proj, grid)
    limit = 10.0 * math.tan(TRUSTED_THETA)  # 27.5 m out on the head plane, 10 m below the camera
    jj, ii = np.meshgrid(np.arange(grid.cols), np.arange(grid.rows))
    x, y = grid.to_plane(ii, jj)
    # Nothing wider than the cone is seen; within it, the grid ends at the footprint's seen radius
    # (the image's own edge at 60 deg along it, north; test_the_grid_ends_at_the_seen_radius).
    across = np.abs(x) < 0.5
    seen_r = proj.lens.seen_radius() if proj.lens is not None else 0.0
    assert 17.0 < seen_r < limit
    assert view[across & (np.abs(y) < seen_r - 0.5)].all() and not view[np.hypot(x, y) > limit + 0.5].any()
    assert grid.y0 > -limit - 1.0  # the grid ends where the trusted ground does
    far = proj.image_to_plane(proj.plane_to_image(np.array([[0.0, limit + 5.0]])))
    assert far[0] == pytest.approx([0.0, limit + 5.0], abs=1e-6)


def test_the_grid_ends_at_the_seen_radius_through_a_wide_lens() -> None:
    # A fisheye:160 at 20 m sees trusted ground 50 m out along its image's long side but 32 m
    # across; the landing rules count on the round 32 m (Intrinsics.seen_ratio), and the grid ends
    # there: 633 cells a side instead of 802 (GridParams.max_extent). Beyond, the ground is unseen
    # (never free) though the lens sees it, and a person found there is still on the plane.
    K = Intrinsics.from_fov(640, 480, 160.0, "fisheye")
    pose = Pose(0.0, 5.0, -2.0, -20.0, 0.0, 0.0, 0.0)
    proj = PlaneProjection.from_pose(K, Mount(), pose, 1.7)
    assert proj.lens is not None
    seen_r = proj.lens.seen_radius()
    assert seen_r == pytest.approx(18.3 * K.seen_ratio()) and 31.0 < seen_r < 32.0
    grid = grid_for_view(proj, (480, 640), GridParams())
    assert grid.rows <= 2 * seen_r / grid.cell + 2 and grid.cols <= 2 * seen_r / grid.cell + 2
    out, view = sample_with_view(np.full((480, 640), 255, np.uint8), proj, grid)
    x, y = grid.to_plane(*np.meshgrid(np.arange(grid.rows), np.arange(grid.cols), indexing="ij"))
    # Along the image's long side (east, with yaw 0) the view runs to the grid's end.
    assert view[(np.abs(x - 5.0) < 0.5) & (np.abs(y + 2.0) < seen_r - 0.5)].all()
    assert out[(np.abs(x - 5.0) < 0.5) & (np.abs(y + 2.0) < seen_r - 0.5)].all()
    beyond = np.array([[5.0, -2.0 + seen_r + 8.0]])  # 40 m out east: in the lens, off the grid
    assert np.isfinite(proj.lens.seen_to_image(beyond)).all()
    assert grid.y0 + (grid.rows - 1) * grid.cell < beyond[0, 1]
    assert proj.image_to_plane(proj.plane_to_image(beyond))[0] == pytest.approx(beyond[0], abs=1e-6)
    # A pinhole's grid is the one it always was: its whole image, the long side wider than its
    # seen radius (0.525 x 18.3 m), not cut to it.
    K70 = Intrinsics.from_fov(640, 480, 70.0)
    pin = PlaneProjection.from_pose(K70, Mount(), pose, 1.7)
    pg = grid_for_view(pin, (480, 640), GridParams())
    corners = pin.image_to_plane(np.array([[0.0, 0.0], [639.0, 0.0], [639.0, 479.0], [0.0, 479.0]]))
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    assert pg.x0 <= lo[0] and pg.y0 <= lo[1]
    assert pg.x0 + (pg.cols - 1) * pg.cell >= hi[0] - pg.cell and pg.y0 + (pg.rows - 1) * pg.cell >= hi[1] - pg.cell
    assert (hi - lo).max() > 2 * 18.3 * K70.seen_ratio() + 2.0
