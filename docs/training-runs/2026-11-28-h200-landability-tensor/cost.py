"""The cost rows of LANDABILITY_CARD.md (2026-11-28): the shipped density model, the MCNN peer and
the given landability models timed alternately run by run (``latency_pair_ms``: 40 runs each, 2
onnxruntime threads) on one held-out semantic-drone photo resized to 640x480 and 1280x720.

    python docs/training-runs/2026-11-28-h200-landability-tensor/cost.py [--shared ../shared] MODEL.onnx ...
"""

from __future__ import annotations

import argparse
from pathlib import Path

from companion.evaluation import datasets as D
from companion.evaluation.cli import PRESETS
from companion.evaluation.metrics import bench_frame, latency_pair_ms
from companion.pipeline.density import DensityModel
from companion.pipeline.landability import LandabilityModel


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shared", type=Path, default=Path("../shared"))
    ap.add_argument("models", nargs="+", type=Path)
    args = ap.parse_args()
    src = D.semantic_drone(args.shared, "val")[0].image()
    dens = DensityModel(Path("companion/models/slz-density.onnx"), threads=2)
    peer = DensityModel(args.shared / "peers" / "mcnn-shb.onnx", threads=2, overrides=dict(PRESETS["mcnn"]))
    lands = [LandabilityModel(p, threads=2) for p in args.models]
    for hw in ((480, 640), (720, 1280)):
        res = latency_pair_ms([dens, peer, *lands], bench_frame(src, hw), 40)
        d, m = res[0]["median"], res[1]["median"]
        print(f"{hw[1]}x{hw[0]}: density {d:.1f} ms, MCNN {m:.1f} ms, density/MCNN {d / m:.3f}")
        for path, r in zip(args.models, res[2:]):
            print(f"   {path.name}: {r['median']:.1f} ms (p10 {r['p10']:.1f}), (density + it)/MCNN {(d + r['median']) / m:.3f}")


if __name__ == "__main__":
    main()
