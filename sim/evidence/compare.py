"""Two results files of ``companion sim-scenarios`` side by side, seed by seed: what a change did,
and whether it is more than chance.

``companion sim-compare BEFORE.jsonl AFTER.jsonl [--starved] [--json]``

The same seed flown twice is a *pair*: the same world, the same crowd at the same world time, the
same autopilot. Verdicts still differ from run to run (the loop runs on wall-clock time on a
shared machine, so the vehicle meets the walkers a little earlier or later), and the differences
between two settings on a few dozen seeds are often no larger than between two runs of one
setting (docs/design.md has several such days). So each figure is compared over the pairs, and
the comparison says how likely a difference that large would be if the change did nothing:

- per flight yes/no figures (an unsafe landing, a strike, a companion landing with nobody within
  ``r_0``, a handback, a landing on ground nobody walks into, a touchdown on unlandable ground
  (a tree, a bench, a car, a roof: ``unlandable_touchdown``, whoever landed), and with
  ``--starved`` a starved flight): the pairs where only BEFORE says yes
  and where only AFTER says yes, and the exact two-sided McNemar p-value (the binomial test of
  those discordant pairs at one half; scipy). Pairs that agree say nothing about the change;
- time from trigger to touchdown (over the pairs where both landed), the time the vehicle took
  over its last 3.5 m (``last_metres_s``, whoever landed: what a walker has to reach the point
  unseen; over the pairs whose rows carry it), phase changes, zone
  losses (``sim.flights.flight.zone_losses``; over the pairs whose rows carry them) and the service's
  frame time at the 95th percentile (what a change in speed moves): the medians of each
  side, the median paired difference and the two-sided Wilcoxon signed-rank p-value (scipy);
- the pairs whose verdict changed, listed, and their share of the pairs with its exact 95 %
  interval (``verdicts_changed_ci95``, Clopper-Pearson): two files of the *same* code and settings
  change some verdicts too (the loop runs on wall-clock time), so this share between two runs of
  one setting is the yardstick for any other pair of files, parallel runs against sequential ones
  included (docs/scale.md, issue 17's "identical verdicts"). Two files flown with ``--lockstep``
  need one too: a rerun of one code from one clock start changes no verdict, but a flight is
  chaotic, and any change also moves how its times round in their last bits, which alone changes
  verdicts (``--clock-start``: the same code from another start). Their yardstick is two files of
  one code flown from two clock starts; a comparison whose two sides differ in nothing else says
  it is one (``clock_only`` in the JSON; ``lockstep``: every pair was flown that way on both
  sides).

A pair is compared only when both flights are clean (not starved: ``sim.flights.results``); ``--starved``
takes starved flights too, as the figures of a loaded machine (the rows still say which were).
Seeds flown in one file only are named and left out. Baseline rows (the autopilot alone) are left
out: they do not change with the companion's settings. A file that holds two rows of one seed and
autopilot (two settings) cannot be paired and is refused (exit 2): compare one setting per file.

Every row is also compared whole (``identity``): a restructuring that must change nothing a
flight does is proven by lockstep rows equal in every field but those the host sets
(``HOST_FIELDS``: wall and CPU time, the frame times and starvation they decide, the host and the
software that flew), baseline rows included; the fields that differ are counted by name.

A p-value below 0.05 says the difference is unlikely under "no change" *for these seeds*; one at
or above it does not say the two are the same: with 0 against k discordant pairs McNemar needs k
>= 6 before it says anything (``MIN_DISCORDANT``), and an unsafe landing is rarer than that in
50 seeds. Figures are the simulator's truth as the rows recorded it, never a log.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import binomtest, wilcoxon

from sim.flights.results import binomial_interval, flown_apart, read_rows

#: The level below which a difference is called beyond chance.
ALPHA = 0.05
#: Unpaired seeds named in the text (the JSON has them all).
LISTED = 10

#: Fields of a row that the host sets, not the flight: left out of ``identity``. Frame times
#: (and ``starved``, decided by them) are wall-clock even in lockstep, where they set only how
#: fast the flight flies, not what it does.
HOST_FIELDS = frozenset({"wall_s", "cpu_s", "host", "software", "processed_fps", "frame_ms_p95", "starved"})

#: A per-flight yes/no question asked of a row (None: the row cannot say).
FlightTest = Callable[[dict[str, Any]], bool | None]


def _landed(row: dict[str, Any]) -> bool:
    return row.get("outcome") in ("safe", "unsafe")


def _on_free_ground(row: dict[str, Any]) -> bool | None:
    """No for a flight that did not land; None for a landing whose row cannot say where."""
    if not _landed(row):
        return False
    where = row.get("in_free_area")
    return None if where is None else bool(where)


BINARY: dict[str, FlightTest] = {
    "unsafe landing": lambda r: r.get("outcome") == "unsafe",
    "strike (anyone within r0 at touchdown, whoever landed)": lambda r: bool(r.get("strike")),
    "companion landing with nobody within r0": lambda r: r.get("outcome") == "safe",
    "handback": lambda r: r.get("outcome") == "handback",
    "companion landing on ground nobody walks into": _on_free_ground,
    "touchdown on a tree, bench, car or roof (whoever landed)":
        lambda r: r.get("unlandable_touchdown") if isinstance(r.get("unlandable_touchdown"), bool) else None,
    # Only with --starved: without it no compared pair holds a starved flight.
    "starved (the frame p95 over the machine's limit)": lambda r: bool(r.get("starved")),
}


def _phases(row: dict[str, Any]) -> float | None:
    phases = row.get("phases")
    return float(len(phases)) if isinstance(phases, list) else None


def _time(row: dict[str, Any]) -> float | None:
    t = row.get("time_to_touchdown_s")
    return float(t) if _landed(row) and isinstance(t, (int, float)) else None


def _number(key: str) -> Callable[[dict[str, Any]], float | None]:
    """The row's number under ``key`` (None when it has none, or not a number)."""
    def get(row: dict[str, Any]) -> float | None:
        v = row.get(key)
        return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None
    return get


def _losses(row: dict[str, Any]) -> float | None:
    n = row.get("zone_losses")
    return float(n) if isinstance(n, int) else None


#: Per-flight numbers compared pair by pair: name -> the number (None: the row cannot say).
NUMERIC: dict[str, Callable[[dict[str, Any]], float | None]] = {
    "time from trigger to touchdown (s; both landed)": _time,
    "time over the last 3.5 m (s; a walker's, unseen)": _number("last_metres_s"),
    "phase changes": _phases,
    "zones given up over them": _losses,
    "service frame time, p95 (ms; what starves a flight)": _number("frame_ms_p95"),
}


def mcnemar_p(only_before: int, only_after: int) -> float:
    """The exact two-sided McNemar p-value of ``only_before`` against ``only_after`` discordant
    pairs (1.0 when there are none)."""
    n = only_before + only_after
    if n == 0:
        return 1.0
    return float(binomtest(min(only_before, only_after), n, 0.5).pvalue)


def _min_discordant() -> int:
    n = 1
    while mcnemar_p(0, n) >= ALPHA:
        n += 1
    return n


#: The fewest discordant pairs, all one way, that McNemar calls beyond chance (6 at 0.05).
MIN_DISCORDANT = _min_discordant()


@dataclass(frozen=True)
class BinaryChange:
    """One yes/no figure over the pairs: how many flights said yes on each side, and the
    discordant pairs (yes before only, yes after only) with their McNemar p-value."""

    name: str
    pairs: int
    before: int
    after: int
    only_before: int
    only_after: int
    p: float


@dataclass(frozen=True)
class NumericChange:
    """One number over the pairs where both rows give it: the medians of each side, the median
    of after less before, and the Wilcoxon signed-rank p-value (None with fewer than 2 pairs or no
    difference at all)."""

    name: str
    pairs: int
    before_median: float | None
    after_median: float | None
    median_difference: float | None
    p: float | None


@dataclass(frozen=True)
class ChangedPair:
    """A seed whose verdict differs between the two files."""

    seed: int
    flavour: str
    world: str
    before: str
    after: str


@dataclass
class Identity:
    """How many rows of the two files are the same flight in every field but ``HOST_FIELDS``:
    ``pairs`` rows paired by seed, autopilot and baseline (baseline rows too), ``identical`` of
    them equal, ``fields`` how many pairs differ in each field that differs."""

    pairs: int = 0
    identical: int = 0
    fields: dict[str, int] = field(default_factory=dict)

    def text(self) -> str:
        """The identity for people."""
        line = (f"rows equal in every field but the host's ({', '.join(sorted(HOST_FIELDS))}): "
                f"{self.identical} of {self.pairs} (baseline rows included)")
        if self.fields:
            line += "; fields that differ: " + ", ".join(f"{k} in {v}" for k, v in sorted(self.fields.items()))
        return line


@dataclass
class Comparison:
    """What ``compare`` found (see the module docstring)."""

    pairs: int = 0
    starved_left_out: int = 0
    only_before: list[tuple[int, str]] = field(default_factory=list)
    only_after: list[tuple[int, str]] = field(default_factory=list)
    settings_before: list[list[str]] = field(default_factory=list)
    settings_after: list[list[str]] = field(default_factory=list)
    binary: list[BinaryChange] = field(default_factory=list)
    numeric: list[NumericChange] = field(default_factory=list)
    changed: list[ChangedPair] = field(default_factory=list)
    #: The share of the pairs whose verdict changed, and its exact 95 % interval (None: no pair).
    verdicts_changed_rate: float | None = None
    verdicts_changed_ci95: list[float] | None = None
    #: Every compared pair was flown in lockstep on both sides (``sim.flights.lockstep``): a rerun of one
    #: code from one clock start changes no verdict, but another start does (the module docstring).
    lockstep: bool = False
    #: What flew each side (``sim.flights.results.software``: Python, the libraries that compute, the
    #: commit), each distinct record once; rows written before they said are left out.
    software_before: list[dict[str, str]] = field(default_factory=list)
    software_after: list[dict[str, str]] = field(default_factory=list)
    #: Both sides in lockstep, flown with the same settings in everything but the clock's start:
    #: the comparison is a yardstick (how far these seeds' verdicts are from chance), not a change.
    clock_only: bool = False
    #: Every row compared whole, baseline rows included (``identity``).
    identity: Identity = field(default_factory=Identity)

    @property
    def beyond_chance(self) -> list[str]:
        """The figures whose difference is beyond chance at ``ALPHA``."""
        out = [b.name for b in self.binary if b.p < ALPHA]
        return out + [n.name for n in self.numeric if n.p is not None and n.p < ALPHA]


def identity(before: list[dict[str, Any]], after: list[dict[str, Any]]) -> Identity:
    """Pair every row (companion and baseline) by seed, autopilot and baseline, and count the pairs
    equal in every field but ``HOST_FIELDS``. A key held twice on a side is paired on neither."""
    def keyed(rows: list[dict[str, Any]]) -> dict[tuple[int, str, bool], dict[str, Any]]:
        out: dict[tuple[int, str, bool], dict[str, Any]] = {}
        twice: set[tuple[int, str, bool]] = set()
        for row in rows:
            key = (int(row["seed"]), str(row["flavour"]), bool(row.get("baseline")))
            if key in out:
                twice.add(key)
            out[key] = row
        return {k: v for k, v in out.items() if k not in twice}

    a, b = keyed(before), keyed(after)
    result = Identity()
    for key in sorted(set(a) & set(b)):
        x, y = a[key], b[key]
        differ = [f for f in sorted(set(x) | set(y)) if f not in HOST_FIELDS and x.get(f) != y.get(f)]
        result.pairs += 1
        result.identical += not differ
        for f in differ:
            result.fields[f] = result.fields.get(f, 0) + 1
    return result


class CompareError(ValueError):
    """The files cannot be compared (unpaired duplicates, nothing in common)."""


def _companion_rows(rows: list[dict[str, Any]], label: str) -> dict[tuple[int, str], dict[str, Any]]:
    out: dict[tuple[int, str], dict[str, Any]] = {}
    for row in rows:
        if row.get("baseline"):
            continue
        key = (int(row["seed"]), str(row["flavour"]))
        if key in out:
            raise CompareError(f"{label} holds two rows of seed {key[0]} on {key[1]} (flown with different "
                               "settings?): compare files of one setting each")
        out[key] = row
    return out


def _flown_with(row: dict[str, Any], clock: bool = True) -> tuple[str, ...]:
    """What a row was flown with beside the defaults: its service settings (``--set``), each way
    it was flown apart from the scenarios' own (``sim.flights.results.flown_apart``: ``--land-speed``,
    ``--crossing-window``, ``--watch-s``, and with ``clock`` ``--clock-start``), and ``lockstep``
    for a flight on the simulated clock (``--lockstep``)."""
    out = tuple(str(x) for x in row.get("settings") or ())
    out = (*out, *(f"{part.name}={part.value}" for part in flown_apart(row) if clock or part.key != "clock"))
    return (*out, "lockstep") if row.get("lockstep") else out


def _software_differs(before: list[dict[str, str]], after: list[dict[str, str]]) -> list[str]:
    """``name BEFORE -> AFTER`` for each part of what flew the two sides that is not one and the
    same on both (several values on a side are joined by ``|``); nothing when a side never said."""
    if not before or not after:
        return []
    out = []
    for name in sorted({k for s in before + after for k in s}):
        b = sorted({s.get(name, "-") for s in before})
        a = sorted({s.get(name, "-") for s in after})
        if b != a or len(b) > 1:
            out.append(f"{name} {'|'.join(b)} -> {'|'.join(a)}")
    return out


def _verdict(row: dict[str, Any]) -> str:
    c = row.get("clearance_m")
    clear = "" if not isinstance(c, (int, float)) else f" {c:.1f} m"
    return f"{row.get('outcome')}{clear}{' (starved)' if row.get('starved') else ''}"


def compare(before: list[dict[str, Any]], after: list[dict[str, Any]], include_starved: bool = False) -> Comparison:
    """Pair two files' companion rows by seed and autopilot and compare them (module docstring)."""
    a, b = _companion_rows(before, "BEFORE"), _companion_rows(after, "AFTER")
    common = sorted(set(a) & set(b))
    if not common:
        raise CompareError("the two files have no seed flown on the same autopilot in common")
    result = Comparison(only_before=sorted(set(a) - set(b)), only_after=sorted(set(b) - set(a)),
                        identity=identity(before, after))
    result.settings_before, result.settings_after = (
        [list(s) for s in sorted({_flown_with(r) for r in rows.values()})] for rows in (a, b))
    result.software_before, result.software_after = (
        [dict(s) for s in sorted({tuple(sorted(r["software"].items())) for r in rows.values()
                                  if isinstance(r.get("software"), dict)})] for rows in (a, b))
    pairs = []
    for key in common:
        if not include_starved and (a[key].get("starved") or b[key].get("starved")):
            result.starved_left_out += 1
            continue
        pairs.append((a[key], b[key]))
    result.pairs = len(pairs)
    result.lockstep = bool(pairs) and all(x.get("lockstep") and y.get("lockstep") for x, y in pairs)
    result.clock_only = result.lockstep and all(
        _flown_with(x) != _flown_with(y) and _flown_with(x, clock=False) == _flown_with(y, clock=False)
        for x, y in pairs)
    for name, test in BINARY.items():
        asked = [(test(x), test(y)) for x, y in pairs]
        said = [(bool(u), bool(v)) for u, v in asked if u is not None and v is not None]
        ob, oa = sum(u and not v for u, v in said), sum(v and not u for u, v in said)
        result.binary.append(BinaryChange(name, len(said), sum(u for u, _ in said), sum(v for _, v in said),
                                          ob, oa, round(mcnemar_p(ob, oa), 4)))
    for name, value in NUMERIC.items():
        both = [(value(x), value(y)) for x, y in pairs]
        xs = np.array([(u, v) for u, v in both if u is not None and v is not None], dtype=float).reshape(-1, 2)
        p = None
        diff = xs[:, 1] - xs[:, 0]
        if len(xs) >= 2 and np.any(diff != 0):
            p = round(float(wilcoxon(xs[:, 0], xs[:, 1]).pvalue), 4)
        result.numeric.append(NumericChange(name, len(xs), _median(xs[:, 0]), _median(xs[:, 1]), _median(diff), p))
    for x, y in pairs:
        if x.get("outcome") != y.get("outcome"):
            result.changed.append(ChangedPair(int(x["seed"]), str(x["flavour"]), str(x.get("world")),
                                              _verdict(x), _verdict(y)))
    if result.pairs:
        lo, hi = binomial_interval(len(result.changed), result.pairs)
        result.verdicts_changed_rate = round(len(result.changed) / result.pairs, 4)
        result.verdicts_changed_ci95 = [round(lo, 4), round(hi, 4)]
    return result


def _median(v: np.ndarray) -> float | None:
    return None if len(v) == 0 else round(float(np.median(v)), 2)


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:g}"


def _p(p: float | None) -> str:
    return "-" if p is None else (f"p = {p:.3f}" + (" *" if p < ALPHA else ""))


def comparison_text(c: Comparison) -> str:
    """The comparison for people."""
    lines = [f"{c.pairs} pairs (one seed, one autopilot, flown in both files)"
             + (f"; {c.starved_left_out} pair(s) with a starved flight left out (--starved takes them)"
                if c.starved_left_out else "")]
    for label, keys in (("only in BEFORE", c.only_before), ("only in AFTER", c.only_after)):
        if keys:
            named = ", ".join(f"{s} {f}" for s, f in keys[:LISTED])
            more = f" and {len(keys) - LISTED} more" if len(keys) > LISTED else ""
            lines.append(f"{label} (left out): {len(keys)} flight(s): {named}{more}")
    lines.append(f"settings: BEFORE {c.settings_before or [[]]}, AFTER {c.settings_after or [[]]}")
    differs = _software_differs(c.software_before, c.software_after)
    if differs:
        lines.append("software differs (another version rounds differently, as another clock start does): "
                     + "; ".join(differs))
    if c.pairs == 0:
        lines.append("no pair is clean (every seed starved on one side or both): nothing to compare. Fly on a "
                     "machine that keeps up, or compare the starved flights with --starved")
        return "\n".join(lines)
    lines.append("")
    lines.append(f"{'per flight':<56} {'BEFORE':>7} {'AFTER':>7}  yes before only / after only")
    for b in c.binary:
        lines.append(f"{b.name:<56} {b.before:>3}/{b.pairs:<3} {b.after:>3}/{b.pairs:<3}  "
                     f"{b.only_before:>3} / {b.only_after:<3}  {_p(b.p)}")
    lines.append("")
    lines.append(f"{'paired numbers':<56} {'median BEFORE':>13} {'AFTER':>7} {'difference':>10}")
    for n in c.numeric:
        lines.append(f"{n.name:<56} {_num(n.before_median):>13} {_num(n.after_median):>7} "
                     f"{_num(n.median_difference):>10}  over {n.pairs} pairs, {_p(n.p)}")
    if c.verdicts_changed_ci95 is not None:
        lo, hi = c.verdicts_changed_ci95
        lines.append("")
        lines.append(f"verdicts changed in {len(c.changed)} of {c.pairs} pairs ({100 * (c.verdicts_changed_rate or 0):.1f} %, "
                     f"95 % exact interval {100 * lo:.1f} to {100 * hi:.1f} %); "
                     + ("the two sides' settings differ only in where the lockstep clock started: of one "
                        "code, this is the yardstick, how far these seeds' verdicts are from chance" if c.clock_only else
                        "both flown in lockstep, where a rerun from one clock start changes none, but any "
                        "change also changes how times round: compare with two clock starts of one code "
                        "(--clock-start)" if c.lockstep else
                        "two runs of one setting change some too: compare with theirs"))
    if c.identity.pairs:
        lines.append(c.identity.text())
    if c.changed:
        lines.append("verdicts that changed:")
        lines += [f"  seed {p.seed:>4} {p.flavour:<9} {p.world:<12} {p.before} -> {p.after}" for p in c.changed]
    lines.append("")
    beyond = c.beyond_chance
    lines.append((f"beyond chance at the {ALPHA:g} level (*): " + "; ".join(beyond)) if beyond else
                 f"no difference is beyond chance at the {ALPHA:g} level on these pairs; that does not make "
                 f"them the same (a yes/no figure needs at least {MIN_DISCORDANT} discordant pairs, all one way)")
    return "\n".join(lines)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("before", type=Path, help="results file (JSON Lines) of the first setting or commit")
    parser.add_argument("after", type=Path, help="results file of the second")
    parser.add_argument("--starved", action="store_true",
                        help="compare starved flights too (left out by default, as in the summary)")
    parser.add_argument("--json", action="store_true", help="print the comparison as JSON")


def run(args: argparse.Namespace) -> int:
    loaded = []
    for path in (args.before, args.after):
        if not path.is_file():
            print(f"error: no results file at {path}", file=sys.stderr)
            return 2
        rows, bad = read_rows(path)
        if bad:
            print(f"warning: {bad} unreadable line(s) in {path} left out", file=sys.stderr)
        loaded.append(rows)
    try:
        c = compare(loaded[0], loaded[1], include_starved=args.starved)
    except CompareError as exc:
        same = identity(loaded[0], loaded[1])
        if not same.pairs or any(not r.get("baseline") for rows in loaded for r in rows):
            print(f"error: {exc}", file=sys.stderr)
            return 2
        # Two files of baseline rows alone (the autopilot's failsafe, no companion): nothing of
        # the companion's to compare, but whether the flights are the same flights.
        print(json.dumps({"identity": asdict(same)}) if args.json else
              "baseline rows only (the autopilot alone): " + same.text())
        return 0
    if args.json:
        # Every figure is a count, a finite p-value or median, or None: plain JSON.
        print(json.dumps({**asdict(c), "beyond_chance": c.beyond_chance, "alpha": ALPHA,
                          "min_discordant": MIN_DISCORDANT}))
    else:
        print(comparison_text(c))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="companion sim-compare", description=__doc__.split("\n\n")[0])
    configure(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
