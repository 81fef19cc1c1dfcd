"""Why a landing zone's edge is where it is: people, unlandable ground, or the end of the view.

A zone's radius is its distance to the nearest non-free cell of the grid it was made on. That
cell says why: it is occupied by people (the density model, or the risk map holding where they
were), by ground the landability model calls unlandable, or it is ground the camera does not see
(outside the view, or outside the grid). Pure numpy on the head-plane grid of
:mod:`companion.pipeline.headplane`.
"""

from __future__ import annotations

import math

import numpy as np

from companion.pipeline.headplane import GridSpec

PEOPLE = "people"
SURFACE = "surface"
VIEW = "view"
EDGES = (PEOPLE, SURFACE, VIEW)


def edge_reason(x: float, y: float, grid: GridSpec, dist: np.ndarray, free_grid: np.ndarray, seen: np.ndarray,
                people_free: np.ndarray | None = None, surface_free: np.ndarray | None = None) -> str:
    """``"people"``, ``"surface"`` or ``"view"`` for the zone centred at plane point (x, y): what
    the nearest non-free cells of ``free_grid`` (255 free; the grid the zone was made on) are.

    dist: ``proposals.distance_cells(free_grid)``, which already knows how far the nearest
    non-free cell is (d cells); only the ring of cells at that distance (to 0.7 cell beyond) is
    looked at, so the cost grows with the zone's perimeter, not its area. seen: 255 where the
    camera sees the cell on this frame. people_free, surface_free: this frame's grids of people
    alone and of the ground alone (0 where occupied / unlandable); None without a landability
    model (then every seen non-free cell is people). Out of the grid, or not seen, is the view.
    Among the ring's cells people win over ground, and ground over the view: people are the
    first concern. A seen cell that neither grid occupies is held by the risk map (somebody stood
    there a moment ago): people.
    """
    rows, cols = free_grid.shape
    i, j = grid.cell_of(x, y)
    if not (0 <= i < rows and 0 <= j < cols):
        return VIEW
    d = float(dist[i, j])
    if d <= 0.0:
        ii, jj = np.array([i]), np.array([j])
    else:
        n = max(16, int(math.ceil(2.0 * math.pi * (d + 0.7) / 0.7)))  # 0.7 cell apart: no cell skipped
        a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
        rr = np.array([d, d + 0.7])[:, None]
        ii = np.rint(i + rr * np.sin(a)).astype(np.int64).ravel()
        jj = np.rint(j + rr * np.cos(a)).astype(np.int64).ravel()
    inside = (ii >= 0) & (ii < rows) & (jj >= 0) & (jj < cols)
    ii, jj = ii[inside], jj[inside]
    ring = (free_grid[ii, jj] == 0) & (seen[ii, jj] > 0)
    if not ring.any():
        return VIEW
    ii, jj = ii[ring], jj[ring]
    ground = np.zeros(len(ii), bool) if surface_free is None else surface_free[ii, jj] == 0
    people = ~ground if people_free is None else people_free[ii, jj] == 0
    if people.any():
        return PEOPLE
    if ground.any():
        return SURFACE
    return PEOPLE
