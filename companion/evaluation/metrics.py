"""The figures a density model is judged by: occupancy head recall and free area, counts, latency.

Recall and free area follow the pipeline exactly: the density map goes through
:func:`companion.pipeline.occupancy.occupancy_map` (threshold above ``min(D)``, 5x5 kernel,
2 dilations by default); a head (or person-box centre) counts as covered when its pixel is
occupied; the free share is the share of the frame's pixels left free. Figures over a data set
pool all heads and all pixels of its images.

For the recall/free curve over many thresholds, :func:`level_map` gives, per image pixel, the
largest threshold at which the pixel is still occupied; ``level > t`` is then exactly the
occupied mask of ``occupancy_map`` at threshold ``t`` (dilation by a box kernel and nearest
upscaling commute with thresholding), so one map serves every threshold.

Recall by person size (:func:`size_recall`, :func:`min_person_px`) needs each person's size, which
only some sets give (``Sample.sizes``: the longer side of the person's box in pixels): the
semantic-drone photos (their person boxes) and the synthetic sets (the pasted silhouettes).
DroneCrowd's 20x20 head boxes, Mall and ShanghaiTech give head points only, so they have none.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from companion.evaluation.datasets import Sample
from companion.pipeline.occupancy import FREE, OccupancyParams, occupancy_map

# Thresholds above min(D) for the curve; geometric so both probability-like maps (ours, 0-1) and
# true density maps (MCNN, ~1e-3 per pixel) get a usable curve.
CURVE_THRESHOLDS: tuple[float, ...] = (0.0, *np.geomspace(1e-4, 0.9, 48).tolist())
#: Person-size bin edges in pixels (longer side of the person's box) for recall by size.
SIZE_EDGES: tuple[float, ...] = (0.0, 5.0, 8.0, 12.0, 16.0, 24.0, 40.0, 64.0, float("inf"))
SIZE_RECALL_TARGET = 0.995
#: Fewest people at or above a size for a 99.5 % claim: below 200, one miss already fails it.
SIZE_MIN_PEOPLE = 200


def level_map(density: np.ndarray, image_hw: tuple[int, int], kernel: int = 5, iterations: int = 2) -> np.ndarray:
    """float32 image-size map: pixel occupied at threshold t  <=>  level > t (see module doc)."""
    d = np.asarray(density, np.float32)
    finite = np.isfinite(d)
    lv: np.ndarray = np.full(d.shape, np.inf, np.float32)
    if finite.any():
        lv[finite] = d[finite] - d[finite].min()
    h, w = image_hw
    if lv.shape != (h, w):
        if lv.shape[0] > h or lv.shape[1] > w:
            raise ValueError(f"density map {lv.shape} larger than the image {image_hw}: not a supported case")
        lv = cv2.resize(lv, (w, h), interpolation=cv2.INTER_NEAREST)
    if iterations > 0 and kernel > 1:
        lv = cv2.dilate(lv, np.ones((kernel, kernel), np.uint8), iterations=iterations)
    return lv


def head_pixels(points: np.ndarray, image_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the pixels holding each point (clipped into the image)."""
    h, w = image_hw
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    cols = np.clip(np.floor(pts[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.floor(pts[:, 1]).astype(int), 0, h - 1)
    return rows, cols


@dataclass
class OccupancyTally:
    """Pooled counts over images at one threshold."""

    heads: int = 0
    covered: int = 0
    pixels: int = 0
    free: int = 0

    @property
    def recall(self) -> float:
        return self.covered / self.heads if self.heads else float("nan")

    @property
    def free_share(self) -> float:
        return self.free / self.pixels if self.pixels else float("nan")


def tally_occupancy(occ_map: np.ndarray, points: np.ndarray) -> OccupancyTally:
    """Counts for one frame's uint8 occupancy map (FREE = 255) and its head points."""
    rows, cols = head_pixels(points, occ_map.shape[:2])
    free = occ_map == FREE
    return OccupancyTally(len(rows), int((~free[rows, cols]).sum()), free.size, int(free.sum()))


@dataclass
class SetResult:
    """Figures of one model on one data set."""

    name: str
    images: int
    threshold: float
    recall: float
    free: float
    heads: int
    curve: list[dict[str, float]] = field(default_factory=list)  # {threshold, recall, free}
    mae: float | None = None
    rmse: float | None = None
    size_recall: list[dict[str, float]] | None = None  # per size bin at ``threshold``; None: no sizes
    min_person_px: float | None = None  # :func:`min_person_px` at ``threshold``; None: not reached / no sizes

    def at_free(self, free: float) -> float:
        """Recall on this set's curve at free share ``free`` (linear interpolation, NaN outside)."""
        pts = sorted((c["free"], c["recall"]) for c in self.curve)
        f = np.array([p[0] for p in pts])
        r = np.array([p[1] for p in pts])
        if not len(f) or free < f[0] or free > f[-1]:
            return float("nan")
        return float(np.interp(free, f, r))

    def best_recall(self) -> tuple[float, float]:
        """(recall, free) at the curve's lowest threshold: the most this model covers at all."""
        c = self.curve[0]
        return c["recall"], c["free"]


def evaluate_set(
    name: str,
    samples: Sequence[Sample],
    density_fn: Callable[[np.ndarray], np.ndarray],
    threshold: float,
    count_fn: Callable[[np.ndarray], float] | None = None,
    thresholds: Sequence[float] = CURVE_THRESHOLDS,
    params: OccupancyParams = OccupancyParams(),
) -> SetResult:
    """Run the model over ``samples`` and pool recall / free area at ``threshold`` and over ``thresholds``.

    count_fn: if given, also the MAE / RMSE of the estimated counts against the annotated ones.
    """
    thr = np.asarray(thresholds, np.float64)
    heads_cov = np.zeros(len(thr), np.int64)
    free_px = np.zeros(len(thr), np.int64)
    total = OccupancyTally()
    errors = []
    sizes: list[np.ndarray] = []
    covered: list[np.ndarray] = []
    op = replace(params, threshold=threshold)
    for s in samples:
        img = s.image()
        hw = img.shape[:2]
        d = density_fn(img)
        occ = occupancy_map(d, hw, op)
        t = tally_occupancy(occ, s.points)
        if s.sizes is not None:
            r, c = head_pixels(s.points, hw)
            sizes.append(np.asarray(s.sizes, np.float64).reshape(-1))
            covered.append(occ[r, c] != FREE)
        total.heads += t.heads
        total.covered += t.covered
        total.pixels += t.pixels
        total.free += t.free
        lv = level_map(d, hw, params.kernel, params.iterations)
        rows, cols = head_pixels(s.points, hw)
        head_lv = np.sort(lv[rows, cols])
        heads_cov += len(head_lv) - np.searchsorted(head_lv, thr, side="right")
        hist_lv = np.sort(lv.ravel())
        free_px += np.searchsorted(hist_lv, thr, side="right")
        if count_fn is not None:
            errors.append(count_fn(d) - len(s.points))
    curve = [
        {"threshold": float(t), "recall": float(c / total.heads) if total.heads else float("nan"),
         "free": float(f / total.pixels)}
        for t, c, f in zip(thr, heads_cov, free_px)
    ]
    res = SetResult(name, len(samples), float(threshold), total.recall, total.free_share, total.heads, curve)
    if errors:
        e = np.asarray(errors)
        res.mae, res.rmse = float(np.abs(e).mean()), float(np.sqrt((e**2).mean()))
    if sizes:
        sz, cov = np.concatenate(sizes), np.concatenate(covered)
        res.size_recall = size_recall(sz, cov)
        res.min_person_px = min_person_px(sz, cov)
    return res


def size_recall(sizes: np.ndarray, covered: np.ndarray, edges: Sequence[float] = SIZE_EDGES) -> list[dict[str, float]]:
    """Recall per person-size bin ``[lo, hi)`` (px): ``{lo, hi, people, covered, recall}`` (recall NaN if empty)."""
    sizes, covered = np.asarray(sizes, np.float64), np.asarray(covered, bool)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (sizes >= lo) & (sizes < hi)
        n, k = int(sel.sum()), int(covered[sel].sum())
        out.append({"lo": float(lo), "hi": float(hi), "people": n, "covered": k,
                    "recall": k / n if n else float("nan")})
    return out


def min_person_px(sizes: np.ndarray, covered: np.ndarray, target: float = SIZE_RECALL_TARGET,
                  edges: Sequence[float] = SIZE_EDGES, min_people: int = SIZE_MIN_PEOPLE) -> float | None:
    """The smallest bin edge ``lo`` (px) from which recall reaches ``target``, or None.

    Conservative on purpose: every non-empty size bin at or above ``lo`` must reach ``target`` on
    its own (not just the pooled people), and at least ``min_people`` people must be that large
    (a 99.5 % claim on fewer is not measurable).
    """
    bins = size_recall(sizes, covered, edges)
    sizes = np.asarray(sizes, np.float64)
    for i, b in enumerate(bins):
        if not b["people"]:
            continue  # never claim a size nobody in the data was measured at
        if int((sizes >= b["lo"]).sum()) < min_people:
            return None
        if all(c["recall"] >= target for c in bins[i:] if c["people"]):
            return b["lo"]
    return None


def latency_ms(density_fn: Callable[[np.ndarray], np.ndarray], frame: np.ndarray, runs: int = 20, warmup: int = 3) -> dict[str, float]:
    """Median / 10th / 90th percentile wall time of ``density_fn(frame)`` in milliseconds."""
    for _ in range(warmup):
        density_fn(frame)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        density_fn(frame)
        times.append((time.perf_counter() - t0) * 1e3)
    return {"median": float(np.median(times)), "p10": float(np.percentile(times, 10)),
            "p90": float(np.percentile(times, 90)), "runs": runs}


def latency_pair_ms(
    fns: Sequence[Callable[[np.ndarray], np.ndarray]], frame: np.ndarray, runs: int = 20, warmup: int = 3
) -> list[dict[str, float]]:
    """Like :func:`latency_ms` for several models timed alternately run by run, so that load from
    other processes on a shared machine falls on all of them alike and their ratio stays fair."""
    for fn in fns:
        for _ in range(warmup):
            fn(frame)
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(runs):
        for fn, ts in zip(fns, times):
            t0 = time.perf_counter()
            fn(frame)
            ts.append((time.perf_counter() - t0) * 1e3)
    return [{"median": float(np.median(t)), "p10": float(np.percentile(t, 10)), "p90": float(np.percentile(t, 90)),
             "runs": runs} for t in times]


def bench_frame(source: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """A real photo resized to ``hw`` (height, width) for latency runs (content does not change cost)."""
    return cv2.resize(source, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)


def best_threshold(results: Iterable[SetResult], min_recall: float | Mapping[str, float]) -> float | None:
    """Largest curve threshold whose recall is >= ``min_recall`` on every one of ``results``;
    ``min_recall`` is one figure for all, or one per set name (every set must be named)."""
    results = list(results)
    need = {r.name: (min_recall[r.name] if isinstance(min_recall, Mapping) else min_recall) for r in results}
    ok = None
    for i, c in enumerate(results[0].curve):
        if all(r.curve[i]["recall"] >= need[r.name] for r in results):
            ok = c["threshold"]
    return ok


def overall_min_person_px(results: Iterable[SetResult]) -> float | None:
    """A model's figure over several sets: the largest per-set ``min_person_px`` among the sets that
    give person sizes; None when none does or any of them never reaches the target (err toward
    "not trusted")."""
    sized = [r.min_person_px for r in results if r.size_recall is not None]
    if not sized or any(v is None for v in sized):
        return None
    return max(v for v in sized if v is not None)
