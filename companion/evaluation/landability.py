"""Figures of a landability model on the semantic-drone photos: IoU per risk level, per class,
and how much of each proposed landing circle truly is landable ground.

* **Per-level IoU**: each pixel's predicted level is the argmax of the model's level
  probabilities (cells brought to pixels by nearest neighbour), its true level the level of its
  labelled class (the grouping in the model's metadata); IoU = TP / (TP + FP + FN), pooled over
  the images. Also the IoU of the binary decision the pipeline makes (unlandable where the
  probability of the unlandable levels exceeds the model's threshold, no dilation).
* **Per class**: the model predicts levels, not the data set's 24 classes, so a class has no IoU
  of its own. Per class we give the share of its pixels put in its own level (``in_level``) and
  the share the pipeline's decision calls unlandable (``unlandable``: should be ~1 for every class
  outside the landable level, ~0 inside it).
* **Landable share of the circles**: the whole pipeline (people density + landability, default
  settings) on each photo under a fixed straight-down projection (``gsd`` m/px); for each proposed
  circle, the share of its pixels whose labelled class is in the landable level.

Pure numpy / OpenCV over :mod:`companion.evaluation.datasets`; the pipeline is imported, not copied.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from companion.evaluation.datasets import Sample, semantic_labels
from companion.geometry.camera import PlaneProjection
from companion.pipeline.landability import LandabilityModel, RiskLevel
from companion.pipeline.slz import PipelineConfig, SLZPipeline

#: Level code of a class that no level holds (never happens for a valid grouping).
NO_LEVEL = 255
#: Ground sample distance assumed for the 750x500 semantic-drone photos (m/px): taken from 5-30 m
#: (ICG), about 4 cm per pixel at 20 m after the halving of shared/README.md.
SEMANTIC_GSD = 0.04


def level_lut(levels: Sequence[RiskLevel], classes: Mapping[str, int]) -> np.ndarray:
    """uint8 lookup table class index -> level index (``NO_LEVEL`` for unused codes).

    ValueError when a level names a class the data set lacks, or a class of the data set is in
    no level (a grouping must say where every class goes)."""
    lut = np.full(256, NO_LEVEL, np.uint8)
    placed: set[str] = set()
    for li, lv in enumerate(levels):
        for c in lv.classes:
            if c not in classes:
                raise ValueError(f"level {lv.name!r} names class {c!r}, which labels/classes.txt does not have")
            lut[classes[c]] = li
            placed.add(c)
    missing = sorted(set(classes) - placed)
    if missing:
        raise ValueError(f"class(es) {', '.join(missing)} of labels/classes.txt are in no level")
    return lut


def cells_to_pixels(cells: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
    """A per-cell map (h', w') or (L, h', w') brought to (H, W) by nearest neighbour (a cell of
    stride s covers s x s pixels; the map's last cells may overhang the image)."""
    h, w = image_hw
    a = np.asarray(cells)
    sy, sx = -(-h // a.shape[-2]), -(-w // a.shape[-1])
    rows = np.minimum(np.arange(h) // sy, a.shape[-2] - 1)
    cols = np.minimum(np.arange(w) // sx, a.shape[-1] - 1)
    return a[..., rows[:, None], cols[None, :]]


@dataclass
class LandabilityResult:
    """Pooled figures on one set of photos (see the module docstring)."""

    images: int
    levels: list[str]
    level_iou: dict[str, float]
    mean_iou: float
    pixel_accuracy: float
    unlandable_iou: float
    landable_iou: float
    class_in_level: dict[str, float]
    class_unlandable: dict[str, float]
    class_pixels: dict[str, int]
    threshold: float
    circles: int = 0
    circle_landable_pooled: float = float("nan")
    circle_landable_min: float = float("nan")
    circle_landable_median: float = float("nan")
    circles_at_least_99: float = float("nan")
    images_with_circles: int = 0
    gsd: float = SEMANTIC_GSD
    per_circle: list[dict[str, Any]] = field(default_factory=list)


def _iou(tp: float, fp: float, fn: float) -> float:
    return tp / (tp + fp + fn) if tp + fp + fn else float("nan")


def circle_mask(proj: PlaneProjection, x: float, y: float, r: float, image_hw: tuple[int, int]) -> np.ndarray:
    """Boolean image mask of the plane circle (x, y, r) metres under ``proj``."""
    a = np.linspace(0.0, 2.0 * np.pi, 144, endpoint=False)
    uv = proj.plane_to_image(np.column_stack([x + r * np.cos(a), y + r * np.sin(a)]))
    mask = np.zeros(image_hw, np.uint8)
    if np.isfinite(uv).all():
        cv2.fillPoly(mask, [np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)], 1, cv2.LINE_8, shift=4)
    return mask.astype(bool)


def evaluate_landability(samples: Sequence[Sample], model: LandabilityModel, classes: Mapping[str, int],
                         density: Callable[[np.ndarray], np.ndarray] | None = None,
                         config: PipelineConfig | None = None, gsd: float = SEMANTIC_GSD,
                         unlandable_levels: Sequence[str] | None = None) -> LandabilityResult:
    """All figures on ``samples`` (semantic-drone photos with label maps).

    density: the people model for the pipeline's circles (None: no circle figures).
    config: the pipeline's settings (default: ``PipelineConfig()``, the model's thresholds).
    unlandable_levels: the configured set (None: all but the landable level).
    """
    spec = model.landability
    names = list(spec.names)
    L = len(names)
    lut = level_lut(spec.levels, classes)
    inv = {v: k for k, v in classes.items()}
    surface = model.unlandable(unlandable_levels)
    unl_idx = set(surface.channels)
    thr = spec.threshold
    conf = np.zeros((L, L), np.int64)  # true x predicted
    n_cls = np.zeros(256, np.int64)
    in_level = np.zeros(256, np.int64)
    called_unl = np.zeros(256, np.int64)
    bin_tp = bin_fp = bin_fn = bin_tn = 0
    shares: list[float] = []
    inside_landable = inside_all = 0
    per_circle: list[dict[str, Any]] = []
    images_with = 0
    proj = PlaneProjection.nadir(gsd)
    pipe_cfg = config or PipelineConfig()
    for s in samples:
        img = s.image()
        hw = img.shape[:2]
        labels = semantic_labels(s)
        truth = lut[labels]
        probs = model(img)
        pred = cells_to_pixels(np.argmax(probs, axis=0).astype(np.uint8), hw)
        p_unl = cells_to_pixels(probs[sorted(unl_idx)].sum(axis=0) if unl_idx else np.zeros(probs.shape[1:]), hw)
        ok = truth != NO_LEVEL
        conf += np.bincount(truth[ok].astype(np.int64) * L + pred[ok], minlength=L * L).reshape(L, L)
        n_cls += np.bincount(labels.ravel(), minlength=256)
        in_level += np.bincount(labels[pred == truth], minlength=256)
        is_unl = p_unl > thr
        called_unl += np.bincount(labels[is_unl], minlength=256)
        true_unl = np.isin(truth, list(unl_idx))
        bin_tp += int((is_unl & true_unl).sum())
        bin_fp += int((is_unl & ~true_unl).sum())
        bin_fn += int((~is_unl & true_unl).sum())
        bin_tn += int((~is_unl & ~true_unl).sum())
        if density is None:
            continue
        pipe = SLZPipeline(density, pipe_cfg, projection=proj, surface=surface)
        res = pipe.process(img, 0.0)
        if res.proposals:
            images_with += 1
        landable_px = truth == names.index(spec.landable)
        for c, edge in zip(res.proposals, res.proposal_edges):
            m = circle_mask(proj, c.x, c.y, c.r, hw)
            n = int(m.sum())
            if n == 0:
                continue
            good = int((m & landable_px).sum())
            inside_landable += good
            inside_all += n
            shares.append(good / n)
            bad = np.bincount(labels[m & ~landable_px], minlength=256)
            per_circle.append({"image": s.name, "x": c.x, "y": c.y, "r": c.r, "pixels": n,
                               "landable": good / n, "edge": edge,
                               "not_landable": {inv.get(k, str(k)): int(v) for k, v in enumerate(bad) if v}})
    tp = np.diag(conf).astype(float)
    fp = conf.sum(axis=0) - tp
    fn = conf.sum(axis=1) - tp
    level_iou = {n: _iou(tp[i], fp[i], fn[i]) for i, n in enumerate(names)}
    valid = [v for v in level_iou.values() if np.isfinite(v)]
    present = {inv[k]: int(n_cls[k]) for k in sorted(inv) if n_cls[k]}
    res_ = LandabilityResult(
        images=len(samples), levels=names, level_iou=level_iou,
        mean_iou=float(np.mean(valid)) if valid else float("nan"),
        pixel_accuracy=float(tp.sum() / max(conf.sum(), 1)),
        unlandable_iou=_iou(bin_tp, bin_fp, bin_fn), landable_iou=_iou(bin_tn, bin_fn, bin_fp),
        class_in_level={inv[k]: float(in_level[k] / n_cls[k]) for k in sorted(inv) if n_cls[k]},
        class_unlandable={inv[k]: float(called_unl[k] / n_cls[k]) for k in sorted(inv) if n_cls[k]},
        class_pixels=present, threshold=thr, gsd=gsd, per_circle=per_circle,
    )
    if density is not None:
        res_.circles = len(shares)
        res_.images_with_circles = images_with
        if shares:
            a = np.asarray(shares)
            res_.circle_landable_pooled = inside_landable / inside_all
            res_.circle_landable_min = float(a.min())
            res_.circle_landable_median = float(np.median(a))
            res_.circles_at_least_99 = float((a >= 0.99).mean())
    return res_
