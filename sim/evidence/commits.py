"""How each LAND of a results file was committed: at a wide lens's commit height, or after its hold.

``python -m sim.evidence.commits RESULTS.jsonl [...] [--json]``

A lens with a commit height (docs/design.md, "The camera's footprint, and where a wide one
commits") descends over a judged zone to that height and commits the LAND there once the frame sees
r0 plus a walker's reach free around the vehicle; while it does not, the LAND is *held*, for as
long as touchdown would take from there, and then the landing goes on down to the LAND height as a
narrow camera's does. The rows of ``companion sim-scenarios`` keep no per-frame trace, but they
keep the controller's texts (``messages``), which say each step. For every companion flight whose
last LAND went out, this reads from them:

- ``planned_m``: the height the judged zone's descent went to before the LAND ("judged at ...:
  descending over it to 8.9 m before the LAND"), the commit height when the lens has one (the
  highest such text of the zone: judged again after its hold ran out, it plans the LAND height);
- ``land_m``: the height the LAND was commanded at ("LAND over zone 24 at 4.5 m");
- ``held``: whether the LAND was held over that zone ("free around the vehicle 5.3 m, not r0 plus
  the 9.8 m a walker covers before touchdown (11.8 m): holding the LAND"), and ``free_m``, the free
  ground the frame saw round the vehicle when the hold began;

and sorts the LAND into one of three paths: ``commit`` (at the planned height: a wide lens
committed there, or a narrow one's LAND height), ``held_out`` (held, then on down to a lower LAND
height: the hold ran its time), ``below`` (commanded lower than planned without a hold: the zone
came out of view or the ground came early). Printed per file: the paths by outcome, and the free
ground round the vehicle when the holds began against what the hold asked for. Rows without a LAND
(handbacks before it) are counted apart.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from sim.flights.results import read_rows

#: A LAND within this of the planned height (m) was commanded there (the texts round to 0.1 m and
#: the descent stops within ``controller.alt_tolerance_m`` of its target).
AT_PLANNED_M = 0.6

_JUDGED = re.compile(r"zone (\d+) judged at [\d.]+ m .*descending over it to ([\d.]+) m before the LAND")
_HELD = re.compile(r"zone (\d+): free around the vehicle ([\d.]+) m, not r0 plus the ([\d.]+) m a walker covers "
                   r"before touchdown \(([\d.]+) m\): holding the LAND")
_LAND = re.compile(r"LAND over zone (\d+) at ([\d.]+) m")


@dataclass(frozen=True)
class Commit:
    """How one flight's last LAND went out (heights in m above the ground, as the texts give them)."""

    seed: int
    world: str
    outcome: str
    zone: int
    land_m: float
    planned_m: float | None
    held: bool
    #: Free ground round the vehicle when the hold began (m), and what it asked for (r0 plus reach).
    free_m: float | None
    needed_m: float | None
    path: str


def commit_of(row: dict[str, Any]) -> Commit | None:
    """The last LAND of a companion row's texts, or None when no LAND went out."""
    texts = [str(m) for m in row.get("messages") or []]
    lands = [(i, m) for i, t in enumerate(texts) if (m := _LAND.search(t))]
    if not lands:
        return None
    at, land = lands[-1]
    zone, land_m = int(land.group(1)), float(land.group(2))
    before = texts[:at]
    planned = [float(m.group(2)) for t in before if (m := _JUDGED.search(t)) and int(m.group(1)) == zone]
    holds = [m for t in before if (m := _HELD.search(t)) and int(m.group(1)) == zone]
    # The highest: a zone judged again after its hold ran out plans the LAND height from then on.
    planned_m = max(planned) if planned else None
    held = bool(holds)
    if planned_m is not None and abs(land_m - planned_m) <= AT_PLANNED_M:
        path = "commit"
    elif held:
        path = "held_out"
    else:
        path = "below"
    return Commit(int(row["seed"]), str(row.get("world")), str(row.get("outcome")), zone, land_m, planned_m, held,
                  float(holds[-1].group(2)) if held else None, float(holds[-1].group(4)) if held else None, path)


def summarise(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The paths by outcome over the companion rows, and the holds' free ground against their need."""
    companion = [r for r in rows if not r.get("baseline")]
    commits = [c for r in companion if (c := commit_of(r)) is not None]
    paths = Counter(f"{c.path} {c.outcome}" for c in commits)
    free = [c.free_m for c in commits if c.free_m is not None]
    need = [c.needed_m for c in commits if c.needed_m is not None]
    return {
        "flights": len(companion),
        "no_land": len(companion) - len(commits),
        "paths": dict(sorted(paths.items())),
        "held": sum(c.held for c in commits),
        "held_free_m": None if not free else {"median": round(statistics.median(free), 1), "min": min(free),
                                               "max": max(free)},
        "held_needed_m": None if not need else round(statistics.median(need), 1),
        "held_then_enough": sum(c.held and c.path == "commit" for c in commits),
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.evidence.commits", description=__doc__.split("\n\n")[0])
    parser.add_argument("results", nargs="+", type=Path, help="results files of companion sim-scenarios (--out)")
    parser.add_argument("--json", action="store_true", help="one JSON object a file, each LAND listed")
    args = parser.parse_args(argv)
    for path in args.results:
        if not path.is_file():
            print(f"sim.evidence.commits: {path}: no such results file", file=sys.stderr)
            return 2
        rows, bad = read_rows(path)
        summary = summarise(rows)
        if args.json:
            landings = [asdict(c) for r in rows if not r.get("baseline") and (c := commit_of(r)) is not None]
            print(json.dumps({"file": str(path), "unreadable_lines": bad, **summary, "landings": landings}))
            continue
        print(f"{path}: {summary['flights']} companion flights, {summary['no_land']} without a LAND"
              + (f", {bad} unreadable lines" if bad else ""))
        for key, n in summary["paths"].items():
            print(f"  {key:<24} {n}")
        if summary["held"]:
            f = summary["held_free_m"]
            print(f"  held {summary['held']}: free round the vehicle when the hold began median {f['median']} m "
                  f"({f['min']}-{f['max']}), asked for {summary['held_needed_m']} m; "
                  f"committed at the commit height after a hold: {summary['held_then_enough']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
