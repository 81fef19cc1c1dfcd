"""What many flights are evidence of: the results file, the summary, and its confidence bounds.

Each flight of ``companion sim-scenarios`` is one JSON object (a *row*: ``FlightResult.as_dict()``
and the runner's own fields) on one line of a JSON Lines results file, appended and flushed as soon
as the flight ends, so a run that dies keeps every flight it finished and a re-run with the same
file flies only the seeds missing from it. The summary is computed from rows, never from a run's
memory, so the figures of a resumed run are those of all its flights.

Counting (docs/scale.md says why):

- a **starved** flight (its service processed frames at less than ``sim.flights.flight.STARVED_SHARE`` of
  the camera's rate: a CPU-starved machine, not the software under test) is not a clean result.
  It is counted in ``starved``, ``starved_outcomes`` and ``starved_strikes`` only, and left out of ``safe``,
  ``handbacks``, ``unsafe``, ``timeouts``, the strikes and every rate; ``total`` counts it.
  So ``total = safe + handbacks + unsafe + timeouts + starved``;
- the rates are per **clean flight** (``clean_flights``: the flights that were not starved):
  unsafe landings, strikes (a touchdown with somebody within ``r_0``, whoever landed, the companion
  or the autopilot after a handback) and companion landings (safe or unsafe), each with its exact
  two-sided 95 % binomial interval (Clopper-Pearson);
- ``min_clearance_m`` and ``max_climb_m`` are safety figures and take every flight, starved ones
  included (a bad number never disappears); ``median_time_to_touchdown_s`` is a performance
  figure and takes the clean flights, and so do ``median_phase_changes`` and
  ``max_phase_changes`` (a flight's phase changes: the controller's recorded phase-change events,
  ``len(row["phases"])``; the controller changes phase only by emitting one);
- ``median_last_metres_s``: over the clean companion landings whose rows carry it, the time the
  vehicle took over its last 3.5 m (``sim.flights.flight.LAST_METRES_M``, on the truth): committed, the
  camera seeing less than ``r_0`` around the point, it is a walker's time to reach it unseen (the
  baseline's: over its touchdowns); None when no row says;
- ``companion_landings_in_free_area`` of ``companion_landings_judged_for_area``: the clean
  companion landings that came down on ground nobody walks into (``in_free_area``: the scene's
  free circle, or beyond every crowd; ``sim.world.crowd.World.nobody_walks_at``), of those whose row
  says either way. A landing in a gap of the crowd may be safe at touchdown and still was a
  gamble on the walkers around it.
- ``unlandable_touchdowns`` of ``touchdowns_judged_for_surface``: the clean flights that touched
  down with part of the vehicle's footprint on ground that is not landable (a tree, a bench, a
  car, a roof: ``unlandable_touchdown``, on the procedural ground's truth), whoever landed, of
  those whose row says either way; ``companion_landings_unlandable``, the companion's landings
  among them. None when no row says (rows flown before the judge knew the ground).
- ``zone_losses`` and ``zone_losses_r0_free``: over the clean flights whose rows carry them, the
  zones the controller gave up while over them (``sim.flights.flight.zone_losses``), and how many of those
  had, by the simulator's truth, nobody within ``r_0`` of the vehicle at that moment: the price of
  the pipeline's caution and of the density model's false detections in closed loop (each loss
  costs a climb back and a new zone); None when no row says.

**Baseline** rows (``baseline: true``: the same scene flown with the autopilot's own failsafe
alone, no companion) have their own key in a results file (``row_key``) and their own summary
(``summarise_baseline``): touchdowns and strikes on the same truth, the strike rate and its bounds.
"""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from scipy.stats import beta

CONFIDENCE = 0.95
#: The last element of a baseline flight's key in a results file.
BASELINE = "baseline"
#: The scenarios' camera (``MODEL:HFOV``, ``sim.flights.spec.camera_name``): the simulator's
#: 70-degree pinhole. Rows flown with another record it (``camera``) and are keyed apart.
DEFAULT_CAMERA = "pinhole:70"
#: The scenarios' LAND descent speed (m/s; ``sim.flights.spec.FlightSpec.land_speed``'s default): the
#: simulated autopilot's ``LAND_SPEED`` / ``MPC_LAND_SPEED``. Rows flown at another speed
#: (``companion sim-scenarios --land-speed``) are keyed apart.
SCENARIO_LAND_SPEED = 1.0
#: The crossing world's window (s after the failsafe; ``sim.world.crowd.CROSSING_WINDOW_S``): rows flown
#: with another (``companion sim-scenarios --crossing-window``) are keyed apart.
SCENARIO_CROSSING_WINDOW_S = (4.0, 24.0)
#: How long the service watches before the failsafe (s; ``sim.flights.spec.FlightSpec.watch_s``'s
#: default): rows flown with another (``companion sim-scenarios --watch-s``) are keyed apart.
SCENARIO_WATCH_S = 4.0
#: Where a lockstep flight's simulated clock starts (s; ``sim.flights.spec.FlightSpec.clock_start_s``'s
#: default). A flight is a chaotic system: the same scene flown on a clock that starts elsewhere
#: rounds its times differently in the last bits and may end in another verdict
#: (docs/scale.md, "How far one flight is from the next"), so the start is fixed and recorded, and
#: rows flown from another (``companion sim-scenarios --clock-start``) are keyed apart.
LOCKSTEP_CLOCK_START_S = 1000.0
#: The clock start of a lockstep row written before the start was fixed: the real
#: ``time.monotonic()`` of its moment, which nobody recorded. Such rows are keyed apart from every
#: row flown since (they cannot be flown again).
UNKNOWN_CLOCK = "unknown"
#: A flight's key in a results file: ``(seed, flavour)``, or ``(seed, flavour, "baseline")``.
RowKey = tuple[Any, ...]
#: The unsafe-rate upper bound the runner reports the distance to (further clean flights needed).
TARGET_UPPER = 0.01


def binomial_interval(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Exact two-sided (Clopper-Pearson) interval for a proportion of ``k`` in ``n``; (0, 1) when
    ``n`` is 0. The same as ``scipy.stats.binomtest(k, n).proportion_ci(confidence, "exact")``."""
    if n < 0 or not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n, got k={k}, n={n}")
    alpha = 1.0 - confidence
    lo = 0.0 if k == 0 else float(beta.ppf(alpha / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - alpha / 2, k + 1, n - k))
    return lo, hi


def further_clean_flights(k: int, n: int, target: float = TARGET_UPPER,
                          confidence: float = CONFIDENCE) -> int:
    """How many more flights, all clean (no further event), bring the upper bound of ``k`` in
    ``n`` under ``target``: the least ``m >= 0`` with ``upper(k, n + m) < target``."""
    def below(m: int) -> bool:
        return binomial_interval(k, n + m, confidence)[1] < target

    if below(0):
        return 0
    hi = 1
    while not below(hi):
        hi *= 2
    lo = hi // 2  # not below at lo (or lo == 0, checked above)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if below(mid):
            hi = mid
        else:
            lo = mid
    return hi


def _proportion(k: int, n: int) -> dict[str, Any]:
    lo, hi = binomial_interval(k, n)
    return {"count": k, "rate": None if n == 0 else round(k / n, 6),
            "ci95": [round(lo, 6), round(hi, 6)]}


def summarise_rows(rows: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """The scenario runner's figures over flight rows (see the module docstring for what counts)."""
    rows = list(rows)
    clean = [r for r in rows if not r.get("starved")]
    starved = [r for r in rows if r.get("starved")]

    def count(rs: list[dict[str, Any]], outcome: str) -> int:
        return sum(r.get("outcome") == outcome for r in rs)

    n = len(clean)
    unsafe = count(clean, "unsafe")
    strikes = sum(bool(r.get("strike")) for r in clean)
    landings = count(clean, "safe") + unsafe
    landed_any = [r for r in rows if r.get("outcome") in ("safe", "unsafe")]
    clear = [r["clearance_m"] for r in landed_any if r.get("clearance_m") is not None]
    times = [r["time_to_touchdown_s"] for r in clean if r.get("time_to_touchdown_s") is not None]
    climbs = [r["max_climb_m"] for r in rows if r.get("max_climb_m") is not None]
    changes = [phase_changes(r) for r in clean]
    judged = [r for r in clean if r.get("outcome") in ("safe", "unsafe") and r.get("in_free_area") is not None]
    u, s, c = _proportion(unsafe, n), _proportion(strikes, n), _proportion(landings, n)
    with_losses = [r for r in clean if isinstance(r.get("zone_losses"), int)]
    on_ground = [r for r in clean if isinstance(r.get("unlandable_touchdown"), bool)]
    last = _last_metres([r for r in clean if r.get("outcome") in ("safe", "unsafe")])
    return {
        "total": len(rows), "safe": count(clean, "safe"), "handbacks": count(clean, "handback"),
        "unsafe": unsafe, "timeouts": count(clean, "timeout"),
        "min_clearance_m": round(min(clear), 3) if clear else None,
        "median_time_to_touchdown_s": round(float(np.median(times)), 2) if times else None,
        "max_climb_m": round(max(climbs), 2) if climbs else None,
        "median_last_metres_s": last,
        "median_phase_changes": float(np.median(changes)) if changes else None,
        "max_phase_changes": max(changes) if changes else None,
        "starved": len(starved),
        "starved_outcomes": {o: count(starved, o) for o in ("safe", "unsafe", "handback", "timeout")
                             if count(starved, o)},
        "starved_strikes": sum(bool(r.get("strike")) for r in starved),
        "clean_flights": n,
        "strikes": strikes,
        "companion_landings": landings,
        "companion_landings_in_free_area": sum(bool(r["in_free_area"]) for r in judged),
        "companion_landings_judged_for_area": len(judged),
        "touchdowns_judged_for_surface": len(on_ground),
        "unlandable_touchdowns": sum(r["unlandable_touchdown"] for r in on_ground) if on_ground else None,
        "companion_landings_unlandable": sum(r["unlandable_touchdown"] for r in on_ground
                                             if r.get("outcome") in ("safe", "unsafe")) if on_ground else None,
        "zone_losses": sum(r["zone_losses"] for r in with_losses) if with_losses else None,
        "zone_losses_r0_free": sum(int(r.get("zone_losses_r0_free") or 0) for r in with_losses)
        if with_losses else None,
        "unsafe_rate": u["rate"], "unsafe_rate_ci95": u["ci95"], "unsafe_rate_upper95": u["ci95"][1],
        "strike_rate": s["rate"], "strike_rate_ci95": s["ci95"], "strike_rate_upper95": s["ci95"][1],
        "companion_landing_rate": c["rate"], "companion_landing_rate_ci95": c["ci95"],
        "clean_flights_to_unsafe_upper95_below_1pct": further_clean_flights(unsafe, n),
    }


def _last_metres(rows: list[dict[str, Any]]) -> float | None:
    """The median of the rows' ``last_metres_s`` (s), None when none carries it."""
    t = [float(r["last_metres_s"]) for r in rows if isinstance(r.get("last_metres_s"), (int, float))]
    return round(float(np.median(t)), 2) if t else None


def phase_changes(row: dict[str, Any]) -> int:
    """How many times the flight's landing controller changed phase (its recorded phase-change
    events: ``FlightResult.phases`` lists the phase each entered)."""
    return len(row.get("phases") or [])


def summarise_baseline(rows: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """The baseline's figures (flights with the autopilot's own failsafe alone): every touchdown
    judged on the truth like the companion's. ``strikes`` and their rate (with its exact 95 %
    interval) per clean flight, the minimum clearance over every touchdown, the median time from
    trigger to touchdown, the flights that did not touch down in time."""
    rows = list(rows)
    s = summarise_rows(rows)
    clear = [r["clearance_m"] for r in rows if r.get("clearance_m") is not None]
    keys = ("total", "clean_flights", "starved", "timeouts", "strikes", "strike_rate", "strike_rate_ci95",
            "strike_rate_upper95", "median_time_to_touchdown_s", "max_climb_m",
            "touchdowns_judged_for_surface", "unlandable_touchdowns")
    return {**{k: s[k] for k in keys}, "min_clearance_m": round(min(clear), 3) if clear else None,
            "median_last_metres_s": _last_metres([r for r in rows if not r.get("starved")])}


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.2f} %"


def summary_text(summary: dict[str, Any]) -> str:
    """The summary for people (the same figures as ``--json``)."""
    n = summary["clean_flights"]
    lines = [
        f"safe landings {summary['safe']}/{summary['total']}, unsafe {summary['unsafe']}, "
        f"handbacks {summary['handbacks']}, timeouts {summary['timeouts']}, starved {summary['starved']}",
    ]
    if summary["starved"]:
        lines.append(f"STARVED: {summary['starved']} flight(s) were starved of CPU (outcomes "
                     f"{summary['starved_outcomes']}, strikes {summary['starved_strikes']}); they are left "
                     "out of the counts and rates below. "
                     "Fly fewer at once (--workers) or give each more CPU (--cpus-per-flight).")
    lines.append(f"minimum clearance at touchdown: {summary['min_clearance_m']} m; median time from "
                 f"trigger to touchdown: {summary['median_time_to_touchdown_s']} s; highest climb "
                 f"above the altitude at the trigger: {summary['max_climb_m']} m")
    for label, key, count in (("unsafe landings", "unsafe_rate", summary["unsafe"]),
                              ("strikes (anyone within r_0 at touchdown)", "strike_rate", summary["strikes"]),
                              ("companion landings", "companion_landing_rate", summary["companion_landings"])):
        lo, hi = summary[f"{key}_ci95"]
        lines.append(f"{label}: {count}/{n} clean flights = {_pct(summary[key])} "
                     f"(95 % exact interval {_pct(lo)} to {_pct(hi)})")
    lines.append(f"phase changes per flight: median {summary['median_phase_changes']}, "
                 f"most {summary['max_phase_changes']}")
    if summary.get("median_last_metres_s") is not None:
        lines.append(f"the companion's landings took a median {summary['median_last_metres_s']} s over their last "
                     "3.5 m (committed, the camera seeing less than r_0: a walker's time to reach the point unseen)")
    if summary.get("companion_landings_judged_for_area"):
        lines.append(f"companion landings on ground nobody walks into (the free area, or beyond the crowd): "
                     f"{summary['companion_landings_in_free_area']} of {summary['companion_landings_judged_for_area']}")
    if summary.get("unlandable_touchdowns") is not None:
        lines.append(f"touchdowns with the vehicle's footprint on unlandable ground (a tree, a bench, a car, a "
                     f"roof; the ground's truth): {summary['unlandable_touchdowns']} of "
                     f"{summary['touchdowns_judged_for_surface']}, the companion's landings "
                     f"{summary['companion_landings_unlandable']}")
    if summary.get("zone_losses") is not None:
        lines.append(f"zones given up while over them: {summary['zone_losses']}, of which "
                     f"{summary['zone_losses_r0_free']} with nobody within r_0 of the vehicle by the truth")
    m = summary["clean_flights_to_unsafe_upper95_below_1pct"]
    lines.append("the unsafe rate's upper 95 % bound is under 1 %" if m == 0 else
                 f"{m} further clean flights would bring the unsafe rate's upper 95 % bound under 1 %")
    return "\n".join(lines)


def baseline_text(summary: dict[str, Any]) -> str:
    """The companion's strikes beside the baseline's (``summary["baseline"]``), for people."""
    b = summary["baseline"]
    lines = []
    for label, s in (("companion", summary), ("baseline (autopilot's failsafe alone, no companion)", b)):
        lo, hi = s["strike_rate_ci95"]
        lines.append(f"strikes, {label}: {s['strikes']}/{s['clean_flights']} clean flights = "
                     f"{_pct(s['strike_rate'])} (95 % exact interval {_pct(lo)} to {_pct(hi)})")
    lines[-1] += (f"; minimum clearance at touchdown {b['min_clearance_m']} m, median time to touchdown "
                  f"{b['median_time_to_touchdown_s']} s, no touchdown {b['timeouts']}"
                  + (f", last 3.5 m in a median {b['median_last_metres_s']} s"
                     if b.get("median_last_metres_s") is not None else ""))
    ratio = summary.get("strikes_vs_baseline")
    none = "- (the baseline struck nobody)" if b["strikes"] == 0 else "-"
    lines.append("companion strike rate / baseline strike rate: "
                 + (none if ratio is None else f"{ratio:.2f}"))
    return "\n".join(lines)


# ---- the results file ------------------------------------------------------------------------

def row_key(row: dict[str, Any]) -> RowKey:
    """What identifies a flight in a results file: its seed and the autopilot it flew with,
    ``"baseline"`` for a baseline flight (so neither kind ever stands for the other on resume),
    the service settings it flew with (``settings``, from ``--set``) when it had any, then each
    way it was flown apart from the scenarios' own (:func:`flown_apart`: the LAND speed, the
    crossing window, the watch, a lockstep clock's start), and ``"lockstep"`` for a flight flown
    on the simulated clock (``sim.flights.lockstep``). The spelling of every part is what results files
    already hold: a changed one would make old files fly their seeds again."""
    key: tuple[Any, ...] = (int(row["seed"]), str(row["flavour"]))
    if row.get("baseline"):
        key = (*key, BASELINE)
    if row.get("settings"):
        key = (*key, "set:" + ";".join(str(s) for s in row["settings"]))
    key = (*key, *(f"{part.key}:{part.value}" for part in flown_apart(row)))
    if row.get("lockstep"):
        key = (*key, "lockstep")
    return key


@dataclass(frozen=True)
class Apart:
    """One way a row was flown apart from the scenarios' own: its part of the row's key
    (``key:value``, :func:`row_key`) and of a comparison's settings line (``name=value``,
    ``sim.evidence.compare``)."""

    key: str
    name: str
    value: str


def flown_apart(row: dict[str, Any]) -> list[Apart]:
    """How a row was flown apart from the scenarios' own, in key order: the LAND speed, the
    crossing window, the watch before the failsafe, the camera (``--camera``), the share of
    runners in the crossing world (``--runners``), a lockstep flight's clock start when
    it is not :data:`LOCKSTEP_CLOCK_START_S` (``unknown`` for a lockstep row written before the
    start was fixed), the link latency added each way (``link_latency_s``, ``--link-latency``),
    and the ground when it is not the drawn one (``ground``: ``photo``; rows of the drawn
    ground carry no such field). The one walk of those fields for keys and for comparisons."""
    out: list[Apart] = []
    land = other_land_speed(row)
    if land is not None:
        out.append(Apart("land", "land_speed", f"{land:g}"))
    window = other_crossing_window(row)
    if window is not None:
        out.append(Apart("cross", "crossing_window", f"{window[0]:g}-{window[1]:g}"))
    watch = other_watch(row)
    if watch is not None:
        out.append(Apart("watch", "watch_s", f"{watch:g}"))
    camera = row.get("camera")
    if camera and camera != DEFAULT_CAMERA:
        out.append(Apart("camera", "camera", str(camera)))
    runners = row.get("runners")
    if runners:  # rows flown without runners have no such field
        out.append(Apart("runners", "runners", f"{float(runners):g}"))
    clock = other_clock_start(row)
    if clock is not None:
        out.append(Apart("clock", "clock_start_s", clock if isinstance(clock, str) else _exact(clock)))
    latency = row.get("link_latency_s")
    if latency:  # rows flown without added latency have no such field
        out.append(Apart("latency", "link_latency_s", _exact(float(latency))))
    ground = row.get("ground")
    if ground is not None and ground != "procedural":
        out.append(Apart("ground", "ground", str(ground)))
    return out


def _exact(value: float) -> str:
    """``value`` as short as ``:g`` writes it where that reads back the same number, else in
    full: two clock starts a millisecond apart are two keys."""
    short = f"{value:g}"
    return short if float(short) == value else repr(value)


def other_land_speed(row: dict[str, Any]) -> float | None:
    """The LAND speed a row was flown at (m/s) when it is not the scenarios' own
    (:data:`SCENARIO_LAND_SPEED`), else None."""
    land = row.get("land_speed")
    return None if land is None or float(land) == SCENARIO_LAND_SPEED else float(land)


def other_crossing_window(row: dict[str, Any]) -> tuple[float, float] | None:
    """The crossing world's window a row was flown with (seconds after the failsafe) when it is
    not the scenarios' own (:data:`SCENARIO_CROSSING_WINDOW_S`), else None."""
    window = row.get("crossing_window")
    if window is None:
        return None
    lo, hi = (float(v) for v in window)
    return None if (lo, hi) == SCENARIO_CROSSING_WINDOW_S else (lo, hi)


def other_watch(row: dict[str, Any]) -> float | None:
    """How long the service watched before the failsafe (s) when it was not the scenarios' own
    (:data:`SCENARIO_WATCH_S`), else None. Rows written before the field existed watched the
    scenarios' own."""
    watch = row.get("watch_s")
    return None if watch is None or float(watch) == SCENARIO_WATCH_S else float(watch)


def other_clock_start(row: dict[str, Any]) -> float | str | None:
    """Where a lockstep row's simulated clock started (s) when it is not
    :data:`LOCKSTEP_CLOCK_START_S`; :data:`UNKNOWN_CLOCK` for a lockstep row without the field
    (written before the start was fixed, on the real clock's reading of its moment); None for the
    default and for every real-time row (its clock is the machine's)."""
    if not row.get("lockstep"):
        return None
    start = row.get("clock_start_s")
    if start is None:
        return UNKNOWN_CLOCK
    return None if float(start) == LOCKSTEP_CLOCK_START_S else float(start)


#: The distributions whose code computes a flight (the model, the vision, the numbers, the link):
#: another version of any of them rounds differently, which can change a verdict as another
#: clock start does, so every row says which flew it.
SOFTWARE = ("companion-slz", "numpy", "onnxruntime", "opencv-python-headless", "scipy", "pymavlink")


@functools.lru_cache(maxsize=1)
def software() -> dict[str, str]:
    """What flew a row: Python's version, each of :data:`SOFTWARE`'s (``?`` where one is not
    installed as a distribution), and ``git``, the commit of the checkout the ``companion`` package
    runs from (``+dirty`` when its tracked files differ from it; absent outside a checkout or
    without git). Asked once per process."""
    import platform
    import subprocess
    from importlib import metadata

    out = {"python": platform.python_version()}
    for name in SOFTWARE:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "?"
    import companion

    here = Path(companion.__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=here, capture_output=True,
                              text=True, timeout=10)
        if head.returncode == 0 and head.stdout.strip():
            dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                   capture_output=True, text=True, timeout=10)
            out["git"] = head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass  # no git here: the versions still say what computed
    return out


def read_rows(path: Path) -> tuple[list[dict[str, Any]], int]:
    """The rows of a results file, and how many lines could not be read (a line cut short by a
    crash, say); a missing file has none."""
    rows: list[dict[str, Any]] = []
    bad = 0
    try:
        text = path.read_text()
    except FileNotFoundError:
        return rows, 0
    for line in text.splitlines():
        if not line.strip():
            continue
        try:
            row = json.loads(line)
            row_key(row)
        except (ValueError, KeyError, TypeError):
            bad += 1
            continue
        rows.append(row)
    return rows, bad


class ResultsFile:
    """A JSON Lines results file open for appending: each row is written, flushed and synced as
    it comes, so a crash loses at most the flight in the air."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        torn = path.exists() and path.stat().st_size > 0 and not path.read_bytes().endswith(b"\n")
        self._f: IO[str] = open(path, "a")
        if torn:  # a line cut short by a crash: end it, so the next row starts on its own line
            self._f.write("\n")

    def append(self, row: dict[str, Any]) -> None:
        self._f.write(json.dumps(row, default=_json_default) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> ResultsFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        v = o.item()
        return None if isinstance(v, float) and not math.isfinite(v) else v
    if isinstance(o, (tuple, Path)):
        return list(o) if isinstance(o, tuple) else str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
