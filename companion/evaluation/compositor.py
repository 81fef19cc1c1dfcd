"""Synthetic top-down crowds: real people cut from drone photos, pasted along real crowd layouts.

numpy / OpenCV only (no torch), so ``companion eval`` can measure on the synthetic hold-out and
training (:mod:`companion.training.train`) can draw crops from it. Nothing generated here is
written into the repository: samples live in memory (or wherever a caller writes them, e.g. /tmp).

Ingredients (formats: ``../shared/README.md``):

* **People** (:class:`Cutout`): each 8-connected component of class 15 (person) in a semantic-drone
  class map, with its photo's pixels and the component as alpha. Components that touch the photo's
  border (cut-off people) or are smaller than ``MIN_CUTOUT_PX`` across (fragments) are skipped.
* **Ground** (:class:`Background`): semantic-drone photos with their people inpainted away (class
  15, dilated, OpenCV Telea inpainting), with their class maps. The DroneCrowd frames are not used
  as ground: their annotation is a 20 px head box per person, and inpainting even 60 px around each
  head left bodies, shadows and unannotated people behind, which would teach "person = ground".
* **Layouts** (:class:`Layouts`): the head points of one frame of a real DroneCrowd trajectory
  sequence (``gt/000NN.mat``): real crowd shapes and densities.

One sample (:meth:`Compositor.sample`): a person size ``s`` is drawn log-uniformly from
``person_px`` (5-40 px by default); the ground is warped (scale, any rotation, crop) so that its own
people would be about ``s`` px across (their median size in that photo) (clipped so the ground still covers half the output;
the rest is mirrored); a frame's layout is scaled so that a DroneCrowd person (``LAYOUT_PERSON_PX``)
becomes ``s`` px, rotated and shifted into the image. At each layout point a cutout of about ``s``
px (+-15 %) is resized (area filter), rotated to any heading, its colour mapped from its own
photo's Lab mean/std to the ground's, blurred with one per-sample camera blur, given a soft drop
shadow (one sun direction per sample) and alpha-blended in. Ground classes drawn over people
(trees) cover them partly. A point is skipped when it falls on ground nobody stands on (water,
pool, bushes, roof, wall, window, fence, car, obstacle), when the person would overlap earlier people by
more than ``max_overlap`` of either's area, or when less than ``min_visible`` of it stays visible.

Labels (:class:`Composite`): per pasted person its full silhouette's bounding box (the target the
training renders, as for the semantic-drone person boxes), its size (the box's longer side, px),
one head point (the visible pixel furthest inside its visible silhouette: it always lies on the
person), and an instance map of visible pixels. Nothing else in the image is a person: the ground's
own people were inpainted away.

Splits (:func:`load_compositor`), deterministic and disjoint between ``train`` and ``val``:
semantic-drone photos (people and ground) follow :func:`companion.evaluation.datasets.semantic_drone`
(sorted index % 5 == 0 is ``val``, the held-out fifth); DroneCrowd layouts: sequences whose number is a multiple of 5,
and sequence 17 (the held-out real frame's), are ``val``, all others ``train``.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.io

from companion.evaluation.datasets import DatasetError, Sample, Split, read_image

PERSON = 15
#: Ground classes a person cannot stand on (semantic-drone ``labels/classes.txt`` indices): water,
#: pool, vegetation (bushes, hedges), roof, wall, window, fence, fence-pole, car, obstacle.
NO_STAND = (5, 7, 8, 9, 10, 11, 13, 14, 17, 22)
#: Ground classes drawn over a person standing in them, seen from above: tree, bald-tree.
OCCLUDERS = (19, 20)
MIN_CUTOUT_PX = 8  # a person component smaller than this across is a fragment, not a person
LAYOUT_PERSON_PX = 20.0  # DroneCrowd's head boxes are 20x20 px at 1920x1080: the person's size there
DEFAULT_SEMANTIC_PERSON_PX = 36.0  # median longer side of the semantic-drone person components


@dataclass(frozen=True)
class Cutout:
    """One person cut from a photo: ``bgr`` (h, w, 3) uint8, ``alpha`` (h, w) float32 in [0, 1];
    ``lab_mean`` / ``lab_std`` (3,) of the whole source photo in OpenCV float Lab (L 0-100)."""

    bgr: np.ndarray
    alpha: np.ndarray
    lab_mean: np.ndarray
    lab_std: np.ndarray
    source: str

    @property
    def size(self) -> int:
        """Longer side of the person's bounding box in source pixels."""
        return max(self.alpha.shape)


@dataclass(frozen=True)
class Background:
    """Person-free ground: ``bgr`` (H, W, 3) uint8; ``classes`` (H, W) uint8 class map;
    ``person_px``: how large a person standing on it appears, in its pixels (sets its scale)."""

    name: str
    bgr: np.ndarray
    classes: np.ndarray
    person_px: float


@dataclass(frozen=True)
class Layouts:
    """Real crowd layouts: per DroneCrowd sequence, its ``anno`` rows ``[frame, track, x1, y1, x2, y2]``."""

    sequences: dict[str, np.ndarray]
    frame_wh: tuple[int, int] = (1920, 1080)

    def sample(self, rng: np.random.Generator) -> tuple[str, np.ndarray]:
        """(``"SSS:frame"``, (N, 2) head points in DroneCrowd pixels) of a random frame."""
        names = sorted(self.sequences)
        name = names[int(rng.integers(len(names)))]
        anno = self.sequences[name]
        frames = np.unique(anno[:, 0])
        f = int(frames[int(rng.integers(len(frames)))])
        rows = anno[anno[:, 0] == f]
        pts = np.stack([(rows[:, 2] + rows[:, 4]) / 2.0, (rows[:, 3] + rows[:, 5]) / 2.0], axis=1)
        return f"{name}:{f}", pts.astype(np.float32)


@dataclass(frozen=True)
class CompositorParams:
    """person_px: (lo, hi) person size range in output pixels, sampled log-uniformly per sample.
    jitter: per-person size spread (std of the log size). max_overlap: largest share of a person's
    silhouette that another may cover. min_visible: least share left visible after occlusion.
    shadow: probability that an image's people cast shadows."""

    person_px: tuple[float, float] = (5.0, 40.0)
    jitter: float = 0.15
    max_overlap: float = 0.25
    min_visible: float = 0.4
    shadow: float = 0.8


@dataclass
class Composite:
    """One synthetic image and its labels (output pixels, origin at the top-left pixel corner).

    image: (H, W, 3) uint8 BGR.
    points: (N, 2) float32 one head point per pasted person (pixel centre inside its visible silhouette).
    boxes: (N, 4) float32 ``x1, y1, x2, y2`` of each person's full pasted silhouette.
    sizes: (N,) float32 person size in pixels (the longer side of its box).
    instances: (H, W) int32, 0 = nobody, k = visible pixel of person k - 1.
    classes: (H, W) uint8 the ground's class map as warped into this image (people not included).
    """

    name: str
    image: np.ndarray
    points: np.ndarray
    boxes: np.ndarray
    sizes: np.ndarray
    instances: np.ndarray
    classes: np.ndarray

    def as_sample(self) -> Sample:
        return Sample(self.name, Path("synthetic") / self.name, self.points, self.boxes,
                      sizes=self.sizes, pixels=self.image)


def _box_side(mask: np.ndarray) -> int:
    """Longer side (px) of the bounding box of ``mask``'s pixels; 0 for an empty mask."""
    ys, xs = np.nonzero(mask)
    return int(max(np.ptp(xs), np.ptp(ys)) + 1) if len(xs) else 0


def _lab_stats(bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (3,) float32 of ``bgr``'s pixels in OpenCV float Lab (L 0-100),
    the std at least 1e-3.

    Bit for bit ``lab.mean(axis=0)`` and ``lab.std(axis=0)`` of the (N, 3) float32 pixels: numpy
    sums a column of them one row after another in float32, and so does ``cv2.reduce`` (its
    row-wise float sum), three times faster than numpy's 3-wide reduction, which dominated the
    photo world's rendering (docs/measurements.md, session 30); the divisions are numpy's own
    (float32 sums divided by an integer count, in place)."""
    lab = cv2.cvtColor(bgr.astype(np.float32) / 255.0, cv2.COLOR_BGR2Lab).reshape(-1, 3)
    n = np.intp(lab.shape[0])
    mean = cv2.reduce(lab, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32F)  # (1, 3)
    np.true_divide(mean, n, out=mean, casting="unsafe")
    dev = lab - mean
    np.multiply(dev, dev, out=dev)
    var = cv2.reduce(dev, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32F)
    np.true_divide(var, n, out=var, casting="unsafe")
    return mean.reshape(3), np.maximum(np.sqrt(var, out=var).reshape(3), 1e-3)


def cutouts_from(image: np.ndarray, classes: np.ndarray, source: str,
                 stats: tuple[np.ndarray, np.ndarray] | None = None) -> list[Cutout]:
    """Every whole person (8-connected class-15 component) of one photo, with its mask as alpha;
    ``stats``: the photo's Lab mean and std when the caller has them (else computed here)."""
    n, cc, stats_, _ = cv2.connectedComponentsWithStats((classes == PERSON).astype(np.uint8), connectivity=8)
    h, w = classes.shape
    mean, std = _lab_stats(image) if stats is None else stats
    out = []
    for k in range(1, n):
        x, y, bw, bh, _area = (int(v) for v in stats_[k])
        if max(bw, bh) < MIN_CUTOUT_PX or x == 0 or y == 0 or x + bw == w or y + bh == h:
            continue
        alpha = (cc[y:y + bh, x:x + bw] == k).astype(np.float32)
        out.append(Cutout(image[y:y + bh, x:x + bw].copy(), alpha, mean, std, f"{source}#{k}"))
    return out


def person_free(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` with the pixels of ``mask`` (dilated 2 px) filled in from around them."""
    if not mask.any():
        return image.copy()
    m = cv2.dilate(mask.astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
    return cv2.inpaint(image, m, 3, cv2.INPAINT_TELEA)


def _semantic_names(root: Path, split: Split) -> list[str]:
    names = sorted(p.name for p in (root / "images").glob("*.jpg"))
    if not names:
        raise DatasetError(f"no images in {root / 'images'}")
    keep = {"val": lambda i: i % 5 == 0, "train": lambda i: i % 5 != 0, "all": lambda i: True}[split]
    return [n for i, n in enumerate(names) if keep(i)]


def load_semantic(shared: Path, split: Split, max_images: int = 0) -> tuple[list[Cutout], list[Background]]:
    """People and person-free ground from the semantic-drone photos of ``split``."""
    root = Path(shared) / "data" / "semantic_drone"
    if not (root / "labels").is_dir():
        raise DatasetError(f"missing {root / 'labels'} (see shared/README.md for the layout)")
    boxes = json.loads((root / "person_boxes.json").read_text())
    names = _semantic_names(root, split)
    if max_images:
        names = names[:max_images]
    cutouts: list[Cutout] = []
    grounds: list[Background] = []
    for name in names:
        img = read_image(root / "images" / name)
        classes = cv2.imread(str(root / "labels" / (Path(name).stem + ".png")), cv2.IMREAD_UNCHANGED)
        if classes is None or classes.shape != img.shape[:2]:
            raise DatasetError(f"class map of {name} is missing or not {img.shape[:2]}")
        cutouts += cutouts_from(img, classes, Path(name).stem)
        b = np.asarray(boxes.get(name, []), np.float32).reshape(-1, 4)
        side = float(np.median(np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]))) if len(b) else DEFAULT_SEMANTIC_PERSON_PX
        grounds.append(Background(Path(name).stem, person_free(img, classes == PERSON), classes, side))
    return cutouts, grounds


def layout_split(sequence: int) -> Split:
    """``val`` for DroneCrowd sequences that are multiples of 5 and for 17 (``img017012``'s), else ``train``."""
    return "val" if sequence % 5 == 0 or sequence == 17 else "train"


def load_layouts(shared: Path, split: Split) -> Layouts:
    root = Path(shared) / "data" / "dronecrowd" / "gt"
    files = sorted(root.glob("[0-9]*.mat"))
    if not files:
        raise DatasetError(f"no DroneCrowd trajectories in {root}")
    seqs = {f.stem: scipy.io.loadmat(f)["anno"].astype(np.float32) for f in files
            if split == "all" or layout_split(int(f.stem)) == split}
    return Layouts(seqs)


class Compositor:
    """Draws :class:`Composite` samples; deterministic for a given ``rng`` state."""

    def __init__(self, cutouts: Sequence[Cutout], grounds: Sequence[Background], layouts: Layouts,
                 params: CompositorParams = CompositorParams()) -> None:
        if not cutouts or not grounds or not layouts.sequences:
            raise ValueError("the compositor needs at least one cutout, one background and one layout")
        self.cutouts = sorted(cutouts, key=lambda c: c.size)
        self._sizes = np.array([c.size for c in self.cutouts], np.float64)
        self.grounds = list(grounds)
        self.layouts = layouts
        self.params = params

    def _cutout(self, size: float, rng: np.random.Generator) -> Cutout:
        # Prefer a source at least 0.7x the wanted size: downscaling keeps detail, upscaling blurs.
        lo = int(np.searchsorted(self._sizes, 0.7 * size))
        lo = min(lo, len(self.cutouts) - 1)
        return self.cutouts[int(rng.integers(lo, len(self.cutouts)))]

    def sample(self, rng: np.random.Generator, size: tuple[int, int] = (512, 512), name: str = "") -> Composite:
        """One synthetic image of ``size`` (height, width) pixels with its labels."""
        p = self.params
        h, w = size
        s = float(np.exp(rng.uniform(math.log(p.person_px[0]), math.log(p.person_px[1]))))
        g = self.grounds[int(rng.integers(len(self.grounds)))]
        gh, gw = g.bgr.shape[:2]
        cover = max(h / gh, w / gw)
        r = max(s / g.person_px, 0.5 * cover)  # ground at the people's scale, but covering half the output
        ang = float(rng.uniform(0, 360))
        gc = (float(rng.uniform(0, gw)), float(rng.uniform(0, gh)))
        m = cv2.getRotationMatrix2D(gc, ang, r)
        m[:, 2] += np.array([w / 2 - gc[0], h / 2 - gc[1]])
        img = cv2.warpAffine(g.bgr, m, (w, h), flags=cv2.INTER_AREA if r < 1 else cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REFLECT_101)
        classes = cv2.warpAffine(g.classes, m, (w, h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REFLECT_101)
        bg_mean, bg_std = _lab_stats(img)
        colour = float(rng.uniform(0.2, 0.7))  # how far the people's colours move to the ground's
        cam_blur = float(rng.uniform(0.3, 0.8))  # one camera blur (Gaussian sigma, px) per image
        sun = float(rng.uniform(0, 2 * math.pi))
        shadow_len, shadow_dark = float(rng.uniform(0.2, 0.6)), float(rng.uniform(0.2, 0.5))
        shadows = rng.random() < p.shadow

        lname, pts = self.layouts.sample(rng)
        f = s / LAYOUT_PERSON_PX
        # Centre the window near a random person of the frame, so that most samples hold a crowd.
        lc = pts[int(rng.integers(len(pts)))] if len(pts) else np.array(self.layouts.frame_wh) / 2
        lc = lc + rng.normal(0, 0.25 * min(h, w) / f, 2)
        la = rng.uniform(0, 2 * math.pi)
        rot = np.array([[math.cos(la), -math.sin(la)], [math.sin(la), math.cos(la)]])
        out_pts = (pts - lc) @ rot.T * f + (w / 2, h / 2)
        order = rng.permutation(len(out_pts))

        inst = np.zeros((h, w), np.int32)
        areas: list[int] = []  # full silhouette pixels per person
        visible: list[int] = []  # its pixels still visible (not under trees or later people)
        boxes: list[tuple[float, float, float, float]] = []
        img_f = img.astype(np.float32)
        for idx in order:
            cx, cy = out_pts[idx]
            if not (0 <= cx < w and 0 <= cy < h):
                continue
            if classes[int(cy), int(cx)] in NO_STAND:
                continue
            lo, hi = p.person_px
            want = float(np.clip(s * np.exp(rng.normal(0, p.jitter)), lo, hi))
            cut = self._cutout(want, rng)
            heading = float(rng.uniform(0, 360))
            pb, pa = self._render(cut, want, heading, cam_blur, bg_mean, bg_std, colour)
            got = _box_side(pa >= 0.5)
            if got and not lo <= got <= hi:  # the silhouette's box at this heading left the range: rescale
                want *= float(np.clip(got, lo, hi)) / got
                pb, pa = self._render(cut, want, heading, cam_blur, bg_mean, bg_std, colour)
            ph, pw = pa.shape
            x0, y0 = int(round(cx - pw / 2)), int(round(cy - ph / 2))
            ix0, iy0, ix1, iy1 = max(x0, 0), max(y0, 0), min(x0 + pw, w), min(y0 + ph, h)
            if ix0 >= ix1 or iy0 >= iy1:
                continue
            sl = (slice(iy0, iy1), slice(ix0, ix1))
            ps = (slice(iy0 - y0, iy1 - y0), slice(ix0 - x0, ix1 - x0))
            alpha = pa[ps]
            full = alpha >= 0.5
            area = int(full.sum())
            if area < 3 or area < 0.5 * (pa >= 0.5).sum():  # mostly outside the image: skip
                continue
            occ = np.isin(classes[sl], OCCLUDERS)
            alpha = alpha * ~occ
            vis = full & ~occ
            if vis.sum() < max(3, p.min_visible * area):
                continue
            under = inst[sl][vis]
            if under.any():
                # Each earlier person keeps most of its silhouette and some visible pixels.
                ids, counts = np.unique(under[under > 0], return_counts=True)
                if counts.sum() > p.max_overlap * area or any(
                        c > p.max_overlap * areas[i - 1] or visible[i - 1] - c < 3 for i, c in zip(ids, counts)):
                    continue
                for i, c in zip(ids, counts):
                    visible[i - 1] -= int(c)
            if shadows:
                self._shadow(img_f, pa, x0, y0, want, sun, shadow_len, shadow_dark)
            a = alpha[..., None]
            img_f[sl] = a * pb[ps] + (1 - a) * img_f[sl]
            areas.append(area)
            visible.append(int(vis.sum()))
            inst[sl][vis] = len(areas)
            ys, xs = np.nonzero(full)
            boxes.append((ix0 + xs.min(), iy0 + ys.min(), ix0 + xs.max() + 1.0, iy0 + ys.max() + 1.0))
        image = np.clip(img_f + 0.5, 0, 255).astype(np.uint8)
        return self._labels(name or lname, image, inst, boxes, classes)

    @staticmethod
    def _render(cut: Cutout, size: float, angle: float, blur: float, bg_mean: np.ndarray, bg_std: np.ndarray,
                colour: float) -> tuple[np.ndarray, np.ndarray]:
        """The cutout at ``size`` px, rotated, colour-matched and blurred: (float32 BGR 0-255, alpha)."""
        k = size / cut.size
        ch, cw = cut.alpha.shape
        nw, nh = max(1, round(cw * k)), max(1, round(ch * k))
        interp = cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR
        bgr: np.ndarray = cv2.resize(cut.bgr, (nw, nh), interpolation=interp).astype(np.float32) / 255.0
        alpha = cv2.resize(cut.alpha, (nw, nh), interpolation=interp)
        # Colour: move the source photo's Lab statistics toward the ground's (exposure, white balance).
        lab = cv2.cvtColor(bgr, cv2.COLOR_BGR2Lab)
        gain = 1 + colour * (np.clip(bg_std / cut.lab_std, 0.7, 1.4) - 1)  # keep the person's own contrast
        gain[1:] = 1.0  # chroma: shift only, a std ratio of near-grey ground would blow it up
        lab = (lab - cut.lab_mean) * gain + cut.lab_mean + colour * (bg_mean - cut.lab_mean)
        lab[..., 0] = np.clip(lab[..., 0], 0, 100)
        bgr = cv2.cvtColor(lab.astype(np.float32), cv2.COLOR_Lab2BGR) * 255.0
        # Rotate about the centre into a square canvas that holds any heading, with a blur margin.
        side = int(math.ceil(math.hypot(nw, nh))) + 4
        m = cv2.getRotationMatrix2D((nw / 2, nh / 2), angle, 1.0)
        m[:, 2] += np.array([side / 2 - nw / 2, side / 2 - nh / 2])
        bgr = cv2.warpAffine(bgr, m, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        alpha = cv2.warpAffine(alpha, m, (side, side), flags=cv2.INTER_LINEAR, borderValue=0)
        bgr = cv2.GaussianBlur(bgr, (0, 0), blur)
        alpha = cv2.GaussianBlur(alpha, (0, 0), blur)
        return bgr, np.clip(alpha, 0, 1)

    @staticmethod
    def _shadow(img: np.ndarray, alpha: np.ndarray, x0: int, y0: int, size: float, sun: float,
                length: float, dark: float) -> None:
        """Darken ``img`` in place under a soft copy of ``alpha`` shifted away from the sun."""
        h, w = img.shape[:2]
        dx, dy = length * size * math.cos(sun), length * size * math.sin(sun)
        sig = 0.12 * size + 0.5
        pad = int(math.ceil(abs(dx) + abs(dy) + 3 * sig)) + 1
        ph, pw = alpha.shape
        canvas = np.zeros((ph + 2 * pad, pw + 2 * pad), np.float32)
        m = np.array([[1, 0, pad + dx], [0, 1, pad + dy]], np.float32)
        canvas = cv2.warpAffine(alpha, m, (canvas.shape[1], canvas.shape[0]), flags=cv2.INTER_LINEAR)
        canvas = cv2.GaussianBlur(canvas, (0, 0), sig)
        cx0, cy0 = x0 - pad, y0 - pad
        ix0, iy0 = max(cx0, 0), max(cy0, 0)
        ix1, iy1 = min(cx0 + canvas.shape[1], w), min(cy0 + canvas.shape[0], h)
        if ix0 >= ix1 or iy0 >= iy1:
            return
        sh = canvas[iy0 - cy0:iy1 - cy0, ix0 - cx0:ix1 - cx0]
        img[iy0:iy1, ix0:ix1] *= (1 - dark * sh)[..., None]

    @staticmethod
    def _labels(name: str, image: np.ndarray, inst: np.ndarray,
                boxes: list[tuple[float, float, float, float]], classes: np.ndarray) -> Composite:
        pts = np.zeros((len(boxes), 2), np.float32)
        for k, (x1, y1, x2, y2) in enumerate(boxes, start=1):
            xa, ya, xb, yb = int(x1), int(y1), int(x2), int(y2)
            vis = (inst[ya:yb, xa:xb] == k).astype(np.uint8)
            # The visible pixel furthest from the silhouette's edge (pad: the box edge is an edge too).
            dist = cv2.distanceTransform(np.pad(vis, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
            r, c = np.unravel_index(int(np.argmax(dist)), dist.shape)
            pts[k - 1] = (xa + c + 0.5, ya + r + 0.5)
        b = np.asarray(boxes, np.float32).reshape(-1, 4)
        sizes = np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]) if len(b) else np.zeros(0, np.float32)
        return Composite(name, image, pts, b, sizes.astype(np.float32), inst, classes)


def load_compositor(shared: Path, split: Split, params: CompositorParams = CompositorParams(),
                    max_images: int = 0) -> Compositor:
    """The compositor of one split (module docstring: which people, ground and layouts each holds).

    max_images: use only the first N semantic-drone photos of the split (quick runs and tests).
    """
    cutouts, grounds = load_semantic(shared, split, max_images)
    return Compositor(cutouts, grounds, load_layouts(shared, split), params)


def synthetic_set(shared: Path, n: int = 200, seed: int = 13, size: tuple[int, int] = (512, 512),
                  split: Split = "val") -> list[Sample]:
    """The synthetic hold-out: ``n`` composites of ``split`` (default ``val``), seeded, as samples."""
    comp = load_compositor(shared, split)
    rng = np.random.default_rng(seed)
    return [comp.sample(rng, size, name=f"synthetic_{split}_{i:04d}").as_sample() for i in range(n)]


def main(argv: list[str] | None = None) -> int:
    """Time the compositor and optionally write samples for a look (never into the repository)::

        python -m companion.evaluation.compositor --shared ../shared --n 100 --size 512 --out /tmp/synth
    """
    import argparse
    import time

    p = argparse.ArgumentParser(description="time synthetic top-down crowd samples; optionally write them")
    p.add_argument("--shared", type=Path, default=Path("../shared"))
    p.add_argument("--split", choices=["train", "val"], default="train")
    p.add_argument("--n", type=int, default=100, help="samples to draw")
    p.add_argument("--size", type=int, default=512, help="side of each sample in pixels")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="write image PNGs and a labels JSON here (outside the repository)")
    args = p.parse_args(argv)
    if args.n < 1 or args.size < 16:
        p.error("--n must be >= 1 and --size >= 16")
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    try:
        comp = load_compositor(args.shared, args.split)
    except DatasetError as exc:
        print(f"compositor: {exc}", file=sys.stderr)
        return 2
    print(f"loaded the {args.split} split in {time.perf_counter() - t0:.1f} s: {len(comp.cutouts)} people, "
          f"{len(comp.grounds)} grounds, {len(comp.layouts.sequences)} layout sequences")
    rng = np.random.default_rng(args.seed)
    times, people, labels = [], [], {}
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
    for i in range(args.n):
        t = time.perf_counter()
        c = comp.sample(rng, (args.size, args.size), name=f"{args.split}_{i:04d}")
        times.append(time.perf_counter() - t)
        people.append(len(c.points))
        if args.out:
            cv2.imwrite(str(args.out / f"{c.name}.png"), c.image)
            labels[c.name] = {"points": c.points.tolist(), "boxes": c.boxes.tolist(), "sizes": c.sizes.tolist()}
    if args.out:
        (args.out / "labels.json").write_text(json.dumps(labels))
    ms = 1e3 * np.asarray(times)
    print(f"{args.n} samples of {args.size}x{args.size}: median {np.median(ms):.1f} ms, mean {ms.mean():.1f} ms, "
          f"p90 {np.percentile(ms, 90):.1f} ms; people per sample median {np.median(people):.0f}, max {max(people)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
