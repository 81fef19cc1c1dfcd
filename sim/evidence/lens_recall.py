"""How far from the image centre the shipped model still finds people through a wide lens (issue 60).

Renders crowds through a camera (``--camera MODEL:HFOV``, e.g. fisheye:160) at several heights,
runs the density model and the service's occupancy step with the model's own threshold, and counts
a person found when their head pixel is occupied (the closed-loop test's rule,
``tests/sim/evidence/test_sim_render_model.py``). People are binned by the angle of their head's ray
from the optical axis (degrees; the image radius of a fisheye grows with it), so the table says out
to which angle the view may be trusted::

    python -m sim.evidence.lens_recall --camera fisheye:160 --heights 10,20,30 --seeds 1-4
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose, camera_extrinsics
from companion.pipeline.occupancy import OCCUPIED, OccupancyParams, occupancy_map
from sim.flights.spec import parse_camera
from sim.world.crowd import default_world
from sim.world.ground import ProceduralGround
from sim.world.render import render_world
from sim.world.walkers import CrowdParams

BIN_DEG = 10.0


def recall_by_angle(camera: str, heights: list[float], seeds: list[int], frames: int = 3,
                    model_path: str | None = None, walkers: int = 30) -> dict[str, object]:
    """Per ``BIN_DEG`` bin of the head ray's angle from the optical axis: people in view, found,
    and the share found. ``walkers``: people walking in the 120 m square world (a sparse crowd:
    in a dense one a missed head is often covered by its neighbours' occupancy)."""
    from companion.config import SHIPPED_MODEL
    from companion.pipeline.density import DensityModel

    lens, hfov = parse_camera(camera)
    K = Intrinsics.from_fov(640, 480, hfov, lens)
    model = DensityModel(model_path or SHIPPED_MODEL, threads=2)
    threshold = model.spec.occupancy_threshold if model.spec.occupancy_threshold is not None else 0.0
    mount = Mount()
    nbins = int(math.ceil(100.0 / BIN_DEG))
    seen = np.zeros(nbins, int)
    found = np.zeros(nbins, int)
    for seed in seeds:
        world = default_world(seed=seed, half_size=60.0,
                              params=CrowdParams(n_walkers=walkers, n_groups=max(1, walkers // 8),
                                                 n_standing=max(1, walkers // 3)))
        ground = ProceduralGround(seed)
        for h in heights:
            for k in range(frames):
                world.step(1.0)
                pose = Pose(0.0, 0.0, 0.0, -h, 0.0, 0.0, 0.5 * k)
                img = render_world(world, pose, K, mount, ground)
                occ = occupancy_map(model(img), img.shape[:2], OccupancyParams(threshold=threshold))
                pos = world.positions()
                uv = PlaneProjection.from_pose(K, mount, pose, head_height=1.7).plane_to_image(pos)
                ext = camera_extrinsics(pose, mount)
                xc = (np.column_stack([pos, np.full(len(pos), -1.7)]) - ext.position) @ ext.R_cv_from_world.T
                theta = np.degrees(np.arctan2(np.hypot(xc[:, 0], xc[:, 1]), xc[:, 2]))
                ok = np.isfinite(uv).all(axis=1)
                ok[ok] = (uv[ok, 0] >= 0) & (uv[ok, 0] <= K.width - 1) & (uv[ok, 1] >= 0) & (uv[ok, 1] <= K.height - 1)
                px = np.round(uv[ok]).astype(int)
                hit = occ[px[:, 1], px[:, 0]] == OCCUPIED
                b = np.minimum((theta[ok] // BIN_DEG).astype(int), nbins - 1)
                np.add.at(seen, b, 1)
                np.add.at(found, b, hit.astype(int))
    rows = [{"from_deg": i * BIN_DEG, "to_deg": (i + 1) * BIN_DEG, "people": int(seen[i]), "found": int(found[i]),
             "recall": None if seen[i] == 0 else round(float(found[i] / seen[i]), 4)} for i in range(nbins)]
    return {"camera": camera, "heights_m": heights, "seeds": seeds, "frames": frames, "walkers": walkers,
            "bins": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--camera", default="fisheye:160")
    parser.add_argument("--heights", default="10,20,30", help="metres, comma-separated")
    parser.add_argument("--seeds", default="1-3", help="e.g. 1-4")
    parser.add_argument("--frames", type=int, default=3, help="frames per seed and height")
    parser.add_argument("--walkers", type=int, default=30, help="walkers in the 120 m world (default 30)")
    parser.add_argument("--model", default=None, help="ONNX density model (default: the shipped one)")
    args = parser.parse_args(argv)
    a, _, b = args.seeds.partition("-")
    seeds = list(range(int(a), int(b or a) + 1))
    res = recall_by_angle(args.camera, [float(h) for h in args.heights.split(",")], seeds, args.frames, args.model,
                          args.walkers)
    json.dump(res, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
