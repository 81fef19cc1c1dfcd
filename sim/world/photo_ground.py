"""Ground made of real nadir photographs: the held-out semantic-drone photos as a mosaic.

**Held out of every training set.** The photos read here are ``../shared/data/semantic_drone/full``:
the held-out fifth of the ICG Semantic Drone Dataset (sorted index % 5 == 0) at its published
1500x1000, with a class map each. No training code of this project reads that folder (the
training and evaluation loaders read ``semantic_drone/images`` and split it by index, and
``companion.evaluation.datasets.refuse_held_out`` refuses the ``full`` folder by name); the
simulator only shows these photos to the service in closed loop, as a test.

Each photo is a patch of ground at its own **ground sampling distance** (GSD, metres per photo
pixel), estimated from what the class map shows (:func:`estimate_gsd`):

- from the cars (class 17) when the photo holds a whole one: the median longer side of the whole
  car components' minimum-area rectangles is :data:`CAR_LENGTH_M` (4.5 m, a typical European car);
- else from the people (class 15): the median longer side of the whole person components'
  minimum-area rectangles is :data:`PERSON_EXTENT_M` (0.85 m). That figure is measured on the
  five photos that hold both (071, 103, 440, 526 and 194: 0.86, 0.75, 0.88, 0.88 and 1.32 m by
  their cars; median 0.88, 0.85 taken to err toward a coarser, not finer, ground): a person
  seen from straight above is shoulders, head and the shadowless body foreshortened toward the
  edge of the frame, longer than a shoulder width (0.45 m) and far shorter than a body;
- else (10 photos with neither) the median GSD of the others.

The resulting GSDs on the 80 photos: 8 set by cars, 62 by people, 10 by the median;
0.0045-0.037 m/px, median 0.0114 (quartiles 0.0068 and 0.0172), so a photo covers 6.7 m x 4.5 m
to 55 m x 37 m of ground, 17 m x 11 m at the median (``python -m sim.world.photo_ground`` lists
each photo's). Finer
patches are stored at :data:`FINEST_M` (0.01 m/px): the camera sees no finer detail than that
from the last metres of a landing.

Layout (:class:`PhotoGround`): the patches sorted by height (tallest first) are packed in
shelves, left to right, into a block about as wide as it is tall, north-up and unmirrored (the
photo's top edge faces north). The ground repeats that block in both directions (endless, as the
procedural ground). What a shelf leaves above a patch or beyond its last patch is filled by that
patch **mirrored** at its north and east edges (pixels, classes and people alike:
``Patch.cell_m``): a flat grey band there looked like the cleanest ground in view and drew
landings. Every ground point's truth is its photo's class
(:data:`PHOTO_CLASSES`, ``labels/classes.txt``); landable are paved area, dirt, grass and gravel
(:data:`PHOTO_LANDABLE`), everything else (water, pool, roof, wall, tree, vegetation, car,
bicycle, obstacles, ...) is not. The people of the photos are people: :meth:`PhotoGround.people`
gives their ground positions for the judge.

Frames: world NED metres (north, east) on the ground plane z = 0. Mosaic convention of
:meth:`PhotoGround.view` is the procedural ground's: pixel ``(col, row)`` =
``((east - e0) / res, (north - n0) / res)``.
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sim.world.ground import tiled_view

#: The semantic-drone classes (``labels/classes.txt``), index -> name.
PHOTO_CLASSES = ("unlabeled", "paved-area", "dirt", "grass", "gravel", "water", "rocks", "pool",
                 "vegetation", "roof", "wall", "window", "door", "fence", "fence-pole", "person", "dog",
                 "car", "bicycle", "tree", "bald-tree", "ar-marker", "obstacle", "conflicting")
#: The classes a vehicle may touch down on: flat, firm, open ground.
PHOTO_LANDABLE = frozenset({"paved-area", "dirt", "grass", "gravel"})
_LANDABLE_IDX = np.array([PHOTO_CLASSES.index(n) for n in sorted(PHOTO_LANDABLE)])
#: The classes people walk on: the landable ones (paths, squares, lawns, tracks). Not roofs,
#: walls, water, pools, trees, vegetation, cars, nor unlabelled ground.
PHOTO_WALKABLE = PHOTO_LANDABLE
_WALKABLE_IDX = np.array([PHOTO_CLASSES.index(n) for n in sorted(PHOTO_WALKABLE)])
#: Resolution (m/px) of the walkable map the photo worlds' walkers keep to.
WALKABLE_RES_M = 0.1
PERSON = 15
CAR = 17
#: A typical car's length (m): the cars of the photos set their scale.
CAR_LENGTH_M = 4.5
#: The longer side (m) of a person's silhouette seen from above in these photos (see the module
#: docstring for how it was measured).
PERSON_EXTENT_M = 0.85
#: The finest ground resolution kept (m/px).
FINEST_M = 0.01
#: A component smaller than this (px across) is a fragment, not a whole car or person.
MIN_COMPONENT_PX = 8
#: BGR of ground no patch covers (none inside the block: each patch fills its cell).
GAP_BGR = (112, 116, 118)
#: Expected size of every photo and its class map (width, height).
PHOTO_WH = (1500, 1000)
#: The fewest photos a folder must hold to make a ground of.
MIN_PHOTOS = 8


class PhotosError(ValueError):
    """The photos folder is missing or not in the documented layout (``images/NNN.jpg`` with
    ``labels/NNN.png`` of the same 1500x1000 size)."""


def check_photos(folder: Path) -> list[str]:
    """The photo names (stems) of ``folder``, checked without decoding every photo: ``images/``
    and ``labels/`` exist, every image has its class map, at least :data:`MIN_PHOTOS`, and the
    first photo and its map decode at :data:`PHOTO_WH`. Raises :class:`PhotosError` naming the
    folder otherwise."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PhotosError(f"photos folder {folder} does not exist")
    images, labels = folder / "images", folder / "labels"
    if not images.is_dir() or not labels.is_dir():
        raise PhotosError(f"photos folder {folder} has no images/ and labels/ folders")
    names = sorted(p.stem for p in images.glob("*.jpg"))
    if len(names) < MIN_PHOTOS:
        raise PhotosError(f"photos folder {folder} holds {len(names)} photos in images/, fewer than {MIN_PHOTOS}")
    missing = [n for n in names if not (labels / f"{n}.png").is_file()]
    if missing:
        raise PhotosError(f"photos folder {folder}: no class map labels/{missing[0]}.png "
                          f"({len(missing)} photos without one)")
    img = cv2.imread(str(images / f"{names[0]}.jpg"), cv2.IMREAD_COLOR)
    lab = cv2.imread(str(labels / f"{names[0]}.png"), cv2.IMREAD_UNCHANGED)
    if img is None or lab is None or lab.ndim != 2 or img.shape[1::-1] != PHOTO_WH or lab.shape[::-1] != PHOTO_WH:
        raise PhotosError(f"photos folder {folder}: {names[0]} is not a {PHOTO_WH[0]}x{PHOTO_WH[1]} photo "
                          "with an 8-bit class map of its size")
    return names


def class_window(classes: np.ndarray, cls: int) -> tuple[slice, slice] | None:
    """The rows and columns of ``classes`` that hold class ``cls``, grown by one pixel on every
    side that is not the map's edge; None when no pixel holds it. Labelled within the window, the
    class's components are the map's own: the same pixels, numbered in the same (raster) order,
    and touching the window's border only where they touch the map's. Photos hold their people
    in about a fifth of the frame, and labelling costs by the pixel (docs/measurements.md,
    session 30)."""
    mask = classes == cls
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    h, w = classes.shape
    return (slice(max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 2, h)),
            slice(max(int(cols[0]) - 1, 0), min(int(cols[-1]) + 2, w)))


@dataclass(frozen=True)
class Components:
    """The 8-connected components of one class of a class map, labelled within its
    :func:`class_window` (``cv2.connectedComponentsWithStats``): ``count`` labels (0 is the
    background), ``labels`` and ``stats`` in the window's pixels, ``centroids`` (count, 2) (x, y) in
    the map's pixels, bit for bit those of labelling the whole map."""

    count: int
    labels: np.ndarray
    stats: np.ndarray
    centroids: np.ndarray


def _components(classes: np.ndarray, cls: int) -> Components | None:
    """The components of class ``cls`` (None when no pixel holds it: most photos hold no car)."""
    window = class_window(classes, cls)
    if window is None:
        return None
    rows, cols = window
    n, cc, stats, cent = cv2.connectedComponentsWithStats((classes[window] == cls).view(np.uint8), connectivity=8)
    # OpenCV's centroid is (sum of the pixels' integer coordinates) / area, in float64: the sum
    # is recovered exactly from the window's centroid (it is an integer far below 2**52), moved to
    # the map's origin and divided as OpenCV divides. Label 0's (the window's background) is not used.
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        sums = np.rint(cent * area) + area * np.array([cols.start, rows.start], np.float64)
        full = sums / area
    return Components(n, cc, stats, full)


def _component_extents(classes: np.ndarray, cls: int, components: Components | None = None) -> list[float]:
    """Longer sides (px) of the minimum-area rectangles of the whole components of ``cls``
    (those touching the border are cut off and left out); ``components``: ``_components(classes,
    cls)`` when the caller has them."""
    found = _components(classes, cls) if components is None else components
    if found is None:
        return []
    n, cc, stats = found.count, found.labels, found.stats
    h, w = cc.shape  # the window's: a component touches its border only where it touches the map's
    out = []
    for k in range(1, n):
        x, y, bw, bh, _a = (int(v) for v in stats[k])
        if max(bw, bh) < MIN_COMPONENT_PX or x == 0 or y == 0 or x + bw == w or y + bh == h:
            continue
        ys, xs = np.nonzero(cc[y:y + bh, x:x + bw] == k)
        (_c, (rw, rh), _ang) = cv2.minAreaRect(np.column_stack([xs, ys]).astype(np.float32))
        out.append(float(max(rw, rh)))
    return out


def estimate_gsd(classes: np.ndarray, people_components: Components | None = None) -> tuple[float | None, str]:
    """The photo's ground sampling distance (m/px) from its class map and what set it ("car",
    "person"), or (None, "none") when it holds neither whole; ``people_components``: the
    person components (``_components(classes, PERSON)``) when the caller has them."""
    cars = _component_extents(classes, CAR)
    if cars:
        return CAR_LENGTH_M / float(np.median(cars)), "car"
    people = _component_extents(classes, PERSON, people_components)
    if people:
        return PERSON_EXTENT_M / float(np.median(people)), "person"
    return None, "none"


@dataclass(frozen=True)
class Patch:
    """One photo laid on the ground: ``bgr`` (H, W, 3) and ``classes`` (H, W) at ``gsd`` m/px,
    its south-west corner at (``north``, ``east``) metres of the block; ``gsd_from``: what set
    its GSD ("car", "person", "median"); ``people_px``: (N, 2) centroids (x, y) of its person
    components in its own pixels. ``cell_m``: the (north, east) extent of the ground the patch
    owns in its shelf (its own size, or more where the shelf leaves room above it or beyond
    it): the photo mirrored at its north and east edges fills it (:class:`PhotoGround`)."""

    name: str
    bgr: np.ndarray
    classes: np.ndarray
    gsd: float
    gsd_from: str
    north: float
    east: float
    people_px: np.ndarray
    cell_m: tuple[float, float] = (0.0, 0.0)

    @property
    def size_m(self) -> tuple[float, float]:
        """(north extent, east extent) in metres."""
        return self.classes.shape[0] * self.gsd, self.classes.shape[1] * self.gsd


def _people_centroids(classes: np.ndarray, components: Components | None = None) -> np.ndarray:
    found = _components(classes, PERSON) if components is None else components
    if found is None:
        return np.empty((0, 2))
    n, stats, cent = found.count, found.stats, found.centroids
    keep = [k for k in range(1, n) if stats[k, cv2.CC_STAT_AREA] >= 12]
    return cent[keep].astype(np.float64).reshape(-1, 2)


@functools.lru_cache(maxsize=2)
def load_patches(folder: str) -> tuple[tuple[Patch, ...], float, float]:
    """The photos of ``folder`` as patches laid out in a block, and the block's (north, east)
    size in metres. Cached per process (a flight's process loads them once)."""
    root = Path(folder)
    names = check_photos(root)
    raw = []
    for name in names:
        bgr = cv2.imread(str(root / "images" / f"{name}.jpg"), cv2.IMREAD_COLOR)
        cls = cv2.imread(str(root / "labels" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        if bgr is None or cls is None or cls.ndim != 2 or bgr.shape[:2] != cls.shape:
            raise PhotosError(f"photos folder {root}: {name} and its class map do not decode at one size")
        found = _components(cls, PERSON)  # labelled once: the scale and the people both read them
        gsd, src = estimate_gsd(cls, found)
        raw.append((name, bgr, cls, gsd, src, _people_centroids(cls, found)))
    known = [g for *_r, g, _s, _p in raw if g is not None]
    median = float(np.median(known)) if known else 0.01
    items = []
    for name, bgr, cls, gsd, src, people in raw:
        g = median if gsd is None else gsd
        if g < FINEST_M:  # keep no finer ground than the camera can see
            k = g / FINEST_M
            size = (max(1, round(cls.shape[1] * k)), max(1, round(cls.shape[0] * k)))
            people = people * (size[0] / cls.shape[1])
            g *= cls.shape[1] / size[0]  # the exact GSD of the resized photo (about FINEST_M)
            bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
            cls = cv2.resize(cls, size, interpolation=cv2.INTER_NEAREST)
        items.append((name, bgr, cls, g, src if gsd is not None else "median", people))
    # Shelf packing, tallest first; of a range of block widths, the one that leaves least gap.
    items.sort(key=lambda it: (-it[2].shape[0] * it[3], it[0]))
    area = sum(it[2].shape[0] * it[3] * it[2].shape[1] * it[3] for it in items)
    best: tuple[float, list[Patch], float, float] | None = None
    for f in np.linspace(0.7, 1.6, 37):
        patches, bn, be = _shelves(items, math.sqrt(area) * float(f))
        if best is None or bn * be < best[0] - 1e-9:
            best = (bn * be, patches, bn, be)
    assert best is not None
    return tuple(best[1]), best[2], best[3]


def _shelves(items: list, width: float) -> tuple[list[Patch], float, float]:
    """Patches packed in shelves no wider than ``width`` m (a patch wider than it gets its own),
    each owning the cell from its south-west corner to its shelf's top and (the last of a
    shelf) to the block's east edge."""
    shelves: list[list[tuple]] = [[]]
    east, block_e = 0.0, 0.0
    for it in items:
        w_m = it[2].shape[1] * it[3]
        if east > 0 and east + w_m > width:
            shelves.append([])
            east = 0.0
        shelves[-1].append(it)
        east += w_m
        block_e = max(block_e, east)
    patches, north = [], 0.0
    for shelf in shelves:
        shelf_h, east = max(it[2].shape[0] * it[3] for it in shelf), 0.0
        for k, (name, bgr, cls, g, src, people) in enumerate(shelf):
            w_m = cls.shape[1] * g
            cell_e = (block_e - east) if k == len(shelf) - 1 else w_m
            patches.append(Patch(name, bgr, cls, g, src, north, east, people, (shelf_h, cell_e)))
            east += w_m
        north += shelf_h
    return patches, north, block_e


def _mirror_images(v: np.ndarray, size: float, lo: float, hi: float) -> list[np.ndarray]:
    """The images of photo coordinates ``v`` (pixels, 0..``size``) under the photo mirrored
    endlessly at its edges (``cv2.BORDER_REFLECT``: period ``2 * size``), each an array of ``v``'s
    length with the images outside [``lo``, ``hi``) set to NaN; only the arrays holding one inside.
    Mirrored people stand where their mirrored pixels are."""
    out = []
    for k in range(math.floor(lo / (2 * size)) - 1, math.ceil(hi / (2 * size)) + 1):
        for img in (v + 2 * k * size, 2 * k * size - v):
            img = np.where((img >= lo) & (img < hi), img, np.nan)
            if np.isfinite(img).any():
                out.append(img)
    return out


@dataclass(frozen=True)
class WalkableMap:
    """Where people walk on the photo ground (``sim.world.walkers.Walkable``): ``mask`` (rows
    north from ``n0``, columns east from ``e0``, ``res`` m/px) is True on :data:`PHOTO_WALKABLE`
    ground. Outside the map nobody walks."""

    n0: float
    e0: float
    res: float
    mask: np.ndarray

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool for (N, 2) ground points (north, east)."""
        p = np.asarray(points, float).reshape(-1, 2)
        r = np.floor((p[:, 0] - self.n0) / self.res)
        c = np.floor((p[:, 1] - self.e0) / self.res)
        ok = (r >= 0) & (r < self.mask.shape[0]) & (c >= 0) & (c < self.mask.shape[1])
        out = np.zeros(len(p), bool)
        out[ok] = self.mask[r[ok].astype(int), c[ok].astype(int)]
        return out


class PhotoGround:
    """An endless ground of real photos (a block of patches repeated), served as cached tiles
    like :class:`sim.world.ground.ProceduralGround`, with its truth per point.

    folder: the photos folder (``images/``, ``labels/``). base_res: finest tile resolution (m/px).
    origin: where the block's south-west corner lies (world north, east m): a scenario moves
    the block, not the scene.
    """

    def __init__(self, folder: Path | str, origin: tuple[float, float] = (0.0, 0.0), base_res: float = 0.02,
                 tile_px: int = 256, max_tiles: int = 192) -> None:
        self.folder = str(Path(folder).resolve())
        self.patches, self.block_n, self.block_e = load_patches(self.folder)
        self.origin = (float(origin[0]), float(origin[1]))
        self.base_res = float(base_res)
        self.tile_px = int(tile_px)
        self._tile = functools.lru_cache(maxsize=max_tiles)(self._make_tile)
        self._pyr: dict[tuple[int, int], np.ndarray] = {}
        self._mosaic_key: tuple | None = None
        self._mosaic: np.ndarray | None = None
        self._lock = threading.Lock()

    # -- painting ----------------------------------------------------------------------------
    def _pyramid(self, i: int, level: int) -> np.ndarray:
        """Patch ``i``'s photo halved ``level`` times (pre-filtered, so a coarse tile does not alias)."""
        key = (i, level)
        if key not in self._pyr:
            self._pyr[key] = self.patches[i].bgr if level == 0 else cv2.pyrDown(self._pyramid(i, level - 1))
        return self._pyr[key]

    def _paint(self, dst: np.ndarray, n0: float, e0: float, res: float, labels: bool,
               blocked: bool = False) -> None:
        """Draw every patch copy over the rectangle of ``dst`` (rows north from ``n0``, columns
        east from ``e0``, ``res`` m/px): the photos (BGR), their classes (``labels``), or 255
        wherever any of a destination pixel's photo pixels is not landable (``blocked``). Each
        patch fills its cell (``Patch.cell_m``): beyond its north and east edges the photo is
        mirrored (pixels and classes alike), so that every ground point is some photo's ground
        and its truth that photo's class, and no flat grey band between photos looks like the
        cleanest ground in view."""
        rows, cols = dst.shape[:2]
        n1, e1 = n0 + rows * res, e0 + cols * res
        on, oe = self.origin
        for bi in range(math.floor((n0 - on) / self.block_n), math.floor((n1 - on) / self.block_n) + 1):
            for bj in range(math.floor((e0 - oe) / self.block_e), math.floor((e1 - oe) / self.block_e) + 1):
                bn, be = on + bi * self.block_n, oe + bj * self.block_e
                for i, p in enumerate(self.patches):
                    cn, ce = p.cell_m
                    pn, pe = bn + p.north, be + p.east
                    if pn >= n1 or pn + cn <= n0 or pe >= e1 or pe + ce <= e0:
                        continue
                    if blocked:
                        src, interp = self._blocked(i, res), cv2.INTER_NEAREST
                        g = p.gsd * p.classes.shape[0] / src.shape[0]
                    elif labels:
                        src, g, interp = p.classes, p.gsd, cv2.INTER_NEAREST
                    else:
                        level = max(0, int(math.floor(math.log2(max(res / p.gsd, 1.0)))))
                        src = self._pyramid(i, level)
                        g, interp = p.gsd * p.bgr.shape[0] / src.shape[0], cv2.INTER_LINEAR
                    H = src.shape[0]
                    # The cell's destination pixels (whole pixels whose centres lie in it).
                    r0 = max(0, math.ceil((pn - n0) / res - 0.5))
                    r1 = min(rows, math.ceil((pn + cn - n0) / res - 0.5))
                    c0 = max(0, math.ceil((pe - e0) / res - 0.5))
                    c1 = min(cols, math.ceil((pe + ce - e0) / res - 0.5))
                    if r0 >= r1 or c0 >= c1:
                        continue
                    # Photo pixel (x, y) centre: east = pe + (x + .5) g, north = pn + (H - y - .5) g
                    # (top edge north); dst pixel (c, r) centre: east = e0 + (c + .5) res, ...
                    # The inverse map (dst -> photo), so that the mirror is the source's border.
                    Minv = np.array([[res / g, 0.0, (e0 + (c0 + 0.5) * res - pe) / g - 0.5],
                                     [0.0, -res / g, H - (n0 + (r0 + 0.5) * res - pn) / g - 0.5]])
                    dst[r0:r1, c0:c1] = cv2.warpAffine(src, Minv, (c1 - c0, r1 - r0),
                                                       flags=interp | cv2.WARP_INVERSE_MAP,
                                                       borderMode=cv2.BORDER_REFLECT)

    def _blocked(self, i: int, res: float) -> np.ndarray:
        """Patch ``i``'s ground that is not landable (255), pooled to about ``res`` m/px so that
        a coarse pixel is blocked when any photo pixel under it is (nothing is lost by sampling)."""
        p = self.patches[i]
        bad = (~np.isin(p.classes, _LANDABLE_IDX)).astype(np.float32)
        k = max(1.0, res / p.gsd)
        size = (max(1, int(round(bad.shape[1] / k))), max(1, int(round(bad.shape[0] / k))))
        pooled = cv2.resize(bad, size, interpolation=cv2.INTER_AREA) if k > 1 else bad
        return np.where(pooled > 0, 255, 0).astype(np.uint8)

    # -- tiles (the texture) ------------------------------------------------------------------
    def res(self, level: int) -> float:
        return self.base_res * (1 << level)

    def tile_size_m(self, level: int) -> float:
        return self.tile_px * self.res(level)

    def _make_tile(self, level: int, ti: int, tj: int) -> np.ndarray:
        res, px = self.res(level), self.tile_px
        img = np.empty((px, px, 3), np.uint8)
        img[:] = GAP_BGR
        self._paint(img, ti * px * res, tj * px * res, res, labels=False)
        return img

    def view(self, n_min: float, n_max: float, e_min: float, e_max: float, res: float,
             max_px: int = 3072) -> tuple[np.ndarray, np.ndarray]:
        """A mosaic covering the rectangle, as :meth:`sim.world.ground.ProceduralGround.view`."""
        return tiled_view(self, self._tile, n_min, n_max, e_min, e_max, res, max_px)

    # -- the truth ----------------------------------------------------------------------------
    def class_map(self, n_min: float, n_max: float, e_min: float, e_max: float, res: float) -> np.ndarray:
        """Class indices (:data:`PHOTO_CLASSES`; 0 between patches) over a rectangle at ``res``
        m/px, rows north from ``n_min``, columns east from ``e_min``."""
        rows, cols = int(math.ceil((n_max - n_min) / res)), int(math.ceil((e_max - e_min) / res))
        if not (res > 0 and rows > 0 and cols > 0) or rows * cols > 8192 * 8192:
            raise ValueError(f"class_map: bad rectangle or resolution (n {n_min}..{n_max}, e {e_min}..{e_max}, res {res})")
        out = np.zeros((rows, cols), np.uint8)
        self._paint(out, n_min, e_min, res, labels=True)
        return out

    def walkable(self, centre: tuple[float, float], half_size: float,
                 res: float = WALKABLE_RES_M) -> WalkableMap:
        """Where people walk in the square of side ``2 * half_size`` m around ``centre`` (world
        north, east), by the class maps."""
        n0, e0 = centre[0] - half_size, centre[1] - half_size
        classes = self.class_map(n0, n0 + 2 * half_size, e0, e0 + 2 * half_size, res)
        return WalkableMap(n0, e0, res, np.isin(classes, _WALKABLE_IDX))

    def surfaces_within(self, north: float, east: float, radius: float = 0.0, res: float = 0.02) -> set[str]:
        """The classes on the disc of ``radius`` m around (north, east) (their names)."""
        half = max(float(radius), 0.0) + 2 * res
        labels = self.class_map(north - half, north + half, east - half, east + half, res)
        c = (np.arange(labels.shape[0]) + 0.5) * res - half
        nn, ee = np.meshgrid(c, (np.arange(labels.shape[1]) + 0.5) * res - half, indexing="ij")
        d = np.hypot(nn, ee)
        if radius <= 0:
            return {PHOTO_CLASSES[int(labels.flat[int(np.argmin(d))])]}
        return {PHOTO_CLASSES[int(v)] for v in np.unique(labels[d <= radius])}

    def surface_at(self, north: float, east: float) -> str:
        (name,) = self.surfaces_within(north, east, 0.0)
        return name

    def people(self, centre: tuple[float, float], half_size: float) -> np.ndarray:
        """(N, 2) ground positions (north, east) of the photos' people within the square of side
        ``2 * half_size`` around ``centre``: every person component's centroid, every copy, and
        every mirror image of it where its photo is mirrored into its cell (``_paint``)."""
        n0, n1 = centre[0] - half_size, centre[0] + half_size
        e0, e1 = centre[1] - half_size, centre[1] + half_size
        on, oe = self.origin
        out = []
        for bi in range(math.floor((n0 - on) / self.block_n), math.floor((n1 - on) / self.block_n) + 1):
            for bj in range(math.floor((e0 - oe) / self.block_e), math.floor((e1 - oe) / self.block_e) + 1):
                bn, be = on + bi * self.block_n, oe + bj * self.block_e
                for p in self.patches:
                    if len(p.people_px) == 0:
                        continue
                    H, W = p.classes.shape
                    ys = _mirror_images(p.people_px[:, 1], H, -(p.cell_m[0] / p.gsd - H), H)
                    xs = _mirror_images(p.people_px[:, 0], W, 0.0, p.cell_m[1] / p.gsd)
                    for y in ys:
                        for x in xs:
                            out.append(np.column_stack([bn + p.north + (H - y) * p.gsd, be + p.east + x * p.gsd]))
        pts = np.vstack(out) if out else np.empty((0, 2))
        ok = (pts[:, 0] >= n0) & (pts[:, 0] <= n1) & (pts[:, 1] >= e0) & (pts[:, 1] <= e1)
        return pts[ok]

    def landable_clearance(self, res: float = 0.1, person_margin_m: float = 1.0) -> np.ndarray:
        """Over one block (rows north, columns east from the block's corner, ``res`` m/px): the
        distance (m) from each point to the nearest ground that is not landable or within
        ``person_margin_m`` of a photo's person (a person's centroid grown by 0.5 m more, the half
        of a body seen from above); a point counts as not landable when any photo pixel under it
        is not."""
        on, oe = self.origin
        rows, cols = int(math.ceil(self.block_n / res)), int(math.ceil(self.block_e / res))
        bad: np.ndarray = np.full((rows, cols), 255, np.uint8)  # what no patch paints: not landable
        self._paint(bad, on, oe, res, labels=False, blocked=True)
        bad = cv2.dilate(bad, np.ones((3, 3), np.uint8))  # a pixel's worth of placement error
        people = np.zeros((rows, cols), np.uint8)
        pts = self.people((on + self.block_n / 2, oe + self.block_e / 2), max(self.block_n, self.block_e))
        for north, east in pts:
            cv2.circle(people, (int((east - oe) / res), int((north - on) / res)),
                       int(math.ceil((person_margin_m + 0.5) / res)), 255, -1)
        free = ((bad == 0) & (people == 0)).astype(np.uint8)
        free[0, :] = free[-1, :] = 0  # the block's edges: what lies beyond is another copy, unknown here
        free[:, 0] = free[:, -1] = 0
        return cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res

    def cell_index(self, res: float = 0.1) -> np.ndarray:
        """Over one block, as :meth:`landable_clearance`: the index (into :attr:`patches`) of the
        photo whose cell (``Patch.cell_m``: the photo and its mirrored fill) holds each point."""
        rows, cols = int(math.ceil(self.block_n / res)), int(math.ceil(self.block_e / res))
        out = np.full((rows, cols), -1, np.int16)
        for i, p in enumerate(self.patches):
            r0, r1 = round(p.north / res), round((p.north + p.cell_m[0]) / res)
            c0, c1 = round(p.east / res), round((p.east + p.cell_m[1]) / res)
            out[r0:r1, c0:c1] = i
        return out

    def places(self, radius: float, res: float = 0.1) -> dict[str, int]:
        """The photos (names) whose cells hold a centre of a landable disc of ``radius`` m with
        none of the photos' people within 1 m of it (:meth:`landable_clearance`), and how many
        such centres (``res`` m apart) each holds."""
        dist = _clearance_cached(self.folder, self.origin, res)
        idx = _cell_index_cached(self.folder, self.origin, res)
        counts = np.bincount(idx[(dist >= radius) & (idx >= 0)].astype(np.int64), minlength=len(self.patches))
        return {self.patches[i].name: int(counts[i]) for i in np.nonzero(counts)[0]}

    def largest_discs(self, res: float = 0.1) -> dict[str, float]:
        """Each photo's largest landable disc (its radius, m) with none of the photos' people
        within 1 m of it, whose centre its cell holds (:meth:`places`)."""
        dist = _clearance_cached(self.folder, self.origin, res)
        idx = _cell_index_cached(self.folder, self.origin, res)
        out = np.zeros(len(self.patches))
        np.maximum.at(out, idx[idx >= 0].astype(np.int64), dist[idx >= 0])
        return {p.name: float(out[i]) for i, p in enumerate(self.patches)}

    def place_centre(self, radius: float, rng: np.random.Generator, res: float = 0.1) -> tuple[str, tuple[float, float]]:
        """A place and a point in it (world north, east) whose disc of ``radius`` m is landable
        ground by the class maps with no photo's person within 1 m of it: the photo drawn from
        ``rng`` among every photo whose cell holds such a point (:meth:`places`), each as likely
        as any other, then the point among that cell's. So a large landable photo holds no more
        scenes than a small one (:meth:`free_centre` draws among all points, and the two largest
        photos held every scene). Raises ValueError when no photo holds one."""
        dist = _clearance_cached(self.folder, self.origin, res)
        idx = _cell_index_cached(self.folder, self.origin, res)
        ok = dist >= radius
        hosts = sorted({int(i) for i in np.unique(idx[ok]) if i >= 0})
        if not hosts:
            raise ValueError(f"no landable disc of {radius:.1f} m on the photo ground ({self.folder})")
        i = hosts[int(rng.integers(len(hosts)))]
        ii, jj = np.nonzero(ok & (idx == i))
        k = int(rng.integers(len(ii)))
        return self.patches[i].name, (float(self.origin[0] + (ii[k] + 0.5) * res),
                                      float(self.origin[1] + (jj[k] + 0.5) * res))

    def free_centre(self, radius: float, rng: np.random.Generator, res: float = 0.1) -> tuple[float, float]:
        """A point (world north, east) whose disc of ``radius`` m is landable ground by the class
        maps with no photo's person within 1 m of it, drawn from ``rng`` among all such points of
        the block. Raises ValueError when the block holds none."""
        dist = _clearance_cached(self.folder, self.origin, res)
        ii, jj = np.nonzero(dist >= radius)
        if len(ii) == 0:
            raise ValueError(f"no landable disc of {radius:.1f} m on the photo ground ({self.folder})")
        k = int(rng.integers(len(ii)))
        return float(self.origin[0] + (ii[k] + 0.5) * res), float(self.origin[1] + (jj[k] + 0.5) * res)


@functools.lru_cache(maxsize=4)
def _clearance_cached(folder: str, origin: tuple[float, float], res: float) -> np.ndarray:
    return PhotoGround(folder, origin).landable_clearance(res)


@functools.lru_cache(maxsize=4)
def _cell_index_cached(folder: str, origin: tuple[float, float], res: float) -> np.ndarray:
    return PhotoGround(folder, origin).cell_index(res)


def main() -> None:
    """Print each photo's GSD and what set it, and the block's size (the module docstring's figures)."""
    import sys

    folder = sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).resolve().parents[3] / "shared" / "data" /
                                                     "semantic_drone" / "full")
    patches, bn, be = load_patches(folder)
    g = np.array([p.gsd for p in patches])
    for p in sorted(patches, key=lambda p: p.name):
        print(f"{p.name}: {p.gsd:.4f} m/px ({p.gsd_from}), {p.size_m[1]:.1f} x {p.size_m[0]:.1f} m, "
              f"{len(p.people_px)} people")
    src = {s: sum(p.gsd_from == s for p in patches) for s in ("car", "person", "median")}
    print(f"{len(patches)} photos, GSD {g.min():.4f}-{g.max():.4f} m/px (median {np.median(g):.4f}), set by {src}; "
          f"block {be:.1f} m east x {bn:.1f} m north")


if __name__ == "__main__":
    main()
