"""Circles on the head plane and their closed-form intersection over union.

The tracker associates landing-zone proposals to tracks by circle IoU (docs/design.md, step 5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Circle:
    """A landing circle: centre (x, y) and radius r, all in head-plane metres."""

    x: float
    y: float
    r: float

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.r], dtype=float)


@dataclass(frozen=True)
class GroundBelow:
    """The ground straight under the camera on one frame: where the vehicle touches down if it
    comes straight down from where the frame was taken.

    x, y: that point on the head plane (m; world north/east when poses are known).
    r: how far the ground around it is free on the grid proposals are made on (m; 0 when it is
        occupied or out of the grid; unseen ground is not free, so ``r <= r_view``).
    r_view: how far the camera's view reaches around it (m).
    calm_s: how long the ground around it (r0 plus a margin) has been watched and seen free (s,
        ``riskmap.GroundRiskMap.calm_s``); NaN when not measured (a frame without a pose).
    """

    x: float
    y: float
    r: float
    r_view: float
    calm_s: float = math.nan

    @property
    def view_limited(self) -> bool:
        """Everything the camera saw within ``r_view`` of the point was free: only the edge of
        the view bounds ``r`` (low over a zone the view is smaller than the zone)."""
        return self.r >= self.r_view - 1e-6


def intersection_area(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Area of the intersection of circles ``a`` (n, 3) and ``b`` (m, 3) as (n, m), in m^2.

    Closed form of the lens area: the sum of the two circular segments cut by the chord.
    """
    a = np.asarray(a, dtype=float).reshape(-1, 3)
    b = np.asarray(b, dtype=float).reshape(-1, 3)
    x1, y1, r1 = (a[:, i, None] for i in range(3))
    x2, y2, r2 = (b[None, :, i] for i in range(3))
    r1 = np.maximum(r1, 0.0)
    r2 = np.maximum(r2, 0.0)
    d = np.hypot(x1 - x2, y1 - y2)
    rmin = np.minimum(r1, r2)
    area = np.zeros(np.broadcast(d, r1, r2).shape)
    nested = d <= np.abs(r1 - r2)
    area = np.where(nested, np.pi * rmin**2, area)
    partial = (d < r1 + r2) & ~nested
    if partial.any():
        dd = np.where(partial, d, 1.0)
        c1 = np.clip((dd**2 + r1**2 - r2**2) / (2 * dd * np.where(r1 > 0, r1, 1.0)), -1, 1)
        c2 = np.clip((dd**2 + r2**2 - r1**2) / (2 * dd * np.where(r2 > 0, r2, 1.0)), -1, 1)
        k = (-dd + r1 + r2) * (dd + r1 - r2) * (dd - r1 + r2) * (dd + r1 + r2)
        lens = r1**2 * np.arccos(c1) + r2**2 * np.arccos(c2) - 0.5 * np.sqrt(np.maximum(k, 0))
        area = np.where(partial, lens, area)
    return area


#: Up to this many pairs ``iou_matrix`` works pair by pair in Python: the tracker's few zones
#: against a frame's few proposals (5 x 5 at most by default) cost 0.2 ms a frame in the two dozen
#: numpy calls of the array form, most of it their overhead.
SMALL_PAIRS = 64


def _iou_pair(x1: float, y1: float, r1: float, x2: float, y2: float, r2: float) -> float:
    """``iou_matrix`` of one pair, the same formulas as ``intersection_area``, in floats."""
    r1, r2 = max(r1, 0.0), max(r2, 0.0)
    d = math.hypot(x1 - x2, y1 - y2)
    if d <= abs(r1 - r2):
        inter = math.pi * min(r1, r2) ** 2
    elif d < r1 + r2:
        c1 = min(max((d * d + r1 * r1 - r2 * r2) / (2 * d * (r1 if r1 > 0 else 1.0)), -1.0), 1.0)
        c2 = min(max((d * d + r2 * r2 - r1 * r1) / (2 * d * (r2 if r2 > 0 else 1.0)), -1.0), 1.0)
        k = (-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2)
        inter = r1 * r1 * math.acos(c1) + r2 * r2 * math.acos(c2) - 0.5 * math.sqrt(max(k, 0.0))
    else:
        inter = 0.0
    union = math.pi * r1 * r1 + math.pi * r2 * r2 - inter
    return min(max(inter / union, 0.0), 1.0) if union > 0 else 0.0


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union of circles ``a`` (n, 3) and ``b`` (m, 3) as an (n, m) array."""
    a = np.asarray(a, dtype=float).reshape(-1, 3)
    b = np.asarray(b, dtype=float).reshape(-1, 3)
    if len(a) * len(b) <= SMALL_PAIRS and np.isfinite(a).all() and np.isfinite(b).all():
        bl = b.tolist()
        return np.array([[_iou_pair(*ca, *cb) for cb in bl] for ca in a.tolist()], dtype=float).reshape(len(a), len(b))
    inter = intersection_area(a, b)
    area_a = np.pi * np.maximum(a[:, 2], 0)[:, None] ** 2
    area_b = np.pi * np.maximum(b[:, 2], 0)[None, :] ** 2
    union = area_a + area_b - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
    return np.clip(iou, 0.0, 1.0)


def circle_iou(a: Circle, b: Circle) -> float:
    return float(iou_matrix(a.as_array(), b.as_array())[0, 0])
