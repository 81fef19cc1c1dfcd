"""Train the landability model: semantic-drone photos -> per-cell probabilities of risk levels.

    companion train-landability --shared ../shared --out companion/models/slz-landability.onnx
    python -m companion.training.landability ...   # the same

A second small network beside the density model (which stays as it is): input the frame, output
``(N, L, H/8, W/8)`` softmax probabilities of the risk levels of :data:`LEVELS` (the grouping of
the semantic-drone classes, written into the model's metadata; ``companion.pipeline.landability``
documents the keys). About 39 k parameters at the default width 32 (the shipped file: width 48, 77 k; its card).

Data: the semantic-drone photos of the training split (``datasets.semantic_drone(..., "train")``,
the same held-out fifth as the density model's stays out), of which every 8th (by sorted name) is
kept aside as *training-side validation* for the threshold; the rest train. Crops get a random
scale, any rotation and a mirror (the photos look straight down), and the photometric changes of
the density training. The target of a cell is the share of its 8x8 pixels in each level (soft
labels); the loss is the cross-entropy weighted per level (:data:`LEVEL_WEIGHTS`: people, vehicles
and water weigh more, as they are rare and the costliest to miss).

The threshold (``companion.unlandable_threshold``) is the largest on a grid at which at least
:data:`LANDABLE_PRECISION` of the pixels the pipeline's decision leaves landable (after its
dilation) truly are landable on the training-side validation photos, and less of the obstacle
pixels than :data:`MAX_LEFT_LANDABLE` are left landable; it errs toward "unlandable".
``--rethreshold MODEL`` applies that rule to a model already exported. ``--device cuda`` trains on a GPU (the shipped model: CPU, one thread).
``--hard-share`` centres part of the crops on the network's own mistakes, found again every
``--mine-every`` steps (hard mining; measured and not used by the shipped model: its card).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from companion.evaluation import datasets as D
from companion.evaluation.landability import level_lut
from companion.pipeline.landability import OUTPUT_KIND, RiskLevel
from companion.pipeline.occupancy import FREE, OccupancyParams, surface_free_map
from companion.training import model as M
from companion.training.augment import photometric
from companion.training.distill import Phase, lr_factor
from companion.training.export import set_metadata
from companion.training.metadata import read_metadata
from companion.training.tensor_crops import TensorCrops

log = logging.getLogger("companion.training.landability")

#: The risk levels, in output-channel order, and the semantic-drone classes in each. "unknown"
#: holds what says nothing about the ground (unlabeled, conflicting annotations) and the survey's
#: AR markers: not landable, erring toward safety.
LEVELS: tuple[RiskLevel, ...] = (
    RiskLevel("landable", ("paved-area", "dirt", "grass", "gravel")),
    RiskLevel("people", ("person", "dog")),
    RiskLevel("vehicles", ("car", "bicycle")),
    RiskLevel("water", ("water", "pool")),
    RiskLevel("vegetation", ("vegetation", "tree", "bald-tree")),
    RiskLevel("obstacles", ("rocks", "roof", "wall", "window", "door", "fence", "fence-pole", "obstacle")),
    RiskLevel("unknown", ("unlabeled", "ar-marker", "conflicting")),
)
LANDABLE = "landable"
LEVEL_WEIGHTS = (1.0, 3.0, 3.0, 3.0, 1.5, 1.5, 1.0)
STRIDE = 8
LANDABLE_PRECISION = 0.99
#: The threshold may leave no more than this share of a level's pixels landable on the
#: validation photos (``choose_threshold``): the obstacles level (roofs, walls) at the 0.43 % that
#: the model of 2026-11-26 left at its threshold. Added 2026-11-28, when models trained longer met
#: the precision at a larger landable share and left more roof there (``LANDABILITY_CARD.md``).
MAX_LEFT_LANDABLE: dict[str, float] = {"obstacles": 0.0043}
THRESHOLDS = tuple(round(t, 3) for t in np.linspace(0.05, 0.9, 18))
VAL_EVERY = 8


def _cbr(cin: int, cout: int, k: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    pad = dilation * (k - 1) // 2
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, pad, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class LandabilityNet(nn.Module):
    """A 2x2 average pool (surfaces need no full-resolution detail), two stride-2 convolutions and
    one more at stride 8; a context branch at stride 16 (a stride-2 convolution, then two dilated
    2 and 4) brought back up and added, so that each cell sees about 300 pixels around it (a roof
    and a yard, a pool and a lawn, can look alike up close) at a quarter of the cost of doing the
    same at stride 8; a 1x1 head to the levels' logits.

    ``context=2`` adds a second branch of the same shape at stride 32 on top of the first (about
    twice the reach: a large flat roof and a square look alike until the cell sees the roof's
    edge), brought back to stride 16 and added; ``context=1`` is the shipped network, module for
    module (its weights load, and a seed draws the same initial weights)."""

    def __init__(self, levels: int = len(LEVELS), width: int = 32, context: int = 1) -> None:
        super().__init__()
        if context not in (1, 2):
            raise ValueError(f"LandabilityNet context must be 1 or 2, not {context!r}")
        self.stem = nn.Sequential(nn.AvgPool2d(2), _cbr(3, 16, 3, 2), _cbr(16, 24, 3, 2), _cbr(24, width, 3))
        self.context = nn.Sequential(_cbr(width, width, 3, 2), _cbr(width, width, 3, dilation=2),
                                     _cbr(width, width, 3, dilation=4))
        self.head = nn.Conv2d(width, levels, 1)
        # Made last, so that context=1 draws the shipped network's initial weights.
        self.context2 = None if context == 1 else nn.Sequential(
            _cbr(width, width, 3, 2), _cbr(width, width, 3, dilation=2), _cbr(width, width, 3, dilation=4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f8 = self.stem(x)
        f16 = self.context(f8)
        if self.context2 is not None:
            f16 = f16 + F.interpolate(self.context2(f16), size=f16.shape[-2:], mode="nearest")
        up = F.interpolate(f16, size=f8.shape[-2:], mode="nearest")
        return self.head(f8 + up)


class Exported(nn.Module):
    """The deployable form: batch norm folded, softmax over the levels."""

    def __init__(self, net: LandabilityNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.softmax(self.net(x), dim=1)


@dataclass
class Photos:
    """Photos in memory: BGR uint8 images and their level maps (uint8, one level code a pixel)."""

    names: list[str]
    images: list[np.ndarray]
    levels: list[np.ndarray]


def load_photos(shared: Path, max_images: int = 0) -> tuple[Photos, Photos]:
    """(train, training-side validation) photos of the semantic-drone training split."""
    lut = level_lut(LEVELS, D.semantic_classes(shared))
    samples = D.semantic_drone(shared, "train")
    if max_images:
        samples = samples[:max_images]
    train, val = Photos([], [], []), Photos([], [], [])
    for i, s in enumerate(samples):
        dst = val if i % VAL_EVERY == VAL_EVERY - 1 else train
        dst.names.append(s.name)
        dst.images.append(s.image())
        dst.levels.append(lut[D.semantic_labels(s)])
    if not train.images or not val.images:
        raise D.DatasetError(f"too few semantic-drone photos ({len(samples)}) for a training and a validation part")
    return train, val


def level_crop(image: np.ndarray, levels: np.ndarray, size: int, rng: np.random.Generator,
               scale: tuple[float, float] = (0.35, 1.4),
               centre: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A ``size`` x ``size`` crop after a random scale, rotation and mirror; the level map is
    warped with nearest neighbour so that no level is invented at a boundary. ``centre`` (x, y
    in the photo's pixels) places the crop's centre there instead of at random (hard mining);
    the random draws are the same either way, so a run without it is unchanged."""
    h, w = image.shape[:2]
    s = float(np.exp(rng.uniform(np.log(scale[0]), np.log(scale[1]))))
    cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    if centre is not None:
        cx, cy = float(centre[0]), float(centre[1])
    m = cv2.getRotationMatrix2D((float(cx), float(cy)), float(rng.uniform(0, 360)), s)
    if rng.random() < 0.5:
        m = np.array([[-1, 0, 0], [0, 1, 0]], np.float64) @ np.vstack([m, [0, 0, 1]])
        m[0, 2] += 2 * cx
    m[0, 2] += size / 2 - cx
    m[1, 2] += size / 2 - cy
    img = cv2.warpAffine(image, m, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    lv = cv2.warpAffine(levels, m, (size, size), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REFLECT_101)
    return img, lv


def soft_target(levels: np.ndarray, n_levels: int, stride: int = STRIDE) -> np.ndarray:
    """(L, h/stride, w/stride) float32: the share of each cell's pixels in each level."""
    h, w = levels.shape
    onehot = (levels[None] == np.arange(n_levels, dtype=levels.dtype)[:, None, None]).astype(np.float32)
    return onehot.reshape(n_levels, h // stride, stride, w // stride, stride).mean(axis=(2, 4))


#: What hard mining looks for (``--mine``): ``false-landable``, the unlandable cells the network
#: leaves landable (the mistakes that can end up inside a landing circle); ``both``, those and,
#: as often, the landable cells it calls unlandable (the ground given up), so that the crops'
#: share of each kind of ground stays as it was.
MINE_KINDS = ("false-landable", "both")


@dataclass
class HardCells:
    """Where the network under training is wrong (hard mining): the centres (x, y, in pixels)
    of cells of the training photos, and of which kind of mistake: 0, unlandable called
    landable; 1, landable called unlandable."""

    photo: np.ndarray  # (K,) int: index into the training photos
    xy: np.ndarray  # (K, 2) float: cell centres in that photo's pixels
    kind: np.ndarray | None = None  # (K,) int 0/1; None: all 0

    def __len__(self) -> int:
        return len(self.photo)

    def draw(self, rng: np.random.Generator) -> int:
        """One cell's index: uniform over the cells of a kind drawn with equal odds among the
        kinds present (uniform over all cells when there is one kind)."""
        if self.kind is None or self.kind.min() == self.kind.max():
            return int(rng.integers(len(self)))
        of_kind = np.flatnonzero(self.kind == int(rng.integers(2)))
        return int(of_kind[int(rng.integers(len(of_kind)))])


def mistaken_cells(probs: np.ndarray, levels: np.ndarray, threshold: float, kind: int = 0,
                   stride: int = STRIDE) -> np.ndarray:
    """(K, 2) float: the centres (x, y, pixels) of the cells of one photo that the network gets
    wrong, by ``kind`` (as :class:`HardCells`): 0, cells the pipeline would leave landable
    (summed unlandable probability below ``threshold``) although most of their pixels are
    unlandable in ``levels`` (level codes; :data:`LANDABLE` is landable); 1, the other way
    round, mostly landable cells at ``threshold`` or more. ``probs`` is (L, h, w) from
    :func:`predict` on that photo, one cell per ``stride`` pixels."""
    land = [lv.name for lv in LEVELS].index(LANDABLE)
    h, w = levels.shape
    lv = np.pad(levels == land, ((0, -h % stride), (0, -w % stride)), mode="edge")
    share = lv.reshape(lv.shape[0] // stride, stride, lv.shape[1] // stride, stride).mean(axis=(1, 3))
    ch, cw = min(probs.shape[1], share.shape[0]), min(probs.shape[2], share.shape[1])
    called_landable = 1.0 - probs[land, :ch, :cw] < threshold
    landable = share[:ch, :cw] >= 0.5
    rows, cols = np.nonzero(called_landable & ~landable if kind == 0 else ~called_landable & landable)
    return np.stack([(cols + 0.5) * stride, (rows + 0.5) * stride], axis=1).astype(np.float64)


def mine_hard_cells(net: nn.Module, photos: Photos, threshold: float, kinds: str = "false-landable") -> HardCells:
    """The hard cells (:data:`MINE_KINDS`) of every training photo, with the network in eval
    mode (restored to training mode after)."""
    if kinds not in MINE_KINDS:
        raise ValueError(f"hard mining looks for one of {', '.join(MINE_KINDS)}, not {kinds!r}")
    was_training = net.training
    net.eval()
    idx, xy, kind = [], [], []
    try:
        for i, (img, lv) in enumerate(zip(photos.images, photos.levels)):
            p = predict(net, img)
            for k in range(2 if kinds == "both" else 1):
                cells = mistaken_cells(p, lv, threshold, k)
                idx.append(np.full(len(cells), i, np.int64))
                xy.append(cells)
                kind.append(np.full(len(cells), k, np.int64))
    finally:
        net.train(was_training)
    return HardCells(np.concatenate(idx), np.concatenate(xy), np.concatenate(kind))


def make_batch(photos: Photos, batch: int, size: int, rng: np.random.Generator,
               hard: HardCells | None = None, hard_share: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """One batch of crops and their soft targets. With ``hard`` cells and ``hard_share`` > 0,
    that share of the crops (drawn per crop) is centred on a hard cell drawn uniformly over all
    of them, so photos with more mistakes give more crops; the rest are random as without."""
    xs = np.empty((batch, 3, size, size), np.float32)
    ys = np.empty((batch, len(LEVELS), size // STRIDE, size // STRIDE), np.float32)
    mean = np.array(M.MEAN, np.float32)[:, None, None]
    std = np.array(M.STD, np.float32)[:, None, None]
    for b in range(batch):
        i = int(rng.integers(len(photos.images)))
        centre = None
        if hard is not None and len(hard) and hard_share > 0 and rng.random() < hard_share:
            k = hard.draw(rng)
            # Jitter within the cell and a little around it, so the crops do not repeat exactly.
            i, centre = int(hard.photo[k]), tuple(hard.xy[k] + rng.uniform(-STRIDE, STRIDE, 2))
        img, lv = level_crop(photos.images[i], photos.levels[i], size, rng, centre=centre)
        img = photometric(img, rng)
        xs[b] = (img.transpose(2, 0, 1).astype(np.float32) * M.SCALE - mean) / std
        ys[b] = soft_target(lv, len(LEVELS))
    return torch.from_numpy(xs), torch.from_numpy(ys)


class BatchStream(torch.utils.data.IterableDataset):
    """Endless training batches made by ``make_batch`` (``--workers``: in DataLoader worker
    processes, each with its own random stream drawn from the seed and its worker id)."""

    def __init__(self, photos: Photos, batch: int, size: int, seed: int) -> None:
        self.photos, self.batch, self.size, self.seed = photos, batch, size, seed

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        info = torch.utils.data.get_worker_info()
        cv2.setNumThreads(1)
        rng = np.random.default_rng([self.seed, 0 if info is None else info.id + 1])
        while True:
            yield make_batch(self.photos, self.batch, self.size, rng)


def loss(logits: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Soft-label cross-entropy, each level's term weighted (``weights`` (L,))."""
    logp = F.log_softmax(logits, dim=1)
    return -(target * logp * weights[None, :, None, None]).sum(dim=1).mean()


def predict(net: nn.Module, image: np.ndarray) -> np.ndarray:
    """(L, ceil(H/8), ceil(W/8)) level probabilities of one photo with the torch network (eval)."""
    h, w = image.shape[:2]
    ph, pw = -h % STRIDE, -w % STRIDE
    img = cv2.copyMakeBorder(image, 0, ph, 0, pw, cv2.BORDER_REPLICATE) if ph or pw else image
    mean = np.array(M.MEAN, np.float32)[:, None, None]
    std = np.array(M.STD, np.float32)[:, None, None]
    x = (img.transpose(2, 0, 1).astype(np.float32) * M.SCALE - mean) / std
    device = next(net.parameters()).device
    with torch.no_grad():
        p = torch.softmax(net(torch.from_numpy(x[None]).to(device)), dim=1)[0].cpu().numpy()
    return p[:, : math.ceil(h / STRIDE), : math.ceil(w / STRIDE)]


def choose_threshold(probs: list[np.ndarray], levels: list[np.ndarray], precision: float = LANDABLE_PRECISION,
                     occupancy: OccupancyParams = OccupancyParams(),
                     max_left: dict[str, float] | None = None) -> tuple[float, list[dict[str, float]]]:
    """The largest threshold of :data:`THRESHOLDS` at which at least ``precision`` of the pixels
    the pipeline leaves landable (:func:`surface_free_map`, with its dilation) truly are landable,
    pooled over the photos, and, for each level named in ``max_left`` (default
    :data:`MAX_LEFT_LANDABLE`), less than that share of its pixels is left landable; the smallest
    threshold when none meets both. Returns it and the curve (threshold, precision, landable
    share of the pixels, and each capped level's share left landable, under ``left_<level>``)."""
    names = [lv.name for lv in LEVELS]
    land = names.index(LANDABLE)
    caps = MAX_LEFT_LANDABLE if max_left is None else max_left
    for name in caps:
        if name not in names or name == LANDABLE:
            raise ValueError(f"a cap on the pixels left landable names an unlandable level, not {name!r}")
    curve = []
    for t in THRESHOLDS:
        kept_by, total_by = _kept_by_level(probs, levels, t, occupancy)
        kept, total = int(kept_by.sum()), int(total_by.sum())
        c = {"threshold": float(t), "precision": float(kept_by[land]) / kept if kept else 1.0,
             "landable": kept / total if total else 0.0}
        for name in caps:
            i = names.index(name)
            c[f"left_{name}"] = float(kept_by[i] / total_by[i]) if total_by[i] else 0.0
        curve.append(c)
    ok = [c["threshold"] for c in curve
          if c["precision"] >= precision and all(c[f"left_{n}"] < cap for n, cap in caps.items())]
    return (max(ok) if ok else min(THRESHOLDS)), curve


def threshold_rule(max_left: dict[str, float] | None = None) -> str:
    """The threshold rule in words, for the model's training note and the log."""
    caps = MAX_LEFT_LANDABLE if max_left is None else max_left
    return (f"largest with landable precision >= {LANDABLE_PRECISION}"
            + "".join(f" and {n} pixels left landable < {100 * v:g} %" for n, v in caps.items())
            + f" on every {VAL_EVERY}th training-split photo (held out of training)")


def export(net: LandabilityNet, out: Path, threshold: float, note: str) -> Path:
    """Fold batch norm, add the softmax, export with dynamic H and W, write the metadata."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    deploy = Exported(M.fold_batchnorm(net)).eval()
    with torch.no_grad():
        torch.onnx.export(deploy, (torch.zeros(1, 3, 480, 640),), str(out), input_names=["input"],
                          output_names=["levels"],
                          dynamic_axes={"input": {0: "n", 2: "h", 3: "w"}, "levels": {0: "n", 2: "h8", 3: "w8"}},
                          opset_version=17, dynamo=False)
    set_metadata(out, {
        "companion.color": M.COLOR,
        "companion.scale": repr(M.SCALE),
        "companion.mean": ",".join(str(v) for v in M.MEAN),
        "companion.std": ",".join(str(v) for v in M.STD),
        "companion.stride": STRIDE,
        "companion.input_multiple": STRIDE,
        "companion.output": OUTPUT_KIND,
        "companion.levels": json.dumps([{"name": lv.name, "classes": list(lv.classes)} for lv in LEVELS]),
        "companion.landable_level": LANDABLE,
        "companion.unlandable_threshold": f"{threshold:.6g}",
        "companion.class_set": "semantic-drone",
        "companion.parameters": M.count_parameters(net),
        "companion.training": note,
    })
    return out


def train(args: argparse.Namespace) -> Path:
    from companion.training.train import start_run, warm_cosine

    device, rng = start_run(args)
    t0 = time.monotonic()
    train_set, val_set = load_photos(Path(args.shared), args.max_images)
    log.info("loaded %d training and %d validation photos in %.0f s", len(train_set.images),
             len(val_set.images), time.monotonic() - t0)
    net = LandabilityNet(width=args.width, context=args.context).to(device)
    log.info("parameters: %d", M.count_parameters(net))
    level_weights = weights_with(args.level_weight)
    log.info("level weights: %s", ", ".join(f"{lv.name} {w:g}" for lv, w in zip(LEVELS, level_weights)))
    weights = torch.tensor(level_weights, dtype=torch.float32, device=device)
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    warm = min(100, max(1, args.steps // 10))
    budget = float(args.seconds)
    # By steps: the LambdaLR of the shipped model, as it was (its rounding reproduces the file);
    # by seconds: the distillation run's Phase and lr_factor, the same shape over the time spent.
    sched = warm_cosine(opt, warm, args.steps)
    batches = None
    crops: TensorCrops | None = None
    if args.tensor_crops:
        crops = TensorCrops(train_set.images, train_set.levels, len(LEVELS), device, STRIDE)
        crop_rng = torch.Generator(device=device)
        crop_rng.manual_seed(args.seed)
        log.info("tensor crops: %d training photos on %s", len(train_set.images), device)
    if args.workers:
        batches = iter(torch.utils.data.DataLoader(
            BatchStream(train_set, args.batch, args.crop, args.seed), batch_size=None,
            num_workers=args.workers, prefetch_factor=4, persistent_workers=True,
            pin_memory=device.type == "cuda"))
    phase = Phase(0 if budget else args.steps, budget)
    running = torch.zeros((), device=device)
    hard: HardCells | None = None
    net.train()
    while not phase.done():
        if budget:
            for g in opt.param_groups:
                g["lr"] = args.lr * lr_factor(phase.progress, phase.k, warm)
        if args.hard_share > 0 and phase.k and phase.k % args.mine_every == 0:
            tm = time.monotonic()
            hard = mine_hard_cells(net, train_set, args.mine_threshold, args.mine)
            wrong_way = int((hard.kind == 1).sum()) if hard.kind is not None else 0
            log.info("step %d: mined %d false-landable and %d false-unlandable cells on %d of %d training "
                     "photos in %.1f s", phase.k, len(hard) - wrong_way, wrong_way, len(np.unique(hard.photo)),
                     len(train_set.images), time.monotonic() - tm)
        if crops is not None:
            x, y = crops.batch(args.batch, args.crop, crop_rng)
        else:
            x, y = (next(batches) if batches is not None
                    else make_batch(train_set, args.batch, args.crop, rng, hard, args.hard_share))
        if device.type != "cpu":
            x, y = x.to(device, non_blocking=True), y.to(device, non_blocking=True)
        batch_loss = loss(net(x), y, weights)
        opt.zero_grad(set_to_none=True)
        batch_loss.backward()
        opt.step()
        if not budget:
            sched.step()
        # Summed on the device: reading the loss each step would wait for the GPU each step.
        running += batch_loss.detach()
        phase.k += 1
        step = phase.k
        if step % 50 == 0 or (not budget and step == args.steps):
            el = time.monotonic() - phase.t0
            log.info("step %d%s loss %.4f lr %.2e %.3f s/step elapsed %.1f min", step,
                     "" if budget else f"/{args.steps}", float(running) / (50 if step % 50 == 0 else step % 50),
                     opt.param_groups[0]["lr"], el / step, el / 60)
            running = torch.zeros((), device=device)
    step, t0 = phase.k, phase.t0
    log.info("trained %d steps, %d crops, in %.1f min", step, step * args.batch, (time.monotonic() - t0) / 60)
    net = net.cpu().eval()
    probs = [predict(net, img) for img in val_set.images]
    pix = [at_pixels(p, lv) for p, lv in zip(probs, val_set.levels)]
    thr, curve = choose_threshold(pix, val_set.levels)
    log_curve(curve)
    log.info("threshold %.3f (%s; %d validation photos)", thr, threshold_rule(), len(val_set.images))
    for name, share in left_landable_by_level(pix, val_set.levels, thr).items():
        log.info("validation: %s pixels left landable at %.3f: %.2f %%", name, thr, 100 * share)
    note = (f"steps={step} batch={args.batch} crop={args.crop} lr={args.lr} seed={args.seed} width={args.width} "
            f"workers={args.workers} seconds={args.seconds:g} context={args.context} tensor_crops={int(args.tensor_crops)} "
            f"level_weights={','.join(f'{w:g}' for w in level_weights)} "
            + (f"hard_share={args.hard_share:g} mine={args.mine} mine_every={args.mine_every} "
               f"mine_threshold={args.mine_threshold:g} " if args.hard_share > 0 else "") +
            f"threads={args.threads} device={args.device} minutes={(time.monotonic() - t0) / 60:.1f}; "
            f"threshold: {threshold_rule()}")
    out = export(net, Path(args.out), thr, note)
    log.info("exported %s (%.1f min)", out, (time.monotonic() - t0) / 60)
    return out


def rethreshold(model: Path, shared: Path, out: Path, threads: int = 1) -> tuple[float, float]:
    """Choose the threshold of an exported landability model again by the current rule
    (:func:`choose_threshold`, :func:`threshold_rule`) on the training-side validation photos, as
    the runtime sees them (onnxruntime); write the model with it to ``out`` (``model`` itself when
    the same path) and the change into its training note. Returns (old, new) threshold. The
    model's levels must be :data:`LEVELS`, in order: the validation maps are made from them."""
    from companion.pipeline.landability import LandabilityModel, LandabilityModelError

    try:
        m = LandabilityModel(model, threads=threads)
    except LandabilityModelError as exc:
        raise ValueError(str(exc)) from None
    want = tuple(lv.name for lv in LEVELS)
    if m.landability.names != want:
        raise ValueError(f"{model}: its levels are {', '.join(m.landability.names)}, not this training's "
                         f"{', '.join(want)}: the threshold cannot be chosen on the same maps")
    _, val = load_photos(shared)
    pix = [at_pixels(m(img), lv) for img, lv in zip(val.images, val.levels)]
    thr, curve = choose_threshold(pix, val.levels)
    log_curve(curve)
    old = float(m.landability.threshold)
    note = read_metadata(model).get("companion.training", "")
    out = Path(out)
    if out.resolve() != Path(model).resolve():
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(model, out)
    set_metadata(out, {
        "companion.unlandable_threshold": f"{thr:.6g}",
        "companion.training": f"{note}; threshold re-chosen {old:g} -> {thr:g} (companion train-landability "
                              f"--rethreshold): {threshold_rule()}",
    })
    log.info("threshold %g -> %g (%s); wrote %s", old, thr, threshold_rule(), out)
    return old, thr


def left_landable_by_level(probs: list[np.ndarray], levels: list[np.ndarray], threshold: float,
                           occupancy: OccupancyParams = OccupancyParams()) -> dict[str, float]:
    """Per level, the share of its pixels (pooled over the photos) that the pipeline's decision
    at ``threshold`` leaves landable: for ``landable`` what is kept, for the others the mistakes
    that could end up inside a landing circle. ``probs`` are (L, H, W) at the photos' pixels."""
    kept, total = _kept_by_level(probs, levels, threshold, occupancy)
    return {lv.name: float(k / t) if t else 0.0 for lv, k, t in zip(LEVELS, kept, total)}


def _kept_by_level(probs: list[np.ndarray], levels: list[np.ndarray], threshold: float,
                   occupancy: OccupancyParams) -> tuple[np.ndarray, np.ndarray]:
    """Per level (pooled over the photos): how many of its pixels the pipeline's decision at
    ``threshold`` leaves landable, and how many there are; (L,) int64 each."""
    land = [lv.name for lv in LEVELS].index(LANDABLE)
    kept = np.zeros(len(LEVELS), np.int64)
    total = np.zeros(len(LEVELS), np.int64)
    for p, lv in zip(probs, levels):
        free = surface_free_map(1.0 - p[land], lv.shape, threshold, occupancy) == FREE
        total += np.bincount(lv.ravel(), minlength=len(LEVELS))[: len(LEVELS)]
        kept += np.bincount(lv[free].ravel(), minlength=len(LEVELS))[: len(LEVELS)]
    return kept, total


def at_pixels(probs: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """(L, H, W): a photo's cell probabilities brought to its level map's pixels (nearest)."""
    return cv2.resize(probs.transpose(1, 2, 0), (levels.shape[1], levels.shape[0]),
                      interpolation=cv2.INTER_NEAREST).transpose(2, 0, 1)


def log_curve(curve: list[dict[str, float]]) -> None:
    """The validation curve of :func:`choose_threshold`, a line a threshold."""
    for c in curve:
        log.info("validation: threshold %.3f landable precision %.4f landable share %.3f obstacles left %.4f",
                 c["threshold"], c["precision"], c["landable"], c["left_obstacles"])


def weights_with(changes: list[str] | None) -> tuple[float, ...]:
    """:data:`LEVEL_WEIGHTS` with ``LEVEL=WEIGHT`` changes (``--level-weight``) applied, in the
    levels' order. A level that is not one of :data:`LEVELS`, or a weight that is not a positive
    finite number, is a ValueError naming it."""
    names = [lv.name for lv in LEVELS]
    weights = list(LEVEL_WEIGHTS)
    for change in changes or []:
        name, sep, value = change.partition("=")
        if not sep or name not in names:
            raise ValueError(f"--level-weight takes LEVEL=WEIGHT with LEVEL one of {', '.join(names)}; "
                             f"got {change!r}")
        try:
            w = float(value)
        except ValueError:
            w = math.nan
        if not (math.isfinite(w) and w > 0):
            raise ValueError(f"--level-weight {name}: the weight must be a positive number, got {value!r}")
        weights[names.index(name)] = w
    return tuple(weights)


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", default="../shared", help="the shared data directory")
    p.add_argument("--out", required=True,
                   help="ONNX file to write (no default: a run never replaces the shipped model unasked)")
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--crop", type=int, default=256, help="crop side in pixels (multiple of 8)")
    p.add_argument("--lr", type=float, default=4e-3)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda[:N]")
    p.add_argument("--width", type=int, default=32, help="channels of the network (default 32, the shipped model)")
    p.add_argument("--context", type=int, default=1, choices=(1, 2),
                   help="context branches: 1 (stride 16, the shipped model) or 2 (and one at stride 32: "
                        "about twice the reach around each cell)")
    p.add_argument("--seconds", type=float, default=0.0,
                   help="train for this long instead of --steps (the learning-rate cosine follows the time)")
    p.add_argument("--workers", type=int, default=0,
                   help="make the crops in this many worker processes (0: in the training loop)")
    p.add_argument("--rethreshold", type=Path, metavar="MODEL",
                   help="train nothing: choose the threshold of this exported model again by the current rule "
                        "on the validation photos and write it, so changed, to --out")
    p.add_argument("--tensor-crops", action="store_true",
                   help="make the crops on --device from the photos held there (companion.training.tensor_crops): "
                        "on a GPU, no CPU worker limits the steps; the CPU path's changes, two approximated")
    p.add_argument("--max-images", type=int, default=0,
                   help="use only the first N photos of the training split (quick runs and tests; 0: all)")
    p.add_argument("--hard-share", type=float, default=0.0,
                   help="hard mining: this share of the crops (0-1) is centred on cells the network "
                        "under training calls landable although they are not (default 0: off, the "
                        "shipped recipe); needs --workers 0")
    p.add_argument("--mine", choices=MINE_KINDS, default="false-landable",
                   help="what hard mining looks for: the unlandable cells called landable (default), or "
                        "'both': those and, as often, the landable cells called unlandable")
    p.add_argument("--mine-every", type=int, default=500,
                   help="look for those cells again every this many steps (default 500)")
    p.add_argument("--mine-threshold", type=float, default=0.3,
                   help="a cell counts as called landable below this summed unlandable probability "
                        "(default 0.3: a margin above the shipped threshold)")
    p.add_argument("--level-weight", action="append", default=[], metavar="LEVEL=WEIGHT",
                   help="weigh this risk level's loss term so (repeatable; default "
                        + ", ".join(f"{lv.name} {w:g}" for lv, w in zip(LEVELS, LEVEL_WEIGHTS)) + ")")


def run(args: argparse.Namespace) -> int:
    from companion.training.train import resolve_device

    try:
        resolve_device(args.device)
        for key in ("steps", "batch", "threads", "width"):
            if getattr(args, key) < 1:
                raise ValueError(f"--{key} must be >= 1, got {getattr(args, key)}")
        if args.workers < 0 or not (math.isfinite(args.seconds) and args.seconds >= 0):
            raise ValueError(f"--workers and --seconds must be >= 0, got {args.workers} and {args.seconds}")
        if args.crop < STRIDE or args.crop % STRIDE:
            raise ValueError(f"--crop must be a positive multiple of {STRIDE}, got {args.crop}")
        if not (0.0 <= args.hard_share <= 1.0) or args.mine_every < 1 or not (0.0 < args.mine_threshold < 1.0):
            raise ValueError("--hard-share must be in [0, 1], --mine-every >= 1 and --mine-threshold in (0, 1); "
                             f"got {args.hard_share}, {args.mine_every} and {args.mine_threshold}")
        if args.hard_share > 0 and args.workers:
            raise ValueError("--hard-share mines in the training loop: use it with --workers 0")
        if args.tensor_crops and (args.workers or args.hard_share > 0):
            raise ValueError("--tensor-crops makes the crops on the device: it takes no --workers or --hard-share")
        if args.max_images < 0:
            raise ValueError(f"--max-images must be >= 0, got {args.max_images}")
        weights_with(args.level_weight)
        if args.rethreshold is not None:
            rethreshold(args.rethreshold, Path(args.shared), Path(args.out), args.threads)
        else:
            train(args)
    except (ValueError, D.DatasetError) as exc:
        print(f"companion train-landability: {exc}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    configure(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    return run(args)


if __name__ == "__main__":
    raise SystemExit(main())
