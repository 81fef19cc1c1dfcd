"""How far around one standing person the service's pipeline marks the ground occupied.

``python -m sim.evidence.person_halo [--heights 4.4,7,10,15] [--distances 2.5,3,3.5,4,5] [--model FILE]
[--seed 18] [--ground photo [--photos DIR]]``

One person stands at a known distance from the point straight below the camera (on the seed's
procedural lawn, four bearings); the camera looks straight down from each height; the service's
pipeline (the shipped model at its threshold, the settings ``companion run`` has) runs on three
frames of the still scene, and the free radius it reports around the point below
(``FrameResult.below.r``) is printed beside the person's true distance. The difference is the
**halo**: how much nearer than they are the pipeline puts a person's occupied ground (the free
radius with nobody there is printed too: where the ground's own marks come first, no halo). A
zone lost with "1.9 m free around the vehicle < r0 2 m" is a person about that much farther than
1.9 m (docs/measurements.md, 2026-11-29). ``--json`` prints the rows.

``--ground photo`` (``--photos DIR``, default ``../shared/data/semantic_drone/full``) asks the same
over the photo world (docs/photo-world.md): the point below is drawn from the seed where the disc
out to the farthest distance plus ``PHOTO_DISC_MARGIN_M`` is walkable (and landable) ground by the
class maps with none of the photos' people within 1 m of it, so the person stands on paved area,
dirt, grass or gravel at every bearing (checked on the class maps); the person is a real
silhouette (``sim.world.photo_people``, one per bearing). Each row also says how far the nearest
of the photos' own people stands (``nearest_other_m``); a halo is None where that person is not
farther than ours (the free radius could be theirs).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from companion import config as settings
from companion.geometry.camera import Intrinsics, Mount, Pose
from sim.evidence.false_positives import HEAD_M
from sim.flights.flight import photo_ground, scene_centre
from sim.flights.scenarios import scenario
from sim.flights.spec import photos_folder
from sim.world.ground import ProceduralGround
from sim.world.photo_ground import PHOTO_WALKABLE, PhotoGround
from sim.world.render import render

BEARINGS_DEG = (0.0, 90.0, 180.0, 270.0)
#: Metres of walkable ground kept beyond the farthest person on the photo ground: half a body.
PHOTO_DISC_MARGIN_M = 0.5


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
    #: The free radius reported at the point with nobody there (m): the ground's own marks. A
    #: halo is None where it is not beyond the person (the marks, not the person, set the radius).
    empty_m: float | None = None
    ground: str = "procedural"
    #: The nearest of the photos' own people from the point below (m); None on the drawn ground.
    nearest_other_m: float | None = None


def parse_floats(text: str) -> list[float]:
    values = [float(v) for v in text.split(",") if v.strip()]
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"expected positive numbers separated by commas, got {text!r}")
    return values


def photo_point(ground: PhotoGround, seed: int, reach_m: float) -> tuple[tuple[float, float], float]:
    """The point below on the photo ground (world north, east) drawn from ``seed``: its disc of
    ``reach_m`` plus ``PHOTO_DISC_MARGIN_M`` is walkable ground with none of the photos' people
    within 1 m of it; and the distance (m) of the nearest of those people from it. Raises
    ValueError when the photos hold no such disc."""
    rng = np.random.default_rng([int(seed), 0x4A10])
    cn, ce = ground.free_centre(reach_m + PHOTO_DISC_MARGIN_M, rng)
    others = ground.people((cn, ce), 60.0)
    near = float(np.hypot(others[:, 0] - cn, others[:, 1] - ce).min()) if len(others) else math.inf
    return (cn, ce), near


def measure(heights: Sequence[float], distances: Sequence[float], model_path: str | None = None,
            seed: int = 18, photos: str | None = None) -> list[HaloRow]:
    """The rows for every height and distance (the seed's lawn under the camera; with ``photos``,
    a point of that folder's photo ground, module docstring)."""
    from companion.service.parts import build_pipeline, load_model

    overrides: dict[str, object] = {"camera.width": 640, "camera.height": 480, "camera.hfov_deg": 70.0}
    if model_path is not None:
        overrides["model.path"] = model_path
    cfg = settings.load(None, overrides)
    model = load_model(cfg)
    K = Intrinsics.from_fov(640, 480, 70.0)
    ground: ProceduralGround | PhotoGround
    near: float | None = None
    if photos is None:
        ground = ProceduralGround(seed)
        cn, ce = scene_centre(scenario(seed))
    else:
        ground = photo_ground(photos)
        (cn, ce), near = photo_point(ground, seed, max(distances))
    def free_radius(person: np.ndarray, bearing: float, who: int, h: float) -> tuple[float, float]:
        """The free radius and the view's reach (m) the pipeline reports at the point after three
        frames of the still scene with ``person`` ((N, 2), N = 0 or 1) in it."""
        pipe = build_pipeline(cfg, model)  # a fresh one: no memory of the last bearing
        result = None
        for k in range(3):
            pose = Pose(0.1 * k, cn, ce, -h, 0.0, 0.0, 0.0)
            img = render(person, pose, K, Mount(), ground, headings=np.array([bearing + 1.0])[:len(person)],
                         seed=1, ids=np.array([who])[:len(person)])
            result = pipe.process(img, pose.t, pose)
        assert result is not None and result.below is not None
        return round(result.below.r, 2), round(result.below.r_view, 2)

    rows = []
    for h in heights:
        empty, _ = free_radius(np.empty((0, 2)), 0.0, 0, h)
        for d in distances:
            free, view = [], 0.0
            for k_bearing, bearing in enumerate(BEARINGS_DEG):
                b = math.radians(bearing)
                person = np.array([[cn + d * math.cos(b), ce + d * math.sin(b)]])
                if isinstance(ground, PhotoGround):
                    surface = ground.surface_at(float(person[0, 0]), float(person[0, 1]))
                    if surface not in PHOTO_WALKABLE:  # the disc was drawn walkable: a fault, not a figure
                        raise RuntimeError(f"the person at {person[0]} stands on {surface}, not walkable ground")
                r, view = free_radius(person, b, k_bearing, h)
                free.append(r)
            # The person sets the radius only where neither the view's end, the ground's own
            # marks nor one of the photos' people comes first.
            other = (near is not None and near <= d) or (empty < view - 1e-6 and empty <= d)
            halo = [None if r >= view - 1e-6 or other else round(d - r, 2) for r in free]
            rows.append(HaloRow(h, d, free, view, halo, empty, "procedural" if photos is None else "photo",
                                None if near is None else round(near, 2)))
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.evidence.person_halo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--heights", default="4.4,7,10,15", help="camera heights (m above the ground)")
    parser.add_argument("--distances", default="2.5,3,3.5,4,5", help="the person's distances from the point (m)")
    parser.add_argument("--model", default=None, help="ONNX density model (default: the shipped one)")
    parser.add_argument("--seed", type=int, default=18, help="the scene's seed (default 18)")
    parser.add_argument("--ground", choices=("procedural", "photo"), default="procedural",
                        help="the drawn ground (default) or the photo world's (docs/photo-world.md)")
    parser.add_argument("--photos", type=Path, default=None,
                        help="the photos of --ground photo (default ../shared/data/semantic_drone/full)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args(argv)
    try:
        photos = photos_folder(args.ground, args.photos)
    except ValueError as exc:
        print(f"sim.evidence.person_halo: --photos: {exc}", file=sys.stderr)
        return 2
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

    if photos is not None:
        try:
            photo_point(photo_ground(photos), args.seed, max(distances))
        except ValueError as exc:  # no walkable disc as wide as the farthest distance
            print(f"sim.evidence.person_halo: --distances: {exc}", file=sys.stderr)
            return 2
    try:
        rows = measure(heights, distances, args.model, args.seed, photos)
    except (ConfigError, DensityModelError) as exc:
        print(f"sim.evidence.person_halo: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps([asdict(r) for r in rows]))
        return 0
    if rows and rows[0].nearest_other_m is not None:
        print(f"photo ground: the nearest of the photos' own people stands {rows[0].nearest_other_m:.2f} m from the point")
    print(f"{'height m':>8} {'person m':>8} {'view m':>6} {'nobody m':>8}  free radius at 4 bearings (m)   halo (m)")
    for r in rows:
        halo = " ".join("-" if v is None else f"{v:.2f}" for v in r.halo_m)
        print(f"{r.height_m:>8g} {r.distance_m:>8g} {r.view_m:>6.2f} {r.empty_m:>8.2f}  "
              f"{' '.join(f'{v:.2f}' for v in r.free_m):<30}  {halo}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
