"""One closed-loop flight: the simulator and its camera in this process, the real service in another.

This is what the demo, the scenario runner and the SITL tests fly. The vehicle hovers over a
crowd; the service (``companion run``, a subprocess, exactly as systemd starts it) watches through
the simulated MJPEG camera and talks MAVLink over loopback UDP; after a while the simulator raises
a failsafe as the autopilot would (ArduPilot switches itself to LAND; PX4 holds for COM_FAIL_ACT_T,
5 s, then switches to AUTO.LAND), and the flight ends at touchdown or at a time limit. The outcome
is judged on the simulator's truth and on the landing controller's typed events, which the service
records in its flight recording (``companion.recording``); never on its log, which is for people
and may be reworded at will. Readiness is the service's ``READY=1`` on a ``NOTIFY_SOCKET``, as
systemd sees it:

- ``safe``: touched down with nobody within ``r_0`` of the touchdown point, with the companion in
  charge;
- ``unsafe``: touched down with somebody within ``r_0``, with the companion in charge;
- ``handback``: the companion handed control back to the autopilot's own failsafe (or never took
  it), and the autopilot landed where it was; counted apart, neither safe nor unsafe;
- ``timeout``: no touchdown within the time limit.

Frames: world NED metres from home, ground z = 0; times in seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from companion.geometry.camera import Intrinsics, Mount
from companion.recording import RecordingError, RecordingReader
from sim.autopilot import AutopilotConfig
from sim.camera_server import CameraServer
from sim.ground import FlatGround, ProceduralGround
from sim.simulator import SimConfig, Simulator
from sim.vehicle import VehicleParams
from sim.walkers import Circle
from sim.world import World, crowd_with_free_area, dense_crowd, dronecrowd_world

log = logging.getLogger("sim.flight")

WORLDS = ("free_area", "dense", "intrusion", "dronecrowd", "uniform")
OUTCOMES = ("safe", "unsafe", "handback", "timeout")
UNIFORM_GROUND_BGR = (70, 140, 95)  # mown grass



@dataclass(frozen=True)
class FlightSpec:
    """What to fly.

    world: ``free_area`` (a crowd with one free circle in view), ``dense`` (people everywhere:
    no safe zone), ``intrusion`` (the free circle is entered by walkers during the descent) or
    ``dronecrowd`` (real DroneCrowd motion, needs ../shared) or ``uniform`` (nobody, and a ground
    of one colour: every frame the same, the largest free circle bounded by the edge of the view).
    start_offset_m: where the vehicle hovers relative to the free circle's centre (north, east);
        the scene is laid out around a park lawn of the procedural ground (``scene_centre``).
    watch_s: seconds the service watches before the failsafe is raised.
    failsafe: the simulator failsafe raised (battery_critical, rc_loss, gcs_loss, battery_low).
    packet_loss: share of MAVLink datagrams dropped each way.
    intrusion_after_s: for ``intrusion``, seconds after the failsafe when walkers reach the circle.
    land_speed: final-descent speed of the autopilot's LAND (m/s; ArduPilot LAND_SPEED).
    home_origin_offset_m: the simulated PX4's home altitude minus its estimator origin's altitude
        (m). The real PX4 converts frame-6 position targets wrongly unless this is 0.
    record_dir: where the service records the flight (a temporary folder when None: the judge
        reads the controller's events from the recording either way).
    service_env: extra environment variables for the service process (tests use it to prove the
        verdict does not depend on the log's wording).
    """

    flavour: str = "ardupilot"
    world: str = "free_area"
    seed: int = 0
    altitude_m: float = 20.0
    start_offset_m: tuple[float, float] = (-5.0, -7.0)
    free_radius_m: float = 7.0
    watch_s: float = 4.0
    failsafe: str = "battery_critical"
    packet_loss: float = 0.0
    intrusion_after_s: float = 7.0
    timeout_s: float = 150.0
    r0_m: float = 2.0
    hfov_deg: float = 70.0
    fps: float = 10.0
    land_speed: float = 1.0
    record_dir: Path | None = None
    service_log: Path | None = None
    service_set: tuple[str, ...] = ()
    home_origin_offset_m: float = 0.0
    service_env: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        if self.world not in WORLDS:
            raise ValueError(f"world must be one of {WORLDS}, got {self.world!r}")
        if self.flavour not in ("ardupilot", "px4"):
            raise ValueError(f"flavour must be ardupilot or px4, got {self.flavour!r}")


@dataclass
class FlightResult:
    """How a flight ended, judged on the simulator's truth."""

    spec: FlightSpec
    outcome: str
    touchdown: tuple[float, float] | None = None
    clearance_m: float | None = None
    time_to_touchdown_s: float | None = None
    phases: list[str] = field(default_factory=list)  # every phase the controller entered, in order
    messages: list[str] = field(default_factory=list)  # the events' STATUSTEXT lines, each once
    events: list[dict] = field(default_factory=list)  # the controller's events as recorded
    free_circle: tuple[float, float, float] | None = None
    trigger_alt_m: float | None = None
    max_climb_m: float | None = None  # highest altitude after the trigger less the altitude at it
    service_exit: int | None = None
    log_tail: str = ""

    @property
    def took_control(self) -> bool:
        return any(p in ("APPROACH", "DESCEND") for p in self.phases)

    @property
    def handed_back(self) -> bool:
        return "HANDBACK" in self.phases

    def as_dict(self) -> dict:
        return {
            "flavour": self.spec.flavour, "world": self.spec.world, "seed": self.spec.seed,
            "outcome": self.outcome,
            "touchdown": None if self.touchdown is None else [round(v, 3) for v in self.touchdown],
            "clearance_m": None if self.clearance_m is None or not math.isfinite(self.clearance_m)
            else round(self.clearance_m, 3),
            "time_to_touchdown_s": None if self.time_to_touchdown_s is None
            else round(self.time_to_touchdown_s, 2),
            "trigger_alt_m": None if self.trigger_alt_m is None else round(self.trigger_alt_m, 2),
            "max_climb_m": None if self.max_climb_m is None else round(self.max_climb_m, 2),
            "home_origin_offset_m": round(self.spec.home_origin_offset_m, 3),
            "phases": self.phases, "messages": self.messages,
        }


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A loopback port nobody is bound to right now."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def scene_centre(spec: FlightSpec) -> tuple[float, float]:
    """Where the scenario happens: the middle of a park lawn of the seed's procedural ground
    (world NED metres), so the one free circle lies on ground a person could land a drone on,
    and the crowd around it stands on lawns, paths, paving and roads alike."""
    return ProceduralGround(spec.seed).lawn_near(80.0, 80.0)


def build_world(spec: FlightSpec) -> tuple[World, Circle | None, tuple[float, float]]:
    """The scenario's world, the free circle it guarantees (None when there is none), and the
    vehicle's start (north, east): ``start_offset_m`` from the circle's centre."""
    cn, ce = scene_centre(spec)
    start = (cn + spec.start_offset_m[0], ce + spec.start_offset_m[1])
    if spec.world == "uniform":
        return World(seed=spec.seed), None, start
    if spec.world == "dense":
        return dense_crowd(seed=spec.seed, centre=start, half_size=45.0, spacing=2.0), None, start
    if spec.world == "dronecrowd":
        return dronecrowd_world(centre=start, seed=spec.seed), None, start
    free = Circle(cn, ce, spec.free_radius_m)
    world = crowd_with_free_area(seed=spec.seed, free=free, centre=(cn, ce), half_size=40.0)
    return world, free, start


def service_command(spec: FlightSpec, link_port: int, camera_url: str, record_dir: Path) -> list[str]:
    """``companion run`` as the flight starts it (a subprocess, like systemd would)."""
    cmd = [sys.executable, "-m", "companion", "--log-level", "INFO", "run",
           "--link", f"udpin:127.0.0.1:{link_port}", "--camera", camera_url,
           "--flavour", spec.flavour,
           "--set", f"camera.hfov_deg={spec.hfov_deg}", "--set", f"camera.fps={spec.fps}",
           "--set", f"pipeline.r0_m={spec.r0_m}", "--set", "log.health_interval_s=5",
           "--record", str(record_dir)]
    for item in spec.service_set:
        cmd += ["--set", item]
    return cmd


class NotifySocket:
    """The ``NOTIFY_SOCKET`` systemd gives a ``Type=notify`` service: a Unix datagram socket on
    which the service says ``READY=1`` (and WATCHDOG, STATUS, STOPPING)."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / "notify.sock"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(self.path))
        self.sock.setblocking(False)
        self.ready = False

    def poll(self) -> None:
        while True:
            try:
                data = self.sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            if b"READY=1" in data.split(b"\n"):
                self.ready = True

    async def wait_ready(self, proc: asyncio.subprocess.Process, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.poll()
            if self.ready:
                return True
            if proc.returncode is not None:
                return False
            await asyncio.sleep(0.05)
        return False

    def close(self) -> None:
        self.sock.close()


def recorded_events(record_dir: Path) -> list[dict]:
    """The landing controller's events (``kind`` "controller") of the flight recorded in
    ``record_dir`` (its newest run), in order; empty when nothing was recorded."""
    runs = sorted(p.parent for p in record_dir.glob("*/meta.json"))
    if not runs:
        return []
    try:
        return list(RecordingReader(runs[-1]).events("controller"))
    except RecordingError as exc:
        log.warning("cannot read the flight recording %s: %s", runs[-1], exc)
        return []


def judge_events(result: FlightResult, events: list[dict]) -> None:
    """Fill the result's phases and messages from the recorded controller events."""
    result.events = events
    for ev in events:
        if ev.get("old") != ev.get("phase") and isinstance(ev.get("phase"), str):
            result.phases.append(ev["phase"])
        text = ev.get("text")
        if isinstance(text, str) and text not in result.messages:
            result.messages.append(text)


async def _pump(stream: asyncio.StreamReader, lines: list[str], sink: TextIO | None) -> None:
    while True:
        raw = await stream.readline()
        if not raw:
            return
        text = raw.decode(errors="replace").rstrip()
        lines.append(text)
        if sink is not None:
            sink.write(text + "\n")
            sink.flush()


async def fly(spec: FlightSpec) -> FlightResult:
    """Fly one scenario end to end and judge it (see the module docstring)."""
    world, free, start = build_world(spec)
    link_port, cam_port = free_port(), free_port(socket.SOCK_STREAM)
    vp = VehicleParams(land_speed=spec.land_speed)
    sim = Simulator(SimConfig(flavour=spec.flavour, outputs=[f"udpout:127.0.0.1:{link_port}"],
                              start_position=(start[0], start[1], -spec.altitude_m), vehicle=vp,
                              autopilot=AutopilotConfig(origin_alt_offset_m=spec.home_origin_offset_m),
                              seed=spec.seed), world=world)
    K = Intrinsics.from_fov(640, 480, spec.hfov_deg)
    ground = FlatGround(UNIFORM_GROUND_BGR) if spec.world == "uniform" else None
    camera = CameraServer(sim.pose, world, K, Mount(), fps=spec.fps, port=cam_port, ground=ground)
    result = FlightResult(spec, "timeout",
                          free_circle=None if free is None else (free.north, free.east, free.radius))
    touchdown: dict[str, object] = {}

    def on_touchdown() -> None:
        if "t" not in touchdown:
            tr = sim.truth
            point = (float(tr.position[0]), float(tr.position[1]))
            touchdown.update(t=time.monotonic(), point=point,
                             clearance=world.nearest_person_distance(point))

    sim.on_touchdown(on_touchdown)
    climb: dict[str, float] = {}

    def watch_climb(_dt: float) -> None:
        # The truth, every physics step from the trigger to touchdown: how high it went.
        if "trigger_alt" in climb and "t" not in touchdown:
            climb["max_alt"] = max(climb.get("max_alt", -math.inf), sim.vehicle.altitude)

    sim.add_stepper(watch_climb)
    lines: list[str] = []
    sink = open(spec.service_log, "w") if spec.service_log is not None else None
    proc = None
    scratch = tempfile.TemporaryDirectory(prefix="companion-flight-")
    record_dir = spec.record_dir if spec.record_dir is not None else Path(scratch.name) / "recording"
    notify = NotifySocket(Path(scratch.name))
    env: Mapping[str, str] = {**os.environ, "PYTHONUNBUFFERED": "1", "NOTIFY_SOCKET": str(notify.path),
                              **dict(spec.service_env)}
    try:
        await sim.start()
        await camera.start()
        proc = await asyncio.create_subprocess_exec(
            *service_command(spec, link_port, camera.url, record_dir), stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, env=dict(env))
        pump = asyncio.create_task(_pump(proc.stderr, lines, sink))  # type: ignore[arg-type]
        if not await notify.wait_ready(proc, timeout=60.0):
            result.outcome = "timeout"
            result.log_tail = "\n".join(lines[-30:])
            raise RuntimeError("the service did not become ready:\n" + result.log_tail)
        if spec.packet_loss > 0:
            sim.set_link_faults(loss=spec.packet_loss)
        await asyncio.sleep(spec.watch_s)
        t_trigger = time.monotonic()
        climb["trigger_alt"] = sim.vehicle.altitude
        sim.inject_failsafe(spec.failsafe)
        if spec.world == "intrusion" and free is not None:
            # Walkers reach the free circle while the companion approaches or descends into it.
            world.add_intrusion(free, t_enter=world.t + spec.intrusion_after_s, count=4,
                                speed=1.4)
        end = t_trigger + spec.timeout_s
        while "t" not in touchdown and time.monotonic() < end:
            if proc.returncode is not None:
                break
            await asyncio.sleep(0.1)
        if "t" in touchdown:
            result.touchdown = touchdown["point"]  # type: ignore[assignment]
            result.clearance_m = float(touchdown["clearance"])  # type: ignore[arg-type]
            result.time_to_touchdown_s = float(touchdown["t"]) - t_trigger  # type: ignore[arg-type]
        # Let the last events of the landing (LANDED) be recorded before stopping the service.
        await asyncio.sleep(0.5)
    finally:
        if proc is not None and proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            try:
                result.service_exit = await asyncio.wait_for(proc.wait(), 5.0)
            except TimeoutError:
                proc.kill()
                result.service_exit = await proc.wait()
        elif proc is not None:
            result.service_exit = proc.returncode
        with contextlib.suppress(Exception):
            await asyncio.wait_for(pump, 2.0)
        await camera.stop()
        await sim.stop()
        if sink is not None:
            sink.close()
        notify.close()
        # The service has stopped (its recorder closed): its events are all on disk.
        judge_events(result, recorded_events(record_dir))
        scratch.cleanup()
    result.log_tail = "\n".join(lines[-40:])
    if "trigger_alt" in climb:
        result.trigger_alt_m = climb["trigger_alt"]
        result.max_climb_m = max(0.0, climb.get("max_alt", climb["trigger_alt"]) - climb["trigger_alt"])
    result.outcome = judge(result, spec.r0_m)
    return result


def judge(result: FlightResult, r0_m: float) -> str:
    """safe / unsafe / handback / timeout from the truth and whether the companion was in charge."""
    if result.touchdown is None:
        return "timeout"
    if result.handed_back or not result.took_control:
        return "handback"
    return "safe" if (result.clearance_m or 0.0) >= r0_m else "unsafe"


def summarise(results: list[FlightResult]) -> dict:
    """The scenario runner's figures: counts, the minimum clearance at touchdown of the landings
    the companion made, and the median time from trigger to touchdown."""
    counts = {k: sum(r.outcome == k for r in results) for k in OUTCOMES}
    landed = [r for r in results if r.outcome in ("safe", "unsafe")]
    clear = [r.clearance_m for r in landed if r.clearance_m is not None]
    times = [r.time_to_touchdown_s for r in results if r.time_to_touchdown_s is not None]
    climbs = [r.max_climb_m for r in results if r.max_climb_m is not None]
    return {
        "total": len(results), "safe": counts["safe"], "handbacks": counts["handback"],
        "unsafe": counts["unsafe"], "timeouts": counts["timeout"],
        "min_clearance_m": round(min(clear), 3) if clear else None,
        "median_time_to_touchdown_s": round(float(np.median(times)), 2) if times else None,
        "max_climb_m": round(max(climbs), 2) if climbs else None,
    }
