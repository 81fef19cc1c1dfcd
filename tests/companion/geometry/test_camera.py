"""Projection between the head plane and the image (pipeline step 3)."""

import math

import numpy as np
import pytest

from companion.geometry.camera import GeometryError, Intrinsics, Mount, PlaneProjection, Pose, camera_extrinsics

K = Intrinsics.from_fov(640, 480, 70.0)


def _grid_points(proj: PlaneProjection, n: int = 7) -> np.ndarray:
    """Plane points that the camera sees (pixels spread over the image, projected down)."""
    u, v = np.meshgrid(np.linspace(0, 639, n), np.linspace(0, 479, n))
    xy = proj.image_to_plane(np.column_stack([u.ravel(), v.ravel()]))
    return xy[np.isfinite(xy).all(axis=1)]


@pytest.mark.parametrize("alt", [8.0, 20.0, 60.0])
@pytest.mark.parametrize("att_deg", [(0, 0, 0), (10, -5, 45), (-15, 12, -170), (3, 25, 90)])
@pytest.mark.parametrize("mount", [Mount(), Mount.from_degrees(0, -60, 0, (0.1, 0.0, 0.05)),
                                   Mount.from_degrees(5, -80, 30, (0.0, -0.05, 0.1))])
def test_plane_image_round_trip_within_a_centimetre(alt, att_deg, mount):
    roll, pitch, yaw = (math.radians(a) for a in att_deg)
    pose = Pose(0.0, 12.0, -7.0, -alt, roll, pitch, yaw)
    proj = PlaneProjection.from_pose(K, mount, pose, head_height=1.7)
    xy = _grid_points(proj)
    assert len(xy) >= 10
    uv = proj.plane_to_image(xy)
    back = proj.image_to_plane(uv)
    assert np.abs(back - xy).max() < 0.01


def test_projection_matches_a_pinhole_camera_built_by_hand():
    pose = Pose(0.0, 3.0, 4.0, -25.0, 0.1, -0.05, 1.0)
    mount = Mount.from_degrees(0, -70, 10, (0.2, 0.0, 0.1))
    ext = camera_extrinsics(pose, mount)
    proj = PlaneProjection.from_pose(K, mount, pose, head_height=1.7)
    xy = _grid_points(proj)
    pts = np.column_stack([xy, np.full(len(xy), -1.7)])
    cam = (ext.R_cv_from_world @ (pts - ext.position).T).T
    assert (cam[:, 2] > 0).all()
    uv = (K.K @ (cam / cam[:, 2:3]).T).T[:, :2]
    assert np.abs(uv - proj.plane_to_image(xy)).max() < 1e-6


def test_straight_down_image_top_is_the_nose():
    pose = Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0)  # nose north
    proj = PlaneProjection.from_pose(K, Mount(), pose)
    centre, north, east = proj.plane_to_image(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
    assert centre == pytest.approx([K.cx, K.cy])
    assert north[1] < centre[1] and north[0] == pytest.approx(centre[0])
    assert east[0] > centre[0] and east[1] == pytest.approx(centre[1])


def test_nadir_mode_matches_general_mode_for_a_straight_down_camera():
    alt, hh = 30.0, 1.7
    pose = Pose(0.0, 5.0, -3.0, -alt, 0.0, 0.0, 0.0)
    general = PlaneProjection.from_pose(K, Mount(), pose, head_height=hh)
    gsd = (alt - hh) / K.fx
    nadir = PlaneProjection.nadir(gsd)
    uv = np.array([[0.0, 0.0], [100.0, 50.0], [639.0, 479.0], [K.cx, K.cy], [400.0, 300.0]])
    n_e = general.image_to_plane(uv)
    xy = nadir.image_to_plane(uv)
    # Nadir plane axes follow the image (x right = east, y down = south), origin at pixel (0, 0).
    east = xy[:, 0] - K.cx * gsd + pose.east
    north = -(xy[:, 1] - K.cy * gsd) + pose.north
    assert np.abs(n_e[:, 1] - east).max() < 0.01
    assert np.abs(n_e[:, 0] - north).max() < 0.01
    assert nadir.plane_to_image(xy) == pytest.approx(uv)


def test_points_behind_the_camera_are_not_mapped_into_the_image():
    # Camera looking forward and slightly down: the plane behind the vehicle is behind the camera.
    pose = Pose(0.0, 0.0, 0.0, -10.0, 0.0, 0.0, 0.0)
    proj = PlaneProjection.from_pose(K, Mount.from_degrees(0, -20, 0), pose)
    uv = proj.plane_to_image(np.array([[-30.0, 0.0], [30.0, 0.0]]))
    assert np.isnan(uv[0]).all()
    assert np.isfinite(uv[1]).all()
    # And pixels above the horizon do not land on the plane.
    assert np.isnan(proj.image_to_plane(np.array([[320.0, 0.0]]))).all()


@pytest.mark.parametrize("field", ["north", "down", "roll", "yaw"])
def test_nan_pose_is_a_clear_error(field):
    values = dict(t=0.0, north=0.0, east=0.0, down=-20.0, roll=0.0, pitch=0.0, yaw=0.0)
    values[field] = float("nan")
    with pytest.raises(GeometryError, match="NaN"):
        PlaneProjection.from_pose(K, Mount(), Pose(**values))


def test_camera_below_the_head_plane_is_a_clear_error():
    with pytest.raises(GeometryError, match="not above the head plane"):
        PlaneProjection.from_pose(K, Mount(), Pose(0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0))


@pytest.mark.parametrize("H, msg", [
    (np.zeros((3, 3)), "not invertible"),
    (np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]), "not invertible"),
    (np.eye(2), "3x3"),
    (np.full((3, 3), np.nan), "NaN"),
])
def test_bad_fixed_homography_is_a_clear_error(H, msg):
    with pytest.raises(GeometryError, match=msg):
        PlaneProjection.from_image_to_plane(H)


def test_bad_gsd_and_intrinsics_are_clear_errors():
    with pytest.raises(GeometryError, match="ground sample distance"):
        PlaneProjection.nadir(0.0)
    with pytest.raises(GeometryError, match="focal"):
        Intrinsics(-1.0, 500.0, 320.0, 240.0, 640, 480)
