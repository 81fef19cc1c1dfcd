"""Augmentation of (image, target map) pairs into fixed-size training crops (numpy / OpenCV).

One affine warp per crop does scale, any rotation (the target views look straight down, so every
heading is plausible), flips and the crop, applied identically to the image and to its target map.
Photometric changes (brightness, contrast, colour, grey, blur, noise) touch the image only.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class GeomAug:
    """Geometric augmentation of one source.

    scale: (lo, hi) range of the image scale factor, sampled log-uniformly.
    rotate: sample any rotation angle (top-down sources) instead of multiples of 90 degrees.
    focus: probability of centring the crop near an annotated person rather than anywhere.
    """

    scale: tuple[float, float] = (0.5, 1.5)
    rotate: bool = True
    focus: float = 0.7


def random_crop(
    image: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    size: int,
    aug: GeomAug,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """A ``size`` x ``size`` crop of ``image`` (uint8) and ``target`` (float) after a random warp."""
    h, w = image.shape[:2]
    s = float(np.exp(rng.uniform(np.log(aug.scale[0]), np.log(aug.scale[1]))))
    angle = rng.uniform(0, 360) if aug.rotate else 90.0 * rng.integers(4)
    if len(points) and rng.random() < aug.focus:
        cx, cy = points[rng.integers(len(points))] + rng.normal(0, size / (4 * s), 2)
    else:
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    m = cv2.getRotationMatrix2D((float(cx), float(cy)), float(angle), s)
    if rng.random() < 0.5:  # mirror about the crop centre's vertical axis
        m = np.array([[-1, 0, 0], [0, 1, 0]], np.float64) @ np.vstack([m, [0, 0, 1]])
        m[0, 2] += 2 * cx
    m[0, 2] += size / 2 - cx
    m[1, 2] += size / 2 - cy
    img = cv2.warpAffine(image, m, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    tgt = cv2.warpAffine(target, m, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return img, tgt


def photometric(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random brightness, contrast, hue/saturation, grey, blur and noise on a BGR uint8 image."""
    img: np.ndarray = image.astype(np.float32)  # float32, then uint8 from the clip on
    if rng.random() < 0.8:
        img = (img - img.mean()) * rng.uniform(0.6, 1.4) + img.mean() + rng.uniform(-40, 40)
    if rng.random() < 0.5:
        img *= rng.uniform(0.85, 1.15, 3).astype(np.float32)  # per-channel gain: white balance
    img = np.clip(img, 0, 255).astype(np.uint8)
    if rng.random() < 0.3:
        hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV).astype(np.int16)
        hsv[..., 0] = (hsv[..., 0] + rng.integers(-12, 13)) % 180
        hsv[..., 1] = np.clip(hsv[..., 1] * rng.uniform(0.5, 1.5), 0, 255)
        img = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2BGR)
    if rng.random() < 0.1:
        img = cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    if rng.random() < 0.2:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.4, 1.2))
    if rng.random() < 0.3:
        noise = rng.normal(0, rng.uniform(2, 8), img.shape).astype(np.float32)
        img = np.clip(img.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    return img
