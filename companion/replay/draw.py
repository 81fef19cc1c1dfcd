"""The paper's figure: a frame with people in red, proposals in green, numbered tracks in blue and
the landing target in yellow, plus, when the pose is known, a north-up view of the head plane.
With the landability model, ground it calls unlandable (water, vehicles, trees, roofs, ...) is
tinted magenta, apart from the people's red.

Pure functions: arrays in, new arrays out (inputs are never modified). Colours are BGR.
Circles live on the head plane, so in the image they are drawn as the projection of a polygon of
points around each circle (ellipses under an oblique camera).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike

from companion.control.touchdown import DescentProfile
from companion.geometry.camera import PlaneProjection
from companion.pipeline.circles import Circle
from companion.pipeline.headplane import GridSpec
from companion.pipeline.occupancy import OCCUPIED
from companion.pipeline.tracker import Track

RED = (0, 0, 255)
GREEN = (0, 200, 0)
BLUE = (255, 80, 0)
YELLOW = (0, 230, 255)
MAGENTA = (220, 0, 220)
WHITE = (255, 255, 255)
#: A zone's label: its circle's blue, lighter, to read on the label's dark box.
LABEL_BLUE = (255, 170, 90)
BLACK = (0, 0, 0)
POLYGON_POINTS = 72


def circle_polygon(x: float, y: float, r: float, n: int = POLYGON_POINTS) -> np.ndarray:
    """(n, 2) plane points (metres) evenly around the circle."""
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.column_stack([x + r * np.cos(a), y + r * np.sin(a)])


def circle_in_image_polygon(proj: PlaneProjection, x: float, y: float, r: float) -> np.ndarray | None:
    """Integer (n, 1, 2) image polygon of a plane circle, or None if any point is not visible
    (behind the camera)."""
    uv = proj.plane_to_image(circle_polygon(x, y, r))
    if not np.isfinite(uv).all():
        return None
    # Fixed-point with 4 fractional bits keeps small ellipses smooth.
    return np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)


def _tint(img: np.ndarray, mask: np.ndarray, color: tuple[int, int, int], alpha: float) -> None:
    if mask.any():
        c = np.array(color, np.float32)
        img[mask] = (img[mask].astype(np.float32) * (1 - alpha) + c * alpha).astype(np.uint8)


#: What is left of a pixel's brightness outside the part of the frame the model looked at.
UNSEEN_DIM = 0.35


def overlay_people(frame: np.ndarray, occupancy_free: np.ndarray, alpha: float = 0.45,
                   surface_free: np.ndarray | None = None, people_free: np.ndarray | None = None,
                   looked_at: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """``frame`` with the occupied pixels (``occupancy_free == 0``) tinted red by ``alpha``.

    With the landability model's ``surface_free`` (0 = unlandable ground), those pixels are tinted
    magenta instead, except where ``people_free`` (the people's own map; default: whatever is
    occupied and not unlandable ground) has people: people stay red wherever they stand.
    ``looked_at`` (``FrameResult.looked_at``): outside this box the model did not look, so the
    pixels are dimmed (unseen), not tinted as people."""
    out = frame.copy()
    occ = occupancy_free == OCCUPIED
    if looked_at is not None:
        x0, y0, x1, y1 = looked_at
        inside = np.zeros(occ.shape, bool)
        inside[y0:y1, x0:x1] = True
        occ &= inside
        out[~inside] = (out[~inside].astype(np.float32) * UNSEEN_DIM).astype(np.uint8)
    if surface_free is None or surface_free.shape != occ.shape:
        _tint(out, occ, RED, alpha)
        return out
    # Unlandable ground is drawn wherever the model marks it: in the landing-point scope
    # (``pipeline.unlandable_scope``) the zones' occupancy is people's alone.
    ground = surface_free == OCCUPIED
    if looked_at is not None:
        ground &= inside
    people = ((people_free == OCCUPIED) & occ) if people_free is not None and people_free.shape == occ.shape \
        else occ & ~ground
    _tint(out, ground & ~people, MAGENTA, alpha)
    _tint(out, people, RED, alpha)
    return out


#: Label font and the dark box behind each label (px around the text, opacity).
FONT = cv2.FONT_HERSHEY_SIMPLEX
LABEL_PAD_PX = 2
LABEL_BOX_ALPHA = 0.6


def label_box(img_shape: tuple[int, ...], text: str, org: tuple[int, int],
              scale: float = 0.5) -> tuple[tuple[int, int], tuple[int, int, int, int]]:
    """Where :func:`_label` draws ``text`` asked at ``org`` (its baseline's left end, px): the
    text's origin moved inside the image (a zone near the edge keeps its whole label) and the
    box behind it (x0, y0, x1, y1, inclusive pixels), both inside the image when it fits."""
    (tw, th), base = cv2.getTextSize(text, FONT, scale, 1)
    h, w = img_shape[:2]
    pad = LABEL_PAD_PX
    x = max(pad, min(int(org[0]), w - 1 - pad - tw))
    y = max(pad + th, min(int(org[1]), h - 1 - pad - base))
    return (x, y), (max(0, x - pad), max(0, y - th - pad), min(w - 1, x + tw + pad), min(h - 1, y + base + pad))


def _label(img: np.ndarray, text: str, org: tuple[int, int], color: tuple[int, int, int],
           scale: float = 0.5) -> tuple[int, int, int, int]:
    """``text`` in ``color`` on a dark translucent box, kept inside the image; the box (x0, y0,
    x1, y1). One stroke of the text only: an outline drawn as thicker text is wider than the
    text (OpenCV's glyph advance grows with the thickness) and shows as a ghost ("TARGETT")."""
    org, (x0, y0, x1, y1) = label_box(img.shape, text, org, scale)
    if x1 >= x0 and y1 >= y0:
        roi = img[y0:y1 + 1, x0:x1 + 1]
        roi[:] = (roi.astype(np.float32) * (1.0 - LABEL_BOX_ALPHA)).astype(np.uint8)
    cv2.putText(img, text, org, FONT, scale, color, 1, cv2.LINE_AA)
    return x0, y0, x1, y1


def _track_text(tr: Track, clearance_m: float | None = None) -> str:
    """``#3 age 12``, and with its predicted clearance at touchdown ``#3 age 12, 4.3 / -12.1 m``:
    the radius free now, then the least clearance left at touchdown if the vehicle committed on
    this frame (negative: a walker could reach the centre first; ``control.touchdown``)."""
    text = f"#{tr.id} age {tr.age}"
    if clearance_m is not None and math.isfinite(clearance_m):
        text += f", {tr.r:.1f} / {clearance_m:+.1f} m"
    return text


def touchdown_clearances(tracks: Sequence[Track], descent: DescentProfile, height_m: float) -> dict[int, float]:
    """Each track's least clearance at touchdown (m, by id) if the vehicle committed from
    ``height_m`` now: the labels of :func:`draw_image_view` (replay and the demo's video)."""
    return {tr.id: descent.clearance_at_touchdown(tr.r, height_m) for tr in tracks}


def draw_image_view(frame: np.ndarray, occupancy_free: np.ndarray, proj: PlaneProjection,
                    proposals: Sequence[Circle], tracks: Sequence[Track],
                    target_id: int | None, surface_free: np.ndarray | None = None,
                    people_free: np.ndarray | None = None,
                    clearances: Mapping[int, float] | None = None,
                    looked_at: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """The annotated camera frame (same size as ``frame``); unlandable ground in magenta when
    ``surface_free`` is given (see :func:`overlay_people`); each track labelled with its
    predicted clearance at touchdown (m, by track id) when ``clearances`` gives it; outside
    ``looked_at`` dimmed (see :func:`overlay_people`)."""
    img = overlay_people(frame, occupancy_free, surface_free=surface_free, people_free=people_free,
                         looked_at=looked_at)
    for c in proposals:
        poly = circle_in_image_polygon(proj, c.x, c.y, c.r)
        if poly is not None:
            cv2.polylines(img, [poly], True, GREEN, 1, cv2.LINE_AA, shift=4)
    for tr in tracks:
        target = tr.id == target_id
        poly = circle_in_image_polygon(proj, tr.x, tr.y, tr.r)
        if poly is None:
            continue
        color, thick = (YELLOW, 3) if target else (BLUE, 2)
        cv2.polylines(img, [poly], True, color, thick, cv2.LINE_AA, shift=4)
        centre = proj.plane_to_image(np.array([[tr.x, tr.y]]))[0]
        if np.isfinite(centre).all():
            u, v = int(round(centre[0])), int(round(centre[1]))
            cv2.drawMarker(img, (u, v), color, cv2.MARKER_CROSS, 10, thick)
            text = _track_text(tr, None if clearances is None else clearances.get(tr.id))
            _label(img, text + (" TARGET" if target else ""), (u + 6, v - 10), color if target else LABEL_BLUE)  # the box ends above the centre row
    return img


def grid_north_up(free_grid: np.ndarray) -> np.ndarray:
    """The head-plane grid (rows = plane y = east, columns = plane x = north) turned so that
    north is up and east is right: display row a = last x column - a, display column b = row b."""
    return np.ascontiguousarray(np.flipud(free_grid.T))


def plane_to_north_up_px(grid: GridSpec, x: ArrayLike, y: ArrayLike, scale: float,
                         offset: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Display pixel (col, row) of plane points in the north-up view drawn at ``scale`` px/cell
    with the grid's top-left corner at ``offset`` (col, row) pixels."""
    col = (np.asarray(y) - grid.y0) / grid.cell
    row = (grid.cols - 1) - (np.asarray(x) - grid.x0) / grid.cell
    return (col + 0.5) * scale - 0.5 + offset[0], (row + 0.5) * scale - 0.5 + offset[1]


#: Plane-view colours (BGR): free, occupied or unseen, and held by the risk map (seen free now,
#: but somebody stood there within the hold: not free for landing).
PLANE_FREE, PLANE_OCCUPIED = WHITE, (40, 40, 120)


def draw_plane_view(free_grid: np.ndarray, grid: GridSpec, proposals: Sequence[Circle],
                    tracks: Sequence[Track], target_id: int | None, size: int) -> np.ndarray:
    """A ``size`` x ``size`` north-up BGR view of the head-plane free grid (white free, dark red
    occupied or unseen), fitted and centred, with the same circles as the image view, a north
    arrow and a scale bar. Square and fixed-size so a video keeps one frame size while the grid's
    shape changes with the pose."""
    g = grid_north_up(free_grid)
    scale = min(size / g.shape[0], size / g.shape[1])
    gh, gw = max(1, int(round(g.shape[0] * scale))), max(1, int(round(g.shape[1] * scale)))
    off = ((size - gw) // 2, (size - gh) // 2)
    small = np.where(g[..., None] > 0, np.array(PLANE_FREE, np.uint8), np.array(PLANE_OCCUPIED, np.uint8))
    img = np.full((size, size, 3), 90, np.uint8)
    img[off[1]:off[1] + gh, off[0]:off[0] + gw] = cv2.resize(
        small.astype(np.uint8), (gw, gh), interpolation=cv2.INTER_NEAREST)

    def poly_of(x: float, y: float, r: float) -> np.ndarray:
        pts = circle_polygon(x, y, r)
        c, rr = plane_to_north_up_px(grid, pts[:, 0], pts[:, 1], scale, off)
        return np.round(np.column_stack([c, rr]) * 16).astype(np.int32).reshape(-1, 1, 2)

    for c in proposals:
        cv2.polylines(img, [poly_of(c.x, c.y, c.r)], True, GREEN, 1, cv2.LINE_AA, shift=4)
    for tr in tracks:
        target = tr.id == target_id
        color, thick = (YELLOW, 3) if target else (BLUE, 2)
        cv2.polylines(img, [poly_of(tr.x, tr.y, tr.r)], True, color, thick, cv2.LINE_AA, shift=4)
        col, row = plane_to_north_up_px(grid, tr.x, tr.y, scale, off)
        _label(img, f"#{tr.id}", (int(col) + 4, int(row) - 4), color if target else LABEL_BLUE)
    cv2.arrowedLine(img, (20, 50), (20, 15), WHITE, 2, cv2.LINE_AA, tipLength=0.3)
    _label(img, "N", (28, 30), WHITE)
    # Scale bar of a round number of metres, about a fifth of the panel.
    metres_per_px = grid.cell / scale
    bar_m = nice_length(size / 5 * metres_per_px)
    bar_px = int(round(bar_m / metres_per_px))
    cv2.line(img, (15, size - 15), (15 + bar_px, size - 15), WHITE, 2)
    _label(img, f"{bar_m:g} m", (15, size - 22), WHITE)
    return img


def nice_length(metres: float) -> float:
    """The largest 1, 2 or 5 x 10^k metres not above ``metres`` (for a scale bar)."""
    k = 10.0 ** np.floor(np.log10(max(metres, 1e-6)))
    return float(max(m * k for m in (1, 2, 5) if m * k <= max(metres, k)))


def compose(image_view: np.ndarray, plane_view: np.ndarray | None) -> np.ndarray:
    """The image view with the plane view (same height) on its right, or alone."""
    if plane_view is None:
        return image_view
    if plane_view.shape[0] != image_view.shape[0]:
        raise ValueError("plane view and image view must have the same height")
    sep = np.full((image_view.shape[0], 4, 3), 128, np.uint8)
    return np.hstack([image_view, sep, plane_view])


def figure(frame: np.ndarray, occupancy_free: np.ndarray, proj: PlaneProjection,
           proposals: Sequence[Circle], tracks: Sequence[Track], target_id: int | None,
           free_grid: np.ndarray | None = None, grid: GridSpec | None = None,
           surface_free: np.ndarray | None = None,
           people_free: np.ndarray | None = None, clearances: Mapping[int, float] | None = None,
           looked_at: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """The full figure of one frame; the plane view is added when ``free_grid`` and ``grid`` are
    given (the replay passes them when the pose is known, so north is meaningful)."""
    view = draw_image_view(frame, occupancy_free, proj, proposals, tracks, target_id, surface_free, people_free,
                           clearances, looked_at)
    plane = None
    if free_grid is not None and grid is not None and free_grid.size:
        plane = draw_plane_view(free_grid, grid, proposals, tracks, target_id, frame.shape[0])
    return compose(view, plane)
