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

Verdicts are about people. What the vehicle touched down *on* is judged apart, on the procedural
ground's own truth (``sim.world.ground.SURFACES``): every touchdown's row lists the surfaces under the
vehicle's footprint (a disc of ``FOOTPRINT_M``), and says whether any of them is not landable
ground (a tree, a bench, a car, a roof): the scenario's free circle often holds a tree or a bench,
and a landing on one is no safe landing whoever stood near.

A **baseline** flight (``FlightSpec.companion = False``) flies the same scene with no service at
all: the simulator raises the same failsafe ``watch_s`` after it starts and the autopilot's own
LAND (PX4: after its COM_FAIL_ACT_T hold) brings the vehicle down where it was. It is judged on
the same truth (where it touched down, who stood within ``r_0``) and, the companion never having
taken control, its outcome is ``handback``; its row says ``baseline: true``.

Frames: world NED metres from home, ground z = 0; times in seconds.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import fcntl
import functools
import logging
import math
import os
import random
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TextIO

import numpy as np

from companion.geometry.camera import Intrinsics, Mount
from companion.parallel import die_with_parent  # also the preexec_fn of a flight's service
from companion.recording import RecordingError, RecordingReader
from sim.flights.results import summarise_rows
from sim.flights.spec import FlightResult, FlightSpec, ZoneLoss, service_command
from sim.vehicle.autopilot import AutopilotConfig
from sim.vehicle.kinematics import VehicleParams
from sim.vehicle.simulator import SimConfig, Simulator
from sim.world.camera_server import CameraServer
from sim.world.crowd import (
    World,
    add_crossing_walkers,
    crowd_with_free_area,
    dense_crowd,
    dronecrowd_world,
)
from sim.world.ground import FlatGround, ProceduralGround
from sim.world.photo_ground import PhotoGround
from sim.world.photo_people import PhotoGroundWithPeople, open_ground_walkers
from sim.world.walkers import Bounds, Circle, Walkable

log = logging.getLogger("sim.flights.flight")

OUTCOMES = ("safe", "unsafe", "handback", "timeout")
UNIFORM_GROUND_BGR = (70, 140, 95)  # mown grass
#: Radius of the ground a vehicle touches down on (m): a small multirotor's half-span with its
#: props (a 0.7-1 m frame), what must be clear of trees and benches for a landing to be on ground.
FOOTPRINT_M = 0.5
#: Seconds the flight goes on after the land detector fires (touchdown), so that the service sees
#: the landed state and records LANDED before it is stopped: EXTENDED_SYS_STATE comes at 2 Hz
#: (ArduPilot) or 1 Hz (PX4), plus time for a loaded machine. 0.5 s lost LANDED on a loaded CI run.
LANDED_GRACE_S = 1.5
#: Seconds between the flight's samples of the truth under the vehicle (``zone_losses``): the
#: camera's frame period at 10 Hz; a walker moves 0.15 m meanwhile.
TRUTH_PERIOD_S = 0.1
#: The last metres of a landing (m above the flat ground): below this the landing is committed
#: (``controller.land_abort_above_m``'s default) and the camera sees less than ``r_0`` around the
#: point, so the time from the vehicle's last moment above it to touchdown (``last_metres_s``, on
#: the truth, whoever landed) is the time a walker has to reach the point unseen.
LAST_METRES_M = 3.5
#: A flight is **starved** (its CPU, not the software under test, decided it) when its service
#: processed frames at less than STARVED_SHARE of the camera's rate, from READY to touchdown (or to
#: the end of the flight), or when the pipeline's time per frame (95th percentile) exceeded
#: STARVED_FRAME_SHARE of the frame period. Measured on an otherwise idle 2-core machine, 34
#: sequential flights processed 8.8-9.8 Hz of 10 (the last metre or two of a descent, below the
#: head plane, gives no usable frames), and the 16 of them timed per frame took 31-38 ms (p95);
#: two flights at once on those 2 cores kept 8.5-9.8 Hz but took 82-105 ms per frame and changed
#: verdicts, so the rate alone does not show it: docs/scale.md.
STARVED_SHARE = 0.7
STARVED_FRAME_SHARE = 0.5
#: Where flights on one machine claim their loopback ports (one file per port, holding the pid).
PORT_CLAIMS_DIR = Path("/tmp/companion-ports")


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A loopback port nobody is bound to right now."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class Touchdown:
    """The first land detection of a flight, judged on the simulator's truth: when
    (``time.monotonic()`` s), where (north, east m), the nearest person then (m) and whether the
    world says nobody walks there (None where it cannot tell)."""

    t: float
    point: tuple[float, float]
    clearance_m: float
    free_ground: bool | None


@dataclass
class PortClaim:
    """A loopback port this process has claimed node-wide (see :func:`reserve_port`)."""

    port: int
    path: Path

    def release(self) -> None:
        """Give the port back (only our own claim is removed)."""
        with contextlib.suppress(OSError):
            if self.path.read_text().strip() == str(os.getpid()):
                self.path.unlink()

    def __enter__(self) -> PortClaim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


@contextlib.contextmanager
def _claims_lock(folder: Path) -> Iterator[None]:
    # Every claim is made under this lock, so that taking over a dead process's claim (check,
    # remove, create) cannot race another claim of the same port; creating one is atomic on its
    # own (O_EXCL). The kernel releases a flock whose holder dies.
    fd = os.open(folder / ".lock", os.O_CREAT | os.O_RDWR, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _claim_alive(path: Path) -> bool:
    try:
        pid = int(path.read_text().strip() or "0")
    except (OSError, ValueError):
        return False  # unreadable or half written by a process that died writing it
    if pid <= 0:
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # somebody else's live process
    return True


def claim_port(port: int, folder: Path | None = None) -> PortClaim | None:
    """Claim ``port`` for this process, node-wide, or None when a live process holds it.

    The claim is the file ``folder/<port>`` created with ``O_CREAT | O_EXCL`` (atomic on a local
    file system: of two processes creating it at once exactly one succeeds) holding our pid. A
    claim whose pid is dead (a crashed flight) is taken over."""
    folder = port_claims_dir() if folder is None else folder
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / str(port)
    with _claims_lock(folder):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if _claim_alive(path):
                return None
            path.unlink(missing_ok=True)
            try:
                fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                return None
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()}\n")
    return PortClaim(port, path)


def port_claims_dir() -> Path:
    """``$COMPANION_PORT_DIR``, else ``/tmp/companion-ports``: one folder per machine."""
    env = os.environ.get("COMPANION_PORT_DIR")
    return Path(env) if env else PORT_CLAIMS_DIR


def _candidate_range() -> tuple[int, int]:
    # Below the kernel's ephemeral range, so that no socket bound to port 0 (another flight's
    # outgoing UDP, an HTTP client) can be handed a port we reserved but have not bound yet.
    try:
        lo = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        lo = 32768
    return (max(1024, lo - 12288), lo - 1) if lo > 4096 else (0, 0)


def _bindable(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def reserve_port(kind: int = socket.SOCK_DGRAM, folder: Path | None = None, attempts: int = 500) -> PortClaim:
    """A loopback port free now and claimed for this process until :meth:`PortClaim.release`.

    Two flights running at once (threads, processes or Ray workers on one machine) never get the
    same port: each candidate is claimed atomically (:func:`claim_port`) before it is used.
    Candidates lie below the kernel's ephemeral range (see ``_candidate_range``)."""
    lo, hi = _candidate_range()
    rng = random.Random(os.urandom(8))
    for _ in range(attempts):
        port = rng.randint(lo, hi) if hi > lo else free_port(kind)
        if not _bindable(port, kind):
            continue
        claim = claim_port(port, folder)
        if claim is None:
            continue
        if _bindable(port, kind):  # still free now that it is ours
            return claim
        claim.release()
    raise RuntimeError(f"no free loopback port could be claimed in {attempts} attempts")


def scene_centre(spec: FlightSpec) -> tuple[float, float]:
    """Where the scenario happens: the middle of a park lawn of the seed's procedural ground
    (world NED metres), so the one free circle lies on ground a person could land a drone on,
    and the crowd around it stands on lawns, paths, paving and roads alike."""
    return ProceduralGround(spec.seed).lawn_near(80.0, 80.0)


@functools.lru_cache(maxsize=2)
def photo_ground(folder: str) -> PhotoGroundWithPeople:
    """The photo ground of ``folder`` with its real-looking people (one per process)."""
    return PhotoGroundWithPeople(folder)


#: Metres of landable ground, by the class maps, that a photo world keeps beyond its free
#: circle's edge: the crowd's keep-out margin (0.3 m) and a vehicle's footprint (FOOTPRINT_M).
PHOTO_FREE_MARGIN_M = 1.0
#: Half the side (m) of the square around the scene whose photo people the judge counts.
PHOTO_PEOPLE_HALF_M = 150.0


def photo_scene_centre(spec: FlightSpec) -> tuple[float, float]:
    """Where a photo world's scenario happens: a point drawn from the seed (its own stream) where
    the free circle (grown by ``PHOTO_FREE_MARGIN_M``) is landable ground by the class maps with
    no photo's person within 1 m of it, on a photo drawn first among every photo that holds
    such a point, each as likely (``PhotoGround.place_centre``); for a world without a free
    circle, any point of the photo block."""
    assert spec.photos is not None
    ground = photo_ground(spec.photos)
    rng = np.random.default_rng([int(spec.seed), 0x9407])
    if spec.world in ("dense", "uniform", "dronecrowd"):
        return (float(rng.uniform(0, ground.block_n)), float(rng.uniform(0, ground.block_e)))
    return ground.place_centre(spec.free_radius_m + PHOTO_FREE_MARGIN_M, rng)[1]


def build_world(spec: FlightSpec) -> tuple[World, Circle | None, tuple[float, float]]:
    """The scenario's world, the free circle it guarantees (None when there is none), and the
    vehicle's start (north, east): ``start_offset_m`` from the circle's centre. On the photo
    ground (``spec.ground``) the photos' people stand in the world (``World.fixed_people``),
    walkers who cross open ground join the crowd (``sim.world.photo_people``), and every walker
    keeps to ground people walk on by the class maps (``PhotoGround.walkable``)."""
    world, free, start = _build_world(spec)
    if spec.ground == "photo":
        assert spec.photos is not None
        centre = start if free is None else (free.north, free.east)
        world.fixed_people = photo_ground(spec.photos).people(centre, PHOTO_PEOPLE_HALF_M)
        if spec.world not in ("uniform", "dronecrowd"):
            half = 45.0 if spec.world in ("dense", "dense_beyond") else 40.0
            around = start if spec.world in ("dense", "dense_beyond") else centre
            world.add_source(open_ground_walkers(Bounds.around(around, half), free, spec.seed,
                                                 walkable=_walkable(spec, around, half)))
    return world, free, start


def _walkable(spec: FlightSpec, centre: tuple[float, float], half: float) -> Walkable | None:
    """Where a crowd of ``half`` m around ``centre`` walks: anywhere on the drawn ground; on the
    photo ground, the ground people walk on by the class maps (1 m beyond the crowd's square)."""
    if spec.ground != "photo":
        return None
    assert spec.photos is not None
    return photo_ground(spec.photos).walkable(centre, half + 1.0)


def crossing_walkable(spec: FlightSpec, free: Circle) -> Walkable | None:
    """Where the crossing world's walkers start, cross and stop (``add_crossing_walkers``):
    anywhere on the drawn ground; on the photo ground, the ground people walk on by the class
    maps around ``free`` (its radius and a crossing's approach, 8 m, and 1 m more)."""
    return _walkable(spec, (free.north, free.east), free.radius + 8.0)


def add_trigger_crossers(world: World, free: Circle, spec: FlightSpec, walkable: Walkable | None) -> None:
    """The crossing world's walkers, drawn at the trigger (``world.t``) as its flight draws them:
    ``spec``'s crossing window and share of runners, on ``walkable`` (``crossing_walkable``; a
    flight makes it before the trigger, where reading the class maps would stall its loop). The
    one draw every rebuilder of a flight's world uses (``sim.evidence.strikes``,
    ``sim.evidence.clear_oracle``), so that theirs is the flight's crowd."""
    add_crossing_walkers(world, free, world.t, spec.seed, window=spec.crossing_window, runners=spec.runners,
                         walkable=walkable)


def _build_world(spec: FlightSpec) -> tuple[World, Circle | None, tuple[float, float]]:
    cn, ce = photo_scene_centre(spec) if spec.ground == "photo" else scene_centre(spec)
    start = (cn + spec.start_offset_m[0], ce + spec.start_offset_m[1])
    if spec.world == "uniform":
        return World(seed=spec.seed), None, start
    if spec.world == "dense":
        return dense_crowd(seed=spec.seed, centre=start, half_size=45.0, spacing=2.0,
                           walkable=_walkable(spec, start, 45.0)), None, start
    if spec.world == "dense_beyond":
        # A dense crowd with one free circle, start_offset_m away: out of the first view, for
        # the search to find.
        free = Circle(cn, ce, spec.free_radius_m)
        return dense_crowd(seed=spec.seed, centre=start, half_size=45.0, spacing=2.0, free=free,
                           walkable=_walkable(spec, start, 45.0)), free, start
    if spec.world == "dronecrowd":
        return dronecrowd_world(centre=start, seed=spec.seed), None, start
    free = Circle(cn, ce, spec.free_radius_m)
    world = crowd_with_free_area(seed=spec.seed, free=free, centre=(cn, ce), half_size=40.0,
                                 walkable=_walkable(spec, (cn, ce), 40.0))
    return world, free, start


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


class FlightService(Protocol):
    """The service a flight flies with, however it runs: ``start`` it (True once it is ready),
    watch ``running``, ``stop`` it (its exit status); ``lines`` are its log lines so far."""

    lines: list[str]

    async def start(self, timeout: float) -> bool: ...

    @property
    def running(self) -> bool: ...

    async def stop(self) -> int | None: ...


class ServiceProcess:
    """``companion run`` in a subprocess, exactly as systemd starts it: ready when it says
    ``READY=1`` on its ``NOTIFY_SOCKET``, stopped by SIGTERM (killed after 5 s), its stderr
    kept in ``lines`` (and written to ``sink``)."""

    def __init__(self, spec: FlightSpec, link_port: int, camera_url: str, record_dir: Path,
                 scratch: Path, sink: TextIO | None) -> None:
        self.command = service_command(spec, link_port, camera_url, record_dir)
        self.notify = NotifySocket(scratch)
        self.env: dict[str, str] = {**os.environ, "PYTHONUNBUFFERED": "1", "NOTIFY_SOCKET": str(self.notify.path),
                                    **dict(spec.service_env)}
        self.sink = sink
        self.lines: list[str] = []
        self.proc: asyncio.subprocess.Process | None = None
        self._pump: asyncio.Task[None] | None = None

    async def start(self, timeout: float) -> bool:
        self.proc = await asyncio.create_subprocess_exec(
            *self.command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE, env=self.env, preexec_fn=die_with_parent)
        assert self.proc.stderr is not None  # asked for with stderr=PIPE
        self._pump = asyncio.create_task(_pump(self.proc.stderr, self.lines, self.sink))
        return await self.notify.wait_ready(self.proc, timeout=timeout)

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.returncode is None

    async def stop(self) -> int | None:
        proc, code = self.proc, None
        if proc is not None and proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            try:
                code = await asyncio.wait_for(proc.wait(), 5.0)
            except (TimeoutError, asyncio.TimeoutError):
                proc.kill()
                code = await proc.wait()
        elif proc is not None:
            code = proc.returncode
        if self._pump is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._pump, 2.0)
        self.notify.close()
        return code


def start_service(spec: FlightSpec, link_port: int, camera: CameraServer, record_dir: Path,
                  scratch: Path, sink: TextIO | None) -> FlightService:
    """The flight's service, not yet started: ``companion run`` in a subprocess (real time), or,
    for a lockstep flight, the same service in this process on the simulated clock
    (``sim.flights.lockstep``)."""
    if spec.lockstep:
        # Imported here, not at the top: the service's stack (config, pipeline, OpenCV) is what a
        # real-time flight's parent never loads, its service being a subprocess.
        from sim.flights.inprocess import InProcessService

        return InProcessService(spec, link_port, camera, record_dir, sink)
    return ServiceProcess(spec, link_port, camera.url, record_dir, scratch, sink)


def recorded_events(record_dir: Path, kind: str | None = "controller") -> list[dict]:
    """The events of one ``kind`` (default the landing controller's, "controller"; None: all) of
    the flight recorded in ``record_dir`` (its newest run), in order; empty when nothing was
    recorded."""
    runs = sorted(p.parent for p in record_dir.glob("*/meta.json"))
    if not runs:
        return []
    try:
        return list(RecordingReader(runs[-1]).events(kind))
    except RecordingError as exc:
        log.warning("cannot read the flight recording %s: %s", runs[-1], exc)
        return []


def processed_rate(frame_times: list[float], t_from: float, t_to: float) -> float | None:
    """Frames processed per second between two ``time.monotonic()`` instants (the service's
    ``zones`` events carry the same clock); None for an empty window."""
    if not t_to > t_from:
        return None
    return sum(t_from <= t <= t_to for t in frame_times) / (t_to - t_from)


#: The phases in which the vehicle is over its zone: a loss there is judged on the truth under it.
OVER_ZONE = ("DESCEND", "LAND")


def zone_losses(events: list[dict], truth: list[tuple[float, float]]) -> list[ZoneLoss]:
    """The zones given up over them (a controller event with ``lost_zone_id`` that left DESCEND or
    LAND: a HOLD, or a re-targeting), each with the truth at that moment.

    ``truth``: ``(time.monotonic(), nearest person to the vehicle in m)`` samples in time order.
    A loss whose nearest person stood ``r0`` or more away was not asked for by ``r0`` at that
    moment: the pipeline's caution (it grows every person it sees), a false detection, or a
    walker still on the way; the row counts them (``zone_losses_r0_free``) so that a density
    model's cost in closed loop is measured, not guessed from its log."""
    times = [t for t, _ in truth]
    out = []
    for ev in events:
        lost, t = ev.get("lost_zone_id"), ev.get("t")
        if not isinstance(lost, int) or ev.get("old") not in OVER_ZONE or not isinstance(t, (int, float)):
            continue
        reason = ev.get("reason")
        if not isinstance(reason, str):
            text = str(ev.get("text", ""))
            start = text.find(" lost (")
            reason = text[start + 7:text.rfind(")")] if start >= 0 else ""
        i = bisect.bisect_right(times, float(t)) - 1
        out.append(ZoneLoss(float(t), lost, reason, truth[i][1] if i >= 0 else math.inf))
    return out


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


#: Given the flight's world and simulator before they start (e.g. to add a stepper that samples
#: the truth, as the demo does to mark people in its video); it must not change the flight.
Observer = Callable[[World, Simulator], None]


async def fly(spec: FlightSpec, observe: Observer | None = None) -> FlightResult:
    """Fly one scenario end to end and judge it (see the module docstring). Its two loopback
    ports are claimed node-wide for the flight (:func:`reserve_port`), so flights may run at once.
    ``observe`` sees the world and the simulator before the flight starts."""
    if spec.lockstep and not getattr(asyncio.get_running_loop(), "lockstep", False):
        raise ValueError("a lockstep flight flies on the simulated clock: sim.flights.lockstep.fly_lockstep(spec)")
    with reserve_port() as link, reserve_port(socket.SOCK_STREAM) as cam:
        return await _fly(spec, link.port, cam.port, observe)


def build_scene(spec: FlightSpec, link_port: int, cam_port: int
                ) -> tuple[World, Circle | None, Simulator, CameraServer]:
    """The scenario's world, its free circle, the simulator (MAVLink out to ``link_port``) and its
    MJPEG camera (on ``cam_port``), not yet started: what a flight needs besides the service."""
    world, free, start = build_world(spec)
    vp = VehicleParams(land_speed=spec.land_speed)
    outputs = [f"udpout:127.0.0.1:{link_port}"]
    if spec.gcs_port is not None:
        forward = "?forward=1" if spec.flavour == "px4" else ""
        outputs = [outputs[0] + forward, f"udpin:127.0.0.1:{spec.gcs_port}{forward}"]
    sim = Simulator(SimConfig(flavour=spec.flavour, outputs=outputs,
                              start_position=(start[0], start[1], -spec.altitude_m), vehicle=vp,
                              autopilot=AutopilotConfig(origin_alt_offset_m=spec.home_origin_offset_m,
                                                        alt_bias_m=spec.alt_bias_m,
                                                        rangefinder_max_m=spec.rangefinder_max_m),
                              seed=spec.seed), world=world)
    K = Intrinsics.from_fov(640, 480, spec.hfov_deg, spec.camera_model)  # the service's camera (service_settings)
    ground: object | None = None
    if spec.world == "uniform":
        ground = FlatGround(UNIFORM_GROUND_BGR)
    elif spec.ground == "photo":
        assert spec.photos is not None
        ground = photo_ground(spec.photos)
    camera = CameraServer(sim.pose, world, K, Mount(), fps=spec.fps, port=cam_port, ground=ground)
    return world, free, sim, camera


def touchdown_surfaces(ground: object, point: tuple[float, float]) -> list[str] | None:
    """The surfaces under a vehicle's footprint (``FOOTPRINT_M`` around ``point``, world NED
    metres) on ``ground``'s truth, sorted (the photo ground's: its class maps' class names); None
    for a ground that does not say (``FlatGround``)."""
    if not isinstance(ground, (ProceduralGround, PhotoGround)):
        return None
    return sorted(ground.surfaces_within(point[0], point[1], FOOTPRINT_M))


async def _fly(spec: FlightSpec, link_port: int, cam_port: int, observe: Observer | None = None) -> FlightResult:
    world, free, sim, camera = build_scene(spec, link_port, cam_port)
    # Made now, not at the trigger: reading the class maps there would stall the flight's loop.
    cross_walkable = crossing_walkable(spec, free) if spec.world == "crossing" and free is not None else None
    if observe is not None:
        observe(world, sim)
    # The world's clock starts when the service is ready (at once for the baseline), so the
    # people at the failsafe are where they are in every run of the seed, however long the
    # service took to start on a loaded machine, and the baseline meets the same crowd.
    world.paused = spec.companion
    result = FlightResult(spec, "timeout",
                          free_circle=None if free is None else (free.north, free.east, free.radius))
    touchdown: list[Touchdown] = []  # the first land detection, judged on the truth

    def on_touchdown() -> None:
        if not touchdown:
            tr = sim.truth
            point = (float(tr.position[0]), float(tr.position[1]))
            touchdown.append(Touchdown(t=time.monotonic(), point=point,
                                       clearance_m=world.nearest_person_distance(point),
                                       free_ground=world.nobody_walks_at(point)))

    sim.on_touchdown(on_touchdown)
    climb: dict[str, float] = {}

    truth: list[tuple[float, float]] = []  # (time.monotonic(), nearest person to the vehicle, m)

    def watch_truth(_dt: float) -> None:
        # The truth from the trigger to touchdown: every physics step, how high it went; every
        # TRUTH_PERIOD_S, the nearest person under the vehicle, for the zone losses' judgement.
        if "trigger_alt" not in climb or touchdown:
            return
        climb["max_alt"] = max(climb.get("max_alt", -math.inf), sim.vehicle.altitude)
        now = time.monotonic()
        if sim.vehicle.altitude > LAST_METRES_M:
            climb["above_t"] = now  # the last metres start after the last such step
        if not truth or now - truth[-1][0] >= TRUTH_PERIOD_S:
            p = sim.truth.position
            truth.append((now, world.nearest_person_distance((float(p[0]), float(p[1])))))

    sim.add_stepper(watch_truth)
    window: dict[str, float] = {}  # READY and the end of the flight, for the processed frame rate
    sink = open(spec.service_log, "w") if spec.service_log is not None else None
    scratch = tempfile.TemporaryDirectory(prefix="companion-flight-")
    record_dir = spec.record_dir if spec.record_dir is not None else Path(scratch.name) / "recording"
    service: FlightService | None = None
    try:
        await sim.start()
        if spec.companion:  # the baseline flies without camera or service
            await camera.start()
            service = start_service(spec, link_port, camera, record_dir, Path(scratch.name), sink)
            if not await service.start(timeout=60.0):
                result.outcome = "timeout"
                result.log_tail = "\n".join(service.lines[-30:])
                raise RuntimeError("the service did not become ready:\n" + result.log_tail)
            window["ready"] = time.monotonic()
            world.paused = False
        if spec.packet_loss > 0 or spec.latency_ms > 0:
            sim.set_link_faults(loss=spec.packet_loss, latency_s=spec.latency_ms / 1000.0)
        await asyncio.sleep(spec.watch_s)
        t_trigger = time.monotonic()
        climb["trigger_alt"] = sim.vehicle.altitude
        result.world_t_trigger = world.t
        sim.inject_failsafe(spec.failsafe)
        if spec.world == "intrusion" and free is not None:
            # Walkers reach the free circle while the companion approaches or descends into it.
            world.add_intrusion(free, t_enter=world.t + spec.intrusion_after_s, count=4,
                                speed=1.4)
        elif spec.world == "crossing" and free is not None:
            # Walkers cross the free circle (the zone the companion lands in) during the descent.
            add_trigger_crossers(world, free, spec, cross_walkable)
        end = t_trigger + spec.timeout_s
        while not touchdown and time.monotonic() < end:
            if service is not None and not service.running:
                break
            await asyncio.sleep(0.1)
        window["end"] = touchdown[0].t if touchdown else time.monotonic()
        if touchdown:
            result.touchdown = touchdown[0].point
            result.clearance_m = touchdown[0].clearance_m
            result.in_free_area = touchdown[0].free_ground
            result.time_to_touchdown_s = touchdown[0].t - t_trigger
            result.touchdown_surfaces = touchdown_surfaces(camera.ground, touchdown[0].point)
            if "above_t" in climb:
                result.last_metres_s = max(0.0, touchdown[0].t - climb["above_t"])
        # Let the last events of the landing (LANDED) be recorded before stopping the service:
        # the landed state reaches it in EXTENDED_SYS_STATE, which the autopilots send at 1-2 Hz.
        await asyncio.sleep(LANDED_GRACE_S)
    finally:
        if service is not None:
            result.service_exit = await service.stop()
        await camera.stop()
        await sim.stop()
        if sink is not None:
            sink.close()
        # The service has stopped (its recorder closed): its events are all on disk.
        recorded = recorded_events(record_dir, None)
        judge_events(result, [e for e in recorded if e.get("kind") == "controller"])
        result.zone_losses = zone_losses(result.events, truth)
        zones = [e for e in recorded if e.get("kind") == "zones" and isinstance(e.get("t"), (int, float))]
        frame_times = [float(e["t"]) for e in zones]
        frame_ms = [float(e["timings_ms"]["total"]) for e in zones
                    if isinstance(e.get("timings_ms"), dict) and isinstance(e["timings_ms"].get("total"), (int, float))]
        scratch.cleanup()
    result.log_tail = "" if service is None else "\n".join(service.lines[-40:])
    if "trigger_alt" in climb:
        result.trigger_alt_m = climb["trigger_alt"]
        result.max_climb_m = max(0.0, climb.get("max_alt", climb["trigger_alt"]) - climb["trigger_alt"])
    if frame_ms:
        result.frame_ms_p95 = float(np.percentile(frame_ms, 95))
    if "ready" in window and "end" in window:
        result.processed_fps = processed_rate(frame_times, window["ready"], window["end"])
    # On the simulated clock no CPU can starve a flight: every piece of work takes its fixed time.
    result.starved = not spec.lockstep and starved(result.processed_fps, result.frame_ms_p95, spec.fps)
    result.outcome = judge(result, spec.r0_m)
    return result


def starved(processed_fps: float | None, frame_ms_p95: float | None, fps: float) -> bool:
    """Whether a flight was starved of CPU: it processed frames at less than ``STARVED_SHARE`` of
    the camera's ``fps``, or its pipeline took more than ``STARVED_FRAME_SHARE`` of a frame
    period per frame (95th percentile, ms). Unknown figures do not make it starved."""
    slow_rate = processed_fps is not None and processed_fps < STARVED_SHARE * fps
    slow_frames = frame_ms_p95 is not None and frame_ms_p95 > STARVED_FRAME_SHARE * 1000.0 / fps
    return slow_rate or slow_frames


def judge(result: FlightResult, r0_m: float) -> str:
    """safe / unsafe / handback / timeout from the truth and whether the companion was in charge."""
    if result.touchdown is None:
        return "timeout"
    if result.handed_back or not result.took_control:
        return "handback"
    return "safe" if (result.clearance_m or 0.0) >= r0_m else "unsafe"


def summarise(results: list[FlightResult]) -> dict:
    """The scenario runner's figures (``sim.flights.results.summarise_rows`` over the flights' rows):
    counts, the minimum clearance at touchdown of the landings the companion made, the median time
    from trigger to touchdown, the highest climb, and the rates with their 95 % bounds."""
    return summarise_rows(r.as_dict() for r in results)
