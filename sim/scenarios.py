"""``companion sim-scenarios``: fly N seeded random scenarios and report the safety figures.

Each seed draws a scenario: autopilot flavour, hover altitude, where the one free circle lies in
view and how large it is, the failsafe that fires, and, for one seed in six, a dense crowd with no
safe zone at all (the right answer there is a handback). Every flight is judged on the simulator's
truth (see ``sim.flight``). Prints safe landings / total, the minimum clearance at touchdown, the
median time from trigger to touchdown and the handbacks; ``--json`` prints one JSON object with
``total, safe, handbacks, unsafe, min_clearance_m, median_time_to_touchdown_s, max_climb_m`` (and
more; ``max_climb_m`` is the most any flight rose above its altitude at the trigger, on the truth).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys

import numpy as np

from sim.flight import FlightResult, FlightSpec, fly, summarise


def parse_seeds(text: str) -> list[int]:
    """``1-50``, ``3``, or ``1,4,9-12``."""
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-", 1)
            lo, hi = int(a), int(b)
            if hi < lo:
                raise ValueError(f"seed range {part!r} runs backwards")
            seeds.extend(range(lo, hi + 1))
        elif part:
            seeds.append(int(part))
    if not seeds:
        raise ValueError("no seeds given")
    return seeds


def scenario(seed: int, flavour: str | None = None) -> FlightSpec:
    """The random scenario of one seed (deterministic)."""
    rng = np.random.default_rng(seed)
    drawn = ("ardupilot", "px4")[int(rng.integers(2))]  # drawn even when overridden, so that a
    fl = flavour or drawn  # seed is the same scene whatever --flavour says
    alt = float(rng.uniform(15.0, 25.0))
    world = "dense" if rng.random() < 1 / 6 else "free_area"
    # Somewhere well inside the view (90 deg camera: half-width ~ altitude).
    bearing = rng.uniform(0, 2 * math.pi)
    dist = rng.uniform(3.0, 0.45 * alt)
    offset = (-dist * math.cos(bearing), -dist * math.sin(bearing))
    radius = float(rng.uniform(5.0, 8.0))
    failsafe = ("battery_critical", "rc_loss", "gcs_loss")[int(rng.integers(3))]
    # The simulated PX4's home sits 0-3 m above or below its estimator's origin, as on a real
    # one (1.48 m in PX4's SIH): frame-6 targets would be read wrongly. Drawn last, so the
    # earlier draws (and every seed's scene) stay what they were.
    offset_m = float(rng.uniform(0.0, 3.0)) * (1.0 if rng.random() < 0.5 else -1.0)
    return FlightSpec(flavour=fl, world=world, seed=seed, altitude_m=alt, start_offset_m=offset,
                      free_radius_m=radius, failsafe=failsafe, home_origin_offset_m=offset_m)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", default="1-10", help="seeds, e.g. 1-50 or 1,4,9-12 (default 1-10)")
    parser.add_argument("--flavour", choices=("ardupilot", "px4"), default=None,
                        help="fly every scenario with this autopilot (default: drawn per seed)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--verbose", action="store_true", help="print each flight's messages")


def run(args: argparse.Namespace) -> int:
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        print(f"companion sim-scenarios: bad --seeds: {exc}", file=sys.stderr)
        return 2
    results: list[FlightResult] = []
    for seed in seeds:
        spec = scenario(seed, args.flavour)
        try:
            res = asyncio.run(fly(spec))
        except RuntimeError as exc:
            print(f"seed {seed}: could not fly: {exc}", file=sys.stderr)
            return 1
        results.append(res)
        clear = "-" if res.clearance_m is None else f"{res.clearance_m:.1f} m"
        ttd = "-" if res.time_to_touchdown_s is None else f"{res.time_to_touchdown_s:.0f} s"
        climb = "-" if res.max_climb_m is None else f"{res.max_climb_m:.1f} m"
        print(f"seed {seed:>3} {spec.flavour:<9} {spec.world:<9} alt {spec.altitude_m:4.1f} m "
              f"-> {res.outcome:<8} clearance {clear:>7}  to touchdown {ttd:>5}  climb {climb:>6}",
              file=sys.stderr if args.json else sys.stdout, flush=True)
        if args.verbose:
            for m in res.messages:
                print(f"      {m}", file=sys.stderr if args.json else sys.stdout)
    summary = summarise(results)
    summary["flights"] = [r.as_dict() for r in results]
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"\nsafe landings {summary['safe']}/{summary['total']}, unsafe {summary['unsafe']}, "
              f"handbacks {summary['handbacks']}, timeouts {summary['timeouts']}")
        print(f"minimum clearance at touchdown: {summary['min_clearance_m']} m; median time from "
              f"trigger to touchdown: {summary['median_time_to_touchdown_s']} s; highest climb "
              f"above the altitude at the trigger: {summary['max_climb_m']} m")
    return 0 if summary["unsafe"] == 0 else 1
