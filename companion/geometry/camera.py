"""Step 3 of the pipeline, geometry: the camera model and the head-plane homography.

Frames (docs/design.md): world = local NED in metres, origin at home, ground at ``z = 0``, head plane at
``z = -h_h``; body = FRD; camera = OpenCV (x right, y down, z forward along the optical axis).

The camera is mounted on the body with a rotation given as roll/pitch/yaw of a "camera FRD" frame
relative to the body (zero = looking forward, image top up; pitch -90 deg = looking straight down
with the image top toward the nose) and an offset in body FRD metres. A gimbal attitude, when known,
replaces the mount rotation.

The mapping between head-plane points ``(x_north, y_east)`` in metres and image pixels is the
homography ``H_img_from_plane = K [c1 c2 (-h_h c3 + t)]`` where ``c_i`` are the columns of the
world-to-camera rotation and ``t`` its translation. Lens distortion is not a homography: the
pipeline undistorts a pinhole's occupancy map first (``Intrinsics.undistort_maps``); a fisheye
(``companion.geometry.lens``) is not a pinhole at all, and its projection goes ray by ray
(``LensView``), ``H`` then being only the pinhole of the same focal length near the centre.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from companion.geometry import lens

# Columns are the OpenCV camera axes expressed in the camera FRD frame:
# cv x (right) = FRD y, cv y (down) = FRD z, cv z (forward) = FRD x.
R_FRD_FROM_CV = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


class GeometryError(ValueError):
    """A pose, calibration or homography that cannot give a valid projection."""


def rotation_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix ``R_parent_from_child`` for aerospace Z-Y-X Euler angles in radians.

    The same convention as MAVLink ATTITUDE: yaw about down, then pitch about the new right axis
    (positive nose up), then roll about the new forward axis (positive right wing down).
    """
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [-sp, sr * cp, cr * cp],
        ]
    )


def rotation_from_quaternion(q: tuple[float, float, float, float]) -> np.ndarray:
    """Rotation matrix from a unit quaternion ``(w, x, y, z)`` (MAVLink order, Hamilton)."""
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n < 1e-9:
        raise GeometryError(f"quaternion {q!r} is not a rotation")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _require_finite(name: str, *values: float) -> None:
    if not all(math.isfinite(float(v)) for v in values):
        raise GeometryError(f"{name} has a NaN or infinite value: {values!r}")


@dataclass(frozen=True)
class Intrinsics:
    """Camera matrix in pixels plus the lens: ``model`` "pinhole" with OpenCV distortion coefficients
    (k1, k2, p1, p2[, k3...]) or "fisheye", OpenCV's equidistant model with ``dist`` = (k1, k2, k3,
    k4) (``companion.geometry.lens``)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = ()
    model: str = "pinhole"

    def __post_init__(self) -> None:
        _require_finite("intrinsics", self.fx, self.fy, self.cx, self.cy, *self.dist)
        if self.model not in lens.MODELS:
            raise GeometryError(f"camera model must be one of {lens.MODELS}, got {self.model!r}")
        if self.model == "fisheye" and len(self.dist) not in (0, 4):
            raise GeometryError(f"a fisheye takes 4 distortion coefficients (k1..k4), got {len(self.dist)}")
        if self.model == "pinhole" and len(self.dist) not in (0, 4, 5, 8, 12, 14):
            raise GeometryError("a pinhole takes 4, 5, 8, 12 or 14 distortion coefficients (OpenCV), "
                                f"got {len(self.dist)}")
        if self.fx <= 0 or self.fy <= 0:
            raise GeometryError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise GeometryError(f"image size must be > 0, got {self.width}x{self.height}")

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, model: str = "pinhole") -> Intrinsics:
        """Square pixels, centred principal point, horizontal field of view in degrees; a fisheye
        is the ideal equidistant lens (``r = f theta``), so fisheye:160 at 4:3 sees 200 degrees
        across the diagonal."""
        if model == "fisheye":
            f = (width / 2.0) / (math.radians(hfov_deg) / 2.0)
        else:
            f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height, model=model)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    def scaled_to(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution (frames resized before processing)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height,
                          self.dist, self.model)

    @property
    def is_fisheye(self) -> bool:
        return self.model == "fisheye"

    def seen_ratio(self, samples: int = 64) -> float:
        """The camera's footprint looking straight down: the ground radius (m) it sees all round
        the point below it per metre of height above the head plane, i.e. the tangent of the
        smallest angle from the optical axis to the edge of what counts as seen (the image border,
        or ``lens.TRUSTED_THETA`` where the lens sees wider). An undistorted pinhole answers from
        its matrix alone (``min(cx, w-1-cx) / fx`` and the same across: 0.525 for the 70-degree
        4:3 camera, the figure the landing rules were first written for); any other lens walks
        ``samples`` pixels of each side of the border through the lens (fisheye:160 at 4:3:
        tan 60 degrees, 1.73)."""
        w, h = self.width - 1.0, self.height - 1.0
        trusted = math.tan(lens.TRUSTED_THETA)
        if self.model == "pinhole" and not self.has_distortion:
            return min(self.cx / self.fx, self.cy / self.fy, (w - self.cx) / self.fx, (h - self.cy) / self.fy,
                       trusted)
        s = np.linspace(0.0, 1.0, samples)
        border = np.concatenate([np.column_stack([s * w, np.zeros(samples)]), np.column_stack([s * w, np.full(samples, h)]),
                                 np.column_stack([np.zeros(samples), s * h]), np.column_stack([np.full(samples, w), s * h])])
        rays = self.unproject(border)
        with np.errstate(invalid="ignore"):
            theta = np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])
        # A border pixel no seen ray reaches (outside a fisheye's image circle) ends the view
        # nearer than the border: its ray's angle is unknown, so the circle through the border's
        # seen pixels nearest the axis bounds the view (rule 1: what is not known is not seen).
        ok = np.isfinite(theta)
        if not ok.any():
            raise GeometryError("the lens sees none of its image border")
        return float(min(math.tan(min(float(theta[ok].min()), math.radians(89.9))), trusted))

    def project(self, xc: np.ndarray, theta: np.ndarray | None = None) -> np.ndarray:
        """Camera-frame points (N, 3) -> pixels (N, 2), NaN where the lens does not see them
        (``theta``: their ``lens.ray_theta``, when known)."""
        return lens.project(self.model, self.K, self.dist, xc, theta)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> unit rays (N, 3) in the camera frame, NaN where nothing seen lands."""
        return lens.unproject(self.model, self.K, self.dist, uv)

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` maps that turn a distorted image into the ideal pinhole image of ``K``
        (pinhole model only: a fisheye goes ray by ray, ``LensView``)."""
        if self.is_fisheye:
            raise GeometryError("a fisheye is not undistorted to a pinhole; project through LensView")
        return cv2.initUndistortRectifyMap(
            self.K, np.asarray(self.dist, dtype=np.float64), None, self.K,
            (self.width, self.height), cv2.CV_16SC2,
        )


@dataclass(frozen=True)
class Mount:
    """Camera mounting on the body: rotation (radians) of the camera FRD frame and offset (m, FRD).

    The default looks straight down (pitch -90 deg) from the body origin.
    """

    roll: float = 0.0
    pitch: float = -math.pi / 2
    yaw: float = 0.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_degrees(cls, roll_deg: float = 0.0, pitch_deg: float = -90.0, yaw_deg: float = 0.0,
                     offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Mount:
        return cls(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg),
                   tuple(float(v) for v in offset))  # type: ignore[arg-type]

    def rotation(self) -> np.ndarray:
        """``R_body_from_camfrd``."""
        _require_finite("camera mount", self.roll, self.pitch, self.yaw, *self.offset)
        return rotation_from_euler(self.roll, self.pitch, self.yaw)


@dataclass(frozen=True)
class Pose:
    """Vehicle pose at one instant.

    t: seconds (monotonic clock of the receiver). north, east, down: body origin in world NED
    metres (down is negative above home). roll, pitch, yaw: radians, MAVLink ATTITUDE convention.
    gimbal: optional ``R_body_from_camfrd`` (3x3) of a gimbal, replacing the fixed mount rotation.
    """

    t: float
    north: float
    east: float
    down: float
    roll: float
    pitch: float
    yaw: float
    gimbal: np.ndarray | None = field(default=None, compare=False)

    def validate(self) -> None:
        _require_finite("vehicle pose", self.t, self.north, self.east, self.down,
                        self.roll, self.pitch, self.yaw)
        if self.gimbal is not None:
            g = np.asarray(self.gimbal, dtype=float)
            if g.shape != (3, 3) or not np.isfinite(g).all():
                raise GeometryError("gimbal rotation must be a finite 3x3 matrix")


@dataclass(frozen=True)
class CameraExtrinsics:
    """World-to-camera transform: ``x_cv = R_cv_from_world @ (p_world - position)``."""

    R_cv_from_world: np.ndarray
    position: np.ndarray  # camera centre in world NED metres


def camera_extrinsics(pose: Pose, mount: Mount) -> CameraExtrinsics:
    """Where the camera is and how it is turned, from the vehicle pose and the mount/gimbal."""
    pose.validate()
    R_world_from_body = rotation_from_euler(pose.roll, pose.pitch, pose.yaw)
    R_body_from_camfrd = mount.rotation() if pose.gimbal is None else np.asarray(pose.gimbal, float)
    R_world_from_cv = R_world_from_body @ R_body_from_camfrd @ R_FRD_FROM_CV
    position = np.array([pose.north, pose.east, pose.down]) + R_world_from_body @ np.asarray(
        mount.offset, dtype=float
    )
    return CameraExtrinsics(R_world_from_cv.T, position)


def _check_homography(H: np.ndarray, what: str) -> np.ndarray:
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3):
        raise GeometryError(f"{what} must be a 3x3 matrix, got shape {H.shape}")
    if not np.isfinite(H).all():
        raise GeometryError(f"{what} has NaN or infinite entries")
    # Relative conditioning, so a homography in metres and one in pixels are judged alike.
    s = np.linalg.svd(H, compute_uv=False)
    if s[-1] <= 1e-9 * s[0]:
        raise GeometryError(f"{what} is not invertible (singular values {s.tolist()})")
    return H


@functools.lru_cache(maxsize=8)
def _seen_ratio(intrinsics: Intrinsics) -> float:
    """``Intrinsics.seen_ratio`` once per lens (it walks the border through the lens: 0.2 ms)."""
    return intrinsics.seen_ratio()


@functools.lru_cache(maxsize=8)
def _seen_edge_rays(intrinsics: Intrinsics, n: int) -> np.ndarray:
    """``LensView.seen_boundary``'s rays in the camera frame (the image border's within
    ``lens.TRUSTED_THETA``, then the trusted cone's within the image): they depend on the lens
    alone, not on the pose, and walking them through it costs 0.8 ms a frame. Cached, read-only."""
    w, h = intrinsics.width, intrinsics.height
    s = np.linspace(0.0, 1.0, n, endpoint=False)
    border = np.concatenate([np.column_stack([s * (w - 1), np.zeros(n)]),
                             np.column_stack([np.full(n, w - 1.0), s * (h - 1)]),
                             np.column_stack([(1 - s) * (w - 1), np.full(n, h - 1.0)]),
                             np.column_stack([np.zeros(n), (1 - s) * (h - 1)])])
    rays = intrinsics.unproject(border)
    with np.errstate(invalid="ignore"):
        rays = rays[rays[:, 2] >= math.cos(lens.TRUSTED_THETA) - 1e-12]
    phi = np.linspace(0.0, 2 * math.pi, 4 * n, endpoint=False)
    st, ct = math.sin(lens.TRUSTED_THETA), math.cos(lens.TRUSTED_THETA)
    cone = np.column_stack([st * np.cos(phi), st * np.sin(phi), np.full(len(phi), ct)])
    uv = intrinsics.project(cone)
    with np.errstate(invalid="ignore"):
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    edge: np.ndarray = np.concatenate([rays, cone[inside]])
    edge.flags.writeable = False
    return edge


@dataclass(frozen=True)
class LensView:
    """The head plane ``z = plane_z`` (world NED) seen through a lens ray by ray: what a homography
    cannot say of a fisheye. ``R_cv_from_world`` and ``position`` as in ``CameraExtrinsics``."""

    intrinsics: Intrinsics
    R_cv_from_world: np.ndarray
    position: np.ndarray
    plane_z: float

    def plane_to_image(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) plane metres (north, east) -> (N, 2) pixels, NaN where the lens does not see."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        d = np.column_stack([p[:, 0] - self.position[0], p[:, 1] - self.position[1],
                             np.full(len(p), self.plane_z - self.position[2])])
        return self.intrinsics.project(d @ self.R_cv_from_world.T)

    def seen_to_image(self, xy: np.ndarray) -> np.ndarray:
        """``plane_to_image``, NaN also where the ray is wider than ``lens.TRUSTED_THETA`` from the
        axis: where the ground counts as seen (the grid's view), people being found there."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        d = np.column_stack([p[:, 0] - self.position[0], p[:, 1] - self.position[1],
                             np.full(len(p), self.plane_z - self.position[2])])
        xc = d @ self.R_cv_from_world.T
        with np.errstate(invalid="ignore"):
            theta = lens.ray_theta(xc)
            wide = theta > lens.TRUSTED_THETA
        uv = self.intrinsics.project(xc, theta)  # a fisheye's projection needs the angles too
        uv[wide] = np.nan
        return uv

    def seen_radius(self) -> float:
        """Metres of head plane seen all round the point below the camera were it looking straight
        down: its height above the plane times ``Intrinsics.seen_ratio`` (the footprint the landing
        rules use). 0 when the camera is not above the plane."""
        return max(0.0, float(self.plane_z - self.position[2])) * _seen_ratio(self.intrinsics)

    def seen_boundary(self, n: int = 32) -> np.ndarray:
        """Plane points (M, 2) around the edge of the ground counted as seen: the image border
        (``4 n`` pixels) within ``lens.TRUSTED_THETA``, and the trusted cone's edge (``4 n`` rays)
        within the image. A row is NaN where that edge's ray misses the plane (above the horizon):
        the seen ground is then unbounded."""
        d = _seen_edge_rays(self.intrinsics, n) @ self.R_cv_from_world  # world NED directions
        drop = self.plane_z - self.position[2]
        out = np.full((len(d), 2), np.nan)
        down = d[:, 2] > 1e-9
        out[down, 0] = self.position[0] + drop / d[down, 2] * d[down, 0]
        out[down, 1] = self.position[1] + drop / d[down, 2] * d[down, 1]
        return out

    def image_to_plane(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) plane metres; NaN for pixels whose rays point at or above the
        horizon (or that the lens does not see): they never meet the plane."""
        rays = self.intrinsics.unproject(uv) @ self.R_cv_from_world  # world NED directions
        drop = self.plane_z - self.position[2]  # > 0: the plane is below the camera
        out = np.full((len(rays), 2), np.nan)
        with np.errstate(invalid="ignore"):
            down = rays[:, 2] > 1e-9
        s = drop / rays[down, 2]
        out[down, 0] = self.position[0] + s * rays[down, 0]
        out[down, 1] = self.position[1] + s * rays[down, 1]
        return out


@dataclass(frozen=True)
class PlaneProjection:
    """The mapping between head-plane metres ``(x, y)`` and image pixels ``(u, v)``.

    ``H`` maps plane -> image (homogeneous); ``H_inv`` image -> plane. For poses, the plane
    coordinates are world north/east; for pose-free modes they are whatever the given homography
    or ground sample distance defines. ``camera_xy`` is the point of the plane under the camera
    (used to centre the metric grid), or None when unknown.
    """

    H: np.ndarray
    H_inv: np.ndarray
    camera_xy: tuple[float, float] | None = None
    # Sign of the homogeneous w of points in front of the camera (a homography is defined up to
    # scale, and a negative scale flips it).
    w_sign: float = 1.0
    # A lens that is not a pinhole (fisheye): projections go ray by ray through it, and ``H`` is
    # only the pinhole of the same camera matrix (good near the image centre).
    lens: LensView | None = field(default=None, compare=False)

    @classmethod
    def from_plane_to_image(cls, H: np.ndarray, camera_xy: tuple[float, float] | None = None
                            ) -> PlaneProjection:
        """``H = K [c1 c2 c3']`` exactly (positive scale), as built by ``from_pose``."""
        H = _check_homography(H, "plane-to-image homography")
        return cls(H, np.linalg.inv(H), camera_xy, 1.0)

    @classmethod
    def from_image_to_plane(cls, H_plane_from_img: np.ndarray,
                            ref_uv: tuple[float, float] = (0.0, 0.0)) -> PlaneProjection:
        """A fixed 3x3 image-to-head-plane matrix (pixels -> metres), as given by a user.

        ``ref_uv`` is a pixel known to see the plane (any pixel of the image, for a camera whose
        whole view is below the horizon); it fixes the sign of the unknown scale.
        """
        Hi = _check_homography(H_plane_from_img, "image-to-plane homography")
        w = Hi[2, 0] * ref_uv[0] + Hi[2, 1] * ref_uv[1] + Hi[2, 2]
        if abs(w) < 1e-12:
            raise GeometryError("image-to-plane homography maps the reference pixel to infinity")
        return cls(np.linalg.inv(Hi), Hi, None, float(np.sign(w)))

    @classmethod
    def nadir(cls, gsd: float) -> PlaneProjection:
        """Camera straight down, ``gsd`` metres per pixel on the head plane.

        Plane axes follow the image: x = u * gsd (right), y = v * gsd (down), origin at the
        top-left pixel, so radii in pixels along the image x axis are exactly ``r / gsd``.
        """
        if not (math.isfinite(gsd) and gsd > 0):
            raise GeometryError(f"ground sample distance must be a number > 0 m/px, got {gsd!r}")
        return cls.from_image_to_plane(np.diag([gsd, gsd, 1.0]))

    @classmethod
    def from_pose(cls, intrinsics: Intrinsics, mount: Mount, pose: Pose,
                  head_height: float = 1.7) -> PlaneProjection:
        """The homography of the head plane ``z = -head_height`` seen from ``pose``."""
        _require_finite("head height", head_height)
        ext = camera_extrinsics(pose, mount)
        R = ext.R_cv_from_world
        t = -R @ ext.position
        if ext.position[2] >= -head_height:
            raise GeometryError(
                f"camera at down={ext.position[2]:.2f} m is not above the head plane "
                f"(z = {-head_height:.2f} m)"
            )
        M = np.column_stack([R[:, 0], R[:, 1], -head_height * R[:, 2] + t])
        below = (float(ext.position[0]), float(ext.position[1]))
        proj = cls.from_plane_to_image(intrinsics.K @ M, below)
        if intrinsics.is_fisheye:
            proj = cls(proj.H, proj.H_inv, below, 1.0, LensView(intrinsics, R, ext.position, -head_height))
        return proj

    def plane_to_image(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) plane metres -> (N, 2) pixels. Points behind the camera (or that the lens does
        not see) come out as NaN."""
        if self.lens is not None:
            return self.lens.plane_to_image(xy)
        return _apply(self.H, xy, self.w_sign)

    def image_to_plane(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) plane metres. Pixels above the horizon come out as NaN."""
        if self.lens is not None:
            return self.lens.image_to_plane(uv)
        return _apply(self.H_inv, uv, self.w_sign)


def _apply(H: np.ndarray, pts: np.ndarray, w_sign: float) -> np.ndarray:
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    w = H[2, 0] * p[:, 0] + H[2, 1] * p[:, 1] + H[2, 2]
    out = np.empty_like(p)
    with np.errstate(divide="ignore", invalid="ignore"):
        out[:, 0] = (H[0, 0] * p[:, 0] + H[0, 1] * p[:, 1] + H[0, 2]) / w
        out[:, 1] = (H[1, 0] * p[:, 0] + H[1, 1] * p[:, 1] + H[1, 2]) / w
    # Sign of w tells which side of the camera the point is: a negative w maps a point behind
    # the camera to a plausible-looking pixel, which must never be taken for a real one.
    out[(w * w_sign) <= 0] = np.nan
    return out
