"""The simulator: vehicle + autopilot flavour + MAVLink links, run in real time on asyncio.

    async with Simulator(SimConfig(flavour="px4", start_position=(0, 0, -10))) as sim:
        ...  # fly it over MAVLink on 127.0.0.1:14550 (udpout), read sim.truth

The physics, the autopilot logic, the optional world (anything with ``step(dt)``) and the
telemetry streams all advance on one clock, the event loop's monotonic time, in steps of
``1 / rate_hz`` seconds. Frames: world NED metres from home, ground ``z = 0``; radians.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from companion.geometry.camera import Pose, rotation_from_euler
from sim.vehicle.ardupilot import ArduPilotCopter
from sim.vehicle.autopilot import Autopilot, AutopilotConfig, Behaviour
from sim.vehicle.endpoint import Endpoint, UdpLink, parse_link
from sim.vehicle.faults import Failsafe, LinkFaults
from sim.vehicle.kinematics import Vehicle, VehicleParams
from sim.vehicle.px4 import OffboardConfig, Px4FailsafeConfig, Px4Multicopter
from sim.vehicle.routing import Routing, routing_for

log = logging.getLogger(__name__)

FLAVOURS = ("ardupilot", "px4")


class Steppable(Protocol):
    def step(self, dt: float) -> Any: ...


@dataclass
class SimConfig:
    """Everything a simulator run needs. Positions world NED metres, yaw radians, rate Hz.

    ``offboard`` and ``px4_failsafe`` apply to the PX4 flavour only; ``seed`` makes the link
    faults and PX4's pre-arming HOME_POSITION wander repeatable (None: fresh entropy).

    ``outputs`` are link URLs (``sim.vehicle.endpoint``); the vehicle forwards MAVLink between them as its
    firmware does (``sim.vehicle.routing``): ArduPilot on every link, PX4 only between links whose URL
    ends in ``?forward=1`` (``MAV_X_FORWARD``).
    """

    flavour: str = "ardupilot"
    outputs: list[str] = field(default_factory=lambda: ["udpout:127.0.0.1:14550"])
    start_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start_yaw: float = 0.0
    battery_remaining: float = 1.0
    rate_hz: float = 50.0
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    offboard: OffboardConfig = field(default_factory=OffboardConfig)
    px4_failsafe: Px4FailsafeConfig = field(default_factory=Px4FailsafeConfig)
    seed: int | None = None

    def __post_init__(self) -> None:
        if self.flavour not in FLAVOURS:
            raise ValueError(f"flavour must be one of {FLAVOURS}, got {self.flavour!r}")
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz!r}")
        for url in self.outputs:
            _kind, _addr, forward = parse_link(url)
            if forward is False and self.flavour == "ardupilot":
                raise ValueError(f"link {url!r}: ArduPilot routes MAVLink on every link; "
                                 "forward= is PX4's MAV_X_FORWARD")


@dataclass(frozen=True)
class Truth:
    """The true state at one instant (world NED m, m/s; radians; mode as the autopilot's)."""

    t: float
    position: np.ndarray
    velocity: np.ndarray
    roll: float
    pitch: float
    yaw: float
    armed: bool
    landed: bool
    on_ground: bool
    custom_mode: int
    mode: str
    battery_remaining: float
    failsafes: frozenset[Failsafe]

    @property
    def altitude(self) -> float:
        return -float(self.position[2])


class Simulator:
    """A simulated multicopter speaking MAVLink as ArduPilot Copter or PX4 over UDP."""

    def __init__(self, config: SimConfig | None = None, world: Steppable | None = None) -> None:
        self.config = config or SimConfig()
        c = self.config
        self.vehicle = Vehicle(c.vehicle, c.start_position, c.start_yaw, c.battery_remaining)
        self.autopilot: Autopilot
        if c.flavour == "px4":
            self.autopilot = Px4Multicopter(self.vehicle, c.autopilot, offboard=c.offboard,
                                            failsafe=c.px4_failsafe, seed=c.seed)
        else:
            self.autopilot = ArduPilotCopter(self.vehicle, c.autopilot)
        self.world = world
        self._steppers: list[Callable[[float], Any]] = []
        if world is not None:
            self._steppers.append(world.step)
        self.endpoint = Endpoint([
            UdpLink(url, c.autopilot.system_id, c.autopilot.component_id,
                    self.autopilot.new_streams(), self._on_message,
                    seed=None if c.seed is None else c.seed + i)
            for i, url in enumerate(c.outputs)])
        self.routing: Routing = routing_for(c.flavour, self.endpoint.links,
                                            c.autopilot.system_id, c.autopilot.component_id)
        self._task: asyncio.Task[None] | None = None
        self._last: float | None = None
        self.steps = 0

    # ----- lifecycle -----

    async def start(self) -> None:
        if self._task is not None:
            return
        loop = asyncio.get_running_loop()
        self.autopilot.start_time = self.autopilot.now = loop.time()
        await self.endpoint.open()
        self._last = loop.time()
        self._task = asyncio.create_task(self._run(), name="simulator")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                pass
        self.endpoint.close()

    async def __aenter__(self) -> Simulator:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.config.rate_hz
        next_t = loop.time()
        while True:
            next_t += period
            now = loop.time()
            if next_t < now:  # fell behind (busy machine): skip ticks rather than burst
                next_t = now + period
            await asyncio.sleep(next_t - now)
            try:
                self._tick(loop.time())
            except Exception:
                # Keep flying: a bug in one step must not silently kill the vehicle's telemetry.
                log.exception("simulator step failed")

    def _tick(self, now: float) -> None:
        dt = now - (self._last if self._last is not None else now)
        self._last = now
        # Sub-step long gaps so limits and the ground contact stay honest.
        remaining = min(dt, 1.0)
        while remaining > 1e-9:
            h = min(remaining, 0.02)
            self.vehicle.step(h)
            remaining -= h
        self.autopilot.tick(now)
        for step in self._steppers:
            step(dt)
        for link in self.endpoint.links:
            for msg_id in link.streams.due(now):
                msg = self.autopilot.build(msg_id)
                if msg is not None:
                    link.send(msg)
        for msg in self.autopilot.pending_status_text():
            for link in self.endpoint.links:
                link.send(msg)
        self.steps += 1

    def _on_message(self, msg: Any, link: UdpLink) -> None:
        # Forward first, then act, as ArduPilot's check_and_forward and PX4's receiver do.
        self.routing.on_message(msg, link)
        self.autopilot.now = asyncio.get_running_loop().time()
        self.autopilot.handle_message(msg, link)

    # ----- what the tests and the camera use -----

    @property
    def truth(self) -> Truth:
        s, ap = self.vehicle.state, self.autopilot
        return Truth(
            t=time.monotonic(), position=s.position.copy(), velocity=s.velocity.copy(),
            roll=s.roll, pitch=s.pitch, yaw=s.yaw, armed=s.armed, landed=s.land_complete,
            on_ground=s.on_ground, custom_mode=ap.custom_mode,
            mode=ap.mode_name(),
            battery_remaining=float(self.vehicle.battery_remaining),
            failsafes=frozenset(ap.failsafes))

    def pose(self) -> Pose:
        """The true pose for the camera renderer: the vehicle's state as of the last physics step,
        and that step's time (``time.monotonic()`` seconds, the clock the telemetry's
        ``time_boot_ms`` counts on). Stamping it with the render time instead put the camera up to
        a starved tick ahead of the telemetry that describes the same state."""
        s = self.vehicle.state
        gimbal = None
        if self.config.autopilot.gimbal_pitch is not None:
            # Earth-stabilised pitch, yaw with the vehicle: R_body_from_cam = R_wb^T R_wc.
            r_wb = rotation_from_euler(s.roll, s.pitch, s.yaw)
            r_wc = rotation_from_euler(0.0, self.config.autopilot.gimbal_pitch, s.yaw)
            gimbal = r_wb.T @ r_wc
        t = self._last if self._last is not None else time.monotonic()
        return Pose(t, float(s.position[0]), float(s.position[1]),
                    float(s.position[2]), s.roll, s.pitch, s.yaw, gimbal)

    @property
    def links(self) -> list[UdpLink]:
        return self.endpoint.links

    @property
    def bad_packets(self) -> int:
        return self.endpoint.bad_packets

    def add_stepper(self, step: Callable[[float], Any]) -> None:
        """Step something else (a world of walking people) with the simulator clock (dt in s)."""
        self._steppers.append(step)

    def on_touchdown(self, callback: Callable[[], None]) -> None:
        """Call ``callback()`` when the land detector fires after flight."""
        self.autopilot.on_touchdown.append(callback)

    def inject_failsafe(self, kind: Failsafe | str) -> None:
        """Make the autopilot raise a failsafe (battery_low, battery_critical, rc_loss, gcs_loss)."""
        self.autopilot.trigger_failsafe(Failsafe(kind))

    def clear_failsafe(self, kind: Failsafe | str) -> None:
        self.autopilot.clear_failsafe(Failsafe(kind))

    def set_link_faults(self, loss: float = 0.0, latency_s: float = 0.0, *,
                        loss_tx: float | None = None, loss_rx: float | None = None,
                        latency_tx_s: float | None = None, latency_rx_s: float | None = None,
                        link: int | None = None) -> None:
        """Drop a share of datagrams and delay the rest, per direction (tx = from the vehicle)."""
        faults = LinkFaults(loss if loss_tx is None else loss_tx,
                            loss if loss_rx is None else loss_rx,
                            latency_s if latency_tx_s is None else latency_tx_s,
                            latency_s if latency_rx_s is None else latency_rx_s)
        targets = self.endpoint.links if link is None else [self.endpoint.links[link]]
        for lk in targets:
            lk.faults.faults = faults

    def take_off(self, altitude: float) -> None:
        """Arm and climb to ``altitude`` m above home as a pilot would (GUIDED / AUTO.TAKEOFF)."""
        ap = self.autopilot
        ap.set_mode(ap.mode_for(Behaviour.GUIDED if ap.FLAVOUR == "ardupilot"
                                else Behaviour.TAKEOFF))
        if not self.vehicle.state.armed:
            ap.arm()
        ap._start_takeoff(altitude)

    async def wait_for(self, predicate: Callable[[Truth], bool], timeout: float) -> Truth:
        """Poll the truth until ``predicate`` holds; TimeoutError after ``timeout`` seconds."""
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        while True:
            t = self.truth
            if predicate(t):
                return t
            if loop.time() > end:
                raise TimeoutError(f"condition not met within {timeout} s; truth: {t}")
            await asyncio.sleep(0.02)
