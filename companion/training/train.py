"""Train the shipped density network from scratch and export it to ONNX.

    python -m companion.training.train --shared ../shared --out companion/models/slz-density.onnx

Data: the semantic drone photos except the held-out fifth (person boxes), five of the six
DroneCrowd frames (``img112008-012``; ``img017012``, another sequence, stays held out) and the
ShanghaiTech B training images (head points). The loss is a weighted binary cross-entropy on
peak-1 Gaussian targets (see ``loss``), biased toward over-estimating people. After training the
model is exported, then calibrated on validation data (:mod:`companion.training.calibrate`) which
stores the occupancy threshold, the count scale and the smallest person size it sees reliably
in the ONNX metadata.

Two optional sources add crops the real data lacks (both 0 by default, which is the shipped model's
configuration; each share is the probability that a crop comes from it, the real sources share the
rest in their fixed proportions):

* ``--synthetic-share``: synthetic top-down crowds from the *train* split of
  :mod:`companion.evaluation.compositor` (people cut from the semantic-drone photos, pasted along
  real DroneCrowd trajectories); target: a box Gaussian per pasted person, as for semantic drone.
* ``--negative-share``: hard negatives (:mod:`companion.training.negatives`): roofs, walls, windows,
  cars, obstacles, trees, fences, road markings and photos with nobody; target: all zero.

``--device cuda`` trains on a CUDA GPU (the default ``cpu`` is what the shipped model used).
Deterministic on the CPU: the same seed and thread count give the same weights; on a GPU, cuDNN's
kernels may make runs differ slightly.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from companion.evaluation import compositor as C
from companion.evaluation import datasets as D
from companion.training import model as M
from companion.training.augment import GeomAug, photometric, random_crop
from companion.training.export import export_onnx
from companion.training.negatives import HardNegatives, check_kinds, class_indices
from companion.training.pack import shb_scale
from companion.training.targets import box_target, point_target

log = logging.getLogger("companion.training")

TRAIN_DRONECROWD = D.DRONECROWD_TRAIN


class CropSource(Protocol):
    """Anything a batch draws crops from: ``weight`` is its share of the crops (relative)."""

    name: str
    weight: float

    def crop(self, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(``size`` x ``size`` BGR uint8 image, float32 target of the same size, peak 1)."""
        ...


@dataclass
class Source:
    """One training source held in memory: images, their target maps, head/box-centre points."""

    name: str
    images: list[np.ndarray]
    targets: list[np.ndarray]  # float16, image size, peak 1
    points: list[np.ndarray]
    aug: GeomAug
    weight: float

    def crop(self, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        i = rng.integers(len(self.images))
        return random_crop(self.images[i], self.targets[i].astype(np.float32), self.points[i], size, self.aug, rng)


@dataclass
class SyntheticSource:
    """Synthetic crowds drawn fresh for every crop; target: a box Gaussian per pasted person."""

    compositor: C.Compositor
    weight: float
    name: str = "synthetic"

    def crop(self, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        comp = self.compositor.sample(rng, (size, size))
        return comp.image, box_target((size, size), comp.boxes)


@dataclass
class NegativeSource:
    """Hard negatives: person-free crops of clutter, all-zero targets."""

    negatives: HardNegatives
    weight: float
    name: str = "hard_negatives"

    def crop(self, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        img, tgt, _kind = self.negatives.crop(size, rng)
        return img, tgt


def load_sources(shared: Path, max_images: int = 0) -> list[Source]:
    """The real sources; ``max_images`` > 0 keeps only the first N images of each (quick runs)."""
    t0 = time.monotonic()
    # A training pack (companion.training.pack) holds ShanghaiTech B downscaled by f: widen its
    # scale range and target sigmas by 1/f so the crops cover the same person sizes (f = 1 here).
    f = shb_scale(shared)
    sd = D.semantic_drone(shared, "train")
    dc = D.dronecrowd_frames(shared, TRAIN_DRONECROWD)
    shb = D.shanghaitech_b(shared, "train")
    if max_images:
        sd, dc, shb = sd[:max_images], dc[:max_images], shb[:max_images]

    def build(name: str, samples: list[D.Sample], make: Callable[[D.Sample, tuple[int, int]], np.ndarray],
              aug: GeomAug, weight: float) -> Source:
        imgs, tgts, pts = [], [], []
        for s in samples:
            img = s.image()
            imgs.append(img)
            tgts.append(make(s, img.shape[:2]).astype(np.float16))
            pts.append(s.points)
        return Source(name, imgs, tgts, pts, aug, weight)

    def boxes_target(s: D.Sample, hw: tuple[int, int]) -> np.ndarray:
        assert s.boxes is not None, f"{s.name} has no person boxes"  # every semantic_drone sample has
        return box_target(hw, s.boxes)

    sources = [
        # Whole people from 5-30 m, straight down: the target domain.
        build("semantic_drone", sd, boxes_target, GeomAug((0.4, 1.6), True, 0.7), 0.45),
        # Tiny people from 40-60 m (20 px head boxes at 1920x1080).
        build("dronecrowd", dc, lambda s, hw: point_target(hw, s.points, sigma=5.0), GeomAug((0.7, 1.4), True, 0.7), 0.2),
        # Dense street crowds, shrunk toward the size of people seen from a drone.
        build("shanghaitech_b", shb, lambda s, hw: point_target(hw, s.points, sigma_range=(3.0 * f, 24.0 * f)),
              GeomAug((0.25 / f, 0.9 / f), True, 0.6), 0.35),
    ]
    log.info("loaded %s in %.0f s", {s.name: len(s.images) for s in sources}, time.monotonic() - t0)
    return sources


def check_shares(synthetic_share: float, negative_share: float, max_images: int = 0) -> None:
    """ValueError naming the flag when the shares or the image limit make no sense."""
    for key, v in (("synthetic share", synthetic_share), ("negative share", negative_share)):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{key} must be in [0, 1], got {v}")
    if synthetic_share + negative_share > 1.0 + 1e-9:
        raise ValueError(f"synthetic share + negative share must be <= 1, got {synthetic_share + negative_share}")
    if max_images < 0:
        raise ValueError(f"max images must be >= 0, got {max_images}")


def all_sources(shared: Path, synthetic_share: float, negative_share: float, max_images: int = 0,
                seed: int = 0, negative_kinds: Sequence[str] | None = None) -> list[CropSource]:
    """The real sources scaled to ``1 - synthetic_share - negative_share`` of the crops, plus the
    synthetic and hard-negative sources at their shares (each loaded only when its share is > 0).
    With both shares 0 this is exactly :func:`load_sources` (the shipped configuration).
    ``negative_kinds``: the hard-negative kinds to draw (None: all; ``negatives.check_kinds``)."""
    check_shares(synthetic_share, negative_share, max_images)
    real = 1.0 - synthetic_share - negative_share
    out: list[CropSource] = []
    if real > 1e-9:
        for s in load_sources(shared, max_images):
            if synthetic_share or negative_share:
                s.weight *= real
            out.append(s)
    if synthetic_share > 0 or negative_share > 0:
        t0 = time.monotonic()
        cutouts, grounds = C.load_semantic(shared, "train", max_images)
        if synthetic_share > 0:
            comp = C.Compositor(cutouts, grounds, C.load_layouts(shared, "train"))
            out.append(SyntheticSource(comp, synthetic_share))
        if negative_share > 0:
            out.append(NegativeSource(HardNegatives.build(grounds, class_indices(shared), seed, negative_kinds),
                                      negative_share))
        log.info("synthetic share %.2f, hard-negative share %.2f: %d people, %d grounds in %.0f s",
                 synthetic_share, negative_share, len(cutouts), len(grounds), time.monotonic() - t0)
    return out


def raw_batch(sources: list[CropSource], batch: int, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, size, size) uint8 BGR crops after photometric augmentation, and their (N, 1, size/4,
    size/4) float32 targets; the crops' sources drawn by weight. Un-normalised, so worker processes
    hand a GPU run a quarter of the bytes (:func:`normalise` there)."""
    w = np.array([s.weight for s in sources])
    xs = np.empty((batch, 3, size, size), np.uint8)
    ys = np.empty((batch, 1, size // M.STRIDE, size // M.STRIDE), np.float32)
    for b in range(batch):
        src = sources[rng.choice(len(sources), p=w / w.sum())]
        img, tgt = src.crop(size, rng)
        xs[b] = photometric(img, rng).transpose(2, 0, 1)
        # Max over each 4x4 cell: a cell touching a person is a person cell (errs toward occupied).
        ys[b, 0] = tgt.reshape(size // M.STRIDE, M.STRIDE, size // M.STRIDE, M.STRIDE).max(axis=(1, 3))
    return xs, ys


def normalise(x: torch.Tensor) -> torch.Tensor:
    """uint8 NCHW BGR on any device -> the network's float32 input (``(x * SCALE - MEAN) / STD``);
    on the CPU, in the data loader, or on the GPU after the uint8 crops are copied there."""
    mean = torch.tensor(M.MEAN, dtype=torch.float32, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(M.STD, dtype=torch.float32, device=x.device).view(1, 3, 1, 1)
    return (x.float() * M.SCALE - mean) / std


def make_batch(sources: list[CropSource], batch: int, size: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    xs, ys = raw_batch(sources, batch, size, rng)
    return normalise(torch.from_numpy(xs)), torch.from_numpy(ys)


def loss(logits: torch.Tensor, target: torch.Tensor, pos_weight: float) -> torch.Tensor:
    """Binary cross-entropy with the positive term weighted ``pos_weight`` times.

    For a soft target t the minimiser is p = a t / (a t + 1 - t) with a = ``pos_weight`` > 1, i.e.
    above t: the network learns to over-estimate where people are, which is the safe direction.
    """
    pw = torch.tensor([pos_weight], dtype=logits.dtype, device=logits.device)
    return F.binary_cross_entropy_with_logits(logits, target, pos_weight=pw)


def resolve_device(name: str) -> torch.device:
    """The torch device of ``--device``; a clear error for CUDA on a machine without it."""
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"--device {name!r} is not a torch device: {exc}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: this torch build or machine has no CUDA device")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"--device must be cpu or cuda[:N], got {name!r}")
    return dev


def start_run(args: argparse.Namespace) -> tuple[torch.device, np.random.Generator]:
    """A training run's start, the same for every model trained here: the device of ``--device``,
    torch seeded with ``--seed`` on ``--threads`` threads (OpenCV on one), and the numpy
    generator of the crops seeded alike."""
    device = resolve_device(args.device)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)
    return device, np.random.default_rng(args.seed)


def warm_cosine(opt: torch.optim.Optimizer, warm: int, steps: int) -> torch.optim.lr_scheduler.LambdaLR:
    """The learning rate by step: a linear warm-up over ``warm`` steps, then a cosine down to 0
    at ``steps`` (the shipped models' schedule, as it was: its rounding reproduces their files)."""
    return torch.optim.lr_scheduler.LambdaLR(
        opt, lambda k: min(1.0, (k + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(k, steps) / steps)))


def train(args: argparse.Namespace) -> Path:
    device, rng = start_run(args)
    sources = all_sources(Path(args.shared), args.synthetic_share, args.negative_share, args.max_images, args.seed,
                          args.negative_kinds)
    net = M.SLZDensityNet().to(device)
    log.info("parameters: %d", M.count_parameters(net))
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = warm_cosine(opt, 100, args.steps)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    running = 0.0
    net.train()
    for step in range(1, args.steps + 1):
        x, y = make_batch(sources, args.batch, args.crop, rng)
        if device.type != "cpu":
            x, y = x.to(device, non_blocking=True), y.to(device, non_blocking=True)
        batch_loss = loss(net(x), y, args.pos_weight)
        opt.zero_grad(set_to_none=True)
        batch_loss.backward()
        opt.step()
        sched.step()
        running += batch_loss.item()
        if step % 50 == 0:
            el = time.monotonic() - t0
            log.info("step %d/%d loss %.4f lr %.2e %.2f s/step elapsed %.1f min", step, args.steps,
                     running / 50, sched.get_last_lr()[0], el / step, el / 60)
            running = 0.0
        if step % 500 == 0 or step == args.steps:
            torch.save({"step": step, "model": net.state_dict(), "args": vars(args)}, work / "last.pt")
    net = net.cpu().eval()
    note = f"steps={args.steps} seed={args.seed} pos_weight={args.pos_weight}"
    if args.synthetic_share or args.negative_share or args.device != "cpu":
        note += f" synthetic_share={args.synthetic_share} negative_share={args.negative_share} device={args.device}"
    if args.negative_kinds is not None:
        note += f" negative_kinds={','.join(args.negative_kinds)}"
    out = export_onnx(net, Path(args.out), {"companion.training": note})
    log.info("exported %s (%.1f min)", out, (time.monotonic() - t0) / 60)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shared", default="../shared", help="the shared data directory")
    p.add_argument("--out", required=True,
                   help="ONNX file to write (no default: a run never replaces a shipped model unasked)")
    p.add_argument("--work", default="/tmp/slz-train", help="checkpoint directory (outside the repo)")
    p.add_argument("--steps", type=int, default=2400)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--crop", type=int, default=256, help="crop side in pixels (multiple of 4)")
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--pos-weight", type=float, default=4.0, help="weight of the 'person here' BCE term")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--synthetic-share", type=float, default=0.0,
                   help="share of crops drawn from synthetic top-down crowds (0-1; default 0)")
    p.add_argument("--negative-share", type=float, default=0.0,
                   help="share of crops drawn from hard negatives: roofs, cars, trees, ... (0-1; default 0)")
    p.add_argument("--negative-kinds", type=lambda v: [k.strip() for k in v.split(",") if k.strip()],
                   default=None, help="comma-separated hard-negative kinds to draw (default: all; "
                   "companion.training.negatives.KINDS, or no-person-photo)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda[:N]")
    p.add_argument("--max-images", type=int, default=0,
                   help="use only the first N images of each source (quick runs and tests; 0: all)")
    p.add_argument("--no-calibrate", action="store_true", help="skip threshold / count-scale calibration")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:  # bad flags and missing data: a clear message and exit 2 before any training
        resolve_device(args.device)
        check_shares(args.synthetic_share, args.negative_share, args.max_images)
        if args.negative_kinds is not None:
            check_kinds(args.negative_kinds)
            if args.negative_share <= 0:
                raise ValueError("--negative-kinds needs --negative-share > 0")
    except ValueError as exc:
        print(f"companion.training.train: {exc}", file=sys.stderr)
        return 2
    try:
        out = train(args)
    except D.DatasetError as exc:
        print(f"companion.training.train: {exc}", file=sys.stderr)
        return 2
    if not args.no_calibrate:
        from companion.training.calibrate import calibrate

        calibrate(out, Path(args.shared), threads=args.threads)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
