"""Loaders for the crowd data sets in ``../shared/data`` (formats: ``../shared/README.md``).

numpy / scipy / OpenCV only, so evaluation runs without torch; training reuses them.
Every loader returns :class:`Sample` records whose annotations are in the image's own pixels
(x right, y down, origin at the top-left pixel corner as the data sets give them).

The semantic-drone validation split is fixed: the images whose index in the sorted list of names
is a multiple of 5 are held out (``semantic_drone_split(..., "val")``), the rest train.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import scipy.io

Split = Literal["train", "val", "all"]

#: The DroneCrowd frames the shipped model trained on (sequence 112, frames 8-12); ``img017012``
#: (another sequence) is held out.
DRONECROWD_TRAIN = [f"img112{k:03d}" for k in range(8, 13)]
# The six real DroneCrowd frames kept in shared/: file stem -> (gt sequence file, 0-based frame).
DRONECROWD_FRAMES: dict[str, tuple[str, int]] = {
    **{name: ("00112.mat", int(name[-3:]) - 1) for name in DRONECROWD_TRAIN},
    "img017012": ("00017.mat", 11),
}
MALL_FIRST, MALL_LAST = 801, 2000
#: Factors of the downscaled semantic-drone hold-out (real photos of smaller people; see ``scaled``).
SEMANTIC_SCALES = (0.5, 0.25)


class DatasetError(FileNotFoundError):
    """A data set is missing or not in the documented layout."""


@dataclass
class Sample:
    """One annotated image.

    points: (N, 2) float32 head points (x, y) in pixels; for box data sets, the box centres.
    boxes: (N, 4) float32 person boxes (x1, y1, x2, y2) in pixels, or None for point data sets.
    sizes: (N,) float32 person size in pixels (longer side of the person's box), or None where the
        data set does not give it (head points alone, or DroneCrowd's fixed 20 px head boxes).
    pixels: the image itself when it lives in memory (synthetic sets), else None (read ``path``).
    """

    name: str
    path: Path
    points: np.ndarray
    boxes: np.ndarray | None = None
    meta: dict[str, object] = field(default_factory=dict)
    sizes: np.ndarray | None = None
    pixels: np.ndarray | None = None

    def image(self) -> np.ndarray:
        """The image as HxWx3 BGR uint8."""
        return self.pixels if self.pixels is not None else read_image(self.path)


#: The held-out semantic-drone photos at full size (``../shared/data/semantic_drone/full``): the
#: simulator's photo ground (``sim.world.photo_ground``), kept out of every training set.
HELD_OUT_FULL = ("semantic_drone", "full")


def refuse_held_out(path: Path) -> None:
    """Raise DatasetError for a path inside ``semantic_drone/full``: those photos are the held-out
    fifth at full size, the simulator's photo ground, and no loader here may read them (so no
    training or calibration set can hold them)."""
    parts = Path(path).resolve().parts
    for i in range(len(parts) - 1):
        if parts[i:i + 2] == HELD_OUT_FULL:
            raise DatasetError(f"{path} is one of the held-out full-size semantic-drone photos (the "
                               "simulator's photo ground): never read for training or calibration")


def read_image(path: Path) -> np.ndarray:
    """A photo of a data set (BGR uint8); refuses the held-out ``semantic_drone/full`` photos."""
    refuse_held_out(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"cannot read image {path}")
    return img


def _need(path: Path) -> Path:
    if not path.exists():
        raise DatasetError(f"missing {path} (see shared/README.md for the layout)")
    return path


def _points(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float32).reshape(-1, 2) if np.size(a) else np.zeros((0, 2), np.float32)
    return a[:, :2].astype(np.float32)


def shanghaitech_b(shared: Path, split: Literal["train", "test"]) -> list[Sample]:
    """ShanghaiTech Part B, ``train`` (400) or ``test`` (the 100 kept in shared), head points."""
    root = _need(Path(shared) / "data" / "shanghaitech_b" / f"{split}_data")
    out = []
    for img in sorted((root / "images").glob("IMG_*.jpg"), key=lambda p: int(p.stem.split("_")[1])):
        gt = _need(root / "ground-truth" / f"GT_{img.stem}.mat")
        pts = scipy.io.loadmat(gt)["image_info"][0, 0][0, 0][0]
        out.append(Sample(img.stem, img, _points(pts)))
    if not out:
        raise DatasetError(f"no images in {root / 'images'}")
    return out


def mall(shared: Path, step: int = 1) -> list[Sample]:
    """Mall frames 801-2000 (every ``step``-th), head points, 640x480."""
    if step < 1:
        raise ValueError(f"mall step must be >= 1, got {step}")
    root = _need(Path(shared) / "data" / "mall")
    frames = scipy.io.loadmat(_need(root / "mall_gt.mat"))["frame"][0]
    out = []
    for n in range(MALL_FIRST, MALL_LAST + 1, step):
        img = _need(root / "frames" / f"seq_{n:06d}.jpg")
        out.append(Sample(img.stem, img, _points(frames[n - 1]["loc"][0, 0])))
    return out


def dronecrowd_frames(shared: Path, names: list[str] | None = None) -> list[Sample]:
    """The real DroneCrowd frames kept in shared (1920x1080), head points (centres of head boxes)."""
    root = _need(Path(shared) / "data" / "dronecrowd")
    cache: dict[str, np.ndarray] = {}
    out = []
    for stem in names or sorted(DRONECROWD_FRAMES):
        gt_name, frame = DRONECROWD_FRAMES[stem]
        if gt_name not in cache:
            cache[gt_name] = scipy.io.loadmat(_need(root / "gt" / gt_name))["anno"]
        anno = cache[gt_name]
        rows = anno[anno[:, 0] == frame]
        pts = np.stack([(rows[:, 2] + rows[:, 4]) / 2.0, (rows[:, 3] + rows[:, 5]) / 2.0], axis=1)
        img = _need(root / "frames" / stem[:6] / f"{stem}.jpg")
        out.append(Sample(stem, img, pts.astype(np.float32), meta={"sequence": gt_name, "frame": frame}))
    return out


def semantic_drone(shared: Path, split: Split = "all") -> list[Sample]:
    """ICG Semantic Drone photos (750x500) with person boxes; ``val`` = sorted index % 5 == 0."""
    root = _need(Path(shared) / "data" / "semantic_drone")
    boxes = json.loads(_need(root / "person_boxes.json").read_text())
    names = sorted(p.name for p in (root / "images").glob("*.jpg"))
    if not names:
        raise DatasetError(f"no images in {root / 'images'}")
    out = []
    for i, name in enumerate(names):
        held_out = i % 5 == 0
        if (split == "val" and not held_out) or (split == "train" and held_out):
            continue
        b = np.asarray(boxes.get(name, []), dtype=np.float32).reshape(-1, 4)
        centres = np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], axis=1)
        sizes = np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]).astype(np.float32)
        out.append(Sample(Path(name).stem, root / "images" / name, centres.astype(np.float32), b, sizes=sizes))
    return out


def semantic_labels(sample: Sample) -> np.ndarray:
    """The per-pixel class map (uint8, the photo's size) of a :func:`semantic_drone` sample:
    ``labels/NNN.png`` beside ``images/NNN.jpg``; class names in ``labels/classes.txt``."""
    path = sample.path.parent.parent / "labels" / f"{sample.path.stem}.png"
    lab = cv2.imread(str(_need(path)), cv2.IMREAD_UNCHANGED)
    if lab is None or lab.ndim != 2 or lab.dtype != np.uint8:
        raise DatasetError(f"cannot read {path} as an 8-bit class map")
    return lab


def semantic_classes(shared: Path) -> dict[str, int]:
    """``labels/classes.txt`` of the semantic drone set as class name -> index."""
    path = _need(Path(shared) / "data" / "semantic_drone" / "labels" / "classes.txt")
    out: dict[str, int] = {}
    for line in path.read_text().splitlines():
        if line.strip():
            idx, name = line.split(maxsplit=1)
            out[name.strip()] = int(idx)
    return out


def scaled(samples: list[Sample], factor: float, suffix: str = "") -> list[Sample]:
    """``samples`` resized by ``factor`` (area filter) in memory, annotations scaled alike.

    Used to measure recall on real photos at person sizes a set lacks (semantic-drone people are
    mostly 16-100 px; at x0.25 they are 4-25 px). A downscaled photo is close to, not the same as,
    one taken from higher up (no extra haze, motion or sensor noise): the model card says so.
    """
    if not 0 < factor <= 1:
        raise ValueError(f"scale factor must be in (0, 1], got {factor}")
    out = []
    for s in samples:
        img = s.image()
        h, w = img.shape[:2]
        small = cv2.resize(img, (max(1, round(w * factor)), max(1, round(h * factor))), interpolation=cv2.INTER_AREA)
        fx, fy = small.shape[1] / w, small.shape[0] / h
        pts = (s.points * np.array([fx, fy], np.float32)).astype(np.float32)
        boxes = None if s.boxes is None else (s.boxes * np.array([fx, fy, fx, fy], np.float32)).astype(np.float32)
        sizes = None if s.sizes is None else (s.sizes * max(fx, fy)).astype(np.float32)
        out.append(Sample(s.name + suffix, s.path, pts, boxes, dict(s.meta), sizes, small))
    return out
