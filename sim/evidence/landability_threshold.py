"""What the landability model's threshold trades on the photo world: free ground marked against
unlandable ground missed.

``python -m sim.evidence.landability_threshold --seeds 1-12 --heights 20,12,8,5 [--thresholds 0.05,0.1,...] [--person-px N]``

Issue 59 item 4 asks whether the landability model can be on by default. Flown on the photo
world it cost clear landings (docs/photo-world.md), and the question behind that is whether any
threshold keeps it useful there. For every seed with a free circle, the seed's photo scene is
rendered straight down over the circle's centre from each height with nobody walking (as
``sim.evidence.false_positives --ground photo``: the photos' own people are in their pixels),
the model runs once, and each threshold is applied through the service's own
``surface_free_map``. Judged on the class maps at the ground points of every 4th pixel of the
frame (``false_positives.STEP``), summed over the seeds per height and threshold:

- ``landable_marked_pct``: the share of the frame's landable ground (paved area, dirt, grass,
  gravel) called unlandable: ground a zone loses for nothing;
- ``unlandable_left_pct``: the share of the frame's unlandable ground (roofs, trees, water, cars,
  people's pixels, ...) left landable: what the model is there to catch and misses. None when
  no frame of that height shows any;
- ``circle_marked_pct``: the mean share of the free circle (all landable, nobody in it) called
  unlandable, and ``circles_over_5``: in how many seeds more than 5 % of it.

The model's own threshold (``companion.unlandable_threshold``, what the service uses unless
``pipeline.unlandable_threshold`` says otherwise) is always among the thresholds. ``--levels``
sums only the named risk levels, as ``pipeline.unlandable_levels`` makes the service do
(default: every level but the landable one, the service's default).
``--person-px N`` feeds the model the frame shrunk as the density model's is
(``companion.pipeline.input_scale``); the service does not do that for this model (0, the
default, is what it does). These seeds' scenes are the photo world's, and the photos are the
held-out fifth: the figures choose no weight, they only say what a threshold costs.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from companion.config.schema import SHIPPED_LANDABILITY
from companion.geometry.camera import Mount, PlaneProjection, Pose
from companion.pipeline.input_scale import density_scale, shrunk
from companion.pipeline.landability import LandabilityModel
from companion.pipeline.occupancy import OCCUPIED, surface_free_map
from sim.evidence.false_positives import HEAD_M, STEP, K, _landable_at
from sim.evidence.person_halo import parse_floats
from sim.flights.flight import build_world, photo_ground
from sim.flights.scenarios import FlightJob, parse_seeds
from sim.flights.spec import photos_folder
from sim.world.crowd import World
from sim.world.render import render_world

#: The thresholds printed unless ``--thresholds`` says otherwise (the model's own is added).
THRESHOLDS = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
#: A circle with more than this share called unlandable counts in ``circles_over_5``.
CIRCLE_SHARE = 0.05


@dataclass(frozen=True)
class ThresholdFigure:
    """One height and one threshold, summed over the seeds (percentages; see the module docstring)."""

    height_m: float
    threshold: float
    landable_marked_pct: float
    unlandable_left_pct: float | None
    circle_marked_pct: float
    circles_over_5: int
    circles: int


def threshold_curve(model: LandabilityModel, seeds: Sequence[int], heights_m: Sequence[float],
                    thresholds: Sequence[float], photos: str, person_px: float = 0.0,
                    levels: Sequence[str] | None = None) -> list[ThresholdFigure]:
    """The figures of every height and threshold over ``seeds``' photo scenes (those with a free
    circle), heights in the order given, thresholds ascending; ``levels``: the risk levels summed
    (None: every level but the landable one); LandabilityModelError naming an unknown one."""
    unlandable_map = model.unlandable(levels)
    ground = photo_ground(photos)
    thresholds = sorted(set(thresholds))
    vv, uu = np.mgrid[0:K.height:STEP, 0:K.width:STEP]
    pixels = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    # Per (height, threshold): pixels of landable marked, landable, unlandable left, unlandable;
    # and each seed's share of its circle marked.
    sums: dict[tuple[float, float], list[int]] = {(h, t): [0, 0, 0, 0] for h in heights_m for t in thresholds}
    circles: dict[tuple[float, float], list[float]] = {(h, t): [] for h in heights_m for t in thresholds}
    for seed in seeds:
        spec = FlightJob(seed, "ardupilot", ground="photo", photos=photos).spec()
        _, free, _ = build_world(spec)
        if free is None:
            continue
        for h in heights_m:
            pose = Pose(0.0, free.north, free.east, -h, 0.0, 0.0, 0.0)
            img = render_world(World(seed=seed), pose, K, Mount(), ground)
            proj = PlaneProjection.from_pose(K, Mount(), pose, head_height=HEAD_M)
            scale = density_scale(proj, img.shape[:2], person_px)
            unlandable = unlandable_map(shrunk(img, scale, model.spec.input_multiple))
            xy = PlaneProjection.from_pose(K, Mount(), pose, head_height=0.0).image_to_plane(pixels)
            seen = np.isfinite(xy).all(axis=1)
            landable = np.zeros(len(xy), bool)
            landable[seen] = _landable_at(ground, xy[seen])
            inside = seen & (np.hypot(xy[:, 0] - free.north, xy[:, 1] - free.east) < free.radius)
            land, unland = landable & seen, ~landable & seen  # the same for every threshold
            for t in thresholds:
                marked = (surface_free_map(unlandable, img.shape[:2], t) == OCCUPIED)[vv.ravel(), uu.ravel()]
                s = sums[(h, t)]
                s[0] += int((marked & land).sum())
                s[1] += int(land.sum())
                s[2] += int((~marked & unland).sum())
                s[3] += int(unland.sum())
                circles[(h, t)].append(float(marked[inside].mean()) if inside.any() else 0.0)
    out = []
    for h in heights_m:
        for t in thresholds:
            lm, ln, ul, un = sums[(h, t)]
            c = circles[(h, t)]
            out.append(ThresholdFigure(h, t, round(100 * lm / max(ln, 1), 2),
                                       None if un == 0 else round(100 * ul / un, 2),
                                       round(100 * float(np.mean(c)), 2) if c else 0.0,
                                       sum(x > CIRCLE_SHARE for x in c), len(c)))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.evidence.landability_threshold",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1-12", help="seeds, e.g. 1-12 or 5,6,28 (default 1-12)")
    ap.add_argument("--heights", default="20,12,8,5", help="heights above the ground in m (default 20,12,8,5)")
    ap.add_argument("--thresholds", default=",".join(f"{t:g}" for t in THRESHOLDS),
                    help="thresholds on the unlandable levels' probability, 0-1 (default %(default)s; the model's "
                         "own is always added)")
    ap.add_argument("--model", type=Path, default=SHIPPED_LANDABILITY,
                    help="ONNX landability model (default: the shipped one)")
    ap.add_argument("--photos", type=Path, default=None,
                    help="the photo world's photos (default ../shared/data/semantic_drone/full)")
    ap.add_argument("--person-px", type=float, default=0.0,
                    help="shrink each view as the density model's is for this many pixels a person "
                         "(default 0: the full frame, as the service feeds this model)")
    ap.add_argument("--levels", default=None,
                    help="comma-separated risk levels to sum, as pipeline.unlandable_levels (default: every level "
                         "but the landable one)")
    ap.add_argument("--json", action="store_true", help="one JSON object per height and threshold")
    args = ap.parse_args(argv)
    try:
        photos = photos_folder("photo", args.photos)
        seeds = parse_seeds(args.seeds)
        heights = parse_floats(args.heights)
        thresholds = parse_floats(args.thresholds)
    except ValueError as e:  # a photos folder's error names the folder and what is wrong with it
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not all(0.0 <= t < 1.0 for t in thresholds):
        print("error: --thresholds must lie in [0, 1)", file=sys.stderr)
        return 2
    if not all(HEAD_M < h < 500.0 for h in heights):
        print(f"error: heights must lie between {HEAD_M} m (the head plane) and 500 m", file=sys.stderr)
        return 2
    if not (0.0 <= args.person_px <= 1000.0):
        print("error: --person-px must lie between 0 and 1000", file=sys.stderr)
        return 2
    if not args.model.is_file():
        print(f"error: no model at {args.model}", file=sys.stderr)
        return 2
    try:
        model = LandabilityModel(args.model, threads=2)
        levels = None if args.levels is None else [n.strip() for n in args.levels.split(",") if n.strip()]
        if levels is not None:
            model.levels_index(levels)  # an unknown level is refused before anything is rendered
    except (ValueError, OSError) as e:  # the runner's errors name the file and what is wrong
        print(f"error: {e}", file=sys.stderr)
        return 2
    own = model.landability.threshold
    assert photos is not None  # photos_folder gives a photo ground its folder, or raises
    figures = threshold_curve(model, seeds, heights, [*thresholds, own], photos, args.person_px,
                              levels)
    for f in figures:
        if args.json:
            print(json.dumps(asdict(f)))
            continue
        left = "-" if f.unlandable_left_pct is None else f"{f.unlandable_left_pct:5.1f} %"
        mark = "  (the model's own)" if f.threshold == own else ""
        print(f"{f.height_m:5g} m  threshold {f.threshold:.2f}: landable called unlandable {f.landable_marked_pct:5.1f} %, "
              f"unlandable left {left}, free circle called unlandable {f.circle_marked_pct:5.1f} % "
              f"(over 5 % in {f.circles_over_5} of {f.circles}){mark}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
