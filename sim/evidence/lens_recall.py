"""How far from the image centre the shipped model still finds people through a wide lens (issue 60).

Renders crowds through a camera (``--camera MODEL:HFOV``, e.g. fisheye:160) at several heights,
runs the density model and the service's occupancy step with the model's own threshold, and counts
a person found when their head pixel is occupied (the closed-loop test's rule,
``tests/sim/evidence/test_sim_render_model.py``). People are binned by the angle of their head's ray
from the optical axis (degrees; the image radius of a fisheye grows with it), so the table says out
to which angle the view may be trusted::

    python -m sim.evidence.lens_recall --camera fisheye:160 --heights 10,20,30 --seeds 1-4

``--ground photo`` (``--photos DIR``, default ``../shared/data/semantic_drone/full``, checked as
``sim-scenarios --ground photo`` checks it) asks the same over composited frames: the photo world
(docs/photo-world.md) around the seed's photo scene (``sim.flights.flight.photo_scene_centre``),
the same sparse crowd kept to walkable ground by the class maps and drawn as real silhouettes
(``sim.world.photo_people``), and the photos' own people counted as the photo world's judge counts
them (``PhotoGround.people``: each person component's centroid). A walker is found when the pixel
of its silhouette's centre (``BODY_Z``, where the painter centres it) is occupied, a photo's person
when the pixel of its centroid on the ground is; a photo's person counts only within the ground the
renderer draws (``LENS_RANGE_PER_M`` x the height, at most ``MAX_RANGE``; beyond is haze). Each
bin then also gives both kinds apart (``walkers``, ``photo_people``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose, camera_extrinsics
from companion.pipeline.input_scale import density_scale, shrunk
from companion.pipeline.occupancy import OCCUPIED, OccupancyParams, occupancy_map
from companion.pipeline.slz import PipelineConfig
from sim.flights.flight import photo_ground, photo_scene_centre
from sim.flights.scenarios import FlightJob
from sim.flights.spec import parse_camera, photos_folder
from sim.world.crowd import default_world
from sim.world.ground import ProceduralGround
from sim.world.photo_ground import PhotoGround
from sim.world.photo_people import BODY_Z
from sim.world.render import HEAD_Z, LENS_RANGE_PER_M, MAX_RANGE, render_world
from sim.world.walkers import CrowdParams

BIN_DEG = 10.0
#: Half the side (m) of the square the crowd walks in, around the scene's centre.
HALF_M = 60.0


def _tally(occ: np.ndarray, K: Intrinsics, mount: Mount, pose: Pose, pos: np.ndarray, z_up: float,
           nbins: int) -> tuple[np.ndarray, np.ndarray]:
    """Per angle bin: how many of ``pos`` ((N, 2) north, east m, each at ``z_up`` m above the
    ground) are in the frame, and how many of those fall on an occupied pixel of ``occ``."""
    seen, found = np.zeros(nbins, int), np.zeros(nbins, int)
    if len(pos) == 0:
        return seen, found
    uv = PlaneProjection.from_pose(K, mount, pose, head_height=z_up).plane_to_image(pos)
    ext = camera_extrinsics(pose, mount)
    xc = (np.column_stack([pos, np.full(len(pos), -z_up)]) - ext.position) @ ext.R_cv_from_world.T
    theta = np.degrees(np.arctan2(np.hypot(xc[:, 0], xc[:, 1]), xc[:, 2]))
    ok = np.isfinite(uv).all(axis=1)
    ok[ok] = (uv[ok, 0] >= 0) & (uv[ok, 0] <= K.width - 1) & (uv[ok, 1] >= 0) & (uv[ok, 1] <= K.height - 1)
    px = np.round(uv[ok]).astype(int)
    hit = occ[px[:, 1], px[:, 0]] == OCCUPIED
    b = np.minimum((theta[ok] // BIN_DEG).astype(int), nbins - 1)
    np.add.at(seen, b, 1)
    np.add.at(found, b, hit.astype(int))
    return seen, found


def _recall(people: int, found: int) -> float | None:
    return None if people == 0 else round(float(found / people), 4)


def recall_by_angle(camera: str, heights: list[float], seeds: list[int], frames: int = 3,
                    model_path: str | None = None, walkers: int = 30,
                    photos: str | None = None, person_px: float = 0.0) -> dict[str, object]:
    """Per ``BIN_DEG`` bin of the head ray's angle from the optical axis: people in view, found,
    and the share found. ``walkers``: people walking in the 120 m square world (a sparse crowd:
    in a dense one a missed head is often covered by its neighbours' occupancy). ``photos``: the
    checked photos folder of the photo world (module docstring); None for the drawn ground.
    ``person_px``: the pipeline's setting of that name (a pinhole's frame shrunk before the model
    so that the smallest person spans that many pixels; 0: the full frame)."""
    from companion.config import SHIPPED_MODEL
    from companion.pipeline.density import DensityModel

    lens, hfov = parse_camera(camera)
    K = Intrinsics.from_fov(640, 480, hfov, lens)
    model = DensityModel(model_path or SHIPPED_MODEL, threads=2)
    threshold = model.spec.occupancy_threshold if model.spec.occupancy_threshold is not None else 0.0
    mount = Mount()
    head_m = PipelineConfig().head_height_m  # the head plane the service projects frames on
    nbins = int(math.ceil(100.0 / BIN_DEG))
    seen = np.zeros((2, nbins), int)  # walkers, the photos' own people
    found = np.zeros((2, nbins), int)
    for seed in seeds:
        ground: ProceduralGround | PhotoGround
        if photos is None:
            ground, centre, walkable = ProceduralGround(seed), (0.0, 0.0), None
        else:
            ground = photo_ground(photos)
            centre = photo_scene_centre(FlightJob(seed, "px4", ground="photo", photos=photos).spec())
            walkable = ground.walkable(centre, HALF_M + 1.0)
        world = default_world(seed=seed, half_size=HALF_M, centre=centre,
                              params=CrowdParams(n_walkers=walkers, n_groups=max(1, walkers // 8),
                                                 n_standing=max(1, walkers // 3), walkable=walkable))
        for h in heights:
            reach = min(MAX_RANGE, LENS_RANGE_PER_M * h)
            own = np.empty((0, 2)) if not isinstance(ground, PhotoGround) else ground.people(centre, reach)
            own = own[np.hypot(own[:, 0] - centre[0], own[:, 1] - centre[1]) <= reach]
            for k in range(frames):
                world.step(1.0)
                pose = Pose(0.0, centre[0], centre[1], -h, 0.0, 0.0, 0.5 * k)
                img = render_world(world, pose, K, mount, ground)
                scale = 1.0
                if person_px > 0 and not K.is_fisheye:  # as SLZPipeline.process shrinks it
                    proj = PlaneProjection.from_pose(K, mount, pose, head_height=head_m)
                    scale = density_scale(proj, img.shape[:2], person_px)
                occ = occupancy_map(model(shrunk(img, scale, model.spec.stride)), img.shape[:2],
                                    OccupancyParams(threshold=threshold))
                # A drawn walker's head; a silhouette's centre, where the painter puts it.
                z_walker = -HEAD_Z if photos is None else -BODY_Z
                for i, (pos, z_up) in enumerate(((world.positions(), z_walker), (own, 0.0))):
                    s, f = _tally(occ, K, mount, pose, pos, z_up, nbins)
                    seen[i] += s
                    found[i] += f
    rows: list[dict[str, object]] = []
    for i in range(nbins):
        n, m = int(seen[:, i].sum()), int(found[:, i].sum())
        row: dict[str, object] = {"from_deg": i * BIN_DEG, "to_deg": (i + 1) * BIN_DEG, "people": n, "found": m,
                                  "recall": _recall(n, m)}
        if photos is not None:
            for j, name in enumerate(("walkers", "photo_people")):
                row[name] = {"people": int(seen[j, i]), "found": int(found[j, i]),
                             "recall": _recall(int(seen[j, i]), int(found[j, i]))}
        rows.append(row)
    return {"camera": camera, "ground": "procedural" if photos is None else "photo", "heights_m": heights,
            "seeds": seeds, "frames": frames, "walkers": walkers, "person_px": person_px, "bins": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.evidence.lens_recall", description=__doc__.splitlines()[0])
    parser.add_argument("--camera", default="fisheye:160")
    parser.add_argument("--heights", default="10,20,30", help="metres, comma-separated")
    parser.add_argument("--seeds", default="1-3", help="e.g. 1-4")
    parser.add_argument("--frames", type=int, default=3, help="frames per seed and height")
    parser.add_argument("--walkers", type=int, default=30, help="walkers in the 120 m world (default 30)")
    parser.add_argument("--model", default=None, help="ONNX density model (default: the shipped one)")
    parser.add_argument("--ground", choices=("procedural", "photo"), default="procedural",
                        help="the drawn ground (default) or the photo world's (docs/photo-world.md)")
    parser.add_argument("--person-px", type=float, default=0.0,
                        help="the pipeline's pipeline.person_px: a pinhole's frame shrunk so that the smallest person "
                             "spans this many pixels (default 0: the full frame)")
    parser.add_argument("--photos", type=Path, default=None,
                        help="the photos of --ground photo (default ../shared/data/semantic_drone/full)")
    args = parser.parse_args(argv)
    try:
        photos = photos_folder(args.ground, args.photos)
    except ValueError as exc:
        print(f"sim.evidence.lens_recall: --photos: {exc}", file=sys.stderr)
        return 2
    a, _, b = args.seeds.partition("-")
    seeds = list(range(int(a), int(b or a) + 1))
    res = recall_by_angle(args.camera, [float(h) for h in args.heights.split(",")], seeds, args.frames, args.model,
                          args.walkers, photos, args.person_px)
    json.dump(res, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
