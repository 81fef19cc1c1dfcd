"""The simulated camera's picture: the ground and the people seen from the vehicle's pose.

Rendering goes through the service's own camera model (:mod:`companion.geometry.camera`): the
ground plane ``z = 0`` is drawn with its plane-to-image homography (``cv2.warpPerspective`` of a
procedural texture), then every person is drawn as a few 3-D parts projected with the camera
extrinsics and intrinsics, so a head at ``z = -1.7`` lands exactly where
``PlaneProjection.from_pose(..., head_height=1.7)`` says it does.

A person seen from above (modelled on how people look in top-down drone photos, not copied from
any): a soft shadow on the ground; legs (apart when walking) and arms as strokes; shoulders/torso
as an ellipse ~0.5 m x 0.3 m at ``z = -1.4`` in a clothing colour; the head as an ellipse
~0.2 m wide at ``z = -1.7``, mostly dark hair with a skin face patch toward the heading, or a cap.

World = local NED metres (ground z = 0); people are ground points (north, east) with a heading in
radians from north toward east. Camera = OpenCV (x right, y down, z forward). Images are BGR uint8.
A pinhole's distortion is not rendered (its frames are ideal pinhole images of ``intrinsics.K``); a
fisheye (``intrinsics.model == "fisheye"``) is rendered through its lens: the ground pixel by pixel
(each pixel's ray met with the ground, ``render_ground_lens``) and the people's 3-D parts projected
through the same lens model the service uses (``Intrinsics.project``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from companion.geometry.camera import Intrinsics, Mount, Pose, camera_extrinsics

HEAD_Z = -1.7  # m, centre of the head (the pipeline's head plane)
SHOULDER_Z = -1.4  # m
HIP_Z = -0.9  # m
SKY = (225, 205, 190)  # BGR, hazy sky above the horizon
OUTSIDE_LENS = (0, 0, 0)  # BGR, pixels outside a fisheye's image circle
HAZE = (180, 175, 170)  # BGR, ground beyond the rendered range
MAX_RANGE = 250.0  # m of ground drawn around the camera
# A fisheye's ground is drawn out to this many times the camera's height (rays up to 80.5 deg from
# straight down): one mosaic of at most 3072 px a side then stays about as fine as the lens's centre
# pixel (height / f); beyond is haze, as beyond MAX_RANGE.
LENS_RANGE_PER_M = 6.0
SHIFT = 4  # fixed-point bits for sub-pixel drawing
_ONE = float(1 << SHIFT)
# Sun from the south-west at 58 deg elevation: shadows fall north-east, ~0.6 x body height long.
SUN_SHADOW = np.array([math.cos(math.radians(40)), math.sin(math.radians(40))]) / math.tan(math.radians(58))


class Ground(Protocol):
    def view(self, n_min: float, n_max: float, e_min: float, e_max: float, res: float,
             max_px: int = ...) -> tuple[np.ndarray, np.ndarray]: ...


class WorldView(Protocol):
    """What ``render_world`` reads of a world (a :class:`sim.world.crowd.World`); ``seed`` and ``ids``
    are used when present."""

    @property
    def t(self) -> float: ...

    def positions(self) -> np.ndarray: ...

    def headings(self) -> np.ndarray: ...

    def moving(self) -> np.ndarray: ...


def plane_homography(intrinsics: Intrinsics, mount: Mount, pose: Pose, z: float = 0.0) -> np.ndarray:
    """3x3 homography mapping points ``(north, east)`` of the horizontal plane at world height
    ``z`` (NED metres; 0 = ground, -1.7 = head plane) to image pixels ``(u, v)``.

    The same construction as ``PlaneProjection.from_pose`` (``K [r1 r2 z*r3 + t]``) for any z.
    """
    ext = camera_extrinsics(pose, mount)
    R = ext.R_cv_from_world
    t = -R @ ext.position
    return intrinsics.K @ np.column_stack([R[:, 0], R[:, 1], z * R[:, 2] + t])


def project_points(points: np.ndarray, intrinsics: Intrinsics, mount: Mount, pose: Pose
                   ) -> tuple[np.ndarray, np.ndarray]:
    """World NED points (..., 3) -> pixels (..., 2) and depth along the optical axis (..., ) m."""
    ext = camera_extrinsics(pose, mount)
    p = np.asarray(points, float)
    xc = (p - ext.position) @ ext.R_cv_from_world.T
    if intrinsics.is_fisheye:
        # Through the lens; the "depth" is the range (m), -1 where the lens does not see the point.
        uv = intrinsics.project(xc.reshape(-1, 3)).reshape(*xc.shape[:-1], 2)
        rng = np.linalg.norm(xc, axis=-1)
        return uv, np.where(np.isfinite(uv).all(axis=-1), rng, -1.0)
    z = xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * xc[..., 0] / z + intrinsics.cx
        v = intrinsics.fy * xc[..., 1] / z + intrinsics.cy
    return np.stack([u, v], axis=-1), z


@dataclass(frozen=True)
class Looks:
    """Per-person colours (BGR uint8 rows) and whether they wear a cap."""

    clothes: np.ndarray
    trousers: np.ndarray
    hair: np.ndarray
    skin: np.ndarray
    cap: np.ndarray

    def __len__(self) -> int:
        return len(self.clothes)


# Clothing seen from above in drone photos is mostly dark, white or muted, with some bright tops.
_CLOTHES = np.array([
    (25, 25, 25), (40, 40, 45), (70, 45, 30), (60, 60, 60), (110, 110, 110), (235, 235, 235),
    (200, 200, 205), (40, 40, 180), (40, 110, 220), (160, 90, 40), (60, 140, 60), (150, 60, 140),
    (40, 200, 230), (120, 160, 200), (80, 50, 120), (30, 30, 100),
], np.uint8)
_CLOTHES_P = np.array([12, 10, 8, 7, 6, 9, 5, 6, 4, 6, 4, 4, 3, 4, 4, 4], float)
_TROUSERS = np.array([(30, 30, 30), (90, 55, 35), (60, 60, 60), (140, 140, 150), (40, 45, 70),
                      (200, 200, 200)], np.uint8)
_HAIR = np.array([(20, 20, 25), (30, 35, 45), (25, 45, 70), (60, 90, 130), (140, 140, 150)], np.uint8)
_SKIN = np.array([(150, 175, 215), (120, 150, 200), (90, 120, 170), (60, 85, 120)], np.uint8)


def people_looks(n: int, seed: int = 0) -> Looks:
    """Deterministic colours for ``n`` people (person i always looks the same for one seed)."""
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 0x1005])
    clothes = _CLOTHES[rng.choice(len(_CLOTHES), n, p=_CLOTHES_P / _CLOTHES_P.sum())].astype(int)
    clothes = np.clip(clothes + rng.integers(-15, 16, (n, 3)), 0, 255).astype(np.uint8)
    trousers = _TROUSERS[rng.integers(0, len(_TROUSERS), n)]
    hair = _HAIR[rng.choice(len(_HAIR), n, p=[0.45, 0.25, 0.15, 0.08, 0.07])]
    skin = _SKIN[rng.integers(0, len(_SKIN), n)]
    cap = rng.random(n) < 0.12
    return Looks(clothes, trousers, hair, skin, cap)


def looks_for(ids: np.ndarray, seed: int = 0) -> Looks:
    """Deterministic colours for people by id (a person looks the same whatever the others do)."""
    from sim.world.ground import _hash01

    ids = np.asarray(ids, np.int64).ravel()

    def pick(table: np.ndarray, salt: int, p: np.ndarray | None = None) -> np.ndarray:
        u = _hash01(seed * 7919 + salt, ids, np.full_like(ids, salt))
        if p is None:
            return table[np.minimum((u * len(table)).astype(int), len(table) - 1)]
        cdf = np.cumsum(p) / np.sum(p)
        return table[np.minimum(np.searchsorted(cdf, u), len(table) - 1)]

    return Looks(pick(_CLOTHES, 1, _CLOTHES_P), pick(_TROUSERS, 2), pick(_HAIR, 3, np.array([0.45, 0.25, 0.15, 0.08, 0.07])),
                 pick(_SKIN, 4), _hash01(seed * 7919 + 5, ids, np.full_like(ids, 5)) < 0.12)


def _ellipse(k: int) -> np.ndarray:
    a = np.linspace(0, 2 * math.pi, k, endpoint=False)
    return np.column_stack([np.cos(a), np.sin(a)])


_E12 = _ellipse(12)
_E8 = _ellipse(8)


def _parts(pos: np.ndarray, heading: np.ndarray, moving: np.ndarray, phase: np.ndarray
           ) -> dict[str, np.ndarray]:
    """3-D points (N, K, 3) world NED of each body part of N people."""
    n = len(pos)
    f = np.column_stack([np.cos(heading), np.sin(heading)])  # forward, (north, east)
    r = np.column_stack([-np.sin(heading), np.cos(heading)])  # right

    def ring(centre_ne: np.ndarray, z: float, a_f: float, a_r: float, unit: np.ndarray) -> np.ndarray:
        ne = (centre_ne[:, None, :] + unit[None, :, :1] * a_f * f[:, None, :]
              + unit[None, :, 1:] * a_r * r[:, None, :])
        return np.concatenate([ne, np.full((n, len(unit), 1), z)], axis=2)

    # The shadow: a body-long ellipse on the ground away from the sun.
    sd = SUN_SHADOW * 1.7
    shadow_c = pos + sd / 2
    L = float(np.hypot(*sd)) / 2 + 0.1
    ang = math.atan2(sd[1], sd[0])
    su = np.array([math.cos(ang), math.sin(ang)])
    sr = np.array([-math.sin(ang), math.cos(ang)])
    sh = shadow_c[:, None, :] + _E12[None, :, :1] * L * su + _E12[None, :, 1:] * 0.22 * sr
    shadow = np.concatenate([sh, np.zeros((n, 12, 1))], axis=2)

    swing = np.where(moving, 0.3 * np.sin(phase), 0.0)[:, None]
    hip = np.concatenate([pos, np.full((n, 1), HIP_Z)], axis=1)
    feet_l = np.concatenate([pos - 0.1 * r + swing * f, np.zeros((n, 1))], axis=1)
    feet_r = np.concatenate([pos + 0.1 * r - swing * f, np.zeros((n, 1))], axis=1)
    sho_l = np.concatenate([pos - 0.2 * r, np.full((n, 1), SHOULDER_Z + 0.05)], axis=1)
    sho_r = np.concatenate([pos + 0.2 * r, np.full((n, 1), SHOULDER_Z + 0.05)], axis=1)
    hand_l = np.concatenate([pos - 0.28 * r - swing * f, np.full((n, 1), -0.8)], axis=1)
    hand_r = np.concatenate([pos + 0.28 * r + swing * f, np.full((n, 1), -0.8)], axis=1)
    elbow_l = (sho_l + hand_l) / 2
    elbow_r = (sho_r + hand_r) / 2
    return {
        "shadow": shadow,
        "limbs": np.stack([hip, feet_l, hip, feet_r, sho_l, hand_l, sho_r, hand_r,
                           sho_l, elbow_l, sho_r, elbow_r], axis=1),
        "torso": ring(pos, SHOULDER_Z, 0.15, 0.25, _E12),
        "face": ring(pos + 0.045 * f, HEAD_Z + 0.04, 0.085, 0.075, _E8),
        "hair": ring(pos - 0.015 * f, HEAD_Z, 0.095, 0.085, _E8),
        "centre": np.concatenate([pos, np.full((n, 1), HEAD_Z)], axis=1)[:, None, :],
    }


def view_footprint(intrinsics: Intrinsics, mount: Mount, pose: Pose, max_range: float = MAX_RANGE,
                   samples: int = 9) -> tuple[float, float, float, float, float]:
    """Ground rectangle (n_min, n_max, e_min, e_max) seen by the camera, clipped to ``max_range``
    metres around the camera, and the ground sample distance (m/px) at the image centre."""
    ext = camera_extrinsics(pose, mount)
    Kinv = np.linalg.inv(intrinsics.K)
    us = np.linspace(0, intrinsics.width - 1, samples)
    vs = np.linspace(0, intrinsics.height - 1, samples)
    uu, vv = np.meshgrid(us, vs)
    pix = np.column_stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    d = (pix @ Kinv.T) @ ext.R_cv_from_world  # ray directions in world NED
    c = ext.position
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -c[2] / d[:, 2]
    hit = c[:2] + d[:, :2] * s[:, None]
    horiz = np.hypot(hit[:, 0] - c[0], hit[:, 1] - c[1])
    far = ~(d[:, 2] > 1e-9) | ~np.isfinite(horiz) | (horiz > max_range)
    if far.any():
        dh = d[far, :2]
        nrm = np.hypot(dh[:, 0], dh[:, 1])
        dh = np.where(nrm[:, None] > 1e-9, dh / np.maximum(nrm, 1e-12)[:, None], 0.0)
        hit[far] = c[:2] + dh * max_range
    # Ground sample distance at the centre pixel: the ground step of one pixel in u and in v.
    cu, cv_ = intrinsics.cx, intrinsics.cy
    p3 = np.array([[cu, cv_, 1.0], [cu + 1, cv_, 1.0], [cu, cv_ + 1, 1.0]])
    dc = (p3 @ Kinv.T) @ ext.R_cv_from_world
    if dc[0, 2] > 1e-9:
        g = c[:2] + dc[:, :2] * (-c[2] / dc[:, 2])[:, None]
        gsd = float(min(np.hypot(*(g[1] - g[0])), np.hypot(*(g[2] - g[0]))))
    else:
        gsd = max_range / intrinsics.fx
    return (float(hit[:, 0].min()), float(hit[:, 0].max()), float(hit[:, 1].min()),
            float(hit[:, 1].max()), max(gsd, 1e-4))


@functools.lru_cache(maxsize=4)
def _pixel_rays(intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unit ray (camera frame) of every pixel as three float32 (h, w) images x, y, z (0 outside the
    lens's view), and the mask of the pixels the lens sees. Read-only: the same camera comes every
    frame."""
    uu, vv = np.meshgrid(np.arange(intrinsics.width, dtype=float), np.arange(intrinsics.height, dtype=float))
    rays = intrinsics.unproject(np.column_stack([uu.ravel(), vv.ravel()]))
    seen = np.isfinite(rays).all(axis=1).reshape(uu.shape)
    rays = np.nan_to_num(rays, nan=0.0).astype(np.float32)
    out = tuple(np.ascontiguousarray(rays[:, i].reshape(uu.shape)) for i in range(3)) + (seen,)
    for arr in out:
        arr.flags.writeable = False
    return out


def render_ground_lens(pose: Pose, intrinsics: Intrinsics, mount: Mount, ground: Ground) -> np.ndarray:
    """``render_ground`` through a lens that is not a pinhole: each pixel's ray met with the ground
    z = 0 and looked up in the ground's mosaic (sky where the ray does not go down, black outside
    the lens's image circle, haze beyond ``LENS_RANGE_PER_M`` x the height)."""
    rx, ry, rz, seen = _pixel_rays(intrinsics)
    ext = camera_extrinsics(pose, mount)
    c = ext.position
    R = ext.R_cv_from_world.astype(np.float32)  # world direction d_j = sum_i ray_i R[i, j]
    dn = R[0, 0] * rx + R[1, 0] * ry + R[2, 0] * rz
    de = R[0, 1] * rx + R[1, 1] * ry + R[2, 1] * rz
    dd = R[0, 2] * rx + R[1, 2] * ry + R[2, 2] * rz
    height = max(-float(c[2]), 1e-3)
    reach = min(MAX_RANGE, LENS_RANGE_PER_M * height)
    down = dd > 1e-6
    # Horizontal distance per unit height is |d_h| / d_down: within reach when |d_h| <= k d_down.
    near = down & (dn * dn + de * de <= np.float32((reach / height) ** 2) * dd * dd)
    s = np.float32(height) / np.where(near, dd, np.float32(1.0))
    gsd = height / max(intrinsics.fx, intrinsics.fy)  # the centre pixel's, straight down
    mosaic, A = ground.view(c[0] - reach, c[0] + reach, c[1] - reach, c[1] + reach, gsd)
    A = A.astype(np.float64)
    n_off, e_off = s * dn, s * de
    mx = np.float32(A[0, 0]) * n_off + np.float32(A[0, 1]) * e_off + np.float32(A[0, 0] * c[0] + A[0, 1] * c[1] + A[0, 2])
    my = np.float32(A[1, 0]) * n_off + np.float32(A[1, 1]) * e_off + np.float32(A[1, 0] * c[0] + A[1, 1] * c[1] + A[1, 2])
    mx[~near] = -1e4
    img = cv2.remap(mosaic, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=HAZE)
    img[seen & ~down] = SKY
    img[~seen] = OUTSIDE_LENS
    return img


def render_ground(pose: Pose, intrinsics: Intrinsics, mount: Mount, ground: Ground) -> np.ndarray:
    """The ground plane z = 0 as the camera sees it (sky above the horizon), BGR uint8."""
    if intrinsics.is_fisheye:
        return render_ground_lens(pose, intrinsics, mount, ground)
    w, h = intrinsics.width, intrinsics.height
    n0, n1, e0, e1, gsd = view_footprint(intrinsics, mount, pose)
    mosaic, A = ground.view(n0, n1, e0, e1, gsd)
    G = plane_homography(intrinsics, mount, pose, 0.0)
    M = G @ np.linalg.inv(A)  # mosaic pixel -> image pixel
    img = cv2.warpPerspective(mosaic, M, (w, h), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=HAZE)
    # Rays that do not go down never meet the ground: paint them sky. down-component is linear
    # in (u, v), so the horizon is a straight line.
    ext = camera_extrinsics(pose, mount)
    row = (ext.R_cv_from_world.T @ np.linalg.inv(intrinsics.K))[2]
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float) @ row
    if (corners <= 1e-9).any():
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        sky = (row[0] * uu + row[1] * vv + row[2]) <= 1e-9
        img[sky] = SKY
    return img


def _to_fixed(uv: np.ndarray) -> np.ndarray:
    return np.round(uv * _ONE).astype(np.int32)


def render(world_positions: np.ndarray, pose: Pose, intrinsics: Intrinsics, mount: Mount,
           ground: Ground, headings: np.ndarray | None = None, moving: np.ndarray | None = None,
           looks: Looks | None = None, t: float = 0.0, seed: int = 0, blur: float = 0.6,
           ids: np.ndarray | None = None) -> np.ndarray:
    """One camera frame: BGR uint8 of ``intrinsics.height x intrinsics.width`` (640x480 by default
    intrinsics of the simulator).

    world_positions: (N, 2) people's ground positions (north, east), metres.
    pose, intrinsics, mount: the camera model of the service (``companion.geometry.camera``).
    ground: a :class:`sim.world.ground.ProceduralGround` or anything with its ``view`` method.
    headings: (N,) radians from north toward east (default: all facing north).
    moving: (N,) bool, walking people swing their legs and arms (default: none).
    looks: per-person colours (default: ``people_looks(N, seed)``).
    t: seconds, drives the walking gait phase.
    blur: Gaussian sigma in pixels of the lens/motion softness applied at the end (0 = none).
    ids: (N,) the people's stable ids; a ground that carries its own ``people_painter`` (the photo
    ground's real silhouettes, ``sim.world.photo_people``) draws the people instead, by id.
    """
    img = render_ground(pose, intrinsics, mount, ground)
    pos = np.asarray(world_positions, float).reshape(-1, 2)
    n = len(pos)
    if n:
        hd = np.zeros(n) if headings is None else np.asarray(headings, float).ravel()
        mv = np.zeros(n, bool) if moving is None else np.asarray(moving, bool).ravel()
        lk = looks if looks is not None and len(looks) >= n else people_looks(n, seed)
        painter = getattr(ground, "people_painter", None)
        if painter is not None:
            painter.paint(img, pos, hd, lk, pose, intrinsics, mount, ids)
        else:
            _draw_people(img, pos, hd, mv, lk, t, pose, intrinsics, mount)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    return img


def _draw_people(img: np.ndarray, pos: np.ndarray, hd: np.ndarray, mv: np.ndarray, lk: Looks,
                 t: float, pose: Pose, intrinsics: Intrinsics, mount: Mount) -> None:
    w, h = intrinsics.width, intrinsics.height
    # Cull people whose head is behind the camera or far outside the frame first.
    c_uv, c_z = project_points(np.column_stack([pos, np.full(len(pos), HEAD_Z)]), intrinsics, mount, pose)
    f = max(intrinsics.fx, intrinsics.fy)
    margin = 2.5 * f / np.maximum(c_z, 1e-6)  # ~2.5 m around the head covers the shadow
    keep = ((c_z > 0.3) & (c_uv[:, 0] > -margin) & (c_uv[:, 0] < w + margin)
            & (c_uv[:, 1] > -margin) & (c_uv[:, 1] < h + margin))
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return
    # Painter's order: far people first.
    idx = idx[np.argsort(-c_z[idx])]
    phase = 2 * math.pi * 0.9 * t + idx * 1.7  # ~0.9 strides per second, desynchronised
    parts = _parts(pos[idx], hd[idx], mv[idx], phase)
    uv = {k: project_points(v, intrinsics, mount, pose) for k, v in parts.items()}
    if any((z <= 0.05).any() for _, z in uv.values()):
        ok = np.all(np.concatenate([z for _, z in uv.values()], axis=1) > 0.05, axis=1)
        idx = idx[ok]
        uv = {k: (p[ok], z[ok]) for k, (p, z) in uv.items()}
    px_per_m = f / uv["centre"][1][:, 0]

    # Shadows all at once on a mask, then darken: they overlap each other and the ground softly.
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, list(_to_fixed(uv["shadow"][0])), 255, cv2.LINE_AA, SHIFT)
    shade = cv2.cvtColor(255 - (mask >> 1) + (mask >> 3), cv2.COLOR_GRAY2BGR)  # 255 = none, 160 = full
    cv2.multiply(img, shade, dst=img, scale=1.0 / 255.0)

    # Python-level loop: plain lists and tuples keep the per-person overhead to a few us.
    limbs = _to_fixed(uv["limbs"][0]).tolist()
    torso = list(_to_fixed(uv["torso"][0]))
    face = list(_to_fixed(uv["face"][0]))
    hair = list(_to_fixed(uv["hair"][0]))
    leg_w = np.maximum(1, np.round(0.13 * px_per_m)).astype(int).tolist()
    arm_w = np.maximum(1, np.round(0.09 * px_per_m)).astype(int).tolist()
    sleeve_w = np.maximum(1, np.round(0.14 * px_per_m)).astype(int).tolist()
    trousers = lk.trousers[idx].tolist()
    clothes = lk.clothes[idx].tolist()
    skin = lk.skin[idx].tolist()
    hair_c = lk.hair[idx].tolist()
    cap = lk.cap[idx].tolist()
    line, fill, AA = cv2.line, cv2.fillPoly, cv2.LINE_AA
    for k in range(len(idx)):
        L = limbs[k]
        lw, aw, tr, sk = leg_w[k], arm_w[k], trousers[k], skin[k]
        line(img, L[0], L[1], tr, lw, AA, SHIFT)
        line(img, L[2], L[3], tr, lw, AA, SHIFT)
        line(img, L[4], L[5], sk, aw, AA, SHIFT)
        line(img, L[6], L[7], sk, aw, AA, SHIFT)
        line(img, L[8], L[9], clothes[k], sleeve_w[k], AA, SHIFT)
        line(img, L[10], L[11], clothes[k], sleeve_w[k], AA, SHIFT)
        fill(img, [torso[k]], clothes[k], AA, SHIFT)
        if cap[k]:
            fill(img, [hair[k]], clothes[k], AA, SHIFT)
        else:
            fill(img, [face[k]], sk, AA, SHIFT)
            fill(img, [hair[k]], hair_c[k], AA, SHIFT)


def render_world(world: WorldView, pose: Pose, intrinsics: Intrinsics, mount: Mount,
                 ground: Ground, **kwargs: float) -> np.ndarray:
    """:func:`render` of a :class:`sim.world.crowd.World` at its current time (positions, headings,
    walking state and the world's seed for the people's looks)."""
    seed = getattr(world, "seed", 0)
    ids = world.ids() if hasattr(world, "ids") else None
    looks = looks_for(ids, seed) if ids is not None else None
    return render(world.positions(), pose, intrinsics, mount, ground,
                  headings=world.headings(), moving=world.moving(),
                  looks=looks, t=world.t, seed=seed, ids=ids, **kwargs)
