"""How far a frame may be shrunk before the density model runs, so that people still look the
size the model finds them at.

The density model is trained and calibrated to find people from about 5 px across (the drone
rule keeps 99.5 % of them at its threshold, the smallest included). Low over the ground the same
people are 30-60 px across, and the model, run on the full frame, marks the ground's own grain
as people: on the photo world (docs/photo-world.md) the shipped model marks 11 % of the free
circle's real paving from 8 m and 8 % from 5 m, where it marks 0.4-0.7 % of the drawn lawns.
Shrunk so that the smallest person is still ``person_px`` across, the frame keeps every person
at a size the model is validated on and loses the grain (``python -m sim.evidence.false_positives
--ground photo --person-px N``).

The smallest person is ``PERSON_M`` (0.4 m, a child or a person seen square from above; the
same figure as ``control.descent.person_trust_height``) on the head plane, where the view
reaches farthest: the frame's corners and edge midpoints (for a pinhole the ground scale is
smallest at the frame's border). A view that reaches the horizon has no smallest size: it is
never shrunk. Pure functions over a :class:`PlaneProjection`; no I/O.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from companion.geometry.camera import PlaneProjection

#: The smallest person (m across) the shrink must keep at ``person_px`` pixels.
PERSON_M = 0.4
#: Never shrink below this share of the frame's side: a floor on the map's resolution (a 640 px
#: frame keeps 160 px, 40 output cells of a stride-4 model).
MIN_SCALE = 0.25


def smallest_person_px(proj: PlaneProjection, hw: tuple[int, int], person_m: float = PERSON_M) -> float:
    """How many pixels a ``person_m``-wide person on the head plane spans where the frame sees
    farthest (its corners and edge midpoints); 0 when any of them does not see the plane (the
    horizon, or a lens's edge), so that nothing is shrunk then.

    The local scale at a pixel is the square root of the head-plane area one pixel covers
    (metres per pixel, from the projection of the pixel's two neighbours)."""
    h, w = hw
    u = np.array([0.5, w / 2, w - 0.5, 0.5, w - 0.5, 0.5, w / 2, w - 0.5])
    v = np.array([0.5, 0.5, 0.5, h / 2, h / 2, h - 0.5, h - 0.5, h - 0.5])
    uv = np.stack([u, v], axis=1)
    p0 = proj.image_to_plane(uv)
    pu = proj.image_to_plane(uv + [1.0, 0.0])
    pv = proj.image_to_plane(uv + [0.0, 1.0])
    if not (np.isfinite(p0).all() and np.isfinite(pu).all() and np.isfinite(pv).all()):
        return 0.0
    a, b = pu - p0, pv - p0
    area = np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])  # m^2 per pixel
    m_per_px = float(np.sqrt(area.max()))
    return person_m / m_per_px if m_per_px > 0 and math.isfinite(m_per_px) else 0.0


def density_scale(proj: PlaneProjection, hw: tuple[int, int], person_px: float, person_m: float = PERSON_M,
                  min_scale: float = MIN_SCALE) -> float:
    """The factor (``min_scale`` to 1) to shrink a frame of ``hw`` by so that the smallest person
    (``smallest_person_px``) spans at least ``person_px`` pixels; 1 (the full frame) when
    ``person_px`` is 0 or the view has no smallest person."""
    if person_px <= 0:
        return 1.0
    seen = smallest_person_px(proj, hw, person_m)
    if seen <= person_px:
        return 1.0
    return max(min_scale, person_px / seen)


def scaled_size(hw: tuple[int, int], scale: float, multiple: int) -> tuple[int, int]:
    """(height, width) of the shrunk frame: ``scale`` of each side, rounded up to a whole
    ``multiple`` (the model's stride), never larger than the frame."""
    h, w = hw
    return (min(h, max(multiple, math.ceil(h * scale / multiple) * multiple)),
            min(w, max(multiple, math.ceil(w * scale / multiple) * multiple)))


def shrunk(frame: np.ndarray, scale: float, multiple: int) -> np.ndarray:
    """``frame`` (H, W[, C]) shrunk by ``scale`` to ``scaled_size`` (area interpolation: the
    grain averages out, as a camera with fewer pixels would see it); ``frame`` itself when
    ``scale`` is 1 or more."""
    if scale >= 1.0:
        return frame
    h, w = scaled_size(frame.shape[:2], scale, multiple)
    return cv2.resize(frame, (w, h), interpolation=cv2.INTER_AREA)
