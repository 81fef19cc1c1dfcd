"""The service: one asyncio process wiring link, camera, pipeline, failsafe, controller, recorder.

Start-up: load the density model (a bad file stops start-up, naming it), open the MAVLink link,
start the camera, wait for the first autopilot heartbeat, then tell systemd READY=1. From then on:

- the frame loop takes the newest camera frame (older ones are dropped and counted, never
  queued), pairs it with the pose at its capture time (placed on the autopilot's clock, and
  waiting up to ``MAX_TELEMETRY_LAG_S`` (``companion.mavlink.clock``) for the telemetry sampled
  after it rather than holding an older pose), records it, runs the pipeline in a worker
  thread (onnxruntime and OpenCV release the GIL) and hands the zones to the landing controller.
  A frame without a fresh pose is recorded but never used for decisions;
- the failsafe monitor turns telemetry into a trigger for the controller; SIGUSR1 is a local
  trigger;
- the command server answers every command a ground station addresses to the companion
  (``companion.mavlink.gcs_commands``): the trigger, camera and live-view information, and
  UNSUPPORTED for the rest; from the start, before the autopilot is heard;
- the health loop logs per-stage timings, frame counters and link/camera state every
  ``log.health_interval_s``, reports external faults (no autopilot heartbeat, camera not
  delivering) as ``STATUS=degraded: ...`` while it keeps feeding the systemd watchdog (a restart
  cannot fix an unplugged camera; the service reconnects by itself), and stops feeding it only on
  an internal fault, a pipeline call stuck beyond ``PIPELINE_STUCK_S`` (see ``health.assess``);
- the ground station sees the companion's health in its HEARTBEAT, each state change and decision
  as one STATUSTEXT, and a few numbers at ``gcs.values_hz`` (``gcs.GroundStation``); with
  ``live.enabled`` a small HTTP server gives a status page and the annotated live view (``web``);
- in shadow mode (``controller.shadow``, ``companion run --shadow``) everything runs and every
  decision is reported and recorded, marked shadow, but no command reaches the autopilot (the
  landing runner withholds them) and stopping hands nothing back;
- SIGTERM/SIGINT stop everything within 2 s (STOPPING=1 first); every shutdown step is guarded,
  so a failing one (a full disk, anything) is logged and the others still run, and the exit
  status is still 0.

The parts and what every concern reads from them are in ``wiring``; the frame loop, the reports
(health loop, ground station, status page) and the shutdown are mixins on them in ``frame_loop``,
``reports`` and ``shutdown``. This module puts them together with the start-up and the
controller's events.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from typing import Any

from companion import config as settings
from companion.control.commands import Command, Goto, Handback
from companion.control.events import Event
from companion.control.landing import LandingController
from companion.control.trigger import Trigger
from companion.mavlink.autopilot import FlavourError
from companion.mavlink.failsafe import FailsafeMonitor
from companion.mavlink.flavours import select_flavour
from companion.mavlink.statustext import event_severity, shadow_text
from companion.mavlink.timesync import run_timesync
from companion.recording import FlightRecorder
from companion.service.frame_loop import FrameLoop
from companion.service.landing_runner import LandingRunner
from companion.service.reports import Reports
from companion.service.shutdown import SHUTDOWN_BUDGET_S as SHUTDOWN_BUDGET_S  # the unit's stop budget
from companion.service.shutdown import Shutdown

log = logging.getLogger("companion.service")


class Service(FrameLoop, Reports, Shutdown):
    """The running daemon. ``await Service(cfg, model).run()`` returns the exit code.

    Its parts are built from the settings unless given (``wiring.ServiceParts``); the frame loop,
    the reports and the shutdown are mixins on them. Here: start-up, signals, the wiring of the
    parts that depend on the autopilot, and what follows the controller's events.
    """

    # ---- lifecycle ---------------------------------------------------------------------------
    def request_stop(self, why: str = "") -> None:
        if not self.stop_event.is_set():
            log.info("stopping%s", f" ({why})" if why else "")
            self.notifier.stopping()
            self.stop_event.set()

    def _install_signals(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            loop.add_signal_handler(signal.SIGTERM, self.request_stop, "SIGTERM")
            loop.add_signal_handler(signal.SIGINT, self.request_stop, "SIGINT")
            loop.add_signal_handler(signal.SIGUSR1, self._local_trigger)
        except (RuntimeError, ValueError):
            # Not the main thread (a test driving the service in-process): it stops by
            # request_stop() instead.
            log.debug("signal handlers not installed: not in the main thread")

    def _local_trigger(self) -> None:
        if self.monitor is None:
            log.warning("SIGUSR1 ignored: not connected to the autopilot yet")
            return
        self.monitor.trigger_local("SIGUSR1 to the service")

    def _warn_unsigned(self, connected: bool = True) -> None:
        """Loud, at start and at every link-up: an unsigned link trusts whoever claims the ids."""
        if connected and self.link.config.signing_key is None:
            log.warning("MAVLink link %s is UNSIGNED: anyone who reaches it can feed the companion a pose "
                        "or a fake heartbeat and be flown to. Set link.signing_key_file and "
                        "link.require_signing (docs/signing.md).", self.cfg.link.url)

    async def run(self) -> int:
        self._install_signals()
        c = self.cfg
        self.state.attach(self.link)
        self.commands.attach()
        self._warn_unsigned()
        self.link.on_link_change(self._warn_unsigned)
        try:
            await self.link.start()
        except OSError as exc:
            log.error("cannot open the MAVLink link %s: %s", c.link.url, exc)
            return 1
        self.camera.start()
        await self._start_web()
        tasks: list[asyncio.Task[Any]] = []
        try:
            self.notifier.status(f"waiting for the autopilot heartbeat on {c.link.url}")
            if not await self._wait_heartbeat():
                return 0  # stopped before the autopilot appeared
            try:
                self._wire_vehicle()
            except FlavourError as exc:
                log.error("%s", exc)
                return 2
            if self.monitor is not None and c.failsafe.local_trigger and c.failsafe.local_socket:
                try:
                    await self.monitor.start_local_socket()
                    log.info("local trigger socket: %s", c.failsafe.local_socket)
                except (OSError, ValueError) as exc:
                    log.error("local trigger socket %s not started: %s", c.failsafe.local_socket, exc)
            if c.recorder.enabled:
                self._start_recorder()
            log.info("ready: model %s, link %s, camera %s", c.model.path, c.link.url, c.camera.source)
            if self.shadow:
                log.warning("SHADOW MODE: decisions are reported and recorded, no command is sent to the "
                            "autopilot (controller.shadow)")
            self.gcs.set_ready(self._ready_texts())
            self.notifier.ready(self._status_line())
            tasks = [
                asyncio.create_task(self._frame_loop(), name="frames"),
                asyncio.create_task(self._health_loop(), name="health"),
            ]
            tasks.append(asyncio.create_task(run_timesync(self.link, self.state.clock), name="timesync"))
            if self.runner is not None:
                tasks.append(asyncio.create_task(self.runner.run(), name="controller"))
            if c.gcs.values_hz > 0:
                tasks.append(asyncio.create_task(self._values_loop(), name="named values"))
            if self.live is not None and self.web is not None:
                tasks.append(asyncio.create_task(self.live.run(), name="live view"))
            stop = asyncio.create_task(self.stop_event.wait())
            tasks.append(stop)
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if task is not stop and task.exception() is not None:
                    log.error("task %s failed: %r", task.get_name(), task.exception(),
                              exc_info=task.exception())
                    self.request_stop("internal error")
                    return 1
            return 0
        finally:
            self.notifier.stopping()
            await self._shutdown(tasks)

    async def _wait_heartbeat(self) -> bool:
        """Wait for the first autopilot heartbeat, feeding the watchdog meanwhile (waiting for a
        flight controller to boot is normal, not a hang). False when asked to stop first."""
        interval = self.notifier.watchdog_interval
        last_log = time.monotonic()
        while not self.link.connected:
            if self.stop_event.is_set():
                return False
            if interval:
                self.notifier.watchdog()
            if time.monotonic() - last_log > 10:
                log.info("still waiting for an autopilot heartbeat on %s", self.cfg.link.url)
                last_log = time.monotonic()
            try:
                await asyncio.wait_for(self.stop_event.wait(), 0.05)
            except (TimeoutError, asyncio.TimeoutError):
                pass
        return True

    def _wire_vehicle(self) -> None:
        c = self.cfg
        self.autopilot = select_flavour(self.link, c.link.flavour)
        log.info("autopilot flavour: %s", self.autopilot.name)
        self.monitor = FailsafeMonitor(settings.failsafe_config(c), self.link, self.autopilot)
        self.monitor.attach(self.commands)
        # The landing controller behind its async runner: commands through the autopilot
        # flavour, events recorded here and sent to the ground station as STATUSTEXT.
        self.runner = LandingRunner(LandingController(settings.landing_config(c, self.model.spec)), self.autopilot,
                                    self.state, self.link, shadow=self.shadow)
        self.runner.subscribe(self._on_controller_event)
        self.runner.on_withheld(self._on_withheld)
        self.monitor.subscribe(self._on_trigger)

    # ---- controller events and recording -----------------------------------------------------
    def _on_controller_event(self, event: Event) -> None:
        """Every controller event, as it happens: recorded (the simulator's judge and replay read
        these, never the log) and, for a phase change, logged for the operator."""
        self.events.append(event)
        self.decisions.append((event.t, event_severity(event), shadow_text(event.text) if self.shadow else event.text))
        # In shadow mode every record says so: these are decisions nobody carried out.
        mark = {"shadow": True} if self.shadow else {}
        if event.changed:
            log.warning("landing controller: %s%s -> %s", "(shadow) " if self.shadow else "",
                        event.old.value, event.phase.value)
            self._record_event("phase", event.t, old=event.old.value, new=event.phase.value, **mark)
            if self.cfg.gcs.values_hz > 0 and self.gcs.ready:
                # Every phase reaches the ground station's plot, not only the one a 1 Hz sample
                # happens to catch: a zone right under the camera goes SELECT -> APPROACH ->
                # DESCEND within one frame.
                self._send_values(event.phase)
        record = event.as_record()
        del record["t"]  # the recording's own time field
        self._record_event("controller", event.t, **record, **mark)

    def _on_withheld(self, cmd: Command) -> None:
        """Shadow mode: a command the controller gave and nobody sent, recorded as such."""
        data: dict[str, Any] = {"command": type(cmd).__name__}
        if isinstance(cmd, Goto):
            data.update(zone_id=cmd.zone_id, north=cmd.north, east=cmd.east, rel_alt_m=cmd.target.rel_alt_m)
        elif isinstance(cmd, Handback):
            data.update(action=cmd.action, reason=cmd.reason)
        self._record_event("shadow_command", time.monotonic(), **data)

    def _on_trigger(self, trigger: Trigger) -> None:
        log.warning("failsafe trigger: %s (%s)", trigger.reason, trigger.source.value)
        self._record_event("trigger", trigger.t, reason=trigger.reason, source=trigger.source.value)
        if self.runner is not None:
            self.runner.on_trigger(trigger)
        else:
            log.warning("no landing controller: the autopilot's own failsafe stays in charge")

    #: Telemetry written to the recording's events.jsonl (kind "telemetry"), at the rate received.
    RECORDED_TELEMETRY = ("HEARTBEAT", "ATTITUDE", "GLOBAL_POSITION_INT", "HOME_POSITION", "SYS_STATUS",
                          "BATTERY_STATUS", "EXTENDED_SYS_STATE", "DISTANCE_SENSOR", "STATUSTEXT",
                          "GIMBAL_DEVICE_ATTITUDE_STATUS", "COMMAND_ACK")

    def _record_telemetry(self, msg: Any, t: float) -> None:
        if self.recorder is None:
            return
        data = msg.to_dict()
        data.pop("mavpackettype", None)
        self.recorder.add_event("telemetry", t, msg=msg.get_type(), **{
            k: (v.decode("utf-8", "replace").rstrip("\x00") if isinstance(v, (bytes, bytearray)) else v)
            for k, v in data.items() if k not in ("t", "kind", "msg")})

    def _start_recorder(self) -> None:
        c = self.cfg
        self.recorder = FlightRecorder(
            c.recorder.dir, max_mb=c.recorder.max_mb,
            fps=c.camera.fps, intrinsics=self.intrinsics, mount=self.mount,
            meta={"model": {"path": str(c.model.path), "spec": self.model.spec}, "config": c.to_dict(),
                  "autopilot": self.autopilot.name if self.autopilot else None, "shadow": self.shadow},
        )
        try:
            self.recorder.start()
        except OSError as exc:
            # Recording is a convenience; flying safely is not optional. Keep going without it.
            log.error("recorder disabled: cannot write to %s: %s", c.recorder.dir, exc)
            self.recorder = None
            return
        for name in self.RECORDED_TELEMETRY:
            self.link.subscribe(name, self._record_telemetry)
