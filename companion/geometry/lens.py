"""Lens models: camera-frame rays <-> image pixels, for the pinhole (OpenCV's polynomial distortion)
and the fisheye (OpenCV's equidistant model, ``cv2.fisheye``: ``theta_d = theta (1 + k1 theta^2 +
k2 theta^4 + k3 theta^6 + k4 theta^8)``, ``r_px = f * theta_d``).

Camera frame = OpenCV (x right, y down, z forward along the optical axis). ``theta`` is the angle of
a ray from the optical axis in radians; the fisheye is written here for rays beyond 90 degrees too
(``cv2.fisheye`` divides by z and so stops at 90), up to :data:`MAX_THETA` (200 degrees diagonal).

Every function answers NaN for what the lens does not see: a ray behind a pinhole, a ray beyond
``MAX_THETA`` or beyond where the calibrated polynomial stops growing (there the calibration says
nothing), a pixel outside the image circle those rays make.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

MODELS = ("pinhole", "fisheye")
#: Widest ray (rad from the optical axis) any lens is written for: a 200-degree diagonal view.
MAX_THETA = math.radians(100.0)
#: Widest ray (rad from the optical axis) along which ground counts as seen (free when nobody is
#: found there): the shipped model found at least 99.5 % of the people rendered through a
#: fisheye:160 in every 10-degree bin out to 70 degrees, and 98.5 % at 70-80 (sim.evidence.lens_recall,
#: docs/measurements.md session 26). Beyond it people are still placed, but the ground is unseen.
TRUSTED_THETA = math.radians(70.0)


@functools.lru_cache(maxsize=16)
def fisheye_theta_max(k: tuple[float, ...]) -> float:
    """The widest angle (rad, at most ``MAX_THETA``) up to which ``theta_d(theta)`` keeps growing:
    beyond it one image radius would stand for two rays, so the lens is taken to see nothing."""
    th = np.linspace(0.0, MAX_THETA, 2001)
    d = _dtheta_d(th, k)
    bad = np.flatnonzero(d <= 1e-6)
    return float(MAX_THETA if bad.size == 0 else th[max(bad[0] - 1, 0)])


def _coeffs(k: tuple[float, ...]) -> tuple[float, float, float, float]:
    c = [float(v) for v in k[:4]] + [0.0] * (4 - min(len(k), 4))
    return c[0], c[1], c[2], c[3]


def _theta_d(th: np.ndarray, k: tuple[float, ...]) -> np.ndarray:
    k1, k2, k3, k4 = _coeffs(k)
    t2 = th * th
    out: np.ndarray = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    return out


def _dtheta_d(th: np.ndarray, k: tuple[float, ...]) -> np.ndarray:
    k1, k2, k3, k4 = _coeffs(k)
    t2 = th * th
    out: np.ndarray = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    return out


def ray_theta(xc: np.ndarray) -> np.ndarray:
    """Camera-frame points or rays (N, 3) -> their angles from the optical axis (N,), radians."""
    p = np.asarray(xc, dtype=np.float64).reshape(-1, 3)
    out: np.ndarray = np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2])
    return out


def project(model: str, K: np.ndarray, dist: tuple[float, ...], xc: np.ndarray,
            theta: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame points or rays (N, 3) -> pixels (N, 2); NaN where the lens does not see them.
    ``theta``: their ``ray_theta`` when the caller has it already (a fisheye needs it)."""
    p = np.asarray(xc, dtype=np.float64).reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    out = np.full((len(p), 2), np.nan)
    if model == "fisheye":
        r = np.hypot(x, y)
        th = np.arctan2(r, z) if theta is None else np.asarray(theta, dtype=np.float64).reshape(-1)
        ok = np.isfinite(th) & (th <= fisheye_theta_max(tuple(dist)))
        if ok.all():
            # Every point seen (a grid inside the view, the usual case): the same arithmetic
            # without gathering through the mask and scattering back.
            td = _theta_d(th, dist)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(r > 1e-12, td / r, 0.0)
            a, b = x * s, y * s
            out[:, 0] = fx * a + skew * b + cx
            out[:, 1] = fy * b + cy
            return out
        td = _theta_d(th[ok], dist)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(r[ok] > 1e-12, td / r[ok], 0.0)
        a, b = x[ok] * s, y[ok] * s
        out[ok, 0] = fx * a + skew * b + cx
        out[ok, 1] = fy * b + cy
        return out
    ok = np.isfinite(z) & (z > 1e-9)
    if not ok.any():
        return out
    if any(abs(d) > 0 for d in dist):
        uv, _ = cv2.projectPoints(p[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                  np.asarray(dist, np.float64))
        out[ok] = uv.reshape(-1, 2)
    else:
        out[ok, 0] = fx * x[ok] / z[ok] + skew * y[ok] / z[ok] + cx
        out[ok, 1] = fy * y[ok] / z[ok] + cy
    return out


def unproject(model: str, K: np.ndarray, dist: tuple[float, ...], uv: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> unit rays (N, 3) in the camera frame; NaN where no seen ray lands there."""
    q = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    b = (q[:, 1] - cy) / fy
    a = (q[:, 0] - cx - skew * b) / fx
    if model == "fisheye":
        td = np.hypot(a, b)
        th_max = fisheye_theta_max(tuple(dist))
        ok = np.isfinite(td) & (td <= float(_theta_d(np.array([th_max]), dist)[0]) + 1e-12)
        th = td.copy()
        # Newton on theta_d(theta) = td, as cv2.fisheye.undistortPoints does; monotonic up to th_max.
        for _ in range(20):
            th = th - (_theta_d(th, dist) - td) / _dtheta_d(th, dist)
            th = np.clip(th, 0.0, th_max)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(td > 1e-12, np.sin(th) / td, 1.0)
        rays = np.column_stack([a * s, b * s, np.cos(th)])
        rays[~ok] = np.nan
        return rays
    if any(abs(d) > 0 for d in dist):
        n = cv2.undistortPoints(q.reshape(-1, 1, 2), K, np.asarray(dist, np.float64)).reshape(-1, 2)
        a, b = n[:, 0], n[:, 1]
    rays = np.column_stack([a, b, np.ones(len(q))])
    unit: np.ndarray = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return unit
