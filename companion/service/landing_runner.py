"""The async side of the landing controller: feeds it the vehicle state and executes its commands.

``LandingRunner`` ticks the ``LandingController`` at ``tick_hz`` with the latest ``VehicleState``,
forwards triggers and frames to it, executes the commands it returns through an ``Autopilot``
flavour one at a time (a newer position target replaces one still waiting, so a slow mode change
never builds a backlog of stale targets), reports each result back to it, and hands its typed events
to subscribers (the service records them) and sends their text as STATUSTEXT. Wiring in the service::

    runner = LandingRunner(LandingController(cfg), autopilot, state, link)
    monitor.subscribe(runner.on_trigger)
    task = asyncio.create_task(runner.run())
    ...  # after each frame: runner.on_frame(t, tracker.tracks(), pose)

Shadow mode (``shadow=True``): the controller runs as in a real takeover, but no command reaches
the autopilot: each is *withheld* (kept in ``withheld`` and handed to ``on_withheld`` listeners,
which the service records) and reported to the controller as done. The controller then goes on
deciding as if the autopilot had accepted (re-targets, holds, the commit to LAND, its timeouts), so
the pilot sees what it would do over the scene the camera really sees while the autopilot's own
failsafe flies the vehicle. Reporting them refused instead would end every shadow run in "3
commands failed" after its first target, which tells nothing. The story ends as a real one would
not: the vehicle does not fly to the zone, so the controller sees it coming down elsewhere
(LANDED "vehicle on the ground and disarmed", or a hold or takeover timeout handing back): every
event of a shadow run is therefore marked shadow, in the STATUSTEXT ("SHADOW: ...") and in the
recording.

Stopping (``halt``): the service halts the runner before its exit handback, so that the handback is
the last command the autopilot gets. A halted runner ticks no more, takes no trigger or frame, drops
what is queued and cancels the command in flight (its retries with it: a DO_SET_MODE waiting for an
ACK that never comes would otherwise be resent after the handback, and would hold the link's
per-command lock the handback needs). PX4's setpoint stream is left running: the handback switches
mode first and then stops it (stopping it first makes PX4 fire its offboard-loss action).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Sequence

from companion.control.aim import SpotSource
from companion.control.events import Event
from companion.control.landing import (
    Command,
    Goto,
    Handback,
    Land,
    LandingController,
    Phase,
    VehicleStatus,
)
from companion.control.trigger import Trigger
from companion.geometry.camera import Pose
from companion.mavlink.autopilot import Autopilot
from companion.mavlink.link import MavLink
from companion.mavlink.state import VehicleState
from companion.mavlink.statustext import event_severity, send_statustext, shadow_text
from companion.pipeline.circles import GroundBelow
from companion.pipeline.tracker import Track

log = logging.getLogger(__name__)


def vehicle_status(
    state: VehicleState, autopilot: Autopilot | None = None, now: float | None = None
) -> VehicleStatus | None:
    """The controller's view of the vehicle from the latest telemetry, or None without position/home.

    ``now`` (monotonic s; the clock when None) decides whether the rangefinder is fresh enough to
    give ``agl`` and counts the battery's time left down to it.
    """
    if state.position is None or state.home is None:
        return None
    ned = state.local_ned()
    if ned is None:
        return None
    now = time.monotonic() if now is None else now
    return VehicleStatus(
        state.position.t,
        *ned,
        home=state.home.point,
        mode=autopilot.mode if autopilot is not None else None,
        armed=state.armed,
        on_ground=None if state.landed is None else state.landed.on_ground,
        agl=state.altitude_above_ground(now),
        vn=state.position.vn,
        ve=state.position.ve,
        vd=state.position.vd,
        latency_s=state.clock.latency_s or 0.0,
        battery_s=_battery_s(state, now),
    )


def _battery_s(state: VehicleState, now: float) -> float | None:
    """The flight time the autopilot says its battery has left, counted down to ``now`` (s)."""
    b = state.battery_status  # SYS_STATUS has no time remaining
    if b is None or b.time_remaining_s is None:
        return None
    return max(0.0, b.time_remaining_s - max(0.0, now - b.t))


class LandingRunner:
    def __init__(
        self,
        controller: LandingController,
        autopilot: Autopilot,
        state: VehicleState,
        link: MavLink | None = None,
        *,
        tick_hz: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        shadow: bool = False,
    ) -> None:
        self.controller = controller
        self.autopilot = autopilot
        self.state = state
        self.link = link
        self.tick_hz = tick_hz
        self._clock = clock
        self._pending: list[Command] = []
        self._wake = asyncio.Event()
        self.executed: list[tuple[Command, Exception | None]] = []
        self._stopped_stream = False
        self._listeners: list[Callable[[Event], None]] = []
        self.shadow = shadow
        self.withheld: list[Command] = []  # shadow mode: every command not sent, in order
        self._withheld_listeners: list[Callable[[Command], None]] = []
        self.halted = False
        self._worker: asyncio.Task[None] | None = None
        self._speeds: asyncio.Task[None] | None = None

    def subscribe(self, listener: Callable[[Event], None]) -> None:
        """Call ``listener`` with every controller event, in order, as it is emitted (before its
        STATUSTEXT goes out); the service records them."""
        self._listeners.append(listener)

    def on_withheld(self, listener: Callable[[Command], None]) -> None:
        """Shadow mode: call ``listener`` with every command withheld from the autopilot."""
        self._withheld_listeners.append(listener)

    # -- inputs from the service ---------------------------------------------------------------

    def on_trigger(self, trigger: Trigger) -> None:
        if self.halted:
            return
        self._submit(self.controller.on_trigger(trigger))

    def on_frame(self, t: float, tracks: Sequence[Track], pose: Pose | None,
                 below: GroundBelow | None = None, view: SpotSource | None = None) -> None:
        if self.halted:
            return
        self._submit(self.controller.on_frame(t, tracks, pose, below, view))

    # -- loop ----------------------------------------------------------------------------------

    async def run(self) -> None:
        """Tick and execute until cancelled (stops the autopilot's setpoint stream on the way out)."""
        self._worker = asyncio.create_task(self._execute_loop(), name="landing commands")
        self._speeds = asyncio.create_task(self.read_autopilot_speeds(), name="autopilot speeds")
        try:
            while True:
                self.step()
                await asyncio.sleep(1.0 / self.tick_hz)
        finally:
            await self._stop_tasks()
            await self.autopilot.stop()

    async def halt(self) -> None:
        """Produce no command any more (see the module docstring): no tick, trigger or frame is
        taken, the queue is dropped and the command in flight cancelled. Idempotent; the setpoint
        stream, if any, is the caller's to stop (``autopilot.stop()``) after its handback."""
        if not self.halted:
            log.info("landing runner halted%s", f" ({len(self._pending)} queued command(s) dropped)"
                     if self._pending else "")
        self.halted = True
        self._pending.clear()
        await self._stop_tasks()

    async def _stop_tasks(self) -> None:
        for task in (self._speeds, self._worker):
            # Cancel until it is done: a cancellation racing with a command's completion must
            # not leave the worker alive (and this coroutine waiting for it forever).
            while task is not None and not task.done():
                task.cancel()
                await asyncio.wait({task}, timeout=0.5)

    async def read_autopilot_speeds(self) -> None:
        """Ask the autopilot for its descent speeds (parameters) once; the controller keeps the
        configured ones for what it does not answer. Never fatal."""
        try:
            speeds = await self.autopilot.descent_speeds()
        except Exception:  # a link or parsing fault: the configured speeds stay
            log.exception("reading the autopilot's descent speeds failed")
            return
        self.controller.use_autopilot_speeds(speeds, f"{self.autopilot.name} parameters")
        self._flush_events()

    def step(self) -> None:
        """One tick: the latest vehicle status, then timeouts."""
        if self.halted:
            return
        now = self._clock()
        status = vehicle_status(self.state, self.autopilot, now)
        if status is not None:
            self._submit(self.controller.on_state(status))
        self._submit(self.controller.tick(now))

    def _submit(self, commands: list[Command]) -> None:
        if self.halted:  # a command result arriving as the worker is cancelled: nothing more goes out
            commands = []
        for cmd in commands:
            if isinstance(cmd, Goto):
                self._pending = [c for c in self._pending if not isinstance(c, Goto)]
            elif isinstance(cmd, Handback):
                self._pending.clear()  # nothing queued before a handback may still run
            self._pending.append(cmd)
        if commands:
            self._wake.set()
        self._flush_events()

    async def _execute_loop(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._pending:
                cmd = self._pending.pop(0)
                error: Exception | None = None
                try:
                    await self._execute(cmd)
                except Exception as exc:  # CommandError, FlavourError, or a bug: reported, never fatal
                    error = exc
                    if not isinstance(exc, (RuntimeError, ValueError)):
                        log.exception("executing %s failed", cmd)
                if not self.shadow:  # executed: what reached the autopilot (shadow: ``withheld``)
                    self.executed.append((cmd, error))
                self._submit(self.controller.on_command_result(cmd, error))
            if self.controller.phase in (Phase.HANDBACK, Phase.LANDED) and not self._stopped_stream:
                # Covers the pilot-takeover handback, which sends no command: no stream left behind.
                self._stopped_stream = True
                await self.autopilot.stop()

    async def _execute(self, cmd: Command) -> None:
        if self.shadow:
            self._withhold(cmd)
            return
        if isinstance(cmd, Goto):
            await self.autopilot.goto(cmd.target)
        elif isinstance(cmd, Land):
            await self.autopilot.land()
        elif isinstance(cmd, Handback):
            await self.autopilot.handback(cmd.action)
        else:  # pragma: no cover - exhaustive
            raise TypeError(f"unknown command {cmd!r}")

    def _withhold(self, cmd: Command) -> None:
        """Shadow mode: the command goes nowhere; it is kept and told, and counts as done."""
        self.withheld.append(cmd)
        log.info("shadow: withheld %s", cmd)
        for listener in self._withheld_listeners:
            try:
                listener(cmd)
            except Exception:  # a listener's bug must not stop the controller
                log.exception("withheld-command listener failed on %s", cmd)

    def _flush_events(self) -> None:
        events = self.controller.pop_events()
        for event in events:
            for listener in self._listeners:
                try:
                    listener(event)
                except Exception:  # a listener's bug must not stop the landing
                    log.exception("event listener failed on %s", event)
        if self.link is None:
            return
        for event in events:
            text = shadow_text(event.text) if self.shadow else event.text
            send_statustext(self.link, text, event_severity(event))
        if self.controller.phase in (Phase.HANDBACK, Phase.LANDED) and not self._stopped_stream:
            self._wake.set()  # let the worker stop a setpoint stream
