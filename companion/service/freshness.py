"""Whether a camera frame is fresh, or a frozen camera's: the camera source's freshness check.

A live sensor never gives two frames that are the same over large areas: read noise alone changes
nearly every pixel from one frame to the next, whatever the scene does. A frozen camera does, in
three ways seen in practice:

* it repeats its last buffer: the frame is bit-identical to the previous one (``"repeat"``);
* it cycles through two or a few buffers (a driver's ring, a double-buffered encoder): the frame is
  identical to one a few frames back (``"stale"``);
* it serves a frozen image with a live overlay drawn on it (a clock, an on-screen display): the
  frame is identical to a recent one but for a small region (``"stale"``).

:class:`Freshness` keeps the last :data:`HISTORY` fresh frames' signatures (a strided subsample
of at most :data:`SIGNATURE_SAMPLES`, ~57 kB at 640x480) and cuts each comparison into a
:data:`GRID` of cells: a frame in which at most :data:`MAX_CHANGED_CELLS` of the cells differ at
all (any sample, any channel, by any amount) from one of the history's is stale. Measured on the
simulator's rendered frames (read noise of 1.5 DN, JPEG quality 85; 2026-12-06, session 26): every
cell changes between two frames of a static scene, hovering at 25 m or on the ground at 0.3 m, and
97 % with a noise of 0.5 DN at JPEG quality 70; a frozen frame with a clock drawn on it changes
1.6 % of the cells. The comparison is exact on purpose: a tolerance of 2 DN left 8 % of the cells
changing between live frames on the ground at low noise, which a threshold could not tell from an
overlay.

What errs toward safety: a stale frame taken as live gives zones from the past, so anything a
live sensor would not give counts as stale: a camera without noise over a static scene with a
small moving object, or a heavily denoised stream of a scene that does not change, is refused and
the service reports the camera frozen (and hands back if the controller has the vehicle). A frozen
image that reaches the companion with fresh noise of its own (an analogue link after a frozen
digital source) changes everywhere and is not caught here.
"""

from __future__ import annotations

import hashlib
from collections import deque
from typing import Literal

import numpy as np

#: Rows and columns between the pixels hashed for the repeated-frame digest.
FINGERPRINT_STRIDE = 8
#: Fresh frames a new one is compared with (about a second at 8 frames/s).
HISTORY = 8
#: The largest signature (rows, columns): the frame is subsampled with the smallest strides that
#: fit it (4 x 4 at 640x480).
SIGNATURE_SAMPLES = (120, 160)
#: Cells (rows, columns) a comparison is cut into.
GRID = (12, 16)
#: A frame in which this fraction of the cells or less differs from a recent fresh one is stale.
MAX_CHANGED_CELLS = 0.25

Verdict = Literal["fresh", "repeat", "stale"]


def fingerprint(image: np.ndarray) -> bytes:
    """A 128-bit digest of a strided subsample of ``image`` (and its shape): equal for
    identical images; when it is equal, compare the pixels to be sure."""
    h = hashlib.blake2b(repr(image.shape).encode(), digest_size=16)
    sub = image[::FINGERPRINT_STRIDE, ::FINGERPRINT_STRIDE]
    h.update(np.ascontiguousarray(sub).data)
    return h.digest()


def signature(image: np.ndarray) -> np.ndarray:
    """The strided subsample of ``image`` that frames are compared by (a copy)."""
    rows, cols = SIGNATURE_SAMPLES
    sy = -(-image.shape[0] // rows)
    sx = -(-image.shape[1] // cols)
    return np.ascontiguousarray(image[::sy, ::sx])


def changed_cells(a: np.ndarray, b: np.ndarray) -> float:
    """The fraction of :data:`GRID` cells in which signatures ``a`` and ``b`` (same shape) differ
    in any sample and channel; 1.0 for different shapes."""
    if a.shape != b.shape:
        return 1.0
    h, w = a.shape[:2]
    channels = 1 if a.ndim == 2 else a.shape[2]
    # Channels side by side in each row: a cell's columns are its samples' channels, and the
    # comparison stays on a 2-D array (4x faster than reducing a 3-D one over its channels).
    diff = (a != b).reshape(h, w * channels)
    gh, gw = min(GRID[0], h), min(GRID[1], w)
    rows = (np.arange(gh) * h) // gh
    cols = ((np.arange(gw) * w) // gw) * channels
    cells = np.logical_or.reduceat(np.logical_or.reduceat(diff, rows, axis=0), cols, axis=1)
    return float(cells.mean())


class Freshness:
    """The freshness verdict of each frame against the previous fresh one and the last
    ``history`` fresh ones (see the module docstring). Only fresh frames are remembered, so a
    camera that freezes is compared with its last live frames and its first frozen one."""

    def __init__(self, history: int = HISTORY) -> None:
        self._prev_key: bytes | None = None
        self._prev_image: np.ndarray | None = None
        self._signatures: deque[np.ndarray] = deque(maxlen=history)

    def judge(self, image: np.ndarray) -> Verdict:
        """``"repeat"``: identical to the previous fresh frame; ``"stale"``: the same as a recent
        fresh frame but for a small region; ``"fresh"`` otherwise (and then remembered)."""
        key = fingerprint(image)
        prev = self._prev_image
        if key == self._prev_key and prev is not None and np.array_equal(image, prev):
            return "repeat"
        sig = signature(image)
        if any(changed_cells(sig, old) <= MAX_CHANGED_CELLS for old in self._signatures):
            return "stale"
        self._prev_key, self._prev_image = key, image
        self._signatures.append(sig)
        return "fresh"
