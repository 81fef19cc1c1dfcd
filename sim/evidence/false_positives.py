"""How much of each scenario's lawn a density model marks as people when nobody is there.

``python -m sim.evidence.false_positives --seeds 1-34 --heights 10,20 [--model FILE.onnx] [--ground photo]``

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

``--ground photo`` (``--photos DIR``, default ``../shared/data/semantic_drone/full``) asks the same
over the photo world (docs/photo-world.md): the seed's photo scene, its circle landable by the
class maps with none of the photos' people in it, rendered with no walker (the photos' own people
are in their pixels). The truth is the class maps'. Each row then also says
``free_marked_pct``: the share of the whole frame's free ground (landable, and more than
``PERSON_CLEAR_M`` from every person of the photos) that is marked, the frame-wide figure that
compares a model's false alarms on real texture with the drawn ground's.

A share understates what a few marks cost: one marked cell in the middle of a circle leaves most
of it free and no zone on it. So each row also says ``zone_r_m``, the radius of the largest
circle centred in the free circle that holds no mark (on the head plane, capped at the free
circle's radius): what the zones over the circle can be with nobody there. A zone is flown to
only from ``r0 + radius_margin`` (4 m by default) and kept only while r0 (2 m) stays free.
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
from scipy.spatial import cKDTree

from companion.config import SHIPPED_MODEL
from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.density import DensityModel
from companion.pipeline.input_scale import density_scale, shrunk
from companion.pipeline.landability import LandabilityModel
from companion.pipeline.occupancy import OCCUPIED, OccupancyParams, occupancy_map, surface_free_map
from companion.pipeline.slz import PipelineConfig
from sim.flights.flight import build_world, photo_ground
from sim.flights.scenarios import FlightJob, parse_seeds
from sim.flights.spec import default_photos
from sim.world.crowd import World
from sim.world.ground import LANDABLE_SURFACES, SURFACES, ProceduralGround
from sim.world.photo_ground import PHOTO_CLASSES, PHOTO_LANDABLE, PhotoGround, PhotosError, check_photos
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
_PHOTO_LANDABLE = np.array([name in PHOTO_LANDABLE for name in PHOTO_CLASSES])
#: Metres from a person of the photos within which photo ground does not count as free: half a
#: body (0.5 m) and the marks a real person's density rightly spreads.
PERSON_CLEAR_M = 1.5


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
    ground: str = "procedural"
    free_marked_pct: float | None = None
    zone_r_m: float | None = None
    pitch_deg: float = 0.0


def marked_map(model: DensityModel, img: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(H, W) bool: where the service's occupancy step, fed by ``model`` at its own threshold,
    marks the frame: people for a density model, unlandable ground for a landability model.
    ``scale`` < 1: a density model sees the frame shrunk by it first, as the pipeline does with
    ``pipeline.person_px`` (``input_scale.density_scale``)."""
    if isinstance(model, LandabilityModel):
        spec = model.landability
        unlandable = 1.0 - model(img)[spec.names.index(spec.landable)]
        return surface_free_map(unlandable, img.shape[:2], spec.threshold) == OCCUPIED
    threshold = model.spec.occupancy_threshold if model.spec.occupancy_threshold is not None else 0.0
    return occupancy_map(model(shrunk(img, scale, model.spec.stride)), img.shape[:2],
                         OccupancyParams(threshold=threshold)) == OCCUPIED


def lawn_false_positives(model: DensityModel, seed: int, heights_m: Sequence[float],
                         photos: str | None = None, person_px: float = 0.0, pitch_deg: float = 0.0) -> list[LawnFigure]:
    """The figures of ``seed`` from each of ``heights_m`` (m above the ground); none for a world
    without a free circle. ``photos``: measure the seed's photo world over that folder's photos
    instead of its drawn world. ``person_px``: the pipeline's setting of that name (the frame
    shrunk before the density model; 0: the full frame). ``pitch_deg``: the vehicle pitched by
    this much over the circle's centre (the camera fixed to it), as it is while it flies and holds."""
    job = FlightJob(seed, "ardupilot") if photos is None else FlightJob(seed, "ardupilot", ground="photo", photos=photos)
    spec = job.spec()  # the scene does not depend on the flavour
    world, free, _start = build_world(spec)
    if free is None:
        return []
    ground: ProceduralGround | PhotoGround = ProceduralGround(seed) if photos is None else photo_ground(photos)
    people = np.empty((0, 2)) if world.fixed_people is None else np.asarray(world.fixed_people, float)
    empty = World(seed=seed)
    vv, uu = np.mgrid[0:K.height:STEP, 0:K.width:STEP]
    pixels = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    figures = []
    for height_m in heights_m:
        pose = Pose(0.0, free.north, free.east, -height_m, 0.0, math.radians(pitch_deg), 0.0)
        img = render_world(empty, pose, K, Mount(), ground)
        proj = PlaneProjection.from_pose(K, Mount(), pose, head_height=HEAD_M)
        occ = marked_map(model, img, density_scale(proj, img.shape[:2], person_px))
        xy = proj.image_to_plane(pixels)
        inside = np.hypot(xy[:, 0] - free.north, xy[:, 1] - free.east) < free.radius
        marked = occ[vv.ravel(), uu.ravel()]
        circle = float(marked[inside].mean()) if inside.any() else float("nan")
        truth = _truth_figures(ground, pose, pixels, marked, free)
        free_pct = None if photos is None else _free_marked(ground, pose, pixels, marked, people)
        figures.append(LawnFigure(seed, spec.world, height_m, round(100 * circle, 2),
                                  round(100 * float(marked.mean()), 2), *truth,
                                  ground=spec.ground, free_marked_pct=free_pct,
                                  zone_r_m=_zone_radius(xy, marked, inside, free), pitch_deg=pitch_deg))
    return figures


def _zone_radius(xy: np.ndarray, marked: np.ndarray, inside: np.ndarray, free: Circle) -> float | None:
    """The radius (m) of the largest circle centred on one of the sampled head-plane points
    ``xy`` inside the free circle (``inside``) that holds no ``marked`` point, capped at the free
    circle's radius; None when no sampled point lies inside it."""
    if not inside.any():
        return None
    ok = np.isfinite(xy).all(axis=1)
    hits = xy[ok & marked]
    if not len(hits):
        return round(float(free.radius), 2)
    nearest, _ = cKDTree(hits).query(xy[inside])
    return round(float(min(np.max(nearest), free.radius)), 2)


def _landable_at(ground: ProceduralGround | PhotoGround, xy: np.ndarray) -> np.ndarray:
    """(N,) bool: is the ground at each (north, east) point landable, by ``ground``'s truth
    (sampled at ``TRUTH_RES``)."""
    n0, e0 = float(xy[:, 0].min()) - TRUTH_RES, float(xy[:, 1].min()) - TRUTH_RES
    n1, e1 = float(xy[:, 0].max()) + TRUTH_RES, float(xy[:, 1].max()) + TRUTH_RES
    if isinstance(ground, PhotoGround):
        labels = ground.class_map(n0, n1, e0, e1, TRUTH_RES)
        row = ((xy[:, 0] - n0) / TRUTH_RES).astype(int)
        col = ((xy[:, 1] - e0) / TRUTH_RES).astype(int)
        table = _PHOTO_LANDABLE
    else:
        labels, A = ground.surface_labels(n0, n1, e0, e1, TRUTH_RES)
        col = (A[0, 1] * xy[:, 1] + A[0, 2]).astype(int)
        row = (A[1, 0] * xy[:, 0] + A[1, 2]).astype(int)
        table = _LANDABLE
    row = np.clip(row, 0, labels.shape[0] - 1)
    col = np.clip(col, 0, labels.shape[1] - 1)
    return table[labels[row, col]]


def _truth_figures(ground: ProceduralGround | PhotoGround, pose: Pose, pixels: np.ndarray, marked: np.ndarray,
                   free: Circle) -> tuple[float | None, float | None, float | None]:
    """``(landable_marked_pct, unlandable_pct, unlandable_left_pct)`` of the free circle, judged
    on the ground's truth at the pixels' ground points (see the module docstring)."""
    cn, ce, r = free.north, free.east, free.radius
    xy = PlaneProjection.from_pose(K, Mount(), pose, head_height=0.0).image_to_plane(pixels)
    inside = np.hypot(xy[:, 0] - cn, xy[:, 1] - ce) < r
    if not inside.any():
        return None, None, None
    landable = _landable_at(ground, xy[inside])
    m = marked[inside]
    pct = lambda a: round(100 * float(a.mean()), 2)  # noqa: E731
    return (pct(m[landable]) if landable.any() else None, pct(~landable),
            pct(~m[~landable]) if (~landable).any() else None)


def _free_marked(ground: ProceduralGround | PhotoGround, pose: Pose, pixels: np.ndarray, marked: np.ndarray,
                 people: np.ndarray) -> float | None:
    """The share (%) of the frame's free ground (landable, more than ``PERSON_CLEAR_M`` from every
    one of ``people``, (N, 2) north, east) that is marked; None when the frame shows none."""
    xy = PlaneProjection.from_pose(K, Mount(), pose, head_height=0.0).image_to_plane(pixels)
    ok = np.isfinite(xy).all(axis=1)
    free = np.zeros(len(xy), bool)
    free[ok] = _landable_at(ground, xy[ok])
    if len(people):
        near = np.full(len(xy), np.inf)
        for p in people[np.hypot(people[:, 0] - pose.north, people[:, 1] - pose.east) < 4.0 * abs(pose.down) + 10.0]:
            near = np.minimum(near, np.hypot(xy[:, 0] - p[0], xy[:, 1] - p[1]))
        free &= near > PERSON_CLEAR_M
    return round(100 * float(marked[free].mean()), 2) if free.any() else None


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f} %"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.evidence.false_positives", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1-34", help="seeds, e.g. 1-34 or 5,6,28 (default 1-34)")
    ap.add_argument("--heights", default="10,20", help="heights above the ground in m (default 10,20)")
    ap.add_argument("--model", type=Path, default=SHIPPED_MODEL, help="ONNX density model (default: the shipped one)")
    ap.add_argument("--landability", type=Path, default=None,
                    help="measure this ONNX landability model's unlandable marks instead of --model's people")
    ap.add_argument("--ground", choices=("procedural", "photo"), default="procedural",
                    help="the drawn ground (default) or the photo world's (docs/photo-world.md)")
    ap.add_argument("--photos", type=Path, default=None,
                    help="the photos of --ground photo (default ../shared/data/semantic_drone/full)")
    ap.add_argument("--person-px", type=float, default=0.0,
                    help="the pipeline's pipeline.person_px: shrink each view so that the smallest person spans this "
                         "many pixels (default 0: the full frame)")
    ap.add_argument("--pitch", type=float, default=0.0,
                    help="the vehicle pitched by this many degrees over the circle, the camera fixed to it "
                         "(0-30; default 0: straight down)")
    ap.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    args = ap.parse_args(argv)
    if not (0.0 <= args.pitch <= 30.0):
        print("error: --pitch must lie between 0 and 30 degrees", file=sys.stderr)
        return 2
    photos = None
    if args.ground == "photo":
        folder = args.photos or default_photos()
        try:
            check_photos(folder)
        except PhotosError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        photos = str(folder.resolve())
    try:
        seeds = parse_seeds(args.seeds)
        heights = [float(h) for h in args.heights.split(",")]
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not (0.0 <= args.person_px <= 1000.0):
        print("error: --person-px must lie between 0 and 1000", file=sys.stderr)
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
        figures = lawn_false_positives(model, seed, heights, photos, args.person_px, args.pitch)
        if not figures:
            continue
        if args.json:
            for f in figures:
                print(json.dumps(asdict(f)), flush=True)
        else:
            cells = "  ".join(f"{f.height_m:g} m: lawn {f.circle_pct:5.1f} %, frame {f.frame_pct:4.1f} %, "
                              f"landable ground {_pct(f.landable_marked_pct)}, unlandable {_pct(f.unlandable_pct)} "
                              f"({_pct(f.unlandable_left_pct)} left)"
                              + ("" if f.free_marked_pct is None else f", free ground in frame {_pct(f.free_marked_pct)}")
                              + ("" if f.zone_r_m is None else f", zone r {f.zone_r_m:.1f} m")
                              for f in figures)
            print(f"seed {seed:>3} {figures[0].world:<13} {cells}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
