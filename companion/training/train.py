"""Train the shipped density network from scratch and export it to ONNX.

    python -m companion.training.train --shared ../shared --out companion/models/slz-density.onnx

Data: the semantic drone photos except the held-out fifth (person boxes), five of the six
DroneCrowd frames (``img112008-012``; ``img017012``, another sequence, stays held out) and the
ShanghaiTech B training images (head points). The loss is a weighted binary cross-entropy on
peak-1 Gaussian targets (see ``loss``), biased toward over-estimating people. After training the
model is exported, then calibrated on validation data (:mod:`companion.training.calibrate`) which
stores the occupancy threshold and the count scale in the ONNX metadata.
Deterministic: the same seed and thread count give the same weights.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from companion.evaluation import datasets as D
from companion.training import model as M
from companion.training.augment import GeomAug, photometric, random_crop
from companion.training.export import export_onnx
from companion.training.targets import box_target, point_target

log = logging.getLogger("companion.training")

TRAIN_DRONECROWD = [f"img112{k:03d}" for k in range(8, 13)]


@dataclass
class Source:
    """One training source held in memory: images, their target maps, head/box-centre points."""

    name: str
    images: list[np.ndarray]
    targets: list[np.ndarray]  # float16, image size, peak 1
    points: list[np.ndarray]
    aug: GeomAug
    weight: float


def load_sources(shared: Path) -> list[Source]:
    t0 = time.monotonic()
    sd = D.semantic_drone(shared, "train")
    dc = D.dronecrowd_frames(shared, TRAIN_DRONECROWD)
    shb = D.shanghaitech_b(shared, "train")

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
        build("shanghaitech_b", shb, lambda s, hw: point_target(hw, s.points), GeomAug((0.25, 0.9), True, 0.6), 0.35),
    ]
    log.info("loaded %s in %.0f s", {s.name: len(s.images) for s in sources}, time.monotonic() - t0)
    return sources


def make_batch(sources: list[Source], batch: int, size: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    w = np.array([s.weight for s in sources])
    xs = np.empty((batch, 3, size, size), np.float32)
    ys = np.empty((batch, 1, size // M.STRIDE, size // M.STRIDE), np.float32)
    mean = np.array(M.MEAN, np.float32)[:, None, None]
    std = np.array(M.STD, np.float32)[:, None, None]
    for b in range(batch):
        src = sources[rng.choice(len(sources), p=w / w.sum())]
        i = rng.integers(len(src.images))
        img, tgt = random_crop(src.images[i], src.targets[i].astype(np.float32), src.points[i], size, src.aug, rng)
        img = photometric(img, rng)
        xs[b] = (img.transpose(2, 0, 1).astype(np.float32) * M.SCALE - mean) / std
        # Max over each 4x4 cell: a cell touching a person is a person cell (errs toward occupied).
        ys[b, 0] = tgt.reshape(size // M.STRIDE, M.STRIDE, size // M.STRIDE, M.STRIDE).max(axis=(1, 3))
    return torch.from_numpy(xs), torch.from_numpy(ys)


def loss(logits: torch.Tensor, target: torch.Tensor, pos_weight: float) -> torch.Tensor:
    """Binary cross-entropy with the positive term weighted ``pos_weight`` times.

    For a soft target t the minimiser is p = a t / (a t + 1 - t) with a = ``pos_weight`` > 1, i.e.
    above t: the network learns to over-estimate where people are, which is the safe direction.
    """
    pw = torch.tensor([pos_weight], dtype=logits.dtype)
    return F.binary_cross_entropy_with_logits(logits, target, pos_weight=pw)


def train(args: argparse.Namespace) -> Path:
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)
    rng = np.random.default_rng(args.seed)
    sources = load_sources(Path(args.shared))
    net = M.SLZDensityNet()
    log.info("parameters: %d", M.count_parameters(net))
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    warm = 100
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda k: min(1.0, (k + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(k, args.steps) / args.steps))
    )
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    running = 0.0
    net.train()
    for step in range(1, args.steps + 1):
        x, y = make_batch(sources, args.batch, args.crop, rng)
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
    net.eval()
    out = export_onnx(net, Path(args.out), {"companion.training": f"steps={args.steps} seed={args.seed} pos_weight={args.pos_weight}"})
    log.info("exported %s (%.1f min)", out, (time.monotonic() - t0) / 60)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shared", default="../shared", help="the shared data directory")
    p.add_argument("--out", default="companion/models/slz-density.onnx", help="ONNX file to write")
    p.add_argument("--work", default="/tmp/slz-train", help="checkpoint directory (outside the repo)")
    p.add_argument("--steps", type=int, default=2400)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--crop", type=int, default=256, help="crop side in pixels (multiple of 4)")
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--pos-weight", type=float, default=4.0, help="weight of the 'person here' BCE term")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-calibrate", action="store_true", help="skip threshold / count-scale calibration")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    out = train(args)
    if not args.no_calibrate:
        from companion.training.calibrate import calibrate

        calibrate(out, Path(args.shared), threads=args.threads)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
