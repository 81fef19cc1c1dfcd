"""Whether a world lets the service land clear at all: its landing rules flown with perfect sight.

``python -m sim.evidence.clear_oracle --seeds 1-75 --ground photo [--reach 15] [--json]``

A yardstick world counts against the clear-landing target whether or not anybody could land clear
in it. This asks the world's truth. For every seed whose world has a free circle (free area,
crossing, dense beyond), the world is built as its flight builds it (``sim.flights.scenarios``,
``build_world``; the crossing world's walkers drawn at the trigger), and everybody (the walkers and,
on the photo ground, the people standing in the photos) is stepped from the trigger for
``max_takeover_s``. Every ``DT_S`` the distance to the nearest person is kept at every candidate
landing point: a grid of ``GRID_M`` over the ground within ``--reach`` m of the free circle's
centre that is landable by the ground's truth (the photo class maps, the drawn ground's surfaces)
under the whole footprint (``FOOTPRINT_M``).

The service's rules (``companion.config`` defaults, ``Rules``) are then applied to those distances
as if it saw every person and nothing else, and nothing is ever out of view:

- a point may be **judged** at time t when nobody came within ``r0 + calm margin`` of it over the
  last ``min calm`` seconds (the calm watch), and nobody stood within ``r0 + radius margin`` when
  that watch began (a zone large enough to be flown to);
- it is then **flown down** to the LAND in ``descend_s``; anybody within ``r0`` meanwhile sends
  the vehicle back up (that try fails and the next is looked for);
- the **last metres** take ``last_metres_s`` and are blind; the landing is **clear** when nobody
  is within ``r0`` at touchdown, else unsafe.

Per world: ``foresight``, whether some point and time pass every rule and touch down clear (what
any service held to these rules could do at best); ``earliest``, what the first chance gives (the
point farthest from everybody at the first time any point may be judged, flown down; tried again
after a failed descent): ``clear``, ``unsafe`` or ``none``; and ``judgeable``, the share of
(point, time) pairs that may be judged. Judging starts ``earliest_s`` after the trigger (the
descent from the trigger's height and the approach: the fastest companion landings of the
yardstick touch down 19-23 s after it) and every touchdown must come within ``max_takeover_s``.

What it leaves out is what the service cannot have: the camera's view, its model's misses and
false marks, the walkers it has not seen yet. A world whose ``earliest`` is ``clear`` but whose
flight handed back lost its chance to perception, not to the world or the rules.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from companion import config as settings
from sim.flights.flight import FOOTPRINT_M, add_trigger_crossers, build_world, crossing_walkable, photo_ground
from sim.flights.scenarios import parse_seeds, scenario
from sim.flights.spec import FlightSpec, photos_folder
from sim.world.crowd import CROSSING_WINDOW_S, TICK_S, World
from sim.world.ground import LANDABLE_SURFACES, SURFACES, ProceduralGround
from sim.world.photo_ground import PHOTO_CLASSES, PHOTO_LANDABLE
from sim.world.walkers import Circle

#: Seconds between the samples of the people (a walker covers 0.3 m in one at 1.5 m/s).
DT_S = 0.2
#: Spacing of the candidate landing points (m).
GRID_M = 0.25
#: Resolution at which the ground's truth is read under the footprint (m/px).
LABEL_RES_M = 0.05
#: The trigger's world time in the yardstick's lockstep rows (``world_t_trigger``).
TRIGGER_T_S = 4.0


@dataclass(frozen=True)
class Rules:
    """The service's landing rules in seconds and metres (see the module docstring)."""

    r0_m: float = 2.0
    radius_margin_m: float = 2.0
    calm_margin_m: float = 1.0
    min_calm_s: float = 5.0
    descend_s: float = 4.0
    last_metres_s: float = 4.5
    earliest_s: float = 15.0
    max_takeover_s: float = 90.0

    @classmethod
    def of_defaults(cls) -> Rules:
        """The rules at ``companion.config``'s default settings (the descent and the last metres
        as the yardstick's PX4 and ArduPilot rows fly them: 10 m to the LAND at 4 m at 1.5 m/s,
        ``last_metres_s`` 4.52 s at the simulator's LAND speed of 1 m/s)."""
        cfg = settings.Config()
        c = cfg.controller
        return cls(r0_m=cfg.pipeline.r0_m, radius_margin_m=c.radius_margin_m,
                   calm_margin_m=cfg.pipeline.calm_margin_m, min_calm_s=c.min_calm_s,
                   max_takeover_s=c.max_takeover_s)


@dataclass(frozen=True)
class Verdict:
    """What the rules allow over one world's distances (see the module docstring)."""

    foresight: bool
    earliest: str
    earliest_touchdown_s: float | None
    judgeable: float


def _min_back(a: np.ndarray, steps: int) -> np.ndarray:
    """Per row i, the minimum of rows i - steps .. i (rows before 0: -inf, never enough)."""
    out = a.copy()
    for k in range(1, steps + 1):
        np.minimum(out[k:], a[:-k], out=out[k:])
    out[:steps] = -np.inf
    return out


def judge(dist: np.ndarray, rules: Rules, dt_s: float = DT_S) -> Verdict:
    """The verdicts over ``dist`` (T, P): the distance (m) from each of P candidate points to the
    nearest person at times 0, dt, ... after the trigger."""
    d = np.asarray(dist, np.float64)
    if d.ndim != 2 or d.shape[1] == 0:
        return Verdict(False, "none", None, 0.0)
    steps = lambda s: int(round(s / dt_s))  # noqa: E731
    w_calm, w_desc, w_last = steps(rules.min_calm_s), steps(rules.descend_s), steps(rules.last_metres_s)
    n = d.shape[0]
    first, last = steps(rules.earliest_s), n - 1 - w_desc - w_last
    if last < first:
        return Verdict(False, "none", None, 0.0)
    calm = _min_back(d, w_calm) > rules.r0_m + rules.calm_margin_m
    room = d > rules.r0_m + rules.radius_margin_m
    large = np.zeros_like(room)
    large[w_calm:] = room[:n - w_calm]  # the zone's room when its calm watch began
    judged = (calm & large)[first:last + 1]
    # Nobody within r0 from the judging to the LAND, and nobody there at touchdown.
    descent = _min_back(d[::-1], w_desc)[::-1][first:last + 1] > rules.r0_m
    clear = d[first + w_desc + w_last:last + 1 + w_desc + w_last] > rules.r0_m
    foresight = bool((judged & descent & clear).any())
    earliest, when = "none", None
    i = 0
    while i < len(judged):
        ok = np.flatnonzero(judged[i])
        if not len(ok):
            i += 1
            continue
        j = ok[int(np.argmax(d[first + i, ok]))]
        if descent[i, j]:
            earliest = "clear" if clear[i, j] else "unsafe"
            when = round((first + i + w_desc + w_last) * dt_s, 2)
            break
        i += w_desc  # sent back up: look again once the vehicle is back over the ground
    return Verdict(foresight, earliest, when, float(judged.mean()))


def candidate_points(ground: str, seed: int, centre: tuple[float, float], reach_m: float,
                     photos: str | None) -> np.ndarray:
    """(P, 2) grid points (north, east) within ``reach_m`` of ``centre`` whose whole footprint
    lies on landable ground by the truth of ``ground`` (``photo`` or ``procedural``)."""
    half = reach_m + FOOTPRINT_M + 2 * LABEL_RES_M
    n0, e0 = centre[0] - half, centre[1] - half
    if ground == "photo":
        assert photos is not None
        labels = photo_ground(photos).class_map(n0, n0 + 2 * half, e0, e0 + 2 * half, LABEL_RES_M)
        good = np.array([name in PHOTO_LANDABLE for name in PHOTO_CLASSES])
    else:
        labels, _A = ProceduralGround(seed).surface_labels(n0, n0 + 2 * half, e0, e0 + 2 * half, LABEL_RES_M)
        good = np.array([name in LANDABLE_SURFACES for name in SURFACES])
    landable = good[labels].astype(np.uint8)
    k = 2 * int(math.ceil(FOOTPRINT_M / LABEL_RES_M)) + 1
    landable = cv2.erode(landable, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    ax = np.arange(-reach_m, reach_m + 1e-9, GRID_M)
    nn, ee = np.meshgrid(centre[0] + ax, centre[1] + ax, indexing="ij")
    pts = np.column_stack([nn.ravel(), ee.ravel()])
    pts = pts[np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1]) <= reach_m]
    rows = np.clip(((pts[:, 0] - n0) / LABEL_RES_M).astype(int), 0, landable.shape[0] - 1)
    cols = np.clip(((pts[:, 1] - e0) / LABEL_RES_M).astype(int), 0, landable.shape[1] - 1)
    return pts[landable[rows, cols] > 0]


def distances(world: World, free: Circle, points: np.ndarray, seconds: float, spec: FlightSpec,
              trigger_t: float = TRIGGER_T_S, dt_s: float = DT_S) -> np.ndarray:
    """(T, P) distance (m) from each point to the nearest person, every ``dt_s`` from the trigger
    for ``seconds`` (the crossing world's walkers drawn at the trigger, as its flights do)."""
    while world.t < trigger_t - 1e-9:
        world.step(TICK_S)
    if spec.world == "crossing":
        add_trigger_crossers(world, free, spec, crossing_walkable(spec, free))
    fixed = np.empty((0, 2)) if world.fixed_people is None else np.asarray(world.fixed_people, float).reshape(-1, 2)
    n = int(round(seconds / dt_s)) + 1
    out = np.full((n, len(points)), np.inf, np.float32)
    for i in range(n):
        if i:
            world.step(dt_s)
        people = np.vstack([world.positions(), fixed])
        if len(people) and len(points):
            out[i] = cKDTree(people).query(points)[0]
    return out


@dataclass(frozen=True)
class WorldVerdict:
    """One seed's answer (see the module docstring)."""

    seed: int
    flavour: str
    ground: str
    world: str
    free_radius_m: float
    points: int
    foresight: bool
    earliest: str
    earliest_touchdown_s: float | None
    judgeable: float


def oracle(seed: int, flavour: str, ground: str, photos: str | None, reach_m: float, rules: Rules,
           window: tuple[float, float] = CROSSING_WINDOW_S) -> WorldVerdict | None:
    """The verdicts of seed's world (None: a world without a free circle, the dense one)."""
    spec = scenario(seed, flavour)
    if ground == "photo":
        spec = replace(spec, ground="photo", photos=photos)
    spec = replace(spec, crossing_window=window)
    world, free, _start = build_world(spec)
    if free is None:
        return None
    pts = candidate_points(ground, seed, (free.north, free.east), reach_m, photos)
    d = distances(world, free, pts, rules.max_takeover_s, spec)
    v = judge(d, rules)
    return WorldVerdict(seed, flavour, ground, spec.world, round(free.radius, 2), len(pts), v.foresight, v.earliest,
                        v.earliest_touchdown_s, round(v.judgeable, 4))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.evidence.clear_oracle", description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1-12", help="seeds, e.g. 1-75 (default 1-12)")
    parser.add_argument("--ground", choices=("procedural", "photo"), default="procedural")
    parser.add_argument("--photos", type=Path, default=None,
                        help="the photo world's photos (default ../shared/data/semantic_drone/full beside the checkout)")
    parser.add_argument("--reach", type=float, default=15.0,
                        help="candidate points within this of the free circle's centre (m; default 15)")
    parser.add_argument("--json", action="store_true", help="one JSON object per world, then a summary")
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
        if not (math.isfinite(args.reach) and 0 < args.reach <= 40):
            raise ValueError(f"--reach must be in (0, 40] m, not {args.reach}")
        photos = photos_folder("photo", args.photos) if args.ground == "photo" else None
    except ValueError as exc:
        print(f"sim.evidence.clear_oracle: {exc}", file=sys.stderr)
        return 2
    rules = Rules.of_defaults()
    found = []
    for seed in seeds:
        # Both autopilots fly the same world of a seed (``scenario`` draws it from the seed alone).
        v = oracle(seed, "px4", args.ground, photos, args.reach, rules)
        if v is None:
            continue
        found.append(v)
        if args.json:
            print(json.dumps(asdict(v)), flush=True)
        else:
            print(f"seed {v.seed:>4} {v.world:<12} free r {v.free_radius_m:4.1f} m  foresight "
                  f"{'clear' if v.foresight else 'none':<5}  earliest {v.earliest:<6}"
                  f"{'' if v.earliest_touchdown_s is None else f' at {v.earliest_touchdown_s:.1f} s'}  "
                  f"judgeable {100 * v.judgeable:.0f} %", flush=True)
    n = len(found)
    summary = {"worlds": n, "foresight_clear": sum(v.foresight for v in found),
               "earliest_clear": sum(v.earliest == "clear" for v in found),
               "earliest_unsafe": sum(v.earliest == "unsafe" for v in found),
               "rules": asdict(rules), "reach_m": args.reach, "ground": args.ground}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"{n} worlds with a free circle: a clear landing possible in {summary['foresight_clear']}; "
              f"the first chance lands clear in {summary['earliest_clear']}, unsafe in {summary['earliest_unsafe']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
