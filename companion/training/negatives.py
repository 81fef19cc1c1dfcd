"""Hard negatives: crops centred on things that are not people but look like them from above.

The static clutter that the findings note and the hidden rooftop scene show the network mistaking
for people: roofs, walls, windows, cars, obstacles, trees, fences and road markings, plus whole
photos with nobody in them. All come from the semantic-drone photos of the training split with
their people inpainted away (:func:`companion.evaluation.compositor.load_semantic`), so every crop
has an all-zero target. numpy / OpenCV only.

Kinds are named as in ``labels/classes.txt`` (looked up by name, so a renumbered class list fails
loudly). ``road-marking`` is not a class there: it is the brightest 2 % of an image's paved-area
pixels (painted lines and symbols are brighter than the asphalt or paving around them). Nor is
``path-edge``: the band ``EDGE_PX`` pixels either side of where paved area meets grass. The shipped
model marks one edge of a paved path across a lawn as people (docs/design.md, "Why landing points
sit at a lawn's edge"; ``python -m sim.evidence.false_positives``). Nor is ``landable``: the ground
a vehicle may land on (paved area, dirt, grass, gravel, as the photo world's truth has it) farther
than ``LANDABLE_CLEAR_PX`` from every person pixel of the class map. On the photo world the shipped
models mark 6-11 % of such real ground as people from 5-8 m (asphalt grain, molehills; issue 59),
the free ground a landing needs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.evaluation.compositor import PERSON, Background
from companion.evaluation.datasets import DatasetError
from companion.training.augment import GeomAug, random_crop

KINDS = ("roof", "wall", "window", "car", "obstacle", "tree", "bald-tree", "fence", "fence-pole", "road-marking",
         "path-edge")
#: Kinds drawn only when named (``--negative-kinds``), so that "all kinds", the default every
#: shipped model was trained with, stays what it was.
OPT_IN = ("landable",)
#: The classes of ``landable`` ground (``sim.world.photo_ground.PHOTO_LANDABLE``'s).
LANDABLE = ("paved-area", "dirt", "grass", "gravel")
#: Kinds made from other classes (``kind_mask``), not classes of their own, and the classes they need.
DERIVED = {"road-marking": ("paved-area",), "path-edge": ("paved-area", "grass"), "landable": (*LANDABLE, "person")}
EMPTY = "no-person-photo"
POINTS_PER_IMAGE = 64  # candidate centres kept per (image, kind): enough variety, little memory
MIN_PIXELS = 30  # a kind with fewer pixels in an image is noise in the class map there
EDGE_PX = 4  # half the width of a path-edge band (pixels of the photo, about 0.1 m on the ground)
#: Pixels (of the 750x500 photos, 0.01-0.07 m each) a ``landable`` centre keeps from every person
#: pixel: a crop's centre is then at least a body's width from anyone, so the crops, whose targets
#: are all zero, teach "bare ground" and not "the ground beside a person" (the inpainting's seams).
LANDABLE_CLEAR_PX = 160


def check_kinds(kinds: Sequence[str] | None) -> tuple[str, ...]:
    """The hard-negative kinds to draw: ``kinds`` checked against ``KINDS`` and ``EMPTY`` (None:
    all of them). ValueError naming an unknown or repeated kind, or an empty list."""
    known = (*KINDS, EMPTY, *OPT_IN)
    if kinds is None:
        return (*KINDS, EMPTY)
    unknown = [k for k in kinds if k not in known]
    if unknown:
        raise ValueError(f"unknown hard-negative kind {', '.join(map(repr, unknown))}; known: {', '.join(known)}")
    if not kinds or len(set(kinds)) != len(kinds):
        raise ValueError(f"hard-negative kinds must be a non-empty list without repeats, got {list(kinds)}")
    return tuple(kinds)


def class_indices(shared: Path) -> dict[str, int]:
    """``labels/classes.txt`` as name -> index."""
    path = Path(shared) / "data" / "semantic_drone" / "labels" / "classes.txt"
    if not path.is_file():
        raise DatasetError(f"missing {path} (see shared/README.md for the layout)")
    out = {}
    for line in path.read_text().splitlines():
        if line.strip():
            idx, name = line.split(maxsplit=1)
            out[name.strip()] = int(idx)
    return out


def kind_mask(kind: str, ground: Background, classes: dict[str, int]) -> np.ndarray:
    """Boolean mask of ``kind``'s pixels in ``ground``."""
    if kind == "road-marking":
        paved = ground.classes == classes["paved-area"]
        if paved.sum() < MIN_PIXELS:
            return np.zeros_like(paved)
        grey = cv2.cvtColor(ground.bgr, cv2.COLOR_BGR2GRAY)
        return paved & (grey > np.percentile(grey[paved], 98))
    if kind == "path-edge":
        paved = ground.classes == classes["paved-area"]
        grass = ground.classes == classes["grass"]
        near = np.ones((2 * EDGE_PX + 1, 2 * EDGE_PX + 1), np.uint8)
        near_paved = cv2.dilate(paved.astype(np.uint8), near) > 0
        near_grass = cv2.dilate(grass.astype(np.uint8), near) > 0
        return np.asarray(near_paved & near_grass & (paved | grass))
    if kind == "landable":
        ground_ok = np.isin(ground.classes, [classes[c] for c in LANDABLE])
        clear = cv2.distanceTransform((ground.classes != classes["person"]).astype(np.uint8), cv2.DIST_L2, 5)
        return np.asarray(ground_ok & (clear > LANDABLE_CLEAR_PX))
    return np.asarray(ground.classes == classes[kind])


@dataclass
class HardNegatives:
    """Draws person-free crops centred on a hard-negative kind (uniform over kinds with any pixels,
    ``EMPTY`` counting as one kind: a random crop of a photo with nobody in it).

    aug: the geometric augmentation of each crop (scale range, rotation).
    """

    grounds: list[Background]
    centres: dict[str, list[tuple[int, np.ndarray]]]  # kind -> [(ground index, (K, 2) x, y)]
    aug: GeomAug = GeomAug((0.4, 1.6), True, 1.0)

    @classmethod
    def build(cls, grounds: Sequence[Background], classes: dict[str, int], seed: int = 0,
              kinds: Sequence[str] | None = None) -> HardNegatives:
        """Index the candidate centres of every kind in ``grounds`` (a ground whose class map has
        no person pixel at all is also an ``EMPTY`` photo). ``kinds``: only these (names from
        ``KINDS`` or ``EMPTY``; None: all), to train on one kind alone and measure what it costs."""
        chosen = check_kinds(kinds)
        needed = {c for k in chosen if k != EMPTY for c in DERIVED.get(k, (k,))}
        missing = sorted(c for c in needed if c not in classes)
        if missing:
            raise DatasetError(f"labels/classes.txt has no class named {', '.join(missing)}")
        rng = np.random.default_rng(seed)
        centres: dict[str, list[tuple[int, np.ndarray]]] = {k: [] for k in chosen}
        for gi, g in enumerate(grounds):
            for kind in (*KINDS, *OPT_IN):
                if kind not in centres:
                    continue
                ys, xs = np.nonzero(kind_mask(kind, g, classes))
                if len(xs) >= MIN_PIXELS:
                    pick = rng.choice(len(xs), min(POINTS_PER_IMAGE, len(xs)), replace=False)
                    centres[kind].append((gi, np.stack([xs[pick], ys[pick]], axis=1).astype(np.float32)))
            if EMPTY in centres and not (g.classes == PERSON).any():
                h, w = g.classes.shape
                centres[EMPTY].append((gi, np.array([[w / 2, h / 2]], np.float32)))
        found = {k: v for k, v in centres.items() if v}
        if not found:
            raise DatasetError(f"no hard negative of the kinds {', '.join(chosen)} in {len(grounds)} photos")
        return cls(list(grounds), found)

    @property
    def kinds(self) -> list[str]:
        return sorted(self.centres)

    def crop(self, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, str]:
        """(``size`` x ``size`` BGR uint8 crop, its all-zero float32 target, the kind)."""
        kinds = self.kinds
        kind = kinds[int(rng.integers(len(kinds)))]
        gi, pts = self.centres[kind][int(rng.integers(len(self.centres[kind])))]
        g = self.grounds[gi]
        zero = np.zeros(g.classes.shape, np.float32)
        # EMPTY: anywhere in the photo (focus 0); a kind: near one of its pixels (focus 1).
        aug = GeomAug(self.aug.scale, self.aug.rotate, 0.0 if kind == EMPTY else 1.0)
        img, _ = random_crop(g.bgr, zero, pts[[int(rng.integers(len(pts)))]], size, aug, rng)
        return img, np.zeros((size, size), np.float32), kind
