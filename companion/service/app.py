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
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from collections import deque
from dataclasses import asdict
from typing import Any

import cv2
import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as m

from companion import config as settings
from companion.config import Config
from companion.control.commands import Command, Goto, Handback
from companion.control.events import Event, Phase
from companion.control.landing import LandingController
from companion.control.trigger import Trigger
from companion.geometry.camera import GeometryError, Pose
from companion.mavlink.autopilot import Autopilot, FlavourError
from companion.mavlink.failsafe import TRIGGER_COMMAND, FailsafeMonitor
from companion.mavlink.flavours import select_flavour
from companion.mavlink.gcs_commands import CommandServer, Reply, VideoStream, VideoStreamProvider
from companion.mavlink.link import MavLink
from companion.mavlink.state import MAX_POSE_AGE_S, VehicleState
from companion.mavlink.statustext import event_severity, send_statustext, shadow_text
from companion.mavlink.timesync import run_timesync
from companion.pipeline.density import DensityModel, DensityModelError, FrameError
from companion.pipeline.landability import UnlandableMap
from companion.pipeline.slz import FrameResult, SLZPipeline
from companion.pipeline.tracker import Track
from companion.recording import FlightRecorder
from companion.replay.live_figure import CAPTION_PX
from companion.service.camera import CameraSource, Frame
from companion.service.frame_use import UNUSABLE, FrameUse, geometry_reason, pose_reason
from companion.service.gcs import PHASE_CODES, GroundStation
from companion.service.health import PIPELINE_STUCK_S, FaultLog, FrameCounters, Health, StageTimings, assess
from companion.service.landing_runner import LandingRunner
from companion.service.notify import Notifier
from companion.service.parts import build_camera, build_pipeline
from companion.service.pilot_view import clearance_note, vehicle_fields
from companion.service.web import LiveView, Snapshot, WebServer, live_video_stream, stream_uri

log = logging.getLogger("companion.service")

#: Main-loop tick for watchdog and health checks (s).
TICK_S = 0.25
#: How often a frame waiting for its telemetry checks again (s).
POSE_POLL_S = 0.01
#: Decisions kept for the status page.
DECISIONS_KEPT = 20
#: SIGTERM to exit (s): the promise is 2 s (the unit's TimeoutStopSec=5 is the backstop). Every
#: shutdown step gets at most what is left of it (and at least SHUTDOWN_STEP_MIN_S).
SHUTDOWN_BUDGET_S = 1.8
SHUTDOWN_STEP_MIN_S = 0.05


class Service:
    """The running daemon. ``await Service(cfg, model).run()`` returns the exit code.

    Its parts are built from the settings unless given: a test drives it in-process by handing it
    a link, a camera or a pipeline of its own (real ones, pointed at the simulator). The parts
    that depend on the autopilot (flavour, failsafe monitor, landing runner) are made once its
    first heartbeat says which autopilot it is.
    """

    def __init__(self, cfg: Config, model: DensityModel, notifier: Notifier | None = None, *,
                 link: MavLink | None = None, camera: CameraSource | None = None,
                 pipeline: SLZPipeline | None = None,
                 video_stream: VideoStreamProvider | None = None,
                 surface: UnlandableMap | None = None) -> None:
        self.cfg = cfg
        self.model = model
        self.notifier = notifier or Notifier()
        self.intrinsics = settings.intrinsics(cfg)
        self.mount = settings.mount(cfg)
        self.pipeline = pipeline or build_pipeline(cfg, model, surface)
        self.link = link or MavLink(settings.link_config(cfg))
        # Answers to the ground station's commands. ``video_stream`` gives the live view's
        # VIDEO_STREAM_INFORMATION once there is one (None: "no live view configured"); by
        # default the service's own (``live.enabled``), asked only when a request comes.
        self.commands = CommandServer(self.link, camera=settings.camera_info(cfg),
                                      video=video_stream or self.live_video_stream)
        self.commands.register(TRIGGER_COMMAND, self._trigger_before_wiring)
        # Telemetry placed in time by the autopilot's clock; a frame may still be paired with a
        # held pose up to max_pose_age_s old, which then carries its true age to the controller.
        self.state = VehicleState(max_extrapolation_s=MAX_POSE_AGE_S,
                                  clock=settings.autopilot_clock(cfg))
        self.camera = camera or build_camera(cfg)
        self.timings = StageTimings()
        self.counters = FrameCounters()
        self.frame_use = FrameUse()  # why frames cannot be decided with, for health
        self.stop_event = asyncio.Event()
        self.busy_since: float | None = None
        self.last_processed_t: float | None = None
        self.autopilot: Autopilot | None = None
        self.monitor: FailsafeMonitor | None = None
        self.runner: LandingRunner | None = None
        self.recorder: FlightRecorder | None = None
        self.events: list[Event] = []  # every controller event of this run, in order
        self.shadow = cfg.controller.shadow
        self.gcs = GroundStation(self.link, frame_budget_ms=settings.frame_budget_ms(cfg))
        self.live = LiveView() if cfg.live.enabled else None
        self.web: WebServer | None = None
        self.web_error: str | None = None
        self.decisions: deque[tuple[float, int, str]] = deque(maxlen=DECISIONS_KEPT)  # (t, severity, text)
        self.last_result: FrameResult | None = None

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

    @staticmethod
    def _trigger_before_wiring(msg: Any, t: float, broadcast: bool) -> Reply | None:
        """The trigger before the autopilot is heard: nobody could fly the landing yet."""
        return None if broadcast else Reply(m.MAV_RESULT_DENIED, "SLZ: trigger refused: no autopilot yet")

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

    @property
    def controller(self) -> LandingController | None:
        return None if self.runner is None else self.runner.controller

    @property
    def phase(self) -> str:
        return Phase.MONITOR.value if self.controller is None else self.controller.phase.value

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

    async def _handback_on_exit(self) -> None:
        """Stopping while the companion has the vehicle (GUIDED/OFFBOARD toward a zone, or
        holding) must not leave it hovering with nobody in charge: give it back to the
        autopilot's own failsafe first. In LAND the autopilot is already landing by itself.
        The runner is halted by then (``_shutdown``), so this is the last command sent; PX4's
        setpoint stream stops after it, acknowledged or not."""
        if self.autopilot is None:
            return
        try:
            if self.phase not in ("SELECT", "APPROACH", "DESCEND", "HOLD", "SEARCH") or self.shadow:
                return  # shadow: the companion never had the vehicle, nothing to give back
            action = self.cfg.controller.handback_action
            log.warning("stopping during %s: handing back to the autopilot (%s)", self.phase, action)
            try:
                send_statustext(self.link, f"SLZ: companion stopping; handing back ({action})",
                                m.MAV_SEVERITY_WARNING, last=True)
                # Insist within the shutdown's budget: one packet can be lost (at 20 % loss one
                # shutdown in five left the vehicle in GUIDED/OFFBOARD), so resend every 0.25 s
                # until acknowledged, five times at most (1.25 s).
                await asyncio.wait_for(self.autopilot.handback(action, timeout_s=0.25, retries=4), 1.3)
            except Exception as exc:  # timeouts, refusals: nothing more we can do on the way out
                log.error("handback on exit failed: %r", exc)
        finally:
            await self.autopilot.stop()

    async def _shutdown(self, tasks: list[asyncio.Task[Any]]) -> None:
        """Stop every part, in order, within SHUTDOWN_BUDGET_S. Each step is guarded: one that
        fails (OSError on a full disk, anything) or overruns is logged and the rest still run,
        so a stop always ends with the link closed and exit status 0."""
        deadline = time.monotonic() + SHUTDOWN_BUDGET_S

        def left(most: float) -> float:
            return max(min(most, deadline - time.monotonic()), SHUTDOWN_STEP_MIN_S)

        # Every producer of commands stops before the last handback, so that it is the last
        # command sent: the runner (its ticks, queue and command in flight with its retries)
        # and the link's own requests (message intervals). Nothing else sends commands.
        if self.runner is not None:
            await self._shutdown_step("landing runner", self.runner.halt(), left(0.3))
        self.link.stop_requests()
        if self.runner is not None:
            await self._shutdown_step("handback", self._handback_on_exit(), left(1.4))
        if self.monitor is not None:
            await self._shutdown_step("local trigger socket", self.monitor.stop_local_socket(), left(0.5))
        for task in tasks:
            task.cancel()
        await self._shutdown_step("tasks", self._reap(tasks), left(0.5))
        if self.web is not None:
            await self._shutdown_step("web server", self.web.close(), left(0.5))
        budget = left(1.0)
        await self._shutdown_step("camera", asyncio.to_thread(self.camera.stop, budget), budget + 0.1)
        if self.recorder is not None:
            budget = left(1.0)
            await self._shutdown_step("recorder", asyncio.to_thread(self.recorder.close, budget), budget + 0.1)
        self.gcs.outbox.flush_all()  # texts still waiting their turn: now or never
        await self._shutdown_step("link", self.link.close(), left(1.0))
        log.info("stopped")

    @staticmethod
    async def _reap(tasks: list[asyncio.Task[Any]]) -> None:
        """Wait for cancelled tasks; how they ended does not matter any more."""
        for task in tasks:
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass

    @staticmethod
    async def _shutdown_step(name: str, step: Any, timeout: float) -> None:
        """Await one shutdown step for at most ``timeout`` s; log, never raise, when it fails."""
        try:
            await asyncio.wait_for(step, timeout)
        except (TimeoutError, asyncio.TimeoutError):
            log.error("shutdown: %s did not finish within %.2f s; going on", name, timeout)
        except asyncio.CancelledError:
            me = asyncio.current_task()
            # Task.cancelling() is 3.11+; on 3.10 a cancelled step is logged and the (bounded)
            # shutdown goes on to the next step, the handback included.
            if me is not None and getattr(me, "cancelling", lambda: 0)():
                raise  # this task itself is being cancelled: let it go
            log.error("shutdown: %s failed: cancelled", name)
        except Exception as exc:  # a full disk (OSError), a part's bug: log it and go on
            log.error("shutdown: %s failed: %s: %s", name, type(exc).__name__, exc)

    # ---- frames ------------------------------------------------------------------------------
    def _prepare(self, image: np.ndarray) -> np.ndarray:
        """Frames are brought to the calibrated resolution (the intrinsics describe that size)."""
        w, h = self.intrinsics.width, self.intrinsics.height
        if image.shape[1] != w or image.shape[0] != h:
            image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
        return image

    async def _next_paired_frame(self, pending: deque[Frame]) -> Frame | None:
        """The newest frame whose pose can be judged: the telemetry sampled after its capture
        has arrived (so the pose is interpolated, not held), or it waited ``MAX_TELEMETRY_LAG_S``
        for it. Frames wait in ``pending`` meanwhile; older ready ones are superseded (counted).
        With a 200 ms link the frames are used 200 ms late rather than paired with old poses."""
        frame = await self.camera.next_frame(timeout=POSE_POLL_S if pending else 0.5)
        if frame is not None:
            pending.append(frame)
        now = time.monotonic()
        wait = self.state.clock.max_lag_s
        ready: Frame | None = None
        while pending and (self.state.covers(pending[0].t) or now - pending[0].t > wait):
            if ready is not None:
                self.counters.superseded += 1
            ready = pending.popleft()
        return ready

    async def _frame_loop(self) -> None:
        pending: deque[Frame] = deque(maxlen=64)
        while not self.stop_event.is_set():
            frame = await self._next_paired_frame(pending)
            if frame is None:
                continue
            image = self._prepare(frame.image)
            pose: Pose | None = self.state.pose_at(frame.t)
            if self.recorder is not None:
                # The camera's own JPEG when the frame is recorded as it came (not resized).
                self.recorder.add_frame(frame.index, frame.t, image, pose,
                                        jpeg=frame.jpeg if image is frame.image else None)
            if pose is None:
                # Stale is unsafe: without a pose at capture time the frame can't be placed on
                # the ground, and must not confirm or move any zone.
                self.counters.no_pose += 1
                self._refused(image, pose_reason(self.state))
                continue
            self.busy_since = time.monotonic()
            try:
                result = await asyncio.to_thread(self.pipeline.process, image, frame.t, pose)
            except (FrameError, GeometryError) as exc:
                self.counters.bad += 1
                self._refused(image, UNUSABLE if isinstance(exc, FrameError) else geometry_reason(
                    self.state, pose, self.mount, self.cfg.pipeline.head_height_m))
                # First one visible (e.g. "camera is not above the head plane" on the ground),
                # then only now and then: a stream of identical warnings helps nobody.
                level = logging.INFO if self.counters.bad == 1 or self.counters.bad % 500 == 0 else logging.DEBUG
                log.log(level, "frame %d not usable (%d so far): %s", frame.index, self.counters.bad, exc)
                continue
            except (DensityModelError, ValueError) as exc:
                self.counters.errors += 1
                self._refused(image, UNUSABLE)
                if self.counters.errors <= 10 or self.counters.errors % 100 == 0:
                    log.warning("frame %d: pipeline failed: %s", frame.index, exc)
                continue
            finally:
                self.busy_since = None
            self.counters.processed += 1
            self.last_processed_t = time.monotonic()
            self.frame_use.used(self.last_processed_t)
            self.timings.add(result.timings_ms)
            self.last_result = result
            target: Track | None = None
            if self.runner is not None:
                # The controller decides on this frame before the next is processed: the frame's
                # ground view reads the risk map as this frame left it.
                self.runner.on_frame(frame.t, result.tracks, pose, result.below, result.ground)
                # The zone the vehicle flies to, or would fly to now: the planner's choice, the
                # one rule (the pipeline reports tracks; it does not pick).
                target = self.runner.controller.zone_target()
            now = time.monotonic()
            # Capture to decision: the controller has seen the frame's zones by now.
            self.gcs.frame(result.timings_ms.get("total", float("nan")), (now - frame.t) * 1000.0, now)
            if self.live is not None and self.live.wants(now):
                self.live.offer(Snapshot(image, result, None if target is None else target.id,
                                         self._caption(result, target)), now)
            self._record_event("zones", frame.t, frame=frame.index,
                               tracks=[asdict(t) for t in result.tracks],
                               target=None if target is None else target.id,
                               timings_ms=result.timings_ms)

    def _refused(self, image: np.ndarray, reason: str) -> None:
        """A frame not decided with: counted for health, and shown raw with ``reason`` in the live view."""
        now = time.monotonic()
        self.frame_use.refused(reason, now)
        if self.live is not None and self.live.wants(now):
            self.live.offer(Snapshot(image, None, None, self._caption(None, None), reason), now)

    def _record_event(self, kind: str, t: float, **data: Any) -> None:
        if self.recorder is not None:
            self.recorder.add_event(kind, t, **data)

    # ---- health ------------------------------------------------------------------------------
    def health(self, now: float) -> Health:
        """The verdict: internal faults (pipeline stuck) stop the watchdog, external ones (link,
        camera, frames that cannot be used) are only reported."""
        busy = self.busy_since
        return assess(link_connected=self.link.connected, camera_delivering=self.camera.delivering(now),
                      busy_s=None if busy is None else now - busy, stuck_after_s=PIPELINE_STUCK_S,
                      camera_frozen=self.camera.frozen(now), frames=self.frame_use.state(now))

    def _status_line(self) -> str:
        target = None if self.controller is None else self.controller.zone_target()
        zone = f"oldest stable zone {target.id} r={target.r:.1f} m" if target is not None else "no zone"
        return f"{self.phase}: {zone}"

    # ---- ground station, status page and live view -------------------------------------------
    def _ready_texts(self) -> list[str]:
        """The STATUSTEXTs of readiness (each within 50 characters)."""
        model = self.cfg.model.path.rsplit("/", 1)[-1].removesuffix(".onnx")[:14]
        texts = [f"SLZ: ready, model {model}, camera {self.intrinsics.width}x{self.intrinsics.height}"]
        if self.shadow:
            texts.append("SHADOW: on; the companion will command nothing")
        if self.web_error is not None:
            texts.append(f"SLZ: {self.web_error}"[:50])
        return texts

    async def _start_web(self) -> None:
        """The status page and live view, when enabled. A port in use or an address not on this
        host is logged and told to the ground station, and the service runs on without them:
        the page is a convenience, landing is not."""
        if self.live is None:
            return
        live = self.cfg.live
        web = WebServer(live, self.live, self.status_json)
        try:
            await web.start()
        except OSError as exc:
            self.web_error = f"status page off: {live.address}:{live.port} {exc.strerror or exc}"
            log.error("live.address/live.port: cannot serve the status page and live view on %s:%d: %s; "
                      "running without them", live.address, live.port, exc)
            return
        self.web = web
        log.info("status page on http://%s:%d/, live view %s", live.address, web.port, stream_uri(live))

    def live_video_stream(self) -> VideoStream | None:
        """The live view as VIDEO_STREAM_INFORMATION announces it, None while it is off or could
        not start: the provider of the ground station's camera protocol (``self.commands``)."""
        if self.live is None or self.web is None:
            return None
        w, h = self.intrinsics.width, self.intrinsics.height
        # The figure: the frame and its square head-plane view side by side, under the caption.
        return live_video_stream(self.cfg.live, w + 4 + h, h + CAPTION_PX)

    def _target_numbers(self) -> tuple[Track | None, float | None]:
        """The target (flown to, or the one it would fly to now) and its least clearance at
        touchdown if it committed now: the controller's own figure (``DescentProfile`` with the
        autopilot's descent speeds, as replay computes ``clearance_m``)."""
        c = self.controller
        target = None if c is None else c.zone_target()
        return target, None if c is None or target is None else c.touchdown_clearance(target)

    def _caption(self, result: FrameResult | None, target: Track | None) -> str:
        shadow = "SHADOW  " if self.shadow else ""
        aim = "no target" if target is None else f"target #{target.id} r {target.r:.1f} m"
        zones = "" if result is None else f"zones {len(result.tracks)}  "
        return (f"{shadow}{self.phase}  {zones}{aim}  "
                f"{time.strftime('%H:%M:%S')}")

    def _send_values(self, phase: Phase) -> None:
        """The ground station's numbers now, with ``phase`` as SLZ_PHASE."""
        now = time.monotonic()
        target, clearance = self._target_numbers()
        result = self.last_result
        self.gcs.values(now, phase=phase, zones=0 if result is None else len(result.tracks),
                        health=self.health(now), target_r_m=None if target is None else target.r,
                        clearance_m=clearance)

    async def _values_loop(self) -> None:
        period = 1.0 / self.cfg.gcs.values_hz
        while True:
            self._send_values(Phase(self.phase))
            await asyncio.sleep(period)

    def status_json(self) -> dict[str, Any]:
        """What the status page shows (``/status.json``): plain JSON, no NaN."""
        now = time.monotonic()
        health = self.health(now)
        target, clearance = self._target_numbers()
        result = self.last_result

        def finite(v: float | None, nd: int = 2) -> float | None:
            return None if v is None or not np.isfinite(v) else round(float(v), nd)

        c = self.controller
        zones = [] if result is None else [
            {"id": tr.id, "north_m": finite(tr.x), "east_m": finite(tr.y), "r_m": finite(tr.r), "age": tr.age,
             "clearance_m": None if c is None else finite(c.touchdown_clearance(tr))}
            for tr in result.tracks]
        return {
            "ready": self.gcs.ready,
            "shadow": self.shadow,
            "phase": self.phase,
            "phase_code": PHASE_CODES[Phase(self.phase)],
            "health": {"ok": health.ok, "standby": health.standby, "reason": health.reason,
                       "system_status": self.link.system_status},
            "vehicle": vehicle_fields(self.state, self.autopilot, c, self.events, now),
            "clearance_note": clearance_note(c),
            "zones": zones,
            "target": None if target is None else {"id": target.id, "r_m": finite(target.r),
                                                   "clearance_m": finite(clearance)},
            "frames_processed": self.counters.processed,
            "frame_ms": finite(self.gcs.frame_ms, 1),
            "fps": finite(self.gcs.fps(now), 1),
            "decisions": [{"age_s": round(now - t, 1), "severity": sev, "text": text}
                          for t, sev, text in reversed(self.decisions)],
            "live": None if self.live is None else {"stream": "/stream.mjpg", "clients": self.live.clients,
                                                    "drawn": self.live.stats.drawn, "dropped": self.live.stats.dropped},
        }

    async def _health_loop(self) -> None:
        interval = self.notifier.watchdog_interval
        next_log = time.monotonic() + self.cfg.log.health_interval_s
        faults = FaultLog()  # a few lines per fault, however long it lasts or often it flaps
        last_ping = 0.0
        while not self.stop_event.is_set():
            now = time.monotonic()
            health = self.health(now)
            # External faults keep the pings going (restarting cannot fix them); an internal one
            # stops them, and systemd restarts the process after WatchdogSec.
            if health.feed_watchdog and interval is not None and now - last_ping >= min(interval, 1.0):
                self.notifier.watchdog()
                last_ping = now
            for level, line in faults.update(health, now):
                log.log(level, "health: %s", line)
            self.gcs.update(health, now)
            self.notifier.status(health.status(self._status_line()))
            if now >= next_log:
                next_log = now + self.cfg.log.health_interval_s
                self._log_health(health.ok, health.reason)
            try:
                await asyncio.wait_for(self.stop_event.wait(), TICK_S)
            except (TimeoutError, asyncio.TimeoutError):
                pass

    def _log_health(self, ok: bool, why: str) -> None:
        cs, fc, ls = self.camera.stats, self.counters, self.link.stats
        ck, clock = self.state.clock.stats, self.state.clock
        latency = clock.latency_s
        log.info(
            "health %s: frames camera=%d processed=%d dropped=%d repeated=%d stale=%d corrupt=%d no_pose=%d "
            "superseded=%d bad=%d errors=%d stalls=%d | link rx=%d bad=%d unknown=%d foreign=%d lost=%d "
            "| telemetry late=%d backwards=%d rejected=%d clock=%s latency=%s "
            "| gcs commands=%d refused=%d malformed=%d | timings %s%s",
            "ok" if ok else f"BAD ({why})", cs.frames, fc.processed, cs.dropped, cs.repeated, cs.stale, cs.corrupt,
            fc.no_pose, fc.superseded, fc.bad, fc.errors, cs.stalls, ls.received, ls.bad, ls.unknown,
            self.link.transport.foreign, ls.link_losses, ck.late, ck.backwards, self.state.rejected, clock.source,
            "-" if latency is None else f"{latency * 1000:.0f}ms",
            self.commands.stats.answered, self.commands.stats.refused, self.commands.stats.malformed,
            self.timings.format() or "-",
            "" if self.recorder is None else
            f" | recorder frames={self.recorder.stats.frames} dropped={self.recorder.stats.dropped}"
            f" errors={self.recorder.stats.errors} downsampled={self.recorder.stats.downsampled}",
        )

