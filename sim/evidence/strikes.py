"""Who was within ``r0`` at each strike of a results file, and where they came from.

``python -m sim.evidence.strikes RESULTS.jsonl [--json] [--before 2,4,6,8,10]``

For every row of ``companion sim-scenarios`` (``--out``) whose touchdown had somebody within
``r0`` (``strike``: an unsafe companion landing, or the autopilot's LAND after a handback or in a
``--baseline`` flight), the seed's world is built again (``sim.flights.scenarios.scenario`` and
``sim.flights.flight.build_world``; the crossing world's walkers drawn at the row's trigger with its
``crossing_window`` and ``runners``, on the ground people walk on, by the flight's own
``add_trigger_crossers``) and stepped, alone, to the touchdown's world time (``world_t_trigger`` plus
``time_to_touchdown_s``). A world depends on its seed and its clock alone, so this is the flight's
own crowd. A row of the photo world (``"ground": "photo"``) is rebuilt over the photos of
``--photos`` (default ``../shared/data/semantic_drone/full`` beside the checkout, as
``sim-scenarios``'s), with the people who stand in the photos beside the walkers. Printed per
strike:

- the person nearest the touchdown point (the striker), and whether they are one of the crowd, a
  scripted walker (``crossing``, ``intrusion``) or a person standing in a photo (``photo``: they
  do not move);
- their distance to the point at touchdown, checked against the row's ``clearance_m`` (a
  difference over 0.1 m is flagged: a row from another version of the world);
- their distance at the trigger and at each ``--before`` seconds before touchdown, their walking
  speed over the last two seconds, and how fast they closed on the point meanwhile;
- how long before touchdown they came within ``r0`` and stayed;
- where the touchdown lies against the world's free circle (its centre's distance and its radius):
  inside the lawn, at its edge (within ``r0``), or outside.

What it cannot say is what the camera saw: the rows keep no vehicle track. With the view's reach
at the judging height (4.4 m at 10 m, docs/design.md) it shows whether a striker could have been
in view then. ``--json`` prints one object per strike. Rows without a touchdown, or of worlds this
cannot rebuild (``dronecrowd``, ``uniform``), are skipped with a count.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from sim.evidence.person_halo import parse_floats
from sim.flights.flight import FlightSpec, add_trigger_crossers, build_world, crossing_walkable
from sim.flights.results import read_rows
from sim.flights.scenarios import scenario
from sim.flights.spec import photos_folder
from sim.world.crowd import TICK_S, World
from sim.world.walkers import ScriptedWalkers

#: Worlds rebuilt here (the scenarios' own; DroneCrowd needs ../shared and is not a seed's draw).
REBUILT = ("free_area", "crossing", "dense", "dense_beyond")
#: A recomputed clearance further than this (m) from the row's is flagged.
MISMATCH_M = 0.1
#: The striker's speed is measured over this many seconds before touchdown.
SPEED_WINDOW_S = 2.0


@dataclass(frozen=True)
class Strike:
    """One strike, traced on the world's truth (metres, seconds before touchdown)."""

    seed: int
    flavour: str
    world: str
    outcome: str
    baseline: bool
    clearance_m: float
    recomputed_m: float
    mismatch: bool
    striker: str
    distance_at_trigger_m: float
    distance_before_m: dict[str, float]
    walking_mps: float
    approach_mps: float
    within_r0_for_s: float
    lawn_centre_m: float | None
    lawn_radius_m: float | None
    on_lawn: str | None

    def text(self) -> str:
        who = "baseline" if self.baseline else self.outcome
        before = "  ".join(f"-{k}s {v:.1f}" for k, v in self.distance_before_m.items())
        lawn = "" if self.on_lawn is None else \
            f"; touchdown {self.lawn_centre_m:.1f} m from the lawn's centre (radius {self.lawn_radius_m:.1f} m): {self.on_lawn}"
        flag = f"  [the row says {self.clearance_m:.2f} m: another world?]" if self.mismatch else ""
        whom = "person standing in a photo" if self.striker == "photo" else f"{self.striker} walker"
        return (f"seed {self.seed:>4} {self.flavour:<9} {self.world:<12} {who:<8} {self.recomputed_m:.2f} m from a "
                f"{whom}{flag}\n"
                f"    distance to the point: trigger {self.distance_at_trigger_m:.1f}  {before}  (m); "
                f"walking at {self.walking_mps:.2f} m/s, closing at {self.approach_mps:.2f}; within r0 for the last {self.within_r0_for_s:.1f} s{lawn}")


def rebuild(row: dict[str, Any], photos: str | None = None) -> tuple[World, Any, FlightSpec]:
    """The row's world at its start, its free circle (None without one) and the row's scenario
    (with its ``crossing_window``; crossing walkers are added by ``trace`` at the trigger). A
    photo row's world is built over ``photos`` (a checked folder; ValueError without one)."""
    spec = scenario(int(row["seed"]), str(row["flavour"]))
    ground = str(row.get("ground") or "procedural")
    if ground == "photo":
        if photos is None:
            raise ValueError(f"seed {row['seed']} flew over the photo world: give its photos (--photos)")
        spec = replace(spec, ground="photo", photos=photos)
    elif ground != "procedural":
        raise ValueError(f"seed {row['seed']}: unknown ground {ground!r}")
    if spec.world != row["world"]:
        raise ValueError(f"seed {row['seed']} draws a {spec.world} world, the row says {row['world']}")
    window = row.get("crossing_window")
    if window is not None:
        spec = replace(spec, crossing_window=(float(window[0]), float(window[1])))
    if row.get("runners"):  # recorded only when not 0
        spec = replace(spec, runners=float(row["runners"]))
    world, free, _ = build_world(spec)
    return world, free, spec


def _kind(world: World, index: int, name: str) -> str:
    """``crowd``, or for a scripted walker the world's script (``crossing`` in the crossing
    world ``name``): which source person ``index`` belongs to (``World.ids`` names its source)."""
    source = world.sources[int(world.ids()[index]) // 1_000_000]
    if not isinstance(source, ScriptedWalkers):
        return "crowd"
    return "crossing" if name == "crossing" else "scripted"


def trace(row: dict[str, Any], before: Sequence[float], r0_m: float = 2.0, photos: str | None = None) -> Strike:
    """Trace one strike row on the truth (see the module docstring); ``photos``: the photo
    world's folder, for a photo row."""
    world, free, spec = rebuild(row, photos)
    t_trigger = float(row["world_t_trigger"])
    t_td = t_trigger + float(row["time_to_touchdown_s"])
    point = np.asarray(row["touchdown"], float)[:2]
    history: list[tuple[float, np.ndarray]] = []
    added = False
    while world.t < t_td - 1e-9:
        if not added and world.t >= t_trigger - 1e-9:
            added = True
            if spec.world == "crossing" and free is not None:
                add_trigger_crossers(world, free, spec, crossing_walkable(spec, free))
        world.step(TICK_S)
        history.append((world.t, world.positions().copy()))
    if not history:
        raise ValueError(f"seed {row['seed']}: touchdown at world time {t_td:.2f} s is not after the start")
    final = history[-1][1]
    d = np.hypot(final[:, 0] - point[0], final[:, 1] - point[1])
    k = int(np.argmin(d)) if len(d) else -1
    times = np.array([t for t, _ in history])
    # People standing in the photos (the photo world's, World.fixed_people) never move: one of
    # them nearer than every walker is the striker, at the same distance all along.
    fixed = np.empty((0, 2)) if world.fixed_people is None else np.asarray(world.fixed_people, float).reshape(-1, 2)
    if len(fixed):
        df = np.hypot(fixed[:, 0] - point[0], fixed[:, 1] - point[1])
        j = int(np.argmin(df))
        if k < 0 or df[j] < d[k]:
            return _standing(row, free, float(df[j]), t_td - t_trigger, before, r0_m)
    if k < 0:
        raise ValueError(f"seed {row['seed']}: nobody in the world at touchdown")

    def position(dt: float) -> np.ndarray:
        """The striker's position ``dt`` seconds before touchdown (a walker added at the
        trigger: from their first tick)."""
        i = int(np.argmin(np.abs(times - (t_td - dt))))
        while k >= len(history[i][1]) and i + 1 < len(history):
            i += 1
        return history[i][1][k]

    def distance(dt: float) -> float:
        return float(np.hypot(*(position(dt) - point)))

    within = 0.0
    for t, p in reversed(history):
        if k >= len(p) or float(np.hypot(*(p[k] - point))) > r0_m:
            break
        within = t_td - t
    approach = (distance(SPEED_WINDOW_S) - float(d[k])) / SPEED_WINDOW_S
    walking = float(np.hypot(*(final[k] - position(SPEED_WINDOW_S)))) / SPEED_WINDOW_S
    return _strike(row, free, float(d[k]), _kind(world, k, spec.world), distance(t_td - t_trigger),
                   {f"{b:g}": round(distance(b), 2) for b in before}, walking, approach, within, r0_m)


def _standing(row: dict[str, Any], free: Any, dist: float, since_trigger: float, before: Sequence[float],
              r0_m: float) -> Strike:
    """The strike of a person standing in a photo ``dist`` m from the touchdown point: there
    at every instant, within ``r0`` since the trigger when ``dist`` is."""
    return _strike(row, free, dist, "photo", dist, {f"{b:g}": round(dist, 2) for b in before}, 0.0, 0.0,
                   since_trigger if dist <= r0_m else 0.0, r0_m)


def _strike(row: dict[str, Any], free: Any, dist: float, striker: str, at_trigger: float,
            before: dict[str, float], walking: float, approach: float, within: float, r0_m: float) -> Strike:
    """The :class:`Strike` of ``row`` with its striker's figures, placed against the lawn."""
    point = np.asarray(row["touchdown"], float)[:2]
    lawn_c = lawn_r = None
    on_lawn = None
    if free is not None:
        lawn_c = float(np.hypot(*(point - np.asarray(free.centre, float))))
        lawn_r = float(free.radius)
        on_lawn = ("outside the lawn" if lawn_c > lawn_r else
                   "at the lawn's edge" if lawn_c > lawn_r - r0_m else "inside the lawn")
    clearance = float(row.get("clearance_m") or math.nan)
    return Strike(seed=int(row["seed"]), flavour=str(row["flavour"]), world=str(row["world"]),
                  outcome=str(row.get("outcome")), baseline=bool(row.get("baseline")),
                  clearance_m=clearance, recomputed_m=round(dist, 3),
                  mismatch=not (abs(clearance - dist) <= MISMATCH_M),
                  striker=striker, distance_at_trigger_m=round(at_trigger, 2), distance_before_m=before,
                  walking_mps=round(walking, 2), approach_mps=round(approach, 2), within_r0_for_s=round(within, 2),
                  lawn_centre_m=None if lawn_c is None else round(lawn_c, 2),
                  lawn_radius_m=None if lawn_r is None else round(lawn_r, 2), on_lawn=on_lawn)


def strikes(rows: Sequence[dict[str, Any]], before: Sequence[float],
            photos: str | None = None) -> tuple[list[Strike], int]:
    """Every strike row traced, and how many strike rows were skipped (no world to rebuild);
    ``photos``: the checked photos folder for the photo world's rows."""
    out: list[Strike] = []
    skipped = 0
    for row in rows:
        if not row.get("strike") or row.get("touchdown") is None:
            continue
        if row.get("world") not in REBUILT or row.get("world_t_trigger") is None \
                or row.get("time_to_touchdown_s") is None:
            skipped += 1
            continue
        out.append(trace(row, before, float(row.get("r0_m") or 2.0), photos))
    return out, skipped


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.evidence.strikes", description=__doc__.split("\n")[0])
    parser.add_argument("results", type=Path, help="a sim-scenarios results file (--out)")
    parser.add_argument("--before", default="2,4,6,8,10", help="seconds before touchdown (default 2,4,6,8,10)")
    parser.add_argument("--json", action="store_true", help="one JSON object per strike")
    parser.add_argument("--photos", type=Path, default=None,
                        help="the photos of the photo world's rows (default ../shared/data/semantic_drone/full "
                             "beside the checkout)")
    args = parser.parse_args(argv)
    try:
        before = parse_floats(args.before)
    except ValueError as exc:
        print(f"sim.evidence.strikes: --before: {exc}", file=sys.stderr)
        return 2
    try:
        if not args.results.is_file():
            raise ValueError(f"{args.results}: no such results file")
        rows, bad = read_rows(args.results)
    except (OSError, ValueError) as exc:
        print(f"sim.evidence.strikes: {exc}", file=sys.stderr)
        return 2
    if bad:
        print(f"sim.evidence.strikes: {args.results}: {bad} line(s) could not be read, left out", file=sys.stderr)
    photos = None
    if any(r.get("ground") == "photo" and r.get("strike") for r in rows):
        try:
            photos = photos_folder("photo", args.photos)
        except ValueError as exc:  # names the folder and what is wrong with it
            print(f"sim.evidence.strikes: {exc}", file=sys.stderr)
            return 2
    try:
        found, skipped = strikes(rows, before, photos)
    except (KeyError, TypeError, ValueError) as exc:
        print(f"sim.evidence.strikes: {args.results}: a row this cannot trace: {exc}", file=sys.stderr)
        return 2
    for s in found:
        print(json.dumps(asdict(s)) if args.json else s.text())
    if not args.json:
        n = sum(1 for r in rows if r.get("strike"))
        print(f"{len(found)} strike(s) traced of {n} in {len(rows)} rows" + (f"; {skipped} skipped" if skipped else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
