"""The ground risk map: where people were seen, in the world, over time (issue 11, items 1 and 2).

Every frame's head-plane grid is written into one grid fixed to the world (local NED metres from
home; rows follow plane y = east, columns plane x = north, as in ``headplane``), so evidence
outlives the frame it came from. Per cell the map keeps

- ``last_seen``: when the camera last saw the cell (free or occupied), and
- ``last_occ``: when it last saw it occupied,

in seconds on the capture-time clock. From these, for a frame:

- **unknown**: a cell never seen, or not seen for longer than ``memory_s``, is unknown and never
  free (``known_free`` answers for ground outside the current view).
- **calm** at a point, ``calm_s``: how long the camera has watched every cell within a radius
  without a break of more than ``watch_gap_s`` and seen nobody there. A gap in a walking crowd is
  free on the frame it opens; a lawn nobody walks into stays calm for as long as it is watched.
  Only ground watched now counts (a cell out of view may have been walked over unseen): calm is 0
  where any cell of the disc is not in view. Per cell the map keeps ``seen_since``, when its
  present unbroken watch began.
- **unwalked** at a point, ``unwalked_s``: how long nobody has been seen within a radius since
  the camera first saw all of it, breaks in the watch included (per cell ``first_seen``). Unlike
  calm it survives the vehicle looking away, down low or climbing back, so after a lost zone it
  still tells the lawn that nobody entered since the trigger from the gap walkers crossed 10 s
  ago. It is no proof that nobody came while the camera looked away: it ranks zones
  (the planner's ``prefer_unwalked``), calm still judges the one under the vehicle.

Walking speed: 1.5 m/s by default, above the 1.34 m/s mean free walking speed of pedestrians
(Weidmann, "Transporttechnik der Fussgaenger", ETH Zurich, 1993), so that brisk walkers are
covered; faster movers (runners, cyclists) need a higher setting.

Memory and cost are bounded: the map is a square of ``2 * half_extent_m`` metres at the pipeline's
cell size around the vehicle, recentred (shifting what stays in it) when a frame's grid would
leave it. An update touches only the frame grid's cells. Pure numpy/OpenCV, no I/O.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.geometry.camera import GeometryError
from companion.invariant import require
from companion.pipeline.headplane import GridSpec

NEVER = -np.inf
#: At most this many cells from the centre to an edge: 2,049 cells a side, 32 MiB of float32 times.
MAX_HALF_CELLS = 1024


class RiskMapError(GeometryError):
    """A frame the map cannot take (a non-finite time, time going back, a grid of another cell
    size, or a pose jump); the frame is dropped and counted, the map stays as it was."""


@dataclass(frozen=True)
class RiskMapConfig:
    """cell_m: side of a map cell (m), equal to the pipeline's grid cell. half_extent_m: the map
    covers this far (m) each way around its centre. walk_speed_mps: how fast a person may walk
    (m/s). hold_s: how long a cell seen occupied stays occupied although the camera now sees it
    free (s; covers the network missing a person for that long). memory_s: ground not seen for
    longer than this is unknown again (s). max_jump_m: a frame whose grid moved further than this
    from the previous one within ``max_jump_s`` is a pose jump, not flight (dropped)."""

    cell_m: float = 0.1
    half_extent_m: float = 60.0
    walk_speed_mps: float = 1.5
    hold_s: float = 1.0
    memory_s: float = 10.0
    max_jump_m: float = 15.0
    max_jump_s: float = 0.5
    #: A cell not seen for longer than this (s) starts a new watch: its calm starts again at 0.
    watch_gap_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("cell_m", "half_extent_m", "walk_speed_mps", "memory_s", "max_jump_m", "max_jump_s",
                     "watch_gap_s"):
            v = getattr(self, name)
            require(math.isfinite(v) and v > 0, "risk map", name, "must be > 0", v)
        if not (math.isfinite(self.hold_s) and 0 <= self.hold_s <= self.memory_s):
            raise ValueError(f"risk map hold_s must be in [0, memory_s], got {self.hold_s!r}")
        if self.half_extent_m / self.cell_m > MAX_HALF_CELLS:
            raise ValueError(f"risk map of {self.half_extent_m} m at {self.cell_m} m cells is too large "
                             f"(more than {2 * MAX_HALF_CELLS + 1} cells a side)")


@dataclass(frozen=True)
class Spot:
    """A landing point placed on the map (``GroundRiskMap.farthest_from_walkers``): plane point
    (x, y) (m; world north/east), its distance to the nearest ground people were seen on lately
    (m, capped at the reach asked for), and the same distance at the point it may replace (m;
    NaN when not measured)."""

    x: float
    y: float
    clear_m: float
    aim_clear_m: float = math.nan


@dataclass(frozen=True)
class SpotRequest:
    """Where a landing point may go (the controller asks, the frame's ``slz.GroundView.spot`` answers):
    within ``radius_m`` of plane point (x, y) (m; world north/east), away from the ground people
    were seen on within ``lookback_s`` (s); ``aim`` the present landing point, or None."""

    x: float
    y: float
    radius_m: float
    lookback_s: float
    aim: tuple[float, float] | None = None


@dataclass
class RiskMapStats:
    """Counters since start: frames fused, recentrings, frames dropped (``RiskMapError``), and
    frames whose grid reached past the map and was clipped to it."""

    updates: int = 0
    recentred: int = 0
    dropped: int = 0
    clipped: int = 0


@dataclass
class _Window:
    """The part of a frame grid that lies in the map: slices into both."""

    map_rows: slice
    map_cols: slice
    grid_rows: slice
    grid_cols: slice

    def covers(self, grid: GridSpec) -> bool:
        """The whole grid lies in the map (nothing was clipped)."""
        return (self.grid_rows.stop - self.grid_rows.start, self.grid_cols.stop - self.grid_cols.start) == grid.shape


class GroundRiskMap:
    """See the module docstring. ``update`` a frame, then ask it (``calm_s``, ``unwalked_s``, ``farthest_from_walkers``, ...)."""

    def __init__(self, config: RiskMapConfig | None = None) -> None:
        self.config = config or RiskMapConfig()
        n = 2 * int(math.ceil(self.config.half_extent_m / self.config.cell_m)) + 1
        self.size = n
        # Times are float32 seconds since the first frame (``epoch``): a millisecond's resolution
        # for hours, half the memory of float64 (a 1,201-cell square is 11 MiB for both).
        self.last_seen = np.full((n, n), NEVER, np.float32)
        self.last_occ = np.full((n, n), NEVER, np.float32)
        self.seen_since = np.full((n, n), NEVER, np.float32)
        self.first_seen = np.full((n, n), NEVER, np.float32)
        self.epoch: float | None = None
        self._origin: tuple[int, int] | None = None  # world cell (row, col) of array [0, 0]
        self._last: tuple[float, float, float] | None = None  # (t, x, y) of the previous grid centre
        self.stats = RiskMapStats()
        self.t: float | None = None  # capture time of the newest frame taken

    # -- geometry ----------------------------------------------------------------------------

    def _grid_cell0(self, grid: GridSpec) -> tuple[int, int]:
        """World cell (row, col) of the grid's cell [0, 0]; grids are snapped to whole cells."""
        c = self.config.cell_m
        if abs(grid.cell - c) > 1e-9:
            raise RiskMapError(f"grid cell {grid.cell} m is not the map's {c} m")
        return int(round(grid.y0 / c)), int(round(grid.x0 / c))

    def _recentre(self, row: int, col: int) -> None:
        """Put world cell (row, col) at the middle of the arrays, keeping what stays inside."""
        half = self.size // 2
        new = (row - half, col - half)
        if self._origin is not None:
            dr, dc = new[0] - self._origin[0], new[1] - self._origin[1]
            for a in (self.last_seen, self.last_occ, self.seen_since, self.first_seen):
                shifted = np.full_like(a, NEVER)
                n = self.size
                src_r = slice(max(0, dr), min(n, n + dr))
                dst_r = slice(max(0, -dr), min(n, n - dr))
                src_c = slice(max(0, dc), min(n, n + dc))
                dst_c = slice(max(0, -dc), min(n, n - dc))
                if src_r.start < src_r.stop and src_c.start < src_c.stop:
                    shifted[dst_r, dst_c] = a[src_r, src_c]
                a[...] = shifted
            self.stats.recentred += 1
        self._origin = new

    def _window(self, grid: GridSpec) -> _Window | None:
        """Where ``grid`` lies in the arrays (clipped to them), or None when it misses them or
        the map has no frame yet."""
        if self._origin is None:
            return None
        r0, c0 = self._grid_cell0(grid)
        mr0, mc0 = r0 - self._origin[0], c0 - self._origin[1]
        n = self.size
        rr0, rr1 = max(0, mr0), min(n, mr0 + grid.rows)
        cc0, cc1 = max(0, mc0), min(n, mc0 + grid.cols)
        if rr0 >= rr1 or cc0 >= cc1:
            return None
        return _Window(slice(rr0, rr1), slice(cc0, cc1),
                       slice(rr0 - mr0, rr1 - mr0), slice(cc0 - mc0, cc1 - mc0))

    # -- input -------------------------------------------------------------------------------

    def update(self, grid: GridSpec, free_grid: np.ndarray, seen_grid: np.ndarray, t: float,
               camera_xy: tuple[float, float] | None = None) -> None:
        """Take one frame's head-plane grids (uint8: ``free_grid`` > 0 free, ``seen_grid`` > 0 seen)
        captured at ``t`` seconds from a camera above plane point ``camera_xy`` (m; the grid's
        centre when not given). Raises ``RiskMapError`` (and counts it) for a frame it must not
        take; the map is then unchanged."""
        if camera_xy is None:
            camera_xy = (grid.x0 + grid.cell * (grid.cols - 1) / 2, grid.y0 + grid.cell * (grid.rows - 1) / 2)
        cx, cy = float(camera_xy[0]), float(camera_xy[1])
        try:
            self._check(grid, free_grid, seen_grid, t, cx, cy)
        except RiskMapError:
            self.stats.dropped += 1
            raise
        w = self._window(grid)
        if w is None or not w.covers(grid):
            r0, c0 = self._grid_cell0(grid)
            self._recentre(r0 + grid.rows // 2, c0 + grid.cols // 2)
            w = self._window(grid)
            if w is None or not w.covers(grid):
                self.stats.clipped += 1  # a grid larger than the map: the part outside is not kept
        if self.epoch is None:
            self.epoch = t
        if w is not None:
            seen = seen_grid[w.grid_rows, w.grid_cols] > 0
            occupied = free_grid[w.grid_rows, w.grid_cols] == 0
            occupied &= seen
            rel = np.float32(t - self.epoch)
            last_seen = self.last_seen[w.map_rows, w.map_cols]
            # A cell seen now after a break longer than watch_gap_s starts a new watch.
            restart = seen & (last_seen < rel - np.float32(self.config.watch_gap_s))
            # copyto with a mask writes in place without building index arrays (the hot path).
            np.copyto(self.seen_since[w.map_rows, w.map_cols], rel, where=restart)
            np.copyto(self.first_seen[w.map_rows, w.map_cols], rel, where=seen & (last_seen == NEVER))
            np.copyto(last_seen, rel, where=seen)
            np.copyto(self.last_occ[w.map_rows, w.map_cols], rel, where=occupied)
        self._last = (t, cx, cy)
        self.t = t
        self.stats.updates += 1

    def _check(self, grid: GridSpec, free_grid: np.ndarray, seen_grid: np.ndarray, t: float,
               cx: float, cy: float) -> None:
        if not math.isfinite(t):
            raise RiskMapError(f"frame time {t!r} is not finite")
        if self.t is not None and t < self.t:
            raise RiskMapError(f"frame time {t:.3f} s is before the map's newest {self.t:.3f} s")
        if free_grid.shape != grid.shape or seen_grid.shape != grid.shape:
            raise RiskMapError(f"grids of shape {free_grid.shape}/{seen_grid.shape} for a {grid.shape} grid")
        if not all(math.isfinite(v) for v in (grid.x0, grid.y0, cx, cy)):
            raise RiskMapError("grid or camera position is not finite")
        self._grid_cell0(grid)
        if self._last is not None:
            t1, x1, y1 = self._last
            jump = math.hypot(cx - x1, cy - y1)
            if t - t1 <= self.config.max_jump_s and jump > self.config.max_jump_m:
                raise RiskMapError(f"the camera moved {jump:.1f} m in {t - t1:.2f} s: a pose jump, not flight")

    # -- output ------------------------------------------------------------------------------

    def _rel(self, t: float) -> float:
        """``t`` in the arrays' time base (seconds since the first frame)."""
        return t - (self.epoch if self.epoch is not None else t)

    def known_free(self, grid: GridSpec, t: float) -> np.ndarray:
        """uint8 over ``grid``: 255 where the map's last look at the ground, within ``memory_s``,
        saw it free and nobody stood there within ``hold_s``; else 0 (unknown or occupied). For
        ground outside the current view."""
        out = np.zeros(grid.shape, np.uint8)
        w = self._window(grid)
        if w is None:
            return out
        seen = self.last_seen[w.map_rows, w.map_cols]
        occ = self.last_occ[w.map_rows, w.map_cols]
        now = self._rel(t)
        free = self._looked_free(seen >= now - self.config.memory_s, seen, occ, now)
        out[w.grid_rows, w.grid_cols] = np.where(free, 255, 0)
        return out

    def _looked_free(self, recent: np.ndarray, seen: np.ndarray, occ: np.ndarray, now: float) -> np.ndarray:
        """Of the cells ``recent`` marks (seen lately enough for the caller), those whose last
        look saw them free (a look that saw a cell occupied stamped ``last_occ == last_seen``) and
        that nobody stood on within ``hold_s``: ``seen``/``occ`` are the same cells' times."""
        return recent & (occ < seen) & (occ < now - self.config.hold_s)

    def calm_s(self, x: float, y: float, radius_m: float, t: float) -> float:
        """How long (s, at time ``t``) every cell within ``radius_m`` of plane point (x, y) has
        been watched without a break of more than ``watch_gap_s`` and seen free: the time since the
        latest of those watches began or anybody was last seen there. 0 where any cell of the
        disc is not watched now (out of view, outside the map, never seen), or on a map with no
        frame; never more than the time since the map's first frame."""
        found = self._disc_at(x, y, radius_m, t)
        # None: no frame yet, not finite, or part of the disc outside the map: not watched.
        return 0.0 if found is None else self._calm_in(*found, self._rel(t))

    def _calm_in(self, rows: slice, cols: slice, disc: np.ndarray, now: float) -> float:
        """``calm_s`` of the disc ``_disc_at`` found, at ``now`` in the arrays' time base."""
        if _extremes(self.last_seen[rows, cols], disc)[0] < np.float32(now - self.config.watch_gap_s):
            return 0.0
        start = max(_extremes(self.last_occ[rows, cols], disc)[1], _extremes(self.seen_since[rows, cols], disc)[1])
        return max(0.0, now - start)

    def unwalked_s(self, x: float, y: float, radius_m: float, t: float) -> float:
        """How long (s, at time ``t``) nobody has been seen within ``radius_m`` of plane point (x,
        y) since the camera first saw every cell of that disc: the time since the latest of those
        first looks or of anybody seen there, whatever the camera looked at meanwhile. 0 where any
        cell of the disc was never seen or lies outside the map, or on a map with no frame."""
        found = self._disc_at(x, y, radius_m, t)
        return 0.0 if found is None else self._unwalked_in(*found, self._rel(t))

    def _unwalked_in(self, rows: slice, cols: slice, disc: np.ndarray, now: float) -> float:
        """``unwalked_s`` of the disc ``_disc_at`` found, at ``now`` in the arrays' time base."""
        first_min, first_max = _extremes(self.first_seen[rows, cols], disc)
        if first_min == NEVER:
            return 0.0
        start = max(first_max, _extremes(self.last_occ[rows, cols], disc)[1])
        return max(0.0, now - start)

    def calm_and_unwalked_s(self, x: float, y: float, radius_m: float, t: float) -> tuple[float, float]:
        """``(calm_s(...), unwalked_s(...))`` of one disc, found on the map once for both (the
        pipeline asks both for every confirmed zone, every frame)."""
        found = self._disc_at(x, y, radius_m, t)
        if found is None:
            return 0.0, 0.0
        now = self._rel(t)
        return self._calm_in(*found, now), self._unwalked_in(*found, now)

    def farthest_from_walkers(self, x: float, y: float, radius_m: float, t: float, lookback_s: float,
                              reach_m: float, aim: tuple[float, float] | None = None,
                              factor: int = 3) -> Spot | None:
        """The point within ``radius_m`` of plane point (x, y) farthest from every cell seen
        occupied within ``lookback_s`` of ``t`` (where people stood or walked lately), and that
        distance (m, at most ``reach_m``); also the same distance at ``aim`` (NaN when ``aim`` is
        None or off the window). Where to land inside a zone: a zone's centre is the point
        farthest from the people of *one* frame, and a circle that spans a lawn and an empty gap
        of the crowd beside it has its centre at the lawn's edge, where walkers go round
        (docs/design.md, "Five unsafe landings, one cause"); the map remembers where they went.

        Ties (within one coarse cell) go to the point nearest ``aim`` (else nearest (x, y)), so
        that the answer stays put while the evidence does. Cells are coarsened ``factor`` times
        (a coarse cell is occupied when any of its cells is: coarsening never frees ground).
        Distances are to a cell's nearest side, so a person on a coarse cell's corner is not
        farther than measured. None on a map with no frame, for a non-finite argument, or where
        the window would reach past the map. Cost: one block reduction and one distance transform
        over ``2 * (radius_m + reach_m)`` metres square (about 0.5 ms for 3 m and 8 m)."""
        if self._origin is None or self.t is None or \
                not all(math.isfinite(v) for v in (x, y, radius_m, t, lookback_s, reach_m)):
            return None
        if radius_m < 0 or reach_m <= 0 or lookback_s < 0 or factor < 1:
            raise ValueError(f"farthest_from_walkers needs radius_m >= 0, reach_m > 0, lookback_s >= 0 and "
                             f"factor >= 1, got {radius_m!r}, {reach_m!r}, {lookback_s!r}, {factor!r}")
        c = self.config.cell_m
        big = factor * c
        k = int(math.ceil((radius_m + reach_m) / big)) + 1  # coarse cells from the middle to an edge
        row = int(round(y / c)) - self._origin[0]
        col = int(round(x / c)) - self._origin[1]
        half = k * factor + factor // 2
        r0, c0 = row - half, col - half
        n = (2 * k + 1) * factor
        if r0 < 0 or c0 < 0 or r0 + n > self.size or c0 + n > self.size:
            return None
        since = np.float32(self._rel(t) - lookback_s)
        # Ground not looked at within the lookback may have had anybody on it: as if seen occupied
        # (else a point beside the edge of the view looks far from everybody).
        fine = ((self.last_occ[r0:r0 + n, c0:c0 + n] >= since)
                | (self.last_seen[r0:r0 + n, c0:c0 + n] < since)).view(np.uint8) * np.uint8(255)
        # Area averaging over whole blocks is > 0 exactly where any cell of a block is occupied.
        m = 2 * k + 1
        recent = (cv2.resize(fine, (m, m), interpolation=cv2.INTER_AREA) if factor > 1 else fine) > 0
        # Coarse cell centres on the plane (m): rows are y (east), columns x (north).
        ys = (r0 + self._origin[0] + (factor - 1) / 2 + np.arange(m) * factor) * c
        xs = (c0 + self._origin[1] + (factor - 1) / 2 + np.arange(m) * factor) * c
        if recent.any():
            free = np.where(recent, np.uint8(0), np.uint8(1))
            dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float64)
            dist = np.minimum(dist * big - big * math.sqrt(0.5), reach_m)
            dist[recent] = 0.0
        else:
            dist = np.full(recent.shape, reach_m)
        within = np.hypot(xs[None, :] - x, ys[:, None] - y) <= radius_m
        within[k, k] = True  # the coarse cell of (x, y) itself, whose centre is (x, y) to a fine cell
        best = float(np.max(dist[within]))
        ax, ay = aim if aim is not None else (x, y)
        ties = within & (dist >= best - big)
        near = np.where(ties, np.hypot(xs[None, :] - ax, ys[:, None] - ay), np.inf)
        i, j = np.unravel_index(int(np.argmin(near)), near.shape)
        aim_clear = math.nan
        if aim is not None and all(math.isfinite(v) for v in aim):
            ai, aj = int(round((aim[1] - ys[0]) / big)), int(round((aim[0] - xs[0]) / big))
            if 0 <= ai < dist.shape[0] and 0 <= aj < dist.shape[1]:
                aim_clear = float(dist[ai, aj])
        return Spot(float(xs[j]), float(ys[i]), float(dist[i, j]), aim_clear)

    def _disc_at(self, x: float, y: float, radius_m: float, t: float) -> tuple[slice, slice, np.ndarray] | None:
        """The map's window around plane point (x, y) and the mask of its cells within
        ``radius_m`` (``_disc``): what ``calm_s`` and ``unwalked_s`` read. None on a map with no
        frame, for a non-finite point, radius or time, or when part of the disc lies outside
        the map."""
        if self._origin is None or self.t is None or not all(math.isfinite(v) for v in (x, y, radius_m, t)):
            return None
        c = self.config.cell_m
        row = int(round(y / c)) - self._origin[0]
        col = int(round(x / c)) - self._origin[1]
        k = int(math.ceil(max(radius_m, 0.0) / c))
        if row - k < 0 or col - k < 0 or row + k >= self.size or col + k >= self.size:
            return None
        return slice(row - k, row + k + 1), slice(col - k, col + k + 1), _disc(k, radius_m, c)


@functools.lru_cache(maxsize=8)
def _disc(k: int, radius_m: float, cell_m: float) -> np.ndarray:
    """(2k+1, 2k+1) uint8, 1 on the cells whose square reaches within ``radius_m`` of the middle
    cell's centre (centre within the radius plus half a diagonal), else 0: OpenCV's mask as it is,
    a boolean index as ``disc.view(np.bool_)``. Cached: a pipeline asks for one radius every
    frame, for each zone. Read-only."""
    off = np.arange(-k, k + 1) * cell_m
    disc: np.ndarray = (np.hypot(off[:, None], off[None, :]) <= radius_m + cell_m * math.sqrt(0.5)).astype(np.uint8)
    disc.flags.writeable = False
    return disc


def _extremes(window: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(min, max) of the float32 ``window``'s cells under ``mask``, exactly as ``np.min`` and
    ``np.max`` of ``window[mask > 0]`` (NEVER included), without gathering them into a copy:
    the calm and unwalked measures read five discs per zone per frame, and the copies cost
    three times the reads (``companion bench``'s tracking stage)."""
    low, high, _, _ = cv2.minMaxLoc(window, mask)
    return float(low), float(high)

