"""Step 3 of the pipeline, sampling: the image occupancy map onto a metric grid on the head plane.

The grid is axis-aligned in plane coordinates: cell ``[i, j]`` has its centre at
``(x0 + j * cell, y0 + i * cell)`` metres (columns follow plane x, rows plane y). With poses, plane
x is north and y is east; under ``--nadir`` plane x/y follow the image's u/v.

Cells the camera does not see are *unknown* and never free (value 0), so later stages treat them
as occupied and landing circles stay inside the view.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.geometry.camera import GeometryError, PlaneProjection


@dataclass(frozen=True)
class GridParams:
    """cell: side of a grid cell in metres. max_extent: half-width in metres of the largest grid
    around the point under the camera (bounds the work when the view reaches the horizon; through
    a lens that is not a pinhole, the footprint's seen radius bounds it too, ``_footprint_bounds``)."""

    cell: float = 0.1
    max_extent: float = 40.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cell) and self.cell > 0):
            raise ValueError(f"grid cell size must be > 0 m, got {self.cell!r}")
        if not (math.isfinite(self.max_extent) and self.max_extent >= self.cell):
            raise ValueError(f"grid max_extent must be >= the cell size, got {self.max_extent!r}")


@dataclass(frozen=True)
class GridSpec:
    """Where a grid lies on the head plane: centre of cell [0, 0] at (x0, y0), ``cell`` metres."""

    x0: float
    y0: float
    cell: float
    rows: int
    cols: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    def cell_to_plane(self) -> np.ndarray:
        """3x3 affine matrix taking (col, row, 1) to plane metres (x, y, 1)."""
        return np.array([[self.cell, 0.0, self.x0], [0.0, self.cell, self.y0], [0.0, 0.0, 1.0]])

    def to_plane(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.x0 + np.asarray(cols) * self.cell, self.y0 + np.asarray(rows) * self.cell

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell whose centre is nearest plane point (x, y) (m); it may lie
        off the grid (the caller checks against ``shape``)."""
        return int(round((y - self.y0) / self.cell)), int(round((x - self.x0) / self.cell))


def _footprint_bounds(proj: PlaneProjection, image_hw: tuple[int, int], params: GridParams
                      ) -> tuple[float, float, float, float]:
    h, w = image_hw
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=float)
    if proj.lens is not None:
        # Through a fisheye the image's straight edges are curves on the plane, and the ground
        # seen ends at the trusted cone: walk the edge of what counts as seen.
        pts = proj.lens.seen_boundary()
    else:
        pts = proj.image_to_plane(corners)
    ok = np.isfinite(pts).all(axis=1)
    extent = params.max_extent
    if proj.lens is not None and proj.camera_xy is not None:
        # A wide lens sees far along its image's long side (a fisheye:160 at 20 m: the trusted
        # cone's 50 m, against 32 m across), and the cells there are most of the grid's cost. The
        # landing rules count on the footprint's round part only (``LensView.seen_radius``: the
        # search's spacing, the judging and commit heights), so the grid ends there: beyond it the
        # ground is unseen, never free; people found there are still placed.
        extent = min(extent, max(params.cell, proj.lens.seen_radius()))
    if proj.camera_xy is not None:
        cx, cy = proj.camera_xy
        box = (cx - extent, cy - extent, cx + extent, cy + extent)
    else:
        box = (-math.inf, -math.inf, math.inf, math.inf)
    if ok.all():
        xmin, ymin = pts.min(axis=0)
        xmax, ymax = pts.max(axis=0)
        xmin, ymin = max(xmin, box[0]), max(ymin, box[1])
        xmax, ymax = min(xmax, box[2]), min(ymax, box[3])
    elif proj.camera_xy is not None:
        # Part of the view is above the horizon: the footprint is unbounded, keep the box.
        xmin, ymin, xmax, ymax = box
    else:
        raise GeometryError("the projection maps part of the image above the horizon and no "
                            "camera position bounds the grid")
    if not all(math.isfinite(v) for v in (xmin, ymin, xmax, ymax)):
        raise GeometryError("head-plane footprint is not finite")
    # Keep grids no larger than 2 * max_extent on a side even without a camera position.
    span = 2 * extent
    xmax, ymax = min(xmax, xmin + span), min(ymax, ymin + span)
    return xmin, ymin, xmax, ymax


def grid_for_view(proj: PlaneProjection, image_hw: tuple[int, int], params: GridParams) -> GridSpec:
    """The grid covering what the camera sees, snapped to whole cells so that grids of
    consecutive frames line up (less jitter in the proposals)."""
    xmin, ymin, xmax, ymax = _footprint_bounds(proj, image_hw, params)
    c = params.cell
    x0 = math.floor(xmin / c) * c
    y0 = math.floor(ymin / c) * c
    cols = max(1, int(math.ceil((xmax - x0) / c)) + 1)
    rows = max(1, int(math.ceil((ymax - y0) / c)) + 1)
    return GridSpec(x0, y0, c, rows, cols)


#: Real pixels kept round the image of the seen disk when a lens's frame is cropped for the density
#: model (``lens_crop_box``): the shipped stride-4 models' maps of a crop equal the whole frame's
#: except in the 8 cells (32 px) next to the crop's edges, so the disk's pixels get exactly the
#: whole frame's density. It also covers the free map's erosion before sampling (3-5 px) and the
#: interpolated lens maps (under a pixel).
CROP_MARGIN_PX = 32
#: A crop that keeps more of the frame than this is not made: it would save nothing worth a copy.
CROP_MAX_SHARE = 0.95


def lens_crop_box(proj: PlaneProjection, image_hw: tuple[int, int], multiple: int,
                  max_extent: float = math.inf, margin_px: int = CROP_MARGIN_PX, n: int = 64) -> tuple[int, int, int, int] | None:
    """The part of the image the landing rules can use through a lens that is not a pinhole, as
    a pixel box ``(x0, y0, x1, y1)`` (x1, y1 exclusive; x0, y0 multiples of ``multiple``, x1, y1
    too unless at the frame's edge): the image of the seen disk (``LensView.seen_radius`` round
    the point below the camera, at most ``max_extent``, the grid's window; a cell more for the
    grid's snapping) plus ``margin_px``. Pixels outside it map to ground the rules count as unseen, so
    the density model need not run on them (a fisheye:160 looking down at 4:3: the disk touches
    the short sides, and the box is 512 of the 640 columns). None: the whole frame (a pinhole,
    no camera position, a disk edge the lens does not see, or a box of at least
    ``CROP_MAX_SHARE`` of the frame)."""
    lens = proj.lens
    if lens is None or proj.camera_xy is None or multiple < 1:
        return None
    h, w = image_hw
    # The grid's own radius (``_footprint_bounds``): the seen radius within the window.
    radius = min(lens.seen_radius(), max_extent)
    if not (math.isfinite(radius) and radius > 0):
        return None
    cx, cy = proj.camera_xy
    phi = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    r = radius + 0.1  # the grid snaps to whole cells: a cell's worth more
    uv = lens.plane_to_image(np.column_stack([cx + r * np.cos(phi), cy + r * np.sin(phi)]))
    if not np.isfinite(uv).all():
        return None
    m = multiple
    x0 = max(0, int(math.floor((uv[:, 0].min() - margin_px) / m)) * m)
    y0 = max(0, int(math.floor((uv[:, 1].min() - margin_px) / m)) * m)
    x1 = min(w, int(math.ceil((uv[:, 0].max() + 1 + margin_px) / m)) * m)
    y1 = min(h, int(math.ceil((uv[:, 1].max() + 1 + margin_px) / m)) * m)
    if x1 <= x0 or y1 <= y0 or (x1 - x0) * (y1 - y0) >= CROP_MAX_SHARE * w * h:
        return None
    return x0, y0, x1, y1


def pixels_per_cell(proj: PlaneProjection, grid: GridSpec) -> float:
    """Largest image distance in pixels spanned by one grid cell over the grid (sampled at its
    corners and centre). Sampling a map whose cells span several pixels by nearest neighbour could
    skip an occupied pixel; this tells how much to erode the free map first."""
    xs = [grid.x0, grid.x0 + (grid.cols - 1) * grid.cell]
    ys = [grid.y0, grid.y0 + (grid.rows - 1) * grid.cell]
    pts = [(x, y) for x in xs for y in ys] + [(sum(xs) / 2, sum(ys) / 2)]
    if proj.camera_xy is not None:
        pts.append(proj.camera_xy)
    base = np.array(pts, dtype=float)
    c = grid.cell
    # One projection of the points and their neighbours a cell along x and along y.
    p0, px, py = np.split(proj.plane_to_image(np.concatenate([base, base + [c, 0.0], base + [0.0, c]])), 3)
    d = np.concatenate([np.hypot(*(px - p0).T), np.hypot(*(py - p0).T)])
    d = d[np.isfinite(d)]
    return float(d.max()) if d.size else 1.0


@functools.lru_cache(maxsize=8)
def _whole_view(h: int, w: int, k: int) -> np.ndarray:
    """The whole image seen (uint8 255) with the free map's border erosion by a ``k`` x ``k``
    square (none for ``k`` = 1), so that ground seen free up to the edge of the view reaches
    exactly as far as the view does. The same few (size, kernel) pairs come every frame: cached,
    read-only."""
    whole: np.ndarray = np.full((h, w), 255, np.uint8)
    if k > 1:
        whole = cv2.erode(whole, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    whole.flags.writeable = False
    return whole


def sample_to_grid(free_img: np.ndarray, proj: PlaneProjection, grid: GridSpec) -> np.ndarray:
    """Sample the image free map (255 free, 0 occupied) onto ``grid``: uint8, 255 free, 0 occupied
    or unknown. Conservative: a cell is free only if every image pixel it spans is free."""
    return _sample(free_img, proj, grid, False)[0]


def sample_with_view(free_img: np.ndarray, proj: PlaneProjection, grid: GridSpec,
                     box: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``sample_to_grid``, and the view on the same cells: uint8, 255 where the camera sees the
    cell (free or occupied), 0 where it is unknown. ``box`` (a lens's ``lens_crop_box``): only
    the pixels inside it were looked at, so cells outside are unknown."""
    out, view = _sample(free_img, proj, grid, True, box)
    assert view is not None
    return out, view


@functools.lru_cache(maxsize=8)
def _box_view(h: int, w: int, k: int, box: tuple[int, int, int, int]) -> np.ndarray:
    """``_whole_view`` for a frame of which only ``box`` was looked at. The box moves in steps of
    the model's stride, so most frames find theirs here: cached, read-only."""
    x0, y0, x1, y1 = box
    view: np.ndarray = np.zeros((h, w), np.uint8)
    view[y0:y1, x0:x1] = 255
    if k > 1:
        view = cv2.erode(view, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    view.flags.writeable = False
    return view


def _sample(free_img: np.ndarray, proj: PlaneProjection, grid: GridSpec,
            with_view: bool, box: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    ppc = pixels_per_cell(proj, grid)
    if proj.lens is not None:
        return _sample_lens(free_img, proj, grid, ppc, with_view, box)
    if box is not None:
        raise ValueError("a crop box is a lens's (lens_crop_box); a pinhole's frame is looked at whole")
    src = free_img
    kernel = None
    if ppc > 1.0:
        k = int(math.ceil(ppc)) | 1
        kernel = np.ones((k, k), np.uint8)
        src = cv2.erode(free_img, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    M = proj.H @ grid.cell_to_plane()
    out = cv2.warpPerspective(
        src, M, (grid.cols, grid.rows),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT, borderValue=0,
    )
    # OpenCV divides by w without looking at its sign: cells behind the camera would pick up
    # mirrored pixels. w is affine over the grid, so only check corners before paying for a mask.
    wrow = M[2]
    corners = np.array([[0, 0, 1], [grid.cols - 1, 0, 1], [0, grid.rows - 1, 1],
                        [grid.cols - 1, grid.rows - 1, 1]], dtype=float)
    behind = None
    if (corners @ wrow * proj.w_sign <= 0).any():
        jj, ii = np.meshgrid(np.arange(grid.cols), np.arange(grid.rows))
        behind = (wrow[0] * jj + wrow[1] * ii + wrow[2]) * proj.w_sign <= 0
        out[behind] = 0
    view = None
    if with_view:
        h, w = free_img.shape[:2]
        whole = _whole_view(h, w, 1 if kernel is None else len(kernel))
        view = cv2.warpPerspective(whole, M, (grid.cols, grid.rows),
                                   flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if behind is not None:
            view[behind] = 0
    return out, view


#: Through a lens, the pixel of every ``LENS_STEP``-th cell is projected exactly and the cells
#: between are interpolated (the map is smooth: a fraction of a pixel off at 4 cells); one more
#: pixel of erosion covers that.
LENS_STEP = 4


def lens_maps(proj: PlaneProjection, grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (float32, grid-shaped) giving each cell's pixel through the lens; cells the
    lens does not see or is not trusted on (``LensView.seen_to_image``; or next to one, where interpolation would mix a seen and an unseen cell)
    get -1, outside every image."""
    s = LENS_STEP
    rows = np.arange(0, grid.rows + s, s, dtype=float)
    cols = np.arange(0, grid.cols + s, s, dtype=float)
    cc, rr = np.meshgrid(cols, rows)
    x, y = grid.to_plane(rr.ravel(), cc.ravel())
    assert proj.lens is not None
    # Only ground along rays the model is trusted on counts as seen (lens.TRUSTED_THETA).
    uv = proj.lens.seen_to_image(np.column_stack([x, y])).reshape(len(rows), len(cols), 2)
    finite = np.isfinite(uv)
    # Per coordinate, then both: ``all(axis=2)`` over a last axis of 2 is several times slower.
    ok = (finite[..., 0] & finite[..., 1]).view(np.uint8)
    ok = cv2.erode(ok, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    uv = np.where(finite, uv, -1e4).astype(np.float32)
    size = ((len(cols) - 1) * s + 1, (len(rows) - 1) * s + 1)
    # align corners: coarse node k sits on fine cell k * s (cv2.resize maps pixel centres instead).
    A = np.array([[1.0 / s, 0.0, 0.0], [0.0, 1.0 / s, 0.0]])
    mx = cv2.warpAffine(uv[..., 0], A, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_REPLICATE)[:grid.rows, :grid.cols]
    my = cv2.warpAffine(uv[..., 1], A, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_REPLICATE)[:grid.rows, :grid.cols]
    seen = cv2.warpAffine(ok, A, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)[:grid.rows, :grid.cols]
    unseen = seen == 0
    mx[unseen] = -1.0
    my[unseen] = -1.0
    return mx, my


def _sample_lens(free_img: np.ndarray, proj: PlaneProjection, grid: GridSpec, ppc: float,
                 with_view: bool, box: tuple[int, int, int, int] | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """``_sample`` through a lens that is not a pinhole: each cell looks up its pixel (``lens_maps``)."""
    k = int(math.ceil(ppc + 1.0)) | 1
    kernel = np.ones((k, k), np.uint8)
    src = cv2.erode(free_img, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    mx, my = lens_maps(proj, grid)
    out = cv2.remap(src, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    view = None
    if with_view:
        h, w = free_img.shape[:2]
        # The cache's key: a box given as a list or in numpy integers is the same box.
        whole = (_whole_view(h, w, k) if box is None
                 else _box_view(h, w, k, (int(box[0]), int(box[1]), int(box[2]), int(box[3]))))
        view = cv2.remap(whole, mx, my, cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if box is not None:
            np.minimum(out, view, out=out)  # what was not looked at is not free
    return out, view
