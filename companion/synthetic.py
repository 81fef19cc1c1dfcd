"""Synthetic crowd frames with known free circles, for tests, the benchmark and demos of replay.

Nothing here comes from a data set: people are drawn as dark head-and-shoulder blobs on a
generated ground texture, and ``point_density`` is the ideal density map of the drawn people (what a
perfect model would output), so the post-density stages can be checked against known geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SyntheticScene:
    """people: (N, 2) pixel positions (u, v); free: list of (u, v, r) pixel circles kept empty."""

    width: int
    height: int
    people: np.ndarray
    free: tuple[tuple[float, float, float], ...]


def crowd_scene(width: int = 640, height: int = 480, n_people: int = 150,
                free: tuple[tuple[float, float, float], ...] = ((200.0, 240.0, 90.0),),
                seed: int = 0) -> SyntheticScene:
    """People spread uniformly over the image except inside the ``free`` circles."""
    rng = np.random.default_rng(seed)
    pts: list[tuple[float, float]] = []
    while len(pts) < n_people:
        u, v = rng.uniform(0, width), rng.uniform(0, height)
        if all((u - fu) ** 2 + (v - fv) ** 2 > fr**2 for fu, fv, fr in free):
            pts.append((u, v))
    return SyntheticScene(width, height, np.array(pts, dtype=float).reshape(-1, 2), tuple(free))


def move(scene: SyntheticScene, shift_px: tuple[float, float]) -> SyntheticScene:
    """The same scene seen after the camera slid by ``shift_px`` (people and circles move)."""
    d = np.asarray(shift_px, dtype=float)
    return SyntheticScene(scene.width, scene.height, scene.people + d,
                          tuple((u + d[0], v + d[1], r) for u, v, r in scene.free))


def render(scene: SyntheticScene, seed: int = 0) -> np.ndarray:
    """A BGR frame: textured grey-green ground with a dark blob per person."""
    rng = np.random.default_rng(seed)
    noise: np.ndarray = rng.normal(0, 12, (scene.height // 8 + 1, scene.width // 8 + 1)).astype(np.float32)
    noise = cv2.resize(noise, (scene.width, scene.height), interpolation=cv2.INTER_CUBIC)
    base = np.array([70, 120, 95], np.float32)  # BGR
    frame = np.clip(base[None, None, :] + noise[..., None], 0, 255).astype(np.uint8)
    for u, v in scene.people:
        cv2.ellipse(frame, (int(u), int(v)), (6, 4), 0, 0, 360, (40, 40, 150), -1)
        cv2.circle(frame, (int(u), int(v)), 3, (20, 25, 30), -1)
    return frame


def point_density(scene: SyntheticScene, stride: int = 4) -> np.ndarray:
    """The ideal density map at ``stride``: one unit per person in the cell of its head."""
    h, w = -(-scene.height // stride), -(-scene.width // stride)
    d = np.zeros((h, w), np.float32)
    for u, v in scene.people:
        i, j = int(v // stride), int(u // stride)
        if 0 <= i < h and 0 <= j < w:
            d[i, j] += 1.0
    return d
