"""Training targets: "someone is here" maps with peak 1, rendered in image pixels.

A person box (semantic drone photos, whole person seen from above) becomes an anisotropic
Gaussian with sigma = side / 4 per axis, so the box edge sits at two sigma (value 0.135).
A head point becomes an isotropic Gaussian whose sigma is given (DroneCrowd) or adapted to the
distance to the nearest neighbours (street crowds, where near heads are larger). Overlaps take
the maximum, not the sum: the map says where people are, not how many.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def _splat(out: np.ndarray, cx: float, cy: float, sx: float, sy: float) -> None:
    h, w = out.shape
    x0, x1 = int(max(0, np.floor(cx - 3 * sx))), int(min(w, np.ceil(cx + 3 * sx) + 1))
    y0, y1 = int(max(0, np.floor(cy - 3 * sy))), int(min(h, np.ceil(cy + 3 * sy) + 1))
    if x0 >= x1 or y0 >= y1:
        return
    # +0.5: annotations are in pixel-corner coordinates, pixel (i, j) has its centre at (j+0.5, i+0.5).
    gx = np.exp(-0.5 * ((np.arange(x0, x1) + 0.5 - cx) / sx) ** 2)
    gy = np.exp(-0.5 * ((np.arange(y0, y1) + 0.5 - cy) / sy) ** 2)
    np.maximum(out[y0:y1, x0:x1], gy[:, None] * gx[None, :], out=out[y0:y1, x0:x1])


def box_target(shape_hw: tuple[int, int], boxes: np.ndarray, min_sigma: float = 2.0) -> np.ndarray:
    """float32 map of ``shape_hw`` from (N, 4) boxes ``x1, y1, x2, y2`` in pixels."""
    out = np.zeros(shape_hw, np.float32)
    for x1, y1, x2, y2 in np.asarray(boxes, np.float32).reshape(-1, 4):
        _splat(out, (x1 + x2) / 2, (y1 + y2) / 2, max(min_sigma, (x2 - x1) / 4), max(min_sigma, (y2 - y1) / 4))
    return out


def point_target(
    shape_hw: tuple[int, int],
    points: np.ndarray,
    sigma: float | None = None,
    knn_factor: float = 0.3,
    sigma_range: tuple[float, float] = (3.0, 24.0),
) -> np.ndarray:
    """float32 map of ``shape_hw`` from (N, 2) head points (x, y) in pixels.

    sigma: fixed sigma in pixels; if None, ``knn_factor`` x the mean distance to the three nearest
    other heads, clipped to ``sigma_range`` (the upper end for lone heads).
    """
    pts = np.asarray(points, np.float32).reshape(-1, 2)
    out = np.zeros(shape_hw, np.float32)
    if len(pts) == 0:
        return out
    if sigma is not None:
        sig = np.full(len(pts), float(sigma))
    elif len(pts) > 3:
        d, _ = cKDTree(pts).query(pts, k=4)
        sig = np.clip(knn_factor * d[:, 1:].mean(axis=1), *sigma_range)
    else:
        sig = np.full(len(pts), sigma_range[1])
    for (x, y), s in zip(pts, sig):
        _splat(out, float(x), float(y), float(s), float(s))
    return out
