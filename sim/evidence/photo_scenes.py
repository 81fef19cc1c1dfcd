"""Where the photo world's scenes lie, and where its crossers walk (issue 59, docs/photo-world.md).

``python -m sim.evidence.photo_scenes [--seeds 1-75] [--photos DIR] [--floor 3] [--json]``

For every seed with a free circle (``sim.flights.flight.build_world`` on ``--ground photo``):

- **places**: the photo whose cell holds the scene's centre, as the flights draw it now (a photo
  first, each as likely, then a point in it: ``PhotoGround.place_centre``) and as they drew it
  until session 29 (a point among all of the block's: ``PhotoGround.free_centre``); the distinct
  photos of each, and for the flights' draw the share of each free circle that is landable by
  the class maps (0.02 m) and the nearest of the photos' people to its centre (m);
- **what the photos allow**: how many photos hold a landable disc of R m with none of their
  people within 1 m of it (``PhotoGround.places``), R = 2-9 (the free circle plus 1 m is
  R = 6-9 m for the scenarios' radii of 5-8 m);
- **a proposal, not flown**: were the free radius the drawn one capped at what the place allows
  less 1 m, with the place drawn among the photos that allow at least ``--floor`` m (each as
  likely), how many photos would the scenes use, and how often and how far would the radius
  shrink;
- **crossers**: for the crossing worlds, the share of the crossers' positions (every 0.1 s over
  60 s, the crossings drawn at 0 s) off walkable ground (the 0.1 m walkable map the crowds keep
  to, and the class maps at 0.05 m), drawn as on the drawn ground (``walkable`` None) and as the
  photo flights draw them (``sim.world.crowd.on_walkable_ground``).
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sim.flights.flight import PHOTO_FREE_MARGIN_M, build_world, crossing_walkable, photo_ground
from sim.flights.scenarios import FlightJob, parse_seeds
from sim.flights.spec import photos_folder
from sim.world.crowd import World, add_crossing_walkers
from sim.world.photo_ground import _LANDABLE_IDX, _WALKABLE_IDX, PhotoGround

#: The seconds over which the crossers' positions are read, and how often (s).
CROSSER_SPAN_S = 60.0
CROSSER_STEP_S = 0.1
#: The radii (m) of the landable discs counted per photo.
DISC_RADII_M = (2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0)


@dataclass(frozen=True)
class Scene:
    """One seed's free circle on the photo ground: its world, radius (m), the photo holding its
    centre as drawn now (``photo``) and as drawn until session 29 (``photo_before``), the share
    of its disc landable by the class maps, and the nearest photo person to its centre (m)."""

    seed: int
    world: str
    radius_m: float
    photo: str
    photo_before: str
    landable: float
    nearest_person_m: float


def host(ground: PhotoGround, north: float, east: float) -> str:
    """The photo whose cell (the photo and its mirrored fill) holds the point (world m)."""
    n = (north - ground.origin[0]) % ground.block_n
    e = (east - ground.origin[1]) % ground.block_e
    for p in ground.patches:
        if p.north <= n < p.north + p.cell_m[0] and p.east <= e < p.east + p.cell_m[1]:
            return p.name
    raise ValueError(f"no photo's cell holds ({north:.1f}, {east:.1f})")


def landable_share(ground: PhotoGround, north: float, east: float, radius: float, res: float = 0.02) -> float:
    """The share of the disc of ``radius`` m around the point that is landable by the class maps."""
    labels = ground.class_map(north - radius, north + radius, east - radius, east + radius, res)
    c = (np.arange(labels.shape[0]) + 0.5) * res - radius
    nn, ee = np.meshgrid(c, (np.arange(labels.shape[1]) + 0.5) * res - radius, indexing="ij")
    inside = np.hypot(nn, ee) <= radius
    return float(np.isin(labels[inside], _LANDABLE_IDX).mean())


def scenes(photos: str, seeds: Sequence[int]) -> list[Scene]:
    """The free circles of ``seeds`` (worlds without one are left out)."""
    ground = photo_ground(photos)
    out = []
    for seed in seeds:
        spec = FlightJob(seed, ground="photo", photos=photos).spec()
        if spec.world in ("dense", "uniform", "dronecrowd"):
            continue
        _world, free, _start = build_world(spec)
        assert free is not None
        rng = np.random.default_rng([int(seed), 0x9407])  # the flights' stream (photo_scene_centre)
        before = ground.free_centre(spec.free_radius_m + PHOTO_FREE_MARGIN_M, rng)
        people = ground.people((free.north, free.east), free.radius + 10.0)
        near = float(np.min(np.hypot(people[:, 0] - free.north, people[:, 1] - free.east))) if len(people) else math.inf
        out.append(Scene(seed, spec.world, round(free.radius, 2), host(ground, free.north, free.east),
                         host(ground, *before), landable_share(ground, free.north, free.east, free.radius),
                         round(near, 2)))
    return out


def allowed(ground: PhotoGround) -> dict[float, int]:
    """How many photos hold a landable disc of each of :data:`DISC_RADII_M` (m) with none of
    their people within 1 m of it."""
    return {r: len(ground.places(r)) for r in DISC_RADII_M}


@dataclass(frozen=True)
class Proposal:
    """The capped radius (see the module docstring) over the scenes: photos that allow the
    floor, photos used, scenes whose radius would shrink, and the radii's quartiles (m)."""

    floor_m: float
    photos_allowing: int
    scenes: int
    photos_used: int
    shrunk: int
    radius_quartiles_m: tuple[float, float, float]
    radius_min_m: float


def proposal(photos: str, seeds: Sequence[int], floor_m: float) -> Proposal:
    """What the capped radius would give (not flown; the flights keep the drawn radius)."""
    ground = photo_ground(photos)
    largest = {name: r for name, r in ground.largest_discs().items() if r >= floor_m + PHOTO_FREE_MARGIN_M}
    hosts = sorted(largest)
    used: collections.Counter[str] = collections.Counter()
    radii, shrunk = [], 0
    for seed in seeds:
        spec = FlightJob(seed, ground="photo", photos=photos).spec()
        if spec.world in ("dense", "uniform", "dronecrowd"):
            continue
        rng = np.random.default_rng([int(seed), 0x9407])
        name = hosts[int(rng.integers(len(hosts)))]
        r = min(spec.free_radius_m, float(largest[name]) - PHOTO_FREE_MARGIN_M)
        shrunk += r < spec.free_radius_m
        used[name] += 1
        radii.append(r)
    q = np.percentile(radii, [25, 50, 75]) if radii else np.zeros(3)
    return Proposal(floor_m, len(hosts), len(radii), len(used), shrunk,
                    (round(float(q[0]), 2), round(float(q[1]), 2), round(float(q[2]), 2)),
                    round(float(min(radii)), 2) if radii else math.nan)


@dataclass(frozen=True)
class Crossers:
    """The crossing worlds' crossers over :data:`CROSSER_SPAN_S`: how many crossers and
    positions, the shares off the walkable map and off walkable classes, drawn anywhere
    (``before``) and on walkable ground (``after``), and the crossers whose approach was
    shortened (fewer than 8 m of walkable ground before or beyond the circle)."""

    seeds: list[int]
    crossers: int
    positions: int
    off_map_before: float
    off_classes_before: float
    off_map_after: float
    off_classes_after: float
    shortened: int


def crossers(photos: str, seeds: Sequence[int]) -> Crossers:
    ground = photo_ground(photos)
    counts = {False: [0, 0, 0], True: [0, 0, 0]}
    used, n_cross, shortened = [], 0, 0
    steps = int(round(CROSSER_SPAN_S / CROSSER_STEP_S))
    for seed in seeds:
        spec = FlightJob(seed, ground="photo", photos=photos).spec()
        if spec.world != "crossing":
            continue
        used.append(seed)
        _world, free, _start = build_world(spec)
        assert free is not None
        walkable = crossing_walkable(spec, free)
        assert walkable is not None
        half, res = free.radius + 10.0, 0.05
        labels = ground.class_map(free.north - half, free.north + half, free.east - half, free.east + half, res)
        for on in (False, True):
            world = World(seed=seed)
            drawn = add_crossing_walkers(world, free, 0.0, seed, window=spec.crossing_window,
                                         walkable=walkable if on else None)
            if on:
                n_cross += len(drawn)
                shortened += sum(c.approach_m < 8.0 for c in drawn)
            for _ in range(steps):
                world.step(CROSSER_STEP_S)
                p = world.positions()
                r = np.floor((p[:, 0] - free.north + half) / res).astype(int)
                c = np.floor((p[:, 1] - free.east + half) / res).astype(int)
                counts[on][0] += len(p)
                counts[on][1] += int(np.count_nonzero(~walkable(p)))
                counts[on][2] += int(np.count_nonzero(~np.isin(labels[r, c], _WALKABLE_IDX)))
    pos = max(counts[False][0], 1)
    return Crossers(used, n_cross, counts[False][0], counts[False][1] / pos, counts[False][2] / pos,
                    counts[True][1] / pos, counts[True][2] / pos, shortened)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.evidence.photo_scenes", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="1-75", help="the seeds (default 1-75)")
    parser.add_argument("--photos", type=Path, default=None,
                        help="the photos folder (default ../shared/data/semantic_drone/full)")
    parser.add_argument("--floor", type=float, default=3.0,
                        help="the proposal's smallest free radius (m, default 3: r0 and 1 m)")
    parser.add_argument("--json", action="store_true", help="print everything as one JSON object")
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
        photos = photos_folder("photo", args.photos)
    except ValueError as exc:
        print(f"sim.evidence.photo_scenes: {exc}", file=sys.stderr)
        return 2
    if not (math.isfinite(args.floor) and 0.5 <= args.floor <= 8.0):
        print(f"sim.evidence.photo_scenes: --floor must be 0.5-8 m, not {args.floor:g}", file=sys.stderr)
        return 2
    assert photos is not None
    sc = scenes(photos, seeds)
    allow = allowed(photo_ground(photos))
    prop = proposal(photos, seeds, args.floor)
    cr = crossers(photos, seeds)
    if args.json:
        print(json.dumps({"scenes": [asdict(s) for s in sc], "allowed": {str(k): v for k, v in allow.items()},
                          "proposal": asdict(prop), "crossers": asdict(cr)}))
        return 0
    now = collections.Counter(s.photo for s in sc)
    before = collections.Counter(s.photo_before for s in sc)
    print(f"{len(sc)} free circles (seeds {args.seeds}): on {len(now)} photos {dict(now.most_common())}; "
          f"until session 29 on {len(before)} {dict(before.most_common())}")
    print(f"landable share of each circle: min {min((s.landable for s in sc), default=math.nan):.4f}; "
          f"nearest photo person to a centre less its radius: min "
          f"{min((s.nearest_person_m - s.radius_m for s in sc), default=math.nan):.2f} m")
    print("photos holding a landable disc of R m, nobody within 1 m: "
          + ", ".join(f"R {r:g}: {n}" for r, n in allow.items()))
    print(f"proposal (not flown), radius capped at the place's disc less {PHOTO_FREE_MARGIN_M:g} m, floor "
          f"{prop.floor_m:g} m: {prop.photos_allowing} photos allow it; {prop.scenes} scenes on "
          f"{prop.photos_used} photos, {prop.shrunk} shrunk; radius quartiles {prop.radius_quartiles_m}, "
          f"min {prop.radius_min_m} m")
    print(f"crossers of the crossing worlds {cr.seeds}: {cr.crossers} crossers, {cr.positions} positions over "
          f"{CROSSER_SPAN_S:g} s; off walkable ground (0.1 m map / class maps 0.05 m): drawn anywhere "
          f"{100 * cr.off_map_before:.1f} / {100 * cr.off_classes_before:.1f} %, on walkable ground "
          f"{100 * cr.off_map_after:.1f} / {100 * cr.off_classes_after:.1f} %; approach shortened for "
          f"{cr.shortened}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
