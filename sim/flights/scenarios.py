"""``companion sim-scenarios``: fly N seeded random scenarios and report the safety figures.

Each seed draws a scenario (``scenario``): autopilot flavour, hover altitude, where the one free
circle lies in view and how large it is, the failsafe that fires, PX4's home-origin offset, and
the world. The mix of worlds:

- ``dense`` (one seed in six, half of them): people everywhere, no safe zone at all (the right
  answer there is a handback, after the search found nothing);
- ``dense_beyond`` (the other half of the dense seeds): the same crowd with one free circle
  (radius 6-8 m) 22-30 m away, out of the first view: the search must find it;
- ``crossing`` (a third of the others, about 28 % of seeds): the free area's crowd, and 2-4
  walkers at 1.0-1.5 m/s who cross the free circle, the zone the companion lands in, 4-24 s
  after the failsafe, that is during the descent, and walk on out of it
  (``sim.world.crowd.add_crossing_walkers``);
- ``free_area`` (the rest, about 55 %): a crowd around one free circle in view.

Every draw added later is drawn after the earlier ones, so every seed keeps the scene it had:
the ``crossing`` draw came last and only adds walkers to a ``free_area`` seed's scene. The
``intrusion`` world (walkers who walk into the free circle and stay) is flown by the SITL tests,
not drawn here.

Every flight is judged on the simulator's truth (see ``sim.flights.flight``), handbacks included. Prints
safe landings / total, the minimum clearance at touchdown, the median time from trigger to
touchdown and the handbacks; ``--json`` prints one JSON object with ``total, safe, handbacks,
unsafe, min_clearance_m, median_time_to_touchdown_s, max_climb_m`` (and more; ``max_climb_m`` is
the most any flight rose above its altitude at the trigger, on the truth; ``strikes``, touchdowns
with somebody within r_0 whoever landed; ``median_phase_changes``, ``max_phase_changes``), with
the rates and their exact 95 % bounds of ``sim.flights.results``.

``--baseline`` flies every seed twice: with the companion, and with the autopilot's own failsafe
alone (no service: ``FlightSpec.companion = False``), judged the same way. The JSON then adds
``baseline`` (the baseline's ``total``, ``strikes``, strike rate and bounds, ...) and
``strikes_vs_baseline`` (the companion's strike rate over the baseline's); the companion's keys
stay the companion's alone. Baseline rows say ``baseline: true`` in a results file and are
resumed apart from the companion's.

At scale (docs/scale.md): ``--workers N`` flies N seeds at once on this machine, ``--ray ADDRESS``
sends each flight to a Ray cluster as a task (``--ray auto``: a local Ray), each flight with its
own processes and node-wide claimed ports (``sim.flights.flight.reserve_port``). ``--out FILE.jsonl``
appends each flight's row as it ends and, run again, flies only the seeds not in it yet; the
summary is then computed from the file. A flight whose service could not keep its frame rate is
flagged **starved** and kept out of the clean counts. Before the first companion flight flies
here (not on Ray), the run times the flights' own pipeline at the camera's rate for a few seconds
and says on stderr whether this machine leaves its flights room (``machine_check`` in the JSON;
``--no-machine-check`` skips it); a model that does not load is exit 2 then, before anything flies.

``--land-speed M/S`` flies the simulated autopilot's LAND at that speed (ArduPilot ``LAND_SPEED``,
PX4 ``MPC_LAND_SPEED``; the scenarios' own 1 m/s is faster than either autopilot's default, 0.5
and 0.7 m/s, so its blind last metres are shorter than a vehicle left at defaults has); rows
record it, and resume only from rows flown at the same speed.

``--crossing-window FROM-TO`` draws the crossing world's walkers' crossings over that many seconds
after the failsafe instead of its own 4-24 s (timed for the scenarios' landings at 1 m/s), with as
many more walkers as keep the same rate: landings of different lengths (another LAND speed, the
last metres by the rangefinder) then meet crossings at any time of their descent, not the ones
the window was timed for. Rows record it, and resume only from rows flown with the same window.

``--watch-s S`` lets the service watch the crowd S seconds, the vehicle hovering where it starts,
before the failsafe, instead of the scenarios' own 4 s: a service that ran the whole flight has
seen more of where people walk than that, and its risk map remembers it. The crowd walks on
meanwhile, so a seed meets its failsafe over the same scene but another moment of its crowd, and
the battery has spent the hover. Rows record it, and resume only from rows flown with the same
watch.

``--lockstep`` flies every seed on the simulated clock (``sim.flights.lockstep``): the service in the
flight's own process, every frame costing the same simulated time, so a seed flies the same
flight every time, one at a time, two at a time or on Ray, and no flight can be starved. It is
the tool for comparing two versions of the landing logic and runs 2-5 times faster than real time;
the real-time flights stay the test of the service as a vehicle runs it. Rows say ``lockstep:
true`` and resume only from lockstep rows. A flight is chaotic: any change to the code or the
settings also changes how its times round, and can change a verdict the change has nothing to do
with. ``--clock-start S[,S...]`` flies each seed on a clock that starts at S (the fixed
``sim.flights.results.LOCKSTEP_CLOCK_START_S`` by default), which perturbs nothing but that rounding:
the verdicts that change between two starts of one code are how far a seed's verdict is from
chance, the yardstick for any comparison (docs/scale.md, "How far one flight is from the next").
Rows record ``clock_start_s`` and resume only from rows flown from the same start; lockstep rows
written before the start was fixed (it was the machine's uptime) are never resumed from.

``--ground photo`` flies every seed over real nadir photos instead of the drawn ground: the
held-out semantic-drone photos of ``--photos DIR`` (``../shared/data/semantic_drone/full`` beside
the checkout by default) laid as a mosaic at their own ground sampling distance
(``sim.world.photo_ground``), the same worlds placed where the free circle is landable by the
class maps with none of the photos' people in it, those people counted by the judge, the
walkers drawn as real silhouettes and four more crossing open ground (``sim.world.photo_people``;
docs/photo-world.md). ``touchdown_surfaces`` are then class-map names. A missing or malformed
folder is exit 2 before anything flies. Rows say ``"ground": "photo"`` and resume only from such
rows; the drawn ground's rows carry no such field (``--ground procedural``, the default).

``--set KEY=VALUE`` (repeatable) flies every seed with that service setting, as ``companion run
--set`` takes it (``--set model.path=my.onnx`` flies a researcher's own model in closed loop). A bad
key or value, or a model file that is not there, is exit 2 before anything flies. Rows record the
settings (``settings``), and a results file resumes a seed only from a row flown with the same
settings, so two experiments never mix in one file.

Exit status: 0 all flights clean and none unsafe; 1 an unsafe landing (starved or not); 2 bad
arguments or no way to fan out; 3 no unsafe landing but the evidence is incomplete (a flight
starved, or could not fly: run again with the same ``--out`` to retry those).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import math
import resource
import socket
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from companion import config as settings
from companion.parallel import ParallelError, default_workers, fan_out
from sim.flights.flight import STARVED_FRAME_SHARE, FlightSpec, fly
from sim.flights.results import (
    LOCKSTEP_CLOCK_START_S,
    SCENARIO_LAND_SPEED,
    SCENARIO_WATCH_S,
    ResultsFile,
    RowKey,
    baseline_text,
    read_rows,
    row_key,
    software,
    summarise_baseline,
    summarise_rows,
    summary_text,
)
from sim.flights.spec import GROUNDS, camera_name, parse_camera_and_photos
from sim.flights.spec import service_settings as flight_settings


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
    # one (1.48 m in PX4's SIH): frame-6 targets would be read wrongly. Drawn after the scene, so
    # the earlier draws (and every seed's scene) stay what they were.
    offset_m = float(rng.uniform(0.0, 3.0)) * (1.0 if rng.random() < 0.5 else -1.0)
    # Walkers crossing the free circle during the descent, in a third of the free-area seeds:
    # drawn last (for every seed), so everything drawn before stays; such a seed keeps its crowd,
    # circle and vehicle, and gains the walkers (drawn from the seed in sim.world.crowd).
    if rng.random() < CROSSING_SHARE and world == "free_area":
        world = "crossing"
    # Half the dense crowds gain one free circle out of the first view, 22-30 m away, for the
    # search to find (issue 11, item 4); the other half keep no free ground anywhere, where the
    # right answer is still the handback. Drawn last, for every seed, so every earlier draw stays.
    beyond = rng.random() < BEYOND_SHARE
    far, far_bearing, far_radius = rng.uniform(22.0, 30.0), rng.uniform(0, 2 * math.pi), rng.uniform(6.0, 8.0)
    if beyond and world == "dense":
        world = "dense_beyond"
        offset = (-far * math.cos(far_bearing), -far * math.sin(far_bearing))
        radius = float(far_radius)
    return FlightSpec(flavour=fl, world=world, seed=seed, altitude_m=alt, start_offset_m=offset,
                      free_radius_m=radius, failsafe=failsafe, home_origin_offset_m=offset_m)


#: The fastest LAND ``--land-speed`` takes (m/s). ArduPilot's LAND_SPEED spans 0.3-2 m/s and PX4's
#: MPC_LAND_SPEED 0.6 m/s up to its MPC_Z_VEL_MAX_DN; 3 m/s leaves room for either.
MAX_LAND_SPEED = 3.0
#: ``--watch-s`` bounds (s): the service needs a second of frames before it has seen anything, and
#: the longest watch keeps one flight within minutes of simulated time.
MIN_WATCH_S = 1.0
MAX_WATCH_S = 600.0

#: ``--clock-start`` bounds (s): above 0, as a machine's ``time.monotonic()`` is (0 stands for "no
#: time" in places), and below about four months of uptime.
MIN_CLOCK_START_S = 1.0
MAX_CLOCK_START_S = 1.0e7

#: ``--link-latency`` bound (s, one way): a link slower than this is no link to land by.
MAX_LINK_LATENCY_S = 5.0

#: The share of free-area seeds whose free circle walkers cross during the descent (``crossing``).
CROSSING_SHARE = 1 / 3
#: The share of dense-crowd seeds with one free circle out of the first view (``dense_beyond``).
BEYOND_SHARE = 1 / 2

#: CPUs one flight is given by default. A flight averages 0.8-0.9 of a CPU (the service and this
#: simulator together), but by default its service runs the density model on two threads: two
#: such flights on 2 CPUs took 2.5 times as long per frame as one alone and changed verdicts
#: (docs/scale.md), so a flight gets 2.
CPUS_PER_FLIGHT = 2.0


def model_threads(cpus_per_flight: float) -> int:
    """The onnxruntime threads a flight's service gets (``model.threads``): the whole CPUs it is
    given, at least one, so that N flights at once never run more model threads than the CPUs
    they were given."""
    return max(1, int(cpus_per_flight))


@dataclasses.dataclass(frozen=True)
class FlightJob:
    """One flight to fly: a seed's scenario, its autopilot forced or drawn, with the companion or
    the baseline (the autopilot's own failsafe alone), and (for tests) fields of its
    :class:`FlightSpec` replaced."""

    seed: int
    flavour: str | None = None
    overrides: tuple[tuple[str, Any], ...] = ()
    baseline: bool = False
    #: ``model.threads`` for the flight's service (None: the service's default, 2).
    threads: int | None = None
    #: ``KEY=VALUE`` service settings (``--set``) the flight flies with; part of its key.
    service_set: tuple[str, ...] = ()
    #: The simulated autopilot's LAND speed (m/s, ``--land-speed``; None: the scenario's own,
    #: ``sim.flights.results.SCENARIO_LAND_SPEED``); part of its key when it is another.
    land_speed: float | None = None
    #: The crossing world's window (s after the failsafe, ``--crossing-window``; None: the
    #: world's own, ``sim.world.crowd.CROSSING_WINDOW_S``); part of its key when it is another.
    crossing_window: tuple[float, float] | None = None
    #: The share of the crossing world's walkers who run or cycle (``--runners``, 0-1; 0: none, the
    #: scenarios' own until the yardstick is flown with them); part of its key when it is not 0.
    runners: float = 0.0
    #: Fly on the simulated clock (``sim.flights.lockstep``); part of its key.
    lockstep: bool = False
    #: How long the service watches before the failsafe (s, ``--watch-s``; None: the scenarios'
    #: own, ``sim.flights.results.SCENARIO_WATCH_S``); part of its key when it is another.
    watch_s: float | None = None
    #: Where a lockstep flight's simulated clock starts (s, ``--clock-start``; None: the fixed
    #: ``sim.flights.results.LOCKSTEP_CLOCK_START_S``); part of its key when it is another.
    clock_start: float | None = None
    #: One-way MAVLink latency added each way from the moment the service is ready (s,
    #: ``--link-latency``; None: none); part of its key when it is set.
    link_latency: float | None = None
    #: The camera (``--camera``: lens model and horizontal field of view in degrees) of the simulator
    #: and the service as one (None: the scenarios' own, pinhole:70); part of its key when it is another.
    camera: tuple[str, float] | None = None
    #: The ground (``--ground``): ``procedural`` or ``photo`` with its ``photos`` folder; part of
    #: its key when it is not the drawn one.
    ground: str = "procedural"
    photos: str | None = None

    def spec(self) -> FlightSpec:
        spec = scenario(self.seed, self.flavour)
        if self.ground != "procedural":
            spec = dataclasses.replace(spec, ground=self.ground, photos=self.photos)
        if self.baseline:
            spec = dataclasses.replace(spec, companion=False)
        if self.land_speed is not None:
            spec = dataclasses.replace(spec, land_speed=self.land_speed)
        if self.crossing_window is not None:
            spec = dataclasses.replace(spec, crossing_window=self.crossing_window)
        if self.runners:
            spec = dataclasses.replace(spec, runners=self.runners)
        if self.watch_s is not None:
            spec = dataclasses.replace(spec, watch_s=self.watch_s)
        if self.link_latency is not None:
            spec = dataclasses.replace(spec, latency_ms=self.link_latency * 1000.0)
        if self.camera is not None:
            spec = dataclasses.replace(spec, camera_model=self.camera[0], hfov_deg=self.camera[1])
        if self.overrides:
            spec = dataclasses.replace(spec, **dict(self.overrides))
        if self.service_set:
            spec = dataclasses.replace(spec, service_set=(*spec.service_set, *self.service_set))
        if self.threads is not None and not any(s.startswith("model.threads=") for s in spec.service_set):
            spec = dataclasses.replace(spec, service_set=(*spec.service_set, f"model.threads={self.threads}"))
        if self.lockstep:
            spec = dataclasses.replace(spec, lockstep=True)
            if self.clock_start is not None:
                spec = dataclasses.replace(spec, clock_start_s=self.clock_start)
        return spec

    def model_threads(self) -> int | None:
        """The ``model.threads`` its service flies with: the last one its settings give (a
        ``--set`` or a test's override wins over :attr:`threads`), None for the service's
        default."""
        given = [item.partition("=")[2] for item in self.spec().service_set if item.startswith("model.threads=")]
        if not given:
            return None
        try:
            return int(given[-1])
        except ValueError:
            return None

    def key(self) -> RowKey:
        """Its key in a results file (``sim.flights.results.row_key``): a baseline flight's is its own,
        and so is one flown with other settings or another LAND speed."""
        spec = self.spec()
        return row_key({"seed": self.seed, "flavour": spec.flavour, "baseline": self.baseline,
                        "settings": list(self.service_set), "land_speed": spec.land_speed,
                        "crossing_window": list(spec.crossing_window), "watch_s": spec.watch_s,
                        "lockstep": self.lockstep, "clock_start_s": spec.clock_start_s if self.lockstep else None,
                        "camera": camera_name(spec), **link_latency_field(spec), "ground": spec.ground,
                        **({"runners": spec.runners} if spec.runners else {})})


def _cpu_s() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def fly_seed(job: FlightJob) -> dict[str, Any]:
    """Fly one job and return its row: ``FlightResult.as_dict()`` plus the scenario's altitude and
    failsafe, the flight's wall time, the CPU seconds it used (this process and the service) and
    the host it flew on. Module-level, for worker processes and Ray tasks."""
    spec = job.spec()
    t0, cpu0 = time.monotonic(), _cpu_s()
    if spec.lockstep:
        from sim.flights.lockstep import fly_in_process

        result = fly_in_process(spec)
    else:
        result = asyncio.run(fly(spec))
    row = result.as_dict()
    row.update(altitude_m=round(spec.altitude_m, 2), failsafe=spec.failsafe,
               wall_s=round(time.monotonic() - t0, 2), cpu_s=round(_cpu_s() - cpu0, 2),
               host=socket.gethostname(), model_threads=job.model_threads(), settings=list(job.service_set),
               land_speed=spec.land_speed, crossing_window=list(spec.crossing_window), watch_s=spec.watch_s,
               clock_start_s=spec.clock_start_s if spec.lockstep else None, software=software())
    row.update(link_latency_field(spec))
    return row


def link_latency_field(spec: FlightSpec) -> dict[str, float]:
    """``{"link_latency_s": S}`` for a flight flown with link latency (one way, each way, s), else
    nothing: rows flown without any keep exactly the fields they always had."""
    return {"link_latency_s": spec.latency_ms / 1000.0} if spec.latency_ms > 0 else {}


#: The machine check times the pipeline alone; a flight runs the simulator and the service's
#: recorder beside it. Measured on the 2-core development VM (docs/scale.md, "Before flying"):
#: flights' frame p95 was 1.0-1.51 times the check's, so a check above this share of the limit
#: (1 / 1.5) is called tight: it errs toward warning.
TIGHT_SHARE = 0.66


@dataclasses.dataclass(frozen=True)
class MachineCheck:
    """What this machine gives a flight's pipeline before anything flies (:func:`machine_check`):
    its whole time per frame (ms, median and 95th percentile) at the camera's rate, against the
    time above which a flight counts as starved (``sim.flights.flight.starved``). The check is a lower
    bound on a flight's figure: the flight runs the simulator beside the pipeline."""

    frame_ms_p50: float
    frame_ms_p95: float
    limit_ms: float
    fps: float
    threads: int

    @property
    def starves(self) -> bool:
        """Even alone the pipeline is over the limit: every flight will be starved."""
        return self.frame_ms_p95 > self.limit_ms

    @property
    def tight(self) -> bool:
        """Under the limit alone, but by less than flights add to it (:data:`TIGHT_SHARE`)."""
        return not self.starves and self.frame_ms_p95 > TIGHT_SHARE * self.limit_ms

    def as_dict(self) -> dict[str, Any]:
        return {"frame_ms_p50": round(self.frame_ms_p50, 1), "frame_ms_p95": round(self.frame_ms_p95, 1),
                "limit_ms": round(self.limit_ms, 1), "fps": self.fps, "model_threads": self.threads,
                "starves": self.starves, "tight": self.tight}

    def text(self, workers: int) -> str:
        head = (f"machine check: the flights' pipeline takes {self.frame_ms_p50:.0f} ms a frame here "
                f"(95th percentile {self.frame_ms_p95:.0f} ms; {self.fps:g} Hz, {self.threads} model thread(s), "
                f"nothing else of the flight running)")
        room = ("A faster machine, or a faster model (--set model.path=...; the model card gives the int8 "
                "file's recall cost), gives them room.")
        if self.starves:
            text = (f"{head}, above the {self.limit_ms:.0f} ms at which a flight counts as starved: expect "
                    f"every flight starved (flown, flagged, and left out of the clean counts). {room}")
        elif self.tight:
            text = (f"{head}: close to the {self.limit_ms:.0f} ms at which a flight counts as starved, and a "
                    "flight, which runs the simulator beside it, takes more: expect starved flights. " + room)
        else:
            text = f"{head}; a flight counts as starved above {self.limit_ms:.0f} ms."
        if workers > 1:
            text += f" With {workers} flights at once each gets less than this one did."
        return text


def machine_check(job: FlightJob, frames: int = 40) -> MachineCheck:
    """Time the pipeline a job's service would run (its settings, its model and threads, the
    simulator's 640x480 frames) at the camera's rate on this machine, on the bench's crowd frame
    (``companion.bench.paced_frame_ms``): a few seconds that tell, before an hour of flights,
    whether they can be clean here. Raises ``DensityModelError`` (naming the file) when the
    model does not load."""
    from companion.bench import bench_frame, paced_frame_ms
    from companion.service.parts import build_pipeline, load_landability, load_model

    spec = job.spec()
    # The simulator's camera sends 640x480 frames; the rest is what the service is started with.
    overrides: dict[str, Any] = {"camera.width": 640, "camera.height": 480}
    overrides.update(settings.parse_assignment(item) for item in flight_settings(spec))
    cfg = settings.load(None, overrides)
    model = load_model(cfg)
    pipe = build_pipeline(cfg, model, load_landability(cfg))
    frame, _ = bench_frame(cfg.camera.width, cfg.camera.height)
    ms = paced_frame_ms(pipe, frame, spec.fps, frames)
    return MachineCheck(float(np.median(ms)), float(np.percentile(ms, 95)),
                        STARVED_FRAME_SHARE * 1000.0 / spec.fps, spec.fps, cfg.model.threads)


def plan(jobs: list[FlightJob], done_rows: list[dict[str, Any]]) -> tuple[list[FlightJob], dict[RowKey, dict]]:
    """The jobs still to fly, and the rows of the others already in a results file (by key; the
    last row of a key wins; a baseline row never stands for a companion flight, nor the reverse)."""
    done = {row_key(r): r for r in done_rows}
    wanted = {job.key() for job in jobs}
    kept = {k: r for k, r in done.items() if k in wanted}
    return [job for job in jobs if job.key() not in kept], kept


def flight_line(row: dict[str, Any]) -> str:
    """One flight, for people."""
    def fmt(key: str, form: str) -> str:
        v = row.get(key)
        return "-" if v is None else form.format(v)

    starved = "  STARVED" if row.get("starved") else ""
    losses = "" if not row.get("zone_losses") else \
        f"  zones lost over them {row['zone_losses']} ({row.get('zone_losses_r0_free', 0)} with r0 free)"
    baseline = bool(row.get("baseline"))
    outcome = ("STRIKE" if row.get("strike") else "landed") if baseline else row["outcome"]
    on = "" if not row.get("unlandable_touchdown") else \
        f"  ON {'/'.join(row.get('touchdown_surfaces') or [])}"
    return (f"{'baseline ' if baseline else ''}seed {row['seed']:>3} {row['flavour']:<9} {row['world']:<9} "
            f"alt {fmt('altitude_m', '{:4.1f}')} m "
            f"-> {outcome:<8} clearance {fmt('clearance_m', '{:.1f} m'):>7}  "
            f"to touchdown {fmt('time_to_touchdown_s', '{:.0f} s'):>5}  climb {fmt('max_climb_m', '{:.1f} m'):>6}  "
            f"{fmt('processed_fps', '{:.1f} Hz'):>7}  frame p95 {fmt('frame_ms_p95', '{:.0f} ms'):>6}{on}{losses}{starved}")


def progress_line(done: int, total: int, flown: int, elapsed_s: float, unsafe: int, starved: int) -> str:
    """``flights 12/1000, unsafe 0, starved 1, about 3 h 10 min left`` (the time left at this run's
    pace so far: flights finished per second, whatever flies them)."""
    left = total - done
    if flown > 0 and left > 0:
        s = elapsed_s / flown * left
        eta = f"about {int(s // 3600)} h {int(s % 3600 // 60)} min left" if s >= 3600 else \
            f"about {max(1, round(s / 60))} min left"
    else:
        eta = "done" if left == 0 else "time left unknown"
    return f"flights {done}/{total}, unsafe {unsafe}, starved {starved}, {eta}"


#: Settings naming a file: made absolute here, since the flight's service runs elsewhere.
_FILE_SETTINGS = ("model.path", "model.landability_path")


def service_settings(items: list[str]) -> tuple[str, ...]:
    """``--set`` items checked as the service would check them (ValueError with the reason: a bad
    key or value, a model file that is not there), file paths made absolute, in a stable order."""
    overrides: dict[str, Any] = {}
    for item in items:
        key, value = settings.parse_assignment(item)
        if key in _FILE_SETTINGS:
            path = Path(str(value)).expanduser().resolve()
            if not path.is_file():
                raise ValueError(f"{key}: no such file {path}")
            value = str(path)
        overrides[key] = value
    try:
        settings.load(None, overrides)
    except settings.ConfigError as exc:
        raise ValueError(str(exc)) from None
    return tuple(f"{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in sorted(overrides.items()))


#: The latest a crossing may start, seconds after the failsafe: past the 90 s takeover budget
#: and the autopilot's LAND after a handback.
MAX_CROSSING_S = 300.0


def parse_window(text: str) -> tuple[float, float]:
    """``FROM-TO`` seconds (``--crossing-window``): 0 <= FROM < TO <= :data:`MAX_CROSSING_S`."""
    parts = text.split("-")
    try:
        lo, hi = (float(p) for p in parts) if len(parts) == 2 else (math.nan, math.nan)
    except ValueError:
        lo = hi = math.nan
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi <= MAX_CROSSING_S):
        raise ValueError(f"want FROM-TO seconds after the failsafe, 0 <= FROM < TO <= {MAX_CROSSING_S:g}, "
                         f"not {text!r}")
    return lo, hi


def parse_clock_starts(text: str) -> list[float]:
    """``1000`` or ``1000,1000.001,2000``: lockstep clock starts (s), each within
    :data:`MIN_CLOCK_START_S`-:data:`MAX_CLOCK_START_S`, none twice."""
    starts: list[float] = []
    for part in text.split(","):
        try:
            value = float(part)
        except ValueError:
            raise ValueError(f"want seconds, e.g. 1000 or 1000,2000, not {text!r}") from None
        if not (math.isfinite(value) and MIN_CLOCK_START_S <= value <= MAX_CLOCK_START_S):
            raise ValueError(f"each start must be {MIN_CLOCK_START_S:g}-{MAX_CLOCK_START_S:g} s, not {part.strip()!r}")
        if value in starts:
            raise ValueError(f"{part.strip()!r} is given twice")
        starts.append(value)
    return starts


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", default="1-10", help="seeds, e.g. 1-50 or 1,4,9-12 (default 1-10)")
    parser.add_argument("--flavour", choices=("ardupilot", "px4"), default=None,
                        help="fly every scenario with this autopilot (default: drawn per seed)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--verbose", action="store_true", help="print each flight's messages")
    parser.add_argument("--baseline", action="store_true",
                        help="also fly every seed with the autopilot's own failsafe alone (no companion) "
                             "and report its strikes beside the companion's")
    parser.add_argument("--set", dest="set_", action="append", default=[], metavar="KEY=VALUE",
                        help="fly with this service setting, as 'companion run --set' (repeatable; "
                             "e.g. model.path=my.onnx); recorded in each row")
    parser.add_argument("--land-speed", type=float, default=None, metavar="M/S",
                        help=f"the simulated autopilot's LAND descent speed (ArduPilot LAND_SPEED, PX4 "
                             f"MPC_LAND_SPEED; default {SCENARIO_LAND_SPEED:g} m/s, faster than their own "
                             f"defaults of 0.5 and 0.7): fly your vehicle's; recorded in each row")
    parser.add_argument("--crossing-window", default=None, metavar="FROM-TO",
                        help="seconds after the failsafe over which the crossing world's walkers "
                             "cross the free circle (default 4-24, timed for landings at 1 m/s); a "
                             "wider window keeps the rate with more walkers, so that crossings come "
                             "at any time of a landing: to compare landings of different lengths "
                             "fairly; recorded in each row")
    parser.add_argument("--ground", choices=GROUNDS, default="procedural",
                        help="what the ground is: 'procedural' (drawn; the default, the regression world) or "
                             "'photo' (the held-out semantic-drone photos as a mosaic, their class maps the "
                             "truth, their people counted, real-looking walkers: docs/photo-world.md); "
                             "recorded in each row of a photo world")
    parser.add_argument("--photos", type=Path, default=None, metavar="DIR",
                        help="the photos of --ground photo (images/ and labels/; default "
                             "../shared/data/semantic_drone/full beside the checkout)")
    parser.add_argument("--watch-s", type=float, default=None, metavar="S",
                        help=f"seconds the service watches the crowd, the vehicle hovering, before the "
                             f"failsafe ({MIN_WATCH_S:g}-{MAX_WATCH_S:g}; default {SCENARIO_WATCH_S:g}): what its "
                             f"risk map has seen by then; a service that ran the whole flight has seen "
                             f"more than the default's few seconds; recorded in each row")
    parser.add_argument("--link-latency", type=float, default=None, metavar="S",
                        help=f"one-way MAVLink latency added each way (s, 0-{MAX_LINK_LATENCY_S:g}) from the "
                             "moment the service is ready; with --lockstep it runs on the simulated "
                             "clock, so a seed flown with and without it pairs in sim-compare; "
                             "recorded in each row")
    parser.add_argument("--camera", default=None, metavar="MODEL:HFOV",
                        help="the camera of the simulator and of the service as one: lens model "
                             "(pinhole or fisheye) and horizontal field of view in degrees, e.g. "
                             "pinhole:110 or fisheye:160 (default pinhole:70, the scenarios' own); "
                             "recorded in each row when it is another")
    parser.add_argument("--runners", type=float, default=0.0, metavar="SHARE",
                        help="the share (0-1) of the crossing world's walkers who run or cycle across the "
                             "landing zone at 2.4-3 m/s (default 0, the scenarios' own for now: the default "
                             "changes when the yardstick is flown again); recorded in each row when not 0")
    scale = parser.add_argument_group("at scale (docs/scale.md)")
    scale.add_argument("--workers", type=int, default=None, metavar="N",
                       help="flights at once on this machine (default: its CPUs / --cpus-per-flight, "
                            "at least 1; 1 = one after another in this process)")
    scale.add_argument("--ray", default=None, metavar="ADDRESS",
                       help="send each flight to the Ray cluster at ADDRESS (HOST:6379) as a task; "
                            "'auto' starts a local Ray (needs the 'scale' extra)")
    scale.add_argument("--cpus-per-flight", type=float, default=CPUS_PER_FLIGHT, metavar="CPUS",
                       help=f"CPUs one flight needs (default {CPUS_PER_FLIGHT:g}): sets the default "
                            "--workers, each Ray task's num_cpus and the flight's model.threads (its "
                            "whole CPUs, at least 1)")
    scale.add_argument("--lockstep", action="store_true",
                       help="fly on the simulated clock: the same seed flies the same flight every "
                            "time, at any --workers or on Ray, 2-5 times faster than real time; "
                            "no flight starves (sim.flights.lockstep)")
    scale.add_argument("--clock-start", default=None, metavar="S[,S...]",
                       help=f"with --lockstep: where each flight's simulated clock starts (seconds, "
                            f"{MIN_CLOCK_START_S:g}-{MAX_CLOCK_START_S:g}; default "
                            f"{LOCKSTEP_CLOCK_START_S:g}); several fly every seed once from each: the "
                            "same scene with its times rounded differently, to tell a change's effect "
                            "from how far each verdict is from chance (docs/scale.md); recorded in each row")
    scale.add_argument("--out", type=Path, default=None, metavar="FILE.jsonl",
                       help="append each flight's row here as it ends; seeds already in it are not "
                            "flown again (resume), and the summary is computed from it")
    scale.add_argument("--no-progress", action="store_true", help="no progress line on stderr")
    scale.add_argument("--no-machine-check", action="store_true",
                       help="fly without first timing the flights' pipeline on this machine (a few "
                            "seconds that say whether its flights can be clean here; never with --ray)")


def run(args: argparse.Namespace) -> int:
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        print(f"companion sim-scenarios: bad --seeds: {exc}", file=sys.stderr)
        return 2
    if args.cpus_per_flight <= 0:
        print("companion sim-scenarios: --cpus-per-flight must be > 0", file=sys.stderr)
        return 2
    workers = args.workers if args.workers is not None else default_workers(args.cpus_per_flight)
    if workers < 1:
        print("companion sim-scenarios: --workers must be >= 1", file=sys.stderr)
        return 2
    try:
        service_set = service_settings(args.set_)
    except ValueError as exc:
        print(f"companion sim-scenarios: --set: {exc}", file=sys.stderr)
        return 2
    land = args.land_speed
    if land is not None and not (math.isfinite(land) and 0.1 <= land <= MAX_LAND_SPEED):
        print(f"companion sim-scenarios: --land-speed must be 0.1-{MAX_LAND_SPEED:g} m/s, not {land:g}",
              file=sys.stderr)
        return 2
    try:
        window = None if args.crossing_window is None else parse_window(args.crossing_window)
    except ValueError as exc:
        print(f"companion sim-scenarios: --crossing-window: {exc}", file=sys.stderr)
        return 2
    watch = args.watch_s
    if watch is not None and not (math.isfinite(watch) and MIN_WATCH_S <= watch <= MAX_WATCH_S):
        print(f"companion sim-scenarios: --watch-s must be {MIN_WATCH_S:g}-{MAX_WATCH_S:g} s, not {watch:g}",
              file=sys.stderr)
        return 2
    try:
        starts: Sequence[float | None] = (None,) if args.clock_start is None else parse_clock_starts(args.clock_start)
    except ValueError as exc:
        print(f"companion sim-scenarios: --clock-start: {exc}", file=sys.stderr)
        return 2
    if args.clock_start is not None and not args.lockstep:
        print("companion sim-scenarios: --clock-start needs --lockstep (a real-time flight's clock is the "
              "machine's)", file=sys.stderr)
        return 2
    latency = args.link_latency
    if latency is not None and not (math.isfinite(latency) and 0.0 <= latency <= MAX_LINK_LATENCY_S):
        print(f"companion sim-scenarios: --link-latency must be 0-{MAX_LINK_LATENCY_S:g} s, not {latency:g}",
              file=sys.stderr)
        return 2
    checked = parse_camera_and_photos("companion sim-scenarios", args.camera, args.ground, args.photos)
    if isinstance(checked, str):
        print(checked, file=sys.stderr)
        return 2
    camera, photos = checked.camera, checked.photos
    if not (math.isfinite(args.runners) and 0.0 <= args.runners <= 1.0):
        print(f"companion sim-scenarios: --runners must be a share within 0-1, not {args.runners:g}", file=sys.stderr)
        return 2
    threads = model_threads(args.cpus_per_flight)
    kinds = (False, True) if args.baseline else (False,)
    jobs = [FlightJob(seed, args.flavour, baseline=baseline, threads=threads, service_set=service_set,
                      land_speed=land, crossing_window=window, lockstep=args.lockstep, watch_s=watch,
                      clock_start=start, link_latency=latency or None, camera=camera,
                      runners=args.runners, ground=args.ground, photos=photos)
            for start in starts for seed in dict.fromkeys(seeds) for baseline in kinds]
    return run_jobs(jobs, workers=workers, ray_address=args.ray, cpus_per_flight=args.cpus_per_flight,
                    out=args.out, as_json=args.json, verbose=args.verbose, progress=not args.no_progress,
                    check_machine=not args.no_machine_check)


def run_jobs(jobs: list[FlightJob], *, workers: int = 1, ray_address: str | None = None,
             cpus_per_flight: float = CPUS_PER_FLIGHT, out: Path | None = None, as_json: bool = False,
             verbose: bool = False, progress: bool = False, check_machine: bool = False) -> int:
    """Fly the jobs not yet in ``out`` (all of them without one), report each as it ends, then
    the summary over every job's row; the exit status of the module docstring. With
    ``check_machine``, and companion flights to fly here (not on Ray), first say what
    :func:`machine_check` finds (stderr, and ``machine_check`` in the summary); a model that does
    not load is exit 2 before anything flies."""
    stream = sys.stderr if as_json else sys.stdout
    previous: list[dict[str, Any]] = []
    if out is not None:
        previous, bad = read_rows(out)
        if bad:
            print(f"{out}: {bad} unreadable line(s) skipped (a row cut short by a crash?)", file=sys.stderr)
    todo, kept = plan(jobs, previous)
    if kept:
        print(f"{out}: {len(kept)} of {len(jobs)} flights already there; flying the other {len(todo)}",
              file=sys.stderr)
    machine: MachineCheck | None = None
    first = next((job for job in todo if not job.baseline), None)
    if check_machine and ray_address is None and first is not None:
        from companion.pipeline.density import DensityModelError

        try:
            machine = machine_check(first)
        except DensityModelError as exc:
            print(f"companion sim-scenarios: {exc}", file=sys.stderr)
            return 2
        if first.lockstep:
            print(f"lockstep: flights fly on the simulated clock, each frame costing the same "
                  f"simulated time, so none can starve (the pipeline takes {machine.frame_ms_p50:.0f} ms "
                  "a frame here, which sets only how fast they fly)", file=sys.stderr)
        else:
            print(machine.text(workers), file=sys.stderr)
    rows: dict[RowKey, dict[str, Any]] = dict(kept)
    failed: dict[RowKey, str] = {}
    results = ResultsFile(out) if out is not None else None
    unsafe = sum(r.get("outcome") == "unsafe" for r in kept.values())
    starved = sum(bool(r.get("starved")) for r in kept.values())
    # A live bar on a terminal; one plain line per flight in a log file (no carriage returns).
    live = progress and bool(todo) and sys.stderr.isatty()
    bar = tqdm(total=len(jobs), initial=len(kept), unit="flight", desc="flights", file=sys.stderr,
               disable=not live, dynamic_ncols=True)
    bar.set_postfix(unsafe=unsafe, starved=starved)
    t0 = time.monotonic()
    try:
        for job, res in fan_out(fly_seed, todo, workers=workers, ray_address=ray_address,
                                cpus_per_task=cpus_per_flight):
            if isinstance(res, BaseException):
                failed[job.key()] = f"{type(res).__name__}: {res}"
                tqdm.write(f"{'baseline ' if job.baseline else ''}seed {job.seed}: could not fly: "
                           f"{failed[job.key()]}", file=sys.stderr)
            else:
                if results is not None:
                    results.append(res)
                rows[job.key()] = res
                unsafe += res.get("outcome") == "unsafe"
                starved += bool(res.get("starved"))
                tqdm.write(flight_line(res), file=stream)
                if verbose:
                    for m in res.get("messages", []):
                        tqdm.write(f"      {m}", file=stream)
            bar.update(1)
            bar.set_postfix(unsafe=unsafe, starved=starved)
            if progress and not live:
                print(progress_line(len(rows) + len(failed), len(jobs), len(rows) + len(failed) - len(kept),
                                    time.monotonic() - t0, unsafe, starved), file=sys.stderr, flush=True)
    except ParallelError as exc:
        print(f"companion sim-scenarios: {exc}", file=sys.stderr)
        return 2
    finally:
        bar.close()
        if results is not None:
            results.close()
    wall = time.monotonic() - t0
    if out is not None:  # the figures are the file's: every flight of every run that wrote it
        rows.update(plan(jobs, read_rows(out)[0])[1])
    asked = [rows[job.key()] for job in jobs if job.key() in rows and not job.baseline]
    base_rows = [rows[job.key()] for job in jobs if job.key() in rows and job.baseline]
    summary = summarise_rows(asked)
    summary["could_not_fly"] = sorted({k[0] for k in failed if len(k) == 2})
    summary["run"] = {"flown": len(todo) - len(failed), "wall_s": round(wall, 1),
                      "workers": None if ray_address else workers, "ray": ray_address,
                      "cpus_per_flight": cpus_per_flight, "lockstep": any(job.lockstep for job in jobs)}
    if machine is not None:
        summary["machine_check"] = machine.as_dict()
    summary["flights"] = asked
    if any(job.baseline for job in jobs):
        base = summarise_baseline(base_rows)
        base["could_not_fly"] = sorted({k[0] for k in failed if len(k) == 3})
        base["flights"] = base_rows
        summary["baseline"] = base
        rate, base_rate = summary["strike_rate"], base["strike_rate"]
        summary["strikes_vs_baseline"] = (None if rate is None or not base_rate
                                          else round(rate / base_rate, 4))
    if as_json:
        print(json.dumps(summary))
    else:
        print()
        print(summary_text(summary))
        if "baseline" in summary:
            print(baseline_text(summary))
        if failed:
            print(f"could not fly: seeds {sorted({k[0] for k in failed})} "
                  "(run again with the same --out to retry them)")
    any_unsafe = any(r.get("outcome") == "unsafe" for r in asked)
    if any_unsafe:
        return 1
    incomplete = summary["starved"] or failed or len(asked) + len(base_rows) < len(jobs)
    return 3 if incomplete else 0
