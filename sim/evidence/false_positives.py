"""How much of each scenario's lawn a density model marks as people when nobody is there.

``python -m sim.evidence.false_positives --seeds 1-34 --heights 10,20 [--model FILE.onnx]``

For every seed with a free circle (``sim.flights.flight.build_world``), the seed's procedural ground is
rendered straight down over the circle's centre from each height with *nobody* in the world, the
model runs at its own threshold (``occupancy_threshold`` in its metadata) through the service's
occupancy step, and the share of the free circle's head-plane area marked occupied is printed
(plus the share of the whole frame). Anything marked is a false positive: paths across lawns,
benches, trees. A zone's landing point can only be as central as the lawn the model leaves free
(docs/design.md, "Why landing points sit at a lawn's edge").

``--landability FILE.onnx`` asks the same of a landability model instead: the share of the lawn it
calls unlandable (every level but its landable one, summed, above its own threshold, through the
service's ``surface_free_map``); the landability card's "On the simulator's ground" quotes these
figures.

A lawn is not all landable: the procedural ground puts trees, benches and paths on it, and the
scenario's free circle often holds a tree or a bench (``sim.world.ground.SURFACES``, the ground's own
truth). So each row also judges the marks on the truth, on the ground plane (where a tree or a
bench is, not the head plane where people's heads are): ``landable_marked_pct``, the share of the
circle's truly landable ground (grass, paths, paving) that is marked (a false alarm for either
kind of model); ``unlandable_pct``, the share of the circle that is not landable (trees,
benches); and ``unlandable_left_pct``, the share of that which is left unmarked (a miss for a
landability model; for a density model, what the landability model is there for). The last is
None where the circle holds nothing unlandable.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from companion.config import SHIPPED_MODEL
from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.density import DensityModel
from companion.pipeline.landability import LandabilityModel
from companion.pipeline.occupancy import OCCUPIED, OccupancyParams, occupancy_map, surface_free_map
from companion.pipeline.slz import PipelineConfig
from sim.flights.flight import build_world
from sim.flights.scenarios import parse_seeds, scenario
from sim.world.crowd import World
from sim.world.ground import LANDABLE_SURFACES, SURFACES, ProceduralGround
from sim.world.render import render_world
from sim.world.walkers import Circle

K = Intrinsics.from_fov(640, 480, 70.0)
#: The head plane the service places people on (m above the ground).
HEAD_M = PipelineConfig().head_height_m
#: Sample every STEP-th pixel in both directions (the occupancy map is smooth at that scale).
STEP = 4
#: The truth's resolution (m/px) when judging marks on the ground plane.
TRUTH_RES = 0.04
_LANDABLE = np.array([name in LANDABLE_SURFACES for name in SURFACES])


@dataclass(frozen=True)
class LawnFigure:
    """One seed seen from one height: percentages of the free circle and of the frame marked
    occupied on an empty world."""

    seed: int
    world: str
    height_m: float
    circle_pct: float
    frame_pct: float
    landable_marked_pct: float | None = None
    unlandable_pct: float | None = None
    unlandable_left_pct: float | None = None


def marked_map(model: DensityModel, img: np.ndarray) -> np.ndarray:
    """(H, W) bool: where the service's occupancy step, fed by ``model`` at its own threshold,
    marks the frame: people for a density model, unlandable ground for a landability model."""
    if isinstance(model, LandabilityModel):
        spec = model.landability
        unlandable = 1.0 - model(img)[spec.names.index(spec.landable)]
        return surface_free_map(unlandable, img.shape[:2], spec.threshold) == OCCUPIED
    threshold = model.spec.occupancy_threshold if model.spec.occupancy_threshold is not None else 0.0
    return occupancy_map(model(img), img.shape[:2], OccupancyParams(threshold=threshold)) == OCCUPIED


def lawn_false_positives(model: DensityModel, seed: int, heights_m: Sequence[float]) -> list[LawnFigure]:
    """The figures of ``seed`` from each of ``heights_m`` (m above the ground); none for a world
    without a free circle."""
    spec = scenario(seed, "ardupilot")  # the scene does not depend on the flavour
    _world, free, _start = build_world(spec)
    if free is None:
        return []
    empty, ground = World(seed=seed), ProceduralGround(seed)
    vv, uu = np.mgrid[0:K.height:STEP, 0:K.width:STEP]
    pixels = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    figures = []
    for height_m in heights_m:
        pose = Pose(0.0, free.north, free.east, -height_m, 0.0, 0.0, 0.0)
        img = render_world(empty, pose, K, Mount(), ground)
        occ = marked_map(model, img)
        xy = PlaneProjection.from_pose(K, Mount(), pose, head_height=HEAD_M).image_to_plane(pixels)
        inside = np.hypot(xy[:, 0] - free.north, xy[:, 1] - free.east) < free.radius
        marked = occ[vv.ravel(), uu.ravel()]
        circle = float(marked[inside].mean()) if inside.any() else float("nan")
        truth = _truth_figures(ground, pose, pixels, marked, free)
        figures.append(LawnFigure(seed, spec.world, height_m, round(100 * circle, 2),
                                  round(100 * float(marked.mean()), 2), *truth))
    return figures


def _truth_figures(ground: ProceduralGround, pose: Pose, pixels: np.ndarray, marked: np.ndarray,
                   free: Circle) -> tuple[float | None, float | None, float | None]:
    """``(landable_marked_pct, unlandable_pct, unlandable_left_pct)`` of the free circle, judged
    on the ground's truth at the pixels' ground points (see the module docstring)."""
    cn, ce, r = free.north, free.east, free.radius
    xy = PlaneProjection.from_pose(K, Mount(), pose, head_height=0.0).image_to_plane(pixels)
    inside = np.hypot(xy[:, 0] - cn, xy[:, 1] - ce) < r
    if not inside.any():
        return None, None, None
    labels, A = ground.surface_labels(cn - r, cn + r, ce - r, ce + r, TRUTH_RES)
    pts = xy[inside]
    col = np.clip((A[0, 1] * pts[:, 1] + A[0, 2]).astype(int), 0, labels.shape[1] - 1)
    row = np.clip((A[1, 0] * pts[:, 0] + A[1, 2]).astype(int), 0, labels.shape[0] - 1)
    landable = _LANDABLE[labels[row, col]]
    m = marked[inside]
    pct = lambda a: round(100 * float(a.mean()), 2)  # noqa: E731
    return (pct(m[landable]) if landable.any() else None, pct(~landable),
            pct(~m[~landable]) if (~landable).any() else None)


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f} %"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.evidence.false_positives", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1-34", help="seeds, e.g. 1-34 or 5,6,28 (default 1-34)")
    ap.add_argument("--heights", default="10,20", help="heights above the ground in m (default 10,20)")
    ap.add_argument("--model", type=Path, default=SHIPPED_MODEL, help="ONNX density model (default: the shipped one)")
    ap.add_argument("--landability", type=Path, default=None,
                    help="measure this ONNX landability model's unlandable marks instead of --model's people")
    ap.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    args = ap.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
        heights = [float(h) for h in args.heights.split(",")]
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not all(0.0 < h - HEAD_M < 500.0 for h in heights):
        print(f"error: heights must lie between {HEAD_M} m (the head plane) and 500 m", file=sys.stderr)
        return 2
    path = args.landability or args.model
    if not path.is_file():
        print(f"error: no model at {path}", file=sys.stderr)
        return 2
    try:
        model = LandabilityModel(path, threads=2) if args.landability else DensityModel(path, threads=2)
    except (ValueError, OSError) as e:  # the runners' errors name the file and what is wrong
        print(f"error: {e}", file=sys.stderr)
        return 2
    for seed in seeds:
        figures = lawn_false_positives(model, seed, heights)
        if not figures:
            continue
        if args.json:
            for f in figures:
                print(json.dumps(asdict(f)), flush=True)
        else:
            cells = "  ".join(f"{f.height_m:g} m: lawn {f.circle_pct:5.1f} %, frame {f.frame_pct:4.1f} %, "
                              f"landable ground {_pct(f.landable_marked_pct)}, unlandable {_pct(f.unlandable_pct)} "
                              f"({_pct(f.unlandable_left_pct)} left)" for f in figures)
            print(f"seed {seed:>3} {figures[0].world:<13} {cells}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
