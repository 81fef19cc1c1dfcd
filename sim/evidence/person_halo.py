"""How far around one standing person the service's pipeline marks the ground occupied.

``python -m sim.evidence.person_halo [--heights 4.4,7,10,15] [--distances 2.5,3,3.5,4,5] [--model FILE]``

One person stands at a known distance from the point straight below the camera (on the seed's
procedural lawn, four bearings); the camera looks straight down from each height; the service's
pipeline (the shipped model at its threshold, the settings ``companion run`` has) runs on three
frames of the still scene, and the free radius it reports around the point below
(``FrameResult.below.r``) is printed beside the person's true distance. The difference is the
**halo**: how much nearer than they are the pipeline puts a person's occupied ground. A zone lost
with "1.9 m free around the vehicle < r0 2 m" is a person about that much farther than 1.9 m
(docs/measurements.md, 2026-11-29). ``--json`` prints the rows.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from companion import config as settings
from companion.geometry.camera import Intrinsics, Mount, Pose
from sim.evidence.false_positives import HEAD_M
from sim.flights.flight import scene_centre
from sim.flights.scenarios import scenario
from sim.world.ground import ProceduralGround
from sim.world.render import render

BEARINGS_DEG = (0.0, 90.0, 180.0, 270.0)


@dataclass(frozen=True)
class HaloRow:
    """One height and distance: the free radius reported at each bearing (m), the view's reach
    around the point (m), and the halo (distance less the free radius; None where the view ends
    before the person)."""

    height_m: float
    distance_m: float
    free_m: list[float]
    view_m: float
    halo_m: list[float | None]


def parse_floats(text: str) -> list[float]:
    values = [float(v) for v in text.split(",") if v.strip()]
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"expected positive numbers separated by commas, got {text!r}")
    return values


def measure(heights: Sequence[float], distances: Sequence[float], model_path: str | None = None,
            seed: int = 18) -> list[HaloRow]:
    """The rows for every height and distance (the seed's lawn under the camera)."""
    from companion.service.parts import build_pipeline, load_model

    overrides: dict[str, object] = {"camera.width": 640, "camera.height": 480, "camera.hfov_deg": 70.0}
    if model_path is not None:
        overrides["model.path"] = model_path
    cfg = settings.load(None, overrides)
    model = load_model(cfg)
    K = Intrinsics.from_fov(640, 480, 70.0)
    ground = ProceduralGround(seed)
    cn, ce = scene_centre(scenario(seed))
    rows = []
    for h in heights:
        for d in distances:
            free, view = [], 0.0
            for bearing in BEARINGS_DEG:
                b = math.radians(bearing)
                person = np.array([[cn + d * math.cos(b), ce + d * math.sin(b)]])
                pipe = build_pipeline(cfg, model)  # a fresh one: no memory of the last bearing
                result = None
                for k in range(3):
                    pose = Pose(0.1 * k, cn, ce, -h, 0.0, 0.0, 0.0)
                    img = render(person, pose, K, Mount(), ground, headings=np.array([b + 1.0]), seed=1)
                    result = pipe.process(img, pose.t, pose)
                assert result is not None and result.below is not None
                free.append(round(result.below.r, 2))
                view = round(result.below.r_view, 2)
            halo = [None if r >= view - 1e-6 else round(d - r, 2) for r in free]
            rows.append(HaloRow(h, d, free, view, halo))
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.evidence.person_halo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--heights", default="4.4,7,10,15", help="camera heights (m above the ground)")
    parser.add_argument("--distances", default="2.5,3,3.5,4,5", help="the person's distances from the point (m)")
    parser.add_argument("--model", default=None, help="ONNX density model (default: the shipped one)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args(argv)
    try:
        heights, distances = parse_floats(args.heights), parse_floats(args.distances)
    except ValueError as exc:
        print(f"sim.evidence.person_halo: {exc}", file=sys.stderr)
        return 2
    if not all(h > HEAD_M for h in heights):
        print(f"sim.evidence.person_halo: heights must lie above the head plane ({HEAD_M} m)", file=sys.stderr)
        return 2
    from companion.config import ConfigError
    from companion.pipeline.density import DensityModelError

    try:
        rows = measure(heights, distances, args.model)
    except (ConfigError, DensityModelError) as exc:
        print(f"sim.evidence.person_halo: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps([asdict(r) for r in rows]))
        return 0
    print(f"{'height m':>8} {'person m':>8} {'view m':>6}  free radius at 4 bearings (m)   halo (m)")
    for r in rows:
        halo = " ".join("-" if v is None else f"{v:.2f}" for v in r.halo_m)
        print(f"{r.height_m:>8g} {r.distance_m:>8g} {r.view_m:>6.2f}  {' '.join(f'{v:.2f}' for v in r.free_m):<30}  {halo}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
