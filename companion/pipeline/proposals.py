"""Step 4 of the pipeline: landing-zone proposals, the largest free circles on the head plane.

The distance transform of the free grid gives, at each free cell, the distance to the nearest
occupied or unknown cell; its maximum is the centre and radius of the largest free circle. That
circle is then marked occupied and the next one sought, until ``n_max`` circles or a radius below
``r_min`` metres. Marking a disk occupied only lowers distances near it, so the distances are
updated in a window around the disk instead of recomputing the transform.

Near-ties go to the point nearest a preferred point (the ground under the camera): the maximum of a
distance transform is often a ridge or a plateau (a corridor between people; over empty ground the
whole mid-line of the view's footprint), and a plain argmax picks its first cell, which jumps from
one end of the ridge to the other as the footprint moves. Such a proposal leaves its track behind
(the tracker matches on overlap) and the zone is lost while the ground under it is still free.
Giving up at most ``tie_m`` of radius for the circle nearest the camera keeps proposals where the
vehicle already is; the radius is still the one measured at the chosen centre.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from companion.pipeline.circles import Circle
from companion.pipeline.headplane import GridSpec

# A cell is a square: a circle centred at a cell centre that keeps this far (in cells) short of
# the nearest occupied cell *centre* cannot touch that cell's square anywhere.
_HALF_DIAGONAL = math.sqrt(2.0) / 2.0 + 1e-3  # + float32 rounding of the transform
#: Radius (m) a proposal may give up to sit nearer the preferred point (see the module docstring):
#: small against r_0, larger than the ripples the view's edge and the sampling leave on a ridge.
TIE_M = 0.3


def distance_cells(free_grid: np.ndarray) -> np.ndarray:
    """Euclidean distance (in cells) from each cell centre to the nearest non-free cell centre.

    Everything outside the grid counts as non-free, so circles stay inside the grid.
    """
    if free_grid.ndim != 2:
        raise ValueError(f"free grid must be 2-D, got shape {free_grid.shape}")
    # The transform reads any non-zero uint8 as free: a uint8 grid needs no 0/1 copy first.
    free = free_grid if free_grid.dtype == np.uint8 else (free_grid > 0).astype(np.uint8)
    padded = cv2.copyMakeBorder(free, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return dist[1:-1, 1:-1]


class PointDistance:
    """``distance_cells(free_grid)`` read at a few cells, without the whole transform.

    The nearest non-free cell to a free cell always has a free 4-neighbour (a non-free cell one
    step nearer would be nearer still), so only those border cells need to be measured: a view's
    footprint is a few hundred of them against tens of thousands of cells, and a frame asks for
    a handful of points. The same values as the transform (exact Euclidean, float32), with
    everything outside the grid non-free. Indexed like the array: ``d[i, j]``."""

    def __init__(self, free_grid: np.ndarray) -> None:
        if free_grid.ndim != 2:
            raise ValueError(f"free grid must be 2-D, got shape {free_grid.shape}")
        free = free_grid if free_grid.dtype == np.uint8 else (free_grid > 0).astype(np.uint8)
        padded = cv2.copyMakeBorder(free, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
        cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
        # Dilating can only raise a cell: the difference is > 0 exactly on the border cells.
        border = cv2.subtract(cv2.dilate(padded, cross, borderType=cv2.BORDER_CONSTANT, borderValue=0), padded)
        at = cv2.findNonZero(border)
        at = np.zeros((0, 2)) if at is None else np.asarray(at).reshape(-1, 2)  # (x, y) = (j, i)
        bj, bi = at[:, 0], at[:, 1]
        self._free = padded
        self._bi = (bi - 1).astype(np.float32)
        self._bj = (bj - 1).astype(np.float32)
        self.shape: tuple[int, int] = (int(free_grid.shape[0]), int(free_grid.shape[1]))

    def __getitem__(self, ij: tuple[int, int]) -> float:
        i, j = ij
        if not self._free[i + 1, j + 1] or not len(self._bi):
            return 0.0
        di, dj = self._bi - np.float32(i), self._bj - np.float32(j)
        return float(np.sqrt(np.min(di * di + dj * dj)))


def landing_points(surface_grid: np.ndarray, cell: float, footprint_m: float) -> np.ndarray:
    """bool grid of the cells the vehicle may touch down on: centres whose disc of ``footprint_m``
    (m, the vehicle's radius) touches no non-free cell of ``surface_grid`` (the landability
    model's free grid, ``headplane.sample_to_grid``), measured as ``clearance_at`` measures a
    zone's radius. Outside the grid counts as non-free. ``cell``: the grid's cell (m)."""
    if not (math.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be > 0 m, got {cell!r}")
    if not (math.isfinite(footprint_m) and footprint_m >= 0):
        raise ValueError(f"footprint must be >= 0 m, got {footprint_m!r}")
    # A non-free cell's distance is 0, so the rule alone keeps it out, footprint 0 included.
    return (distance_cells(surface_grid) - _HALF_DIAGONAL) * cell >= footprint_m


def clearance_at(dist: np.ndarray | PointDistance, grid: GridSpec, x: float, y: float) -> float:
    """Radius in metres of the largest circle centred at plane point (x, y) that touches no
    non-free cell, from the distance map of ``distance_cells``; 0 outside the grid.
    (Given the distance map of the *seen* grid instead, it is how far the view reaches.)"""
    i, j = grid.cell_of(x, y)
    if not (0 <= i < dist.shape[0] and 0 <= j < dist.shape[1]):
        return 0.0
    # (x, y) is not exactly the cell centre the distance was measured from: pay the offset.
    off = math.hypot(x - (grid.x0 + j * grid.cell), y - (grid.y0 + i * grid.cell))
    return max(0.0, (float(dist[i, j]) - _HALF_DIAGONAL) * grid.cell - off)


def propose(free_grid: np.ndarray, grid: GridSpec, n_max: int, r_min: float,
            dist: np.ndarray | None = None, prefer: tuple[float, float] | None = None,
            tie_m: float = TIE_M, centres: np.ndarray | None = None) -> list[Circle]:
    """Up to ``n_max`` disjoint free circles, largest first, each with radius >= ``r_min`` metres.

    free_grid: uint8 grid, > 0 where free (see ``headplane.sample_to_grid``).
    dist: its ``distance_cells`` if already computed (it is not modified).
    prefer: a plane point (m; the ground under the camera): of the centres whose circle is within
    ``tie_m`` metres of the largest, the one nearest it is taken. None: the first largest.
    centres: bool grid of the cells a circle may be centred on (``landing_points``: where the
    vehicle may touch down), None: any. The radius is still the free grid's at that centre: the
    largest circle centred on an allowed cell, not the largest circle of the allowed cells.
    Each circle touches no non-free cell (not even a corner of one).
    """
    if free_grid.shape != grid.shape:
        raise ValueError(f"free grid shape {free_grid.shape} does not match grid {grid.shape}")
    if centres is not None and centres.shape != grid.shape:
        raise ValueError(f"centres shape {centres.shape} does not match grid {grid.shape}")
    out: list[Circle] = []
    if n_max <= 0 or free_grid.size == 0:
        return out
    dist = distance_cells(free_grid) if dist is None else dist.copy()
    if centres is not None:
        # Only allowed cells are read (a centre and its radius): 0 elsewhere is never a centre,
        # and the minimum below keeps it 0.
        dist = np.where(centres, dist, np.float32(0.0))
    rows, cols = dist.shape
    pref = None
    if prefer is not None and all(math.isfinite(v) for v in prefer):
        # In cells, as (row, col): prefer's x is along columns, y along rows.
        pref = ((prefer[1] - grid.y0) / grid.cell, (prefer[0] - grid.x0) / grid.cell)
    tie = max(0.0, tie_m) / grid.cell
    for _ in range(n_max):
        flat = int(np.argmax(dist))
        i, j = divmod(flat, cols)
        d = d_max = float(dist[i, j])
        if pref is not None and tie > 0 and (d - _HALF_DIAGONAL) * grid.cell >= r_min:
            # Never below r_min for a nearer centre: the largest circle would have qualified.
            near = np.flatnonzero(dist >= max(d - tie, r_min / grid.cell + _HALF_DIAGONAL))
            if len(near) > 1:
                ni, nj = np.divmod(near, cols)
                k = int(np.argmin((ni - pref[0]) ** 2 + (nj - pref[1]) ** 2))
                i, j = int(ni[k]), int(nj[k])
                d = float(dist[i, j])
        r_cells = d - _HALF_DIAGONAL
        if r_cells <= 0 or r_cells * grid.cell < r_min:
            break
        x, y = grid.to_plane(i, j)
        out.append(Circle(float(x), float(y), r_cells * grid.cell))
        # Only cells closer to the disk than their present distance change: no cell is further
        # than d_max from its nearest non-free cell, so only those within d_max + r of it.
        reach = int(math.ceil(r_cells + d_max)) + 1
        i0, i1 = max(0, i - reach), min(rows, i + reach + 1)
        j0, j1 = max(0, j - reach), min(cols, j + reach + 1)
        ii = np.arange(i0, i1, dtype=np.float32)[:, None] - i
        jj = np.arange(j0, j1, dtype=np.float32)[None, :] - j
        to_disk = np.sqrt(ii * ii + jj * jj) - np.float32(r_cells)
        np.maximum(to_disk, 0.0, out=to_disk)
        window = dist[i0:i1, j0:j1]
        np.minimum(window, to_disk, out=window)
    return out
