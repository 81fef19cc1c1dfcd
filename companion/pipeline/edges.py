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


def edge_reason(x: float, y: float, r: float, grid: GridSpec, free_grid: np.ndarray, seen: np.ndarray,
                people_free: np.ndarray | None = None, surface_free: np.ndarray | None = None) -> str:
    """``"people"``, ``"surface"`` or ``"view"`` for the zone of radius ``r`` metres at plane point
    (x, y): what the nearest non-free cell of ``free_grid`` (255 free; the grid the zone was made
    on) is.

    seen: 255 where the camera sees the cell on this frame. people_free, surface_free: this frame's
    grids of people alone and of the ground alone (0 where occupied / unlandable); None without a
    landability model (then every seen non-free cell is people). Among the cells at the nearest
    distance (half a cell of slack), people win over ground, and ground over the view: people are
    the first concern. A seen cell that neither grid occupies is held by the risk map (somebody
    stood there a moment ago): people.
    """
    rows, cols = free_grid.shape
    ci, cj = (y - grid.y0) / grid.cell, (x - grid.x0) / grid.cell
    # Out of the grid is out of view: how far the centre is from the grid's border (cells).
    to_border = min(ci + 0.5, rows - 0.5 - ci, cj + 0.5, cols - 0.5 - cj)
    reach = max(r / grid.cell, 0.0) + 3.0
    i0, i1 = max(0, int(math.floor(ci - reach))), min(rows, int(math.ceil(ci + reach)) + 1)
    j0, j1 = max(0, int(math.floor(cj - reach))), min(cols, int(math.ceil(cj + reach)) + 1)
    if i0 >= i1 or j0 >= j1:
        return VIEW
    window = free_grid[i0:i1, j0:j1] == 0
    if not window.any():
        return VIEW
    ii = np.arange(i0, i1, dtype=np.float64)[:, None] - ci
    jj = np.arange(j0, j1, dtype=np.float64)[None, :] - cj
    dist = np.where(window, np.hypot(ii, jj), np.inf)
    dmin = float(dist.min())
    if to_border + 0.5 < dmin:
        return VIEW
    near = (dist <= dmin + 0.5) & (seen[i0:i1, j0:j1] > 0)
    if not near.any():
        return VIEW
    ground = (np.zeros_like(near) if surface_free is None else surface_free[i0:i1, j0:j1] == 0) & near
    people = (near & ~ground) if people_free is None else (near & (people_free[i0:i1, j0:j1] == 0))
    if people.any():
        return PEOPLE
    if ground.any():
        return SURFACE
    return PEOPLE
