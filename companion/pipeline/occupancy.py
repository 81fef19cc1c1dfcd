"""Step 2 of the pipeline: density map -> free/occupied map in image pixels.

The paper's rule: a pixel is occupied where ``D - min(D) > threshold`` (threshold 0 by default),
the map is brought to the image size without shrinking occupied areas, dilated twice with a 5x5
kernel of ones (over-estimating people on purpose), and inverted so that free = 255.

A rule measured, not used by the service (``OccupancyParams.min_mass``, 0 = off, the paper's
map): an occupied patch of the density map (8-connected cells above the threshold) whose whole
mass, the sum of ``D - min(D)`` over it, is below ``min_mass`` would be a speck of the ground's
texture rather than a person, and be left free. Low over real paving the shipped model leaves a
few such cells a frame that hold a thousandth of a person, and each of them shrinks a zone and
breaks its calm watch; but it answers some real people it barely sees the same way, so the rule
loses them (``companion eval --min-people``; docs/photo-world.md, "What keeps the companion from
landing clear").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.invariant import require

FREE = 255
OCCUPIED = 0


@dataclass(frozen=True)
class OccupancyParams:
    """Parameters of the occupancy step.

    threshold: density above ``min(D)`` (people per density pixel) that marks a pixel occupied;
        None means "the model's validated threshold" where the caller knows the model
        (``SLZPipeline``), else the paper's 0.
    kernel: side of the square dilation kernel in image pixels (odd, >= 1).
    iterations: how many times the dilation is applied (>= 0).
    min_mass: an occupied patch (8-connected cells above the threshold, at the density map's
        resolution) whose sum of ``D - min(D)`` is below this is not occupied (the density map's
        units: people divided by the model's ``count_scale``); 0 = every patch is (the paper).
    """

    threshold: float | None = None
    kernel: int = 5
    iterations: int = 2
    min_mass: float = 0.0

    def __post_init__(self) -> None:
        threshold = self.threshold
        require(threshold is None or (math.isfinite(threshold) and threshold >= 0), "occupancy", "threshold",
                "must be a finite number >= 0", threshold)
        if int(self.kernel) != self.kernel or self.kernel < 1 or self.kernel % 2 == 0:
            raise ValueError(f"occupancy kernel must be an odd integer >= 1, got {self.kernel!r}")
        if int(self.iterations) != self.iterations or self.iterations < 0:
            raise ValueError(f"occupancy iterations must be an integer >= 0, got {self.iterations!r}")
        require(math.isfinite(self.min_mass) and self.min_mass >= 0, "occupancy", "min_mass",
                "must be a finite number >= 0", self.min_mass)


def occupied_mask(density: np.ndarray, threshold: float = 0.0) -> np.ndarray:
    """Boolean mask, at the density map's own resolution, of where ``D - min(D) > threshold``.

    NaN or infinite density values count as occupied: a broken output must never open space.
    """
    d = np.asarray(density, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"density map must be 2-D, got shape {d.shape}")
    finite = np.isfinite(d)
    if finite.all():  # the usual case: no masked copies
        out: np.ndarray = (d - float(d.min())) > threshold
        return out
    if not finite.any():
        return np.ones(d.shape, dtype=bool)
    dmin = float(d[finite].min())
    occ = ~finite
    occ |= np.where(finite, d - dmin > threshold, True)
    return occ


def drop_specks(occ: np.ndarray, density: np.ndarray, min_mass: float) -> np.ndarray:
    """``occ`` (bool, the density map's shape) without its specks: the 8-connected occupied
    patches whose sum of ``D - min(D)`` is below ``min_mass``. A patch holding a non-finite value
    is kept whatever its sum (a broken output never opens space); ``min_mass`` 0 keeps all."""
    if min_mass <= 0 or not occ.any():
        return occ
    d = np.asarray(density, np.float32)
    finite = np.isfinite(d)
    n, labels = cv2.connectedComponents(occ.astype(np.uint8), connectivity=8)
    excess = np.zeros(d.shape, np.float64)
    if finite.any():
        excess[finite] = d[finite] - float(d[finite].min())
    mass = np.bincount(labels.ravel(), weights=excess.ravel(), minlength=n)
    keep = mass >= min_mass
    if not finite.all():
        keep[np.unique(labels[~finite])] = True
    keep[0] = False  # the free cells' label
    out: np.ndarray = keep[labels]
    return out


def resize_keep_occupied(mask: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """Resize a boolean occupied mask to ``size_hw`` so that no occupied area shrinks.

    Upscaling uses nearest neighbour (every source pixel covers at least one target pixel);
    downscaling in either axis keeps a target pixel occupied if any source pixel under it is.
    """
    h, w = size_hw
    src = mask.astype(np.uint8)
    sh, sw = src.shape
    if (sh, sw) == (h, w):
        return np.array(mask, copy=True)  # not .copy(): typed ndarray for mypy at Python 3.10
    if sh > h or sw > w:
        # INTER_AREA averages the covered source pixels: any occupied one gives a value > 0.
        small = cv2.resize(src * 255, (min(w, sw), min(h, sh)), interpolation=cv2.INTER_AREA)
        src = (small > 0).astype(np.uint8)
    out = cv2.resize(src, (w, h), interpolation=cv2.INTER_NEAREST)
    return out.astype(bool)


#: Unsigned integer types whose width in bytes is a column factor: a byte times 0x0101... is that
#: byte repeated across the word (whatever the byte order), one multiply for a whole block row.
_WORD = {2: (np.uint16, 0x0101), 4: (np.uint32, 0x01010101), 8: (np.uint64, 0x0101010101010101)}


def _repeat_cells(small: np.ndarray, sy: int, sx: int) -> np.ndarray:
    """uint8 ``small`` brought up ``sy`` x ``sx`` times by nearest neighbour (each cell an
    ``sy x sx`` block), as ``cv2.resize(..., INTER_NEAREST)`` at whole factors, about ten times
    faster at 4 x 4 (OpenCV's nearest resize does not special-case whole factors)."""
    if sx in _WORD:
        dtype, ones = _WORD[sx]
        wide = (np.ascontiguousarray(small).astype(dtype) * dtype(ones)).view(np.uint8)
        wide = wide.reshape(small.shape[0], small.shape[1] * sx)
    elif sx > 1:
        wide = np.repeat(small, sx, axis=1)
    else:
        wide = small
    return np.repeat(wide, sy, axis=0) if sy > 1 else np.ascontiguousarray(wide)


def free_from_occupied(occ: np.ndarray, image_hw: tuple[int, int],
                       params: OccupancyParams = OccupancyParams()) -> np.ndarray:
    """The free map at image size (uint8, ``FREE`` or ``OCCUPIED``) of a boolean occupied mask at
    any resolution: brought to the image size without shrinking occupied areas
    (``resize_keep_occupied``), then dilated ``params.iterations`` times by the square kernel.

    The same map, computed cheaper where the image is a whole multiple of the mask (a stride-4
    model on frames of a multiple of 4 pixels): the iterated dilations are one box of radius
    ``r = iterations * (kernel - 1) / 2`` pixels (boxes add up), and a box of ``m`` mask cells on
    the mask, brought up by nearest neighbour, is the box of ``m * s`` pixels on the image (a cell
    is an ``s x s`` block). So the mask is dilated by ``r // s`` cells before the upsampling and
    only the rest, ``r % s`` pixels, after it: at 640x480 the image-sized dilation goes away."""
    h, w = image_hw
    mh, mw = occ.shape
    r = params.iterations * (params.kernel - 1) // 2 if params.kernel > 1 else 0
    if mh == 0 or mw == 0 or h % mh or w % mw or h < mh or w < mw:
        occ_img: np.ndarray = resize_keep_occupied(occ, image_hw).astype(np.uint8) * 255
        if r > 0:
            occ_img = cv2.dilate(occ_img, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        return cv2.bitwise_not(occ_img)
    sy, sx = h // mh, w // mw
    small: np.ndarray = occ.astype(np.uint8) * 255
    ry, rx = r // sy, r // sx
    if ry or rx:
        small = cv2.dilate(small, np.ones((2 * ry + 1, 2 * rx + 1), np.uint8))
    free = _repeat_cells(cv2.bitwise_not(small), sy, sx)
    ey, ex = r - ry * sy, r - rx * sx
    if ey or ex:
        # The rest of the dilation of the occupied cells is an erosion of the free ones.
        free = cv2.erode(free, np.ones((2 * ey + 1, 2 * ex + 1), np.uint8))
    return free


def occupancy_map(
    density: np.ndarray,
    image_hw: tuple[int, int],
    params: OccupancyParams = OccupancyParams(),
) -> np.ndarray:
    """The paper's occupancy map at image size: uint8, ``FREE`` (255) or ``OCCUPIED`` (0).

    density: 2-D density map (any stride) of one frame.
    image_hw: (height, width) of the camera frame in pixels.
    """
    h, w = image_hw
    if h <= 0 or w <= 0:
        raise ValueError(f"image size must be positive, got {image_hw!r}")
    if np.asarray(density).size == 0:
        # No density at all is no evidence of free ground.
        return np.full((h, w), OCCUPIED, np.uint8)
    occ = occupied_mask(density, 0.0 if params.threshold is None else params.threshold)
    occ = drop_specks(occ, density, params.min_mass)
    return free_from_occupied(occ, image_hw, params)


def surface_free_map(
    unlandable: np.ndarray,
    image_hw: tuple[int, int],
    threshold: float,
    params: OccupancyParams = OccupancyParams(),
) -> np.ndarray:
    """The ground's free map at image size: uint8, ``OCCUPIED`` (0) where the landability model
    gives the unlandable levels a probability above ``threshold``, ``FREE`` (255) elsewhere.

    unlandable: 2-D map (any stride) of the probability that a cell's ground is unlandable.
    Unlike people, the probability is absolute (no ``- min``: a frame that is all water is all
    unlandable). Non-finite values and an empty map are unlandable; occupied cells grow on the
    way up as in :func:`occupancy_map` and are dilated by the same kernel, so the two maps are
    combined as equals (``numpy.minimum``).
    """
    h, w = image_hw
    if h <= 0 or w <= 0:
        raise ValueError(f"image size must be positive, got {image_hw!r}")
    p = np.asarray(unlandable, dtype=np.float32)
    if p.size == 0:
        return np.full((h, w), OCCUPIED, np.uint8)
    if p.ndim != 2:
        raise ValueError(f"unlandable map must be 2-D, got shape {p.shape}")
    occ = ~(np.isfinite(p) & (p <= threshold))
    return free_from_occupied(occ, image_hw, params)
