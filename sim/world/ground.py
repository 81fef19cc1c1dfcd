"""Procedural ground texture for the simulated camera: grass, paving, roads, paths, clutter.

Everything is generated from a seed (no image files, nothing from the licensed data sets), in world
NED metres on the ground plane ``z = 0``. The ground is endless and made lazily: square tiles of
``tile_px`` pixels at resolution ``base_res * 2**level`` metres per pixel are drawn on demand and
cached, so a render at 60 m reads coarse tiles and one at 10 m fine ones, and memory stays at a
few tens of MB. A tile is generated the first time it is needed (tens of ms each; the first
frame at a new altitude or place can take a few hundred ms).

Layout: a grid of ``BLOCK`` metre blocks. Every fourth row/column of blocks has a road along its
edge (asphalt, dashed centre line, parked cars); a block is lawn (mowing stripes, footpaths,
trees, benches), paving (slabs), gravel, or carries a flat-roofed building with roof units. The
clutter is there on purpose: static things that a density model must NOT take for people.

Mosaic convention used by :meth:`ProceduralGround.view`: mosaic pixel ``(col, row)`` =
``((east - e0) / res, (north - n0) / res)``, i.e. rows grow northward.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

BLOCK = 32.0  # metres; the layout cell
ROAD_W = 7.0  # metres
SHIFT = 3  # fixed-point bits for sub-pixel drawing
_MASK64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _hash01(seed: int, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice points (splitmix64)."""
    with np.errstate(over="ignore"):
        x = (np.asarray(ix, np.int64).view(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             ^ np.asarray(iy, np.int64).view(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ np.uint64((seed * 0x165667B19E3779F9) & 0xFFFFFFFFFFFFFFFF))
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def value_noise(seed: int, north: np.ndarray, east: np.ndarray, scale: float) -> np.ndarray:
    """Smooth noise in [-1, 1] at ground points (m), lattice spacing ``scale`` m; seamless
    across tiles and levels because it is a function of world position only."""
    u, v = north / scale, east / scale
    i0, j0 = np.floor(u), np.floor(v)
    fu, fv = u - i0, v - j0
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    i0, j0 = i0.astype(np.int64), j0.astype(np.int64)
    a = _hash01(seed, i0, j0)
    b = _hash01(seed, i0 + 1, j0)
    c = _hash01(seed, i0, j0 + 1)
    d = _hash01(seed, i0 + 1, j0 + 1)
    return 2.0 * ((a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv) - 1.0


#: What the ground is, per shape (``Shape.surface``): the simulator's truth for judging where a
#: vehicle touched down and for measuring a landability model on rendered frames. Index 0 is
#: "nothing drawn" (outside every block: never happens on the endless ground).
SURFACES = ("none", "grass", "paving", "gravel", "path", "road", "roof", "tree", "bench", "car")
#: Each surface's risk level, in the landability model's grouping (companion/models/
#: LANDABILITY_CARD.md): grass, paving, gravel, paths and roads are ``landable`` there (the data
#: set's paved-area holds roads too); a bench (or bin) is an ``obstacles`` thing, as a roof is.
SURFACE_LEVEL = {"none": "unknown", "grass": "landable", "paving": "landable", "gravel": "landable",
                 "path": "landable", "road": "landable", "roof": "obstacles", "tree": "vegetation",
                 "bench": "obstacles", "car": "vehicles"}
#: The surfaces a vehicle may touch down on: flat, firm, open ground.
LANDABLE_SURFACES = frozenset(k for k, v in SURFACE_LEVEL.items() if v == "landable")


@dataclass(frozen=True)
class Shape:
    """A filled polygon in ground metres (north, east) with a BGR colour; ``line`` > 0 draws an
    open polyline of that width in metres instead. ``surface``: what the ground under it is (one
    of ``SURFACES``), or None for paint that leaves the ground what it was (mowing stripes, a
    tree's shade, paving joints, a road's dashes)."""

    pts: np.ndarray
    color: tuple[int, int, int]
    line: float = 0.0
    surface: str | None = None


def _rect(cn: float, ce: float, ln: float, le: float, angle: float = 0.0) -> np.ndarray:
    """Corners of a rectangle centred at (cn, ce), sides ln (north) x le (east) m, turned by
    ``angle`` rad from north toward east."""
    c, s = math.cos(angle), math.sin(angle)
    local = np.array([[-ln, -le], [ln, -le], [ln, le], [-ln, le]]) / 2
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + (cn, ce)


def _disc(cn: float, ce: float, r: float, k: int = 16) -> np.ndarray:
    a = np.linspace(0, 2 * math.pi, k, endpoint=False)
    return np.column_stack([cn + r * np.cos(a), ce + r * np.sin(a)])


def _draw(img: np.ndarray, s: Shape, value: tuple[int, int, int] | int, n0: float, e0: float, res: float, line_type: int) -> None:
    """Draw one shape into ``img`` (rows north from ``n0``, columns east from ``e0``, ``res``
    m/px) with ``value``: the texture's colour or the truth's class index."""
    # cv2 point = (x = col, y = row) = ((east - e0) / res, (north - n0) / res), in fixed point.
    pts = np.round(np.column_stack([(s.pts[:, 1] - e0), (s.pts[:, 0] - n0)]) * (float(1 << SHIFT) / res)
                   ).astype(np.int32)
    if s.line > 0:
        cv2.polylines(img, [pts], False, value, max(1, int(round(s.line / res))), line_type, SHIFT)
    else:
        cv2.fillPoly(img, [pts], value, line_type, SHIFT)


def _jit(rng: np.random.Generator, color: tuple[int, int, int], amount: int) -> tuple[int, int, int]:
    """``color`` made lighter or darker by up to ``amount`` with a slight tint (a fifth of it),
    so that neutral greys stay grey."""
    base = int(rng.integers(-amount, amount + 1))
    tint = rng.integers(-(amount // 5), amount // 5 + 1, 3)
    return tuple(int(np.clip(c + base + d, 0, 255)) for c, d in zip(color, tint))  # type: ignore[return-value]


GRASS = (60, 140, 95)
PAVING = (150, 155, 160)
GRAVEL = (140, 160, 175)
ASPHALT = (85, 85, 88)
PATH = (170, 180, 190)
CAR_COLORS = [(230, 230, 230), (30, 30, 30), (160, 160, 165), (40, 40, 170), (150, 80, 30),
              (90, 90, 95), (200, 200, 205)]


class ProceduralGround:
    """An endless, seeded ground texture served as cached tiles.

    seed: layout and texture seed. base_res: finest texture resolution, metres per pixel (0.04 m
    is enough for 640x480 frames from 10 m with a 70 degree lens). tile_px: tile side in pixels.
    max_tiles: tiles kept in the cache.
    """

    def __init__(self, seed: int = 0, base_res: float = 0.04, tile_px: int = 256,
                 max_tiles: int = 192) -> None:
        self.seed = int(seed)
        self.base_res = float(base_res)
        self.tile_px = int(tile_px)
        self._tile = functools.lru_cache(maxsize=max_tiles)(self._make_tile)
        self._blocks = functools.lru_cache(maxsize=512)(self._make_block)
        self._mosaic_key: tuple | None = None
        self._mosaic: np.ndarray | None = None
        # The camera server renders in a worker thread while render_now may run on another.
        self._lock = threading.Lock()

    # -- layout -------------------------------------------------------------------------------
    def _block_rng(self, bi: int, bj: int) -> np.random.Generator:
        return np.random.default_rng([self.seed & 0xFFFFFFFF, bi + (1 << 20), bj + (1 << 20)])

    @staticmethod
    def _draw_kind(rng: np.random.Generator) -> str:
        return str(rng.choice(["grass", "paving", "gravel", "building"], p=[0.55, 0.22, 0.1, 0.13]))

    def block_kind(self, bi: int, bj: int) -> str:
        """What block (bi, bj) is: grass, paving, gravel or building."""
        return self._draw_kind(self._block_rng(bi, bj))

    def lawn_near(self, north: float, east: float, reach: int = 6) -> tuple[float, float]:
        """Centre (north, east) in metres of the grass block without a road along it that is
        nearest to the given point: a park lawn for scenarios that need a landable open area."""
        bi0, bj0 = int(math.floor(north / BLOCK)), int(math.floor(east / BLOCK))
        best: tuple[float, float, float] | None = None
        for bi in range(bi0 - reach, bi0 + reach + 1):
            for bj in range(bj0 - reach, bj0 + reach + 1):
                if bi % 4 == 0 or bj % 4 == 0 or self.block_kind(bi, bj) != "grass":
                    continue
                cn, ce = (bi + 0.5) * BLOCK, (bj + 0.5) * BLOCK
                d = math.hypot(cn - north, ce - east)
                if best is None or d < best[0]:
                    best = (d, cn, ce)
        if best is None:
            raise ValueError(f"no lawn within {reach} blocks of ({north:.0f}, {east:.0f})")
        return best[1], best[2]

    def _make_block(self, bi: int, bj: int) -> tuple[Shape, ...]:
        """The shapes of block (bi, bj), in drawing order, all inside the block."""
        rng = self._block_rng(bi, bj)
        n0, e0 = bi * BLOCK, bj * BLOCK
        shapes: list[Shape] = []
        road_n = bi % 4 == 0  # a road along the block's south edge (runs east-west)
        road_e = bj % 4 == 0  # a road along the block's west edge (runs north-south)
        kind = self._draw_kind(rng)
        base = {"grass": GRASS, "paving": PAVING, "gravel": GRAVEL, "building": PAVING}[kind]
        shapes.append(Shape(_rect(n0 + BLOCK / 2, e0 + BLOCK / 2, BLOCK, BLOCK), _jit(rng, base, 12),
                            surface="paving" if kind == "building" else kind))
        # The usable lot, inside the roads.
        ln0 = n0 + (ROAD_W if road_n else 0.0)
        le0 = e0 + (ROAD_W if road_e else 0.0)
        ln1, le1 = n0 + BLOCK, e0 + BLOCK
        cn, ce = (ln0 + ln1) / 2, (le0 + le1) / 2
        if kind == "grass":
            # Mowing stripes: alternate light and dark bands 2 m wide.
            ang = float(rng.choice([0.0, math.pi / 2]))
            light = _jit(rng, (GRASS[0] + 10, GRASS[1] + 18, GRASS[2] + 12), 4)
            for k in range(int((ln1 - ln0) // 4) if ang == 0.0 else int((le1 - le0) // 4)):
                if ang == 0.0:
                    shapes.append(Shape(_rect(ln0 + 4 * k + 1, ce, 2.0, le1 - le0), light))
                else:
                    shapes.append(Shape(_rect(cn, le0 + 4 * k + 1, ln1 - ln0, 2.0), light))
            for _ in range(int(rng.integers(0, 3))):
                a = rng.uniform(0, math.pi)
                d = np.array([math.cos(a), math.sin(a)]) * BLOCK
                p = np.array([rng.uniform(ln0, ln1), rng.uniform(le0, le1)])
                seg = np.vstack([p - d, p + d])
                seg[:, 0] = np.clip(seg[:, 0], ln0, ln1)
                seg[:, 1] = np.clip(seg[:, 1], le0, le1)
                shapes.append(Shape(seg, _jit(rng, PATH, 10), line=float(rng.uniform(1.5, 2.5)), surface="path"))
            for _ in range(int(rng.integers(0, 4))):
                r = float(rng.uniform(1.8, 3.2))
                tn, te = rng.uniform(ln0 + r, ln1 - r), rng.uniform(le0 + r, le1 - r)
                shapes.append(Shape(_disc(tn + 0.4, te + 0.4, r, 20), (35, 70, 45)))  # its shade
                shapes.append(Shape(_disc(tn, te, r, 20), _jit(rng, (45, 105, 60), 12), surface="tree"))
                shapes.append(Shape(_disc(tn - 0.3 * r, te - 0.3 * r, 0.45 * r, 12),
                                    _jit(rng, (60, 130, 80), 10)))  # its sunlit crown: still the tree
        elif kind == "paving":
            joint = (PAVING[0] - 25, PAVING[1] - 25, PAVING[2] - 25)
            for x in np.arange(ln0, ln1, 1.0):
                shapes.append(Shape(np.array([[x, le0], [x, le1]]), joint, line=0.05))
            for y in np.arange(le0, le1, 1.0):
                shapes.append(Shape(np.array([[ln0, y], [ln1, y]]), joint, line=0.05))
        elif kind == "building":
            bn, be = rng.uniform(8, 16), rng.uniform(8, 16)
            shapes.append(Shape(_rect(cn, ce, bn, be), _jit(rng, (175, 175, 178), 25), surface="roof"))
            shapes.append(Shape(_rect(cn, ce, bn - 0.8, be - 0.8), _jit(rng, (150, 152, 155), 20)))
            for _ in range(int(rng.integers(1, 5))):
                un, ue = cn + rng.uniform(-bn / 3, bn / 3), ce + rng.uniform(-be / 3, be / 3)
                shapes.append(Shape(_rect(un, ue, rng.uniform(0.8, 2.0), rng.uniform(0.8, 2.0)),
                                    _jit(rng, (200, 200, 200), 30)))
        # Benches and bins along the lot (static, person-sized: what the model must ignore).
        for _ in range(int(rng.integers(0, 4))):
            bn_, be_ = rng.uniform(ln0 + 1, ln1 - 1), rng.uniform(le0 + 1, le1 - 1)
            shapes.append(Shape(_rect(bn_, be_, 1.8, 0.5, float(rng.choice([0, math.pi / 2]))),
                                _jit(rng, (40, 70, 110), 15), surface="bench"))
        if road_n:
            shapes.append(Shape(_rect(n0 + ROAD_W / 2, e0 + BLOCK / 2, ROAD_W, BLOCK), _jit(rng, ASPHALT, 5),
                                surface="road"))
            for x in np.arange(e0, e0 + BLOCK, 6.0):
                shapes.append(Shape(np.array([[n0 + ROAD_W / 2, x], [n0 + ROAD_W / 2, x + 3.0]]),
                                    (220, 220, 220), line=0.15))
            for _ in range(int(rng.integers(0, 4))):
                x = rng.uniform(e0 + 3, e0 + BLOCK - 3)
                shapes.append(Shape(_rect(n0 + 1.3, x, 1.8, 4.4),
                                    CAR_COLORS[int(rng.integers(len(CAR_COLORS)))], surface="car"))
                shapes.append(Shape(_rect(n0 + 1.3, x + 0.4, 1.5, 1.4), (60, 55, 50)))
        if road_e:
            shapes.append(Shape(_rect(n0 + BLOCK / 2, e0 + ROAD_W / 2, BLOCK, ROAD_W), _jit(rng, ASPHALT, 5),
                                surface="road"))
            for x in np.arange(n0 + (ROAD_W if road_n else 0.0), n0 + BLOCK, 6.0):
                shapes.append(Shape(np.array([[x, e0 + ROAD_W / 2], [x + 3.0, e0 + ROAD_W / 2]]),
                                    (220, 220, 220), line=0.15))
            for _ in range(int(rng.integers(0, 4))):
                x = rng.uniform(n0 + ROAD_W + 3 if road_n else n0 + 3, n0 + BLOCK - 3)
                shapes.append(Shape(_rect(x, e0 + 1.3, 4.4, 1.8),
                                    CAR_COLORS[int(rng.integers(len(CAR_COLORS)))], surface="car"))
                shapes.append(Shape(_rect(x + 0.4, e0 + 1.3, 1.4, 1.5), (60, 55, 50)))
        return tuple(shapes)

    def _shapes_over(self, n_min: float, n_max: float, e_min: float, e_max: float) -> Iterator[Shape]:
        """The shapes of every block the rectangle touches, block by block in drawing order."""
        for bi in range(math.floor(n_min / BLOCK), math.floor(n_max / BLOCK) + 1):
            for bj in range(math.floor(e_min / BLOCK), math.floor(e_max / BLOCK) + 1):
                yield from self._blocks(bi, bj)

    # -- what the ground is -------------------------------------------------------------------
    def surface_labels(self, n_min: float, n_max: float, e_min: float, e_max: float,
                       res: float) -> tuple[np.ndarray, np.ndarray]:
        """What the ground is over a rectangle: a uint8 image of indices into ``SURFACES`` at
        ``res`` m/px, with the matrix ``A`` of :meth:`view` (``(col, row, 1) ~ A @ (north, east,
        1)``). Drawn from the same shapes in the same order as the texture, without smoothing,
        so a pixel says what the last shape drawn over it is (paint only, ``surface`` None,
        leaves it as it was)."""
        if not (res > 0 and n_max > n_min and e_max > e_min):
            raise ValueError(f"surface_labels needs res > 0 and a non-empty rectangle, got "
                             f"n {n_min}..{n_max}, e {e_min}..{e_max}, res {res}")
        rows, cols = int(math.ceil((n_max - n_min) / res)), int(math.ceil((e_max - e_min) / res))
        if rows * cols > 4096 * 4096:
            raise ValueError(f"surface_labels: {rows}x{cols} pixels is too many; use a coarser res")
        labels = np.zeros((rows, cols), np.uint8)
        for s in self._shapes_over(n_min, n_max, e_min, e_max):
            if s.surface is not None:
                _draw(labels, s, SURFACES.index(s.surface), n_min, e_min, res, cv2.LINE_8)
        A = np.array([[0.0, 1.0 / res, -e_min / res], [1.0 / res, 0.0, -n_min / res], [0.0, 0.0, 1.0]])
        return labels, A

    def surfaces_within(self, north: float, east: float, radius: float = 0.0,
                        res: float = 0.02) -> set[str]:
        """The surfaces on the disc of ``radius`` m around (north, east) (world NED metres): one
        surface for a point (``radius`` 0), more where a footprint straddles an edge."""
        half = max(float(radius), 0.0) + 2 * res
        labels, _A = self.surface_labels(north - half, north + half, east - half, east + half, res)
        c = (np.arange(labels.shape[0]) + 0.5) * res - half
        nn, ee = np.meshgrid(c, (np.arange(labels.shape[1]) + 0.5) * res - half, indexing="ij")
        d = np.hypot(nn, ee)
        if radius <= 0:  # a point: the one pixel nearest to it
            return {SURFACES[int(labels.flat[int(np.argmin(d))])]}
        return {SURFACES[int(v)] for v in np.unique(labels[d <= radius])}

    def surface_at(self, north: float, east: float) -> str:
        """What the ground is at one point (world NED metres): one of ``SURFACES``."""
        (name,) = self.surfaces_within(north, east, 0.0)
        return name

    # -- tiles --------------------------------------------------------------------------------
    def res(self, level: int) -> float:
        """Metres per pixel of tiles at ``level``."""
        return self.base_res * (1 << level)

    def tile_size_m(self, level: int) -> float:
        return self.tile_px * self.res(level)

    def _make_tile(self, level: int, ti: int, tj: int) -> np.ndarray:
        res, px = self.res(level), self.tile_px
        size = px * res
        n0, e0 = ti * size, tj * size
        img = np.zeros((px, px, 3), np.uint8)
        for s in self._shapes_over(n0, n0 + size, e0, e0 + size):
            if 0 < s.line / res < 0.6:
                continue  # a line thinner than a pixel at this level: invisible anyway
            _draw(img, s, s.color, n0, e0, res, cv2.LINE_AA)
        # Brightness variation at 6 m and 1.5 m (worn grass, stains), then sensor-like grain.
        c = (np.arange(px) + 0.5) * res
        nn, ee = np.meshgrid(n0 + c, e0 + c, indexing="ij")
        shade = 1.0 + 0.10 * value_noise(self.seed, nn, ee, 6.0) + 0.06 * value_noise(self.seed + 7, nn, ee, 1.5)
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, level, ti + (1 << 24), tj + (1 << 24)])
        grain = rng.normal(0.0, 5.0 if level == 0 else 3.0, (px, px, 1))
        out = img.astype(np.float32) * shade[..., None].astype(np.float32) + grain.astype(np.float32)
        return np.clip(out, 0, 255).astype(np.uint8)

    def tile(self, level: int, ti: int, tj: int) -> np.ndarray:
        """Tile (ti, tj) of ``level``: covers north ``[ti*S, (ti+1)*S)``, east ``[tj*S, (tj+1)*S)``
        with ``S = tile_size_m(level)``; rows grow northward. Cached; do not modify."""
        return self._tile(int(level), int(ti), int(tj))

    def view(self, n_min: float, n_max: float, e_min: float, e_max: float, res: float,
             max_px: int = 3072) -> tuple[np.ndarray, np.ndarray]:
        """A mosaic covering the ground rectangle at a resolution no coarser than ``res`` m/px
        where possible (coarser when the area would exceed ``max_px`` a side).

        Returns the BGR mosaic and the 3x3 matrix ``A`` with ``(col, row, 1) ~ A @ (north, east, 1)``.
        """
        return tiled_view(self, self.tile, n_min, n_max, e_min, e_max, res, max_px)


class FlatGround:
    """A uniform ground of one BGR colour (for tests that look for drawn people)."""

    def __init__(self, color: tuple[int, int, int] = (170, 170, 170)) -> None:
        self.color = tuple(int(c) for c in color)
        self._img = np.full((4, 4, 3), self.color, np.uint8)

    def view(self, n_min: float, n_max: float, e_min: float, e_max: float, res: float,
             max_px: int = 3072) -> tuple[np.ndarray, np.ndarray]:
        # A 4x4 image stretched over the area: with linear sampling it stays one colour.
        sn = max(n_max - n_min, 1e-6) / 4
        se = max(e_max - e_min, 1e-6) / 4
        A = np.array([[0.0, 1.0 / se, -e_min / se], [1.0 / sn, 0.0, -n_min / sn], [0.0, 0.0, 1.0]])
        return self._img, A


def tiled_view(ground: Any, tile: Callable[[int, int, int], np.ndarray], n_min: float, n_max: float,
               e_min: float, e_max: float, res: float, max_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The mosaic of ``ground``'s tiles (``tile(level, ti, tj)``) covering the rectangle at the
    coarsest level no finer than ``res`` that fits ``max_px``, cached on ``ground`` (its ``_lock``,
    ``_mosaic_key``, ``_mosaic``), and ``A`` with ``(col, row, 1) ~ A @ (north, east, 1)``: the one
    walk of a tiled ground's view, procedural or photographed."""
    level = max(0, int(math.floor(math.log2(max(res, ground.base_res) / ground.base_res))))
    while True:
        S = ground.tile_size_m(level)
        ti0, ti1 = math.floor(n_min / S), math.floor(n_max / S)
        tj0, tj1 = math.floor(e_min / S), math.floor(e_max / S)
        if max(ti1 - ti0 + 1, tj1 - tj0 + 1) * ground.tile_px <= max_px or level >= 12:
            break
        level += 1
    key = (level, ti0, ti1, tj0, tj1)
    with ground._lock:
        if key != ground._mosaic_key:
            rows = [np.hstack([tile(level, ti, tj) for tj in range(tj0, tj1 + 1)])
                    for ti in range(ti0, ti1 + 1)]
            ground._mosaic = np.vstack(rows)
            ground._mosaic_key = key
        mosaic = ground._mosaic
    r = ground.res(level)
    A = np.array([[0.0, 1.0 / r, -tj0 * S / r], [1.0 / r, 0.0, -ti0 * S / r], [0.0, 0.0, 1.0]])
    assert mosaic is not None
    return mosaic, A
