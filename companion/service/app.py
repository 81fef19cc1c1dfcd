"""The service: one asyncio process wiring link, camera, pipeline, failsafe, controller, recorder.

Start-up: load the density model (a bad file stops start-up, naming it), open the MAVLink link,
start the camera, wait for the first autopilot heartbeat, then tell systemd READY=1. From then on:

- the frame loop takes the newest camera frame (older ones are dropped and counted, never
  queued), pairs it with the pose at its capture time, records it, runs the pipeline in a worker
  thread (onnxruntime and OpenCV release the GIL) and hands the zones to the landing controller.
  A frame without a fresh pose is recorded but never used for decisions;
- the failsafe monitor turns telemetry into a trigger for the controller; SIGUSR1 is a local
  trigger;
- the health loop logs per-stage timings, frame counters and link/camera state every
  ``log.health_interval_s`` and feeds the systemd watchdog only while the link is alive, the
  camera delivers and the pipeline is not stuck;
- SIGTERM/SIGINT stop everything within about a second (STOPPING=1 first).
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.config import Config
from companion.geometry.camera import GeometryError, Intrinsics, Mount, Pose
from companion.pipeline.density import DensityModel, DensityModelError, FrameError
from companion.service.camera import CameraSource
from companion.service.health import FrameCounters, StageTimings
from companion.service.notify import Notifier
from companion.recording import FlightRecorder

log = logging.getLogger("companion.service")

#: A pipeline call running longer than this counts as stuck (the watchdog stops being fed).
PIPELINE_STUCK_S = 5.0
#: Main-loop tick for watchdog and health checks (s).
TICK_S = 0.25


def intrinsics_from_config(cfg: Config) -> Intrinsics:
    """Pinhole intrinsics for ``camera.width x camera.height`` from the config (pixels)."""
    c = cfg.camera
    base = Intrinsics.from_fov(c.width, c.height, c.hfov_deg)
    fx = c.fx or base.fx
    fy = c.fy or fx
    cx = base.cx if c.cx < 0 else c.cx
    cy = base.cy if c.cy < 0 else c.cy
    return Intrinsics(fx, fy, cx, cy, c.width, c.height, tuple(c.distortion))


def mount_from_config(cfg: Config) -> Mount:
    c = cfg.camera
    return Mount.from_degrees(c.mount_roll_deg, c.mount_pitch_deg, c.mount_yaw_deg,
                              tuple(c.mount_offset_m))  # type: ignore[arg-type]


def signing_key(cfg: Config) -> bytes | None:
    """The 32-byte MAVLink signing secret from ``link.signing_key_file`` or ``link.signing_key``."""
    from companion.config import ConfigError

    text = cfg.link.signing_key
    if cfg.link.signing_key_file:
        try:
            text = Path(cfg.link.signing_key_file).read_text().strip()
        except OSError as exc:
            raise ConfigError(f"link.signing_key_file {cfg.link.signing_key_file}: {exc.strerror}") from None
        if len(text) != 64 or any(ch not in "0123456789abcdefABCDEF" for ch in text):
            raise ConfigError(f"link.signing_key_file {cfg.link.signing_key_file} must hold 64 "
                              "hexadecimal characters")
    return bytes.fromhex(text) if text else None


def load_model(cfg: Config) -> DensityModel:
    """The density model; raises DensityModelError naming the file."""
    return DensityModel(cfg.model.path, threads=cfg.model.threads, overrides=cfg.model.overrides)


def build_pipeline(cfg: Config, model: DensityModel, intrinsics: Intrinsics, mount: Mount) -> Any:
    from companion.pipeline.headplane import GridParams
    from companion.pipeline.occupancy import OccupancyParams
    from companion.pipeline.slz import PipelineConfig, SLZPipeline
    from companion.pipeline.tracker import TrackerParams

    p = cfg.pipeline
    threshold = p.occupancy_threshold
    if threshold < 0:
        threshold = model.spec.occupancy_threshold or 0.0
    pcfg = PipelineConfig(
        occupancy=OccupancyParams(threshold=threshold, kernel=p.dilate_kernel, iterations=p.dilate_iterations),
        grid=GridParams(cell=p.cell_size_m, max_extent=p.max_extent_m),
        tracker=TrackerParams(sigma_a=p.tracker.sigma_a, r_std=tuple(p.tracker.r_std),  # type: ignore[arg-type]
                              min_iou=p.tracker.min_iou, mu_1=p.tracker.mu_1, mu_2=p.tracker.mu_2,
                              max_tracks=p.n_proposals),
        head_height=p.head_height_m,
        r_0=p.r0_m,
    )
    return SLZPipeline(model, pcfg, intrinsics=intrinsics, mount=mount)


class Service:
    """The running daemon. ``await Service(cfg, model).run()`` returns the exit code."""

    def __init__(self, cfg: Config, model: DensityModel, notifier: Notifier | None = None) -> None:
        self.cfg = cfg
        self.model = model
        self.notifier = notifier or Notifier()
        self.intrinsics = intrinsics_from_config(cfg)
        self.mount = mount_from_config(cfg)
        self.pipeline = build_pipeline(cfg, model, self.intrinsics, self.mount)
        self.timings = StageTimings()
        self.counters = FrameCounters()
        self.stop_event = asyncio.Event()
        self.busy_since: float | None = None
        self.last_processed_t: float | None = None
        self.link: Any = None
        self.state: Any = None
        self.autopilot: Any = None
        self.monitor: Any = None
        self.controller: Any = None
        self.camera: CameraSource | None = None
        self.recorder: FlightRecorder | None = None
        self.last_target: Any = None

    # ---- lifecycle ---------------------------------------------------------------------------
    def request_stop(self, why: str = "") -> None:
        if not self.stop_event.is_set():
            log.info("stopping%s", f" ({why})" if why else "")
            self.notifier.stopping()
            self.stop_event.set()

    def _install_signals(self) -> None:
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, self.request_stop, "SIGTERM")
        loop.add_signal_handler(signal.SIGINT, self.request_stop, "SIGINT")
        loop.add_signal_handler(signal.SIGUSR1, self._local_trigger)

    def _local_trigger(self) -> None:
        if self.monitor is None:
            log.warning("SIGUSR1 ignored: not connected to the autopilot yet")
            return
        self.monitor.trigger_local("SIGUSR1 to the service")

    async def run(self) -> int:
        self._install_signals()
        from companion.mavlink.link import LinkConfig, MavLink, message_rates
        from companion.mavlink.state import VehicleState

        c = self.cfg
        self.link = MavLink(LinkConfig(
            url=c.link.url, system_id=c.link.system_id, component_id=c.link.component_id,
            target_system=c.link.target_system or None, target_component=c.link.target_component,
            heartbeat_timeout_s=c.link.heartbeat_timeout_s, signing_key=signing_key(c),
            message_rates_hz=message_rates(c.link.telemetry_rate_hz),
        ))
        self.state = VehicleState(max_extrapolation_s=c.pipeline.max_pose_age_s)
        self.state.attach(self.link)
        self.camera = CameraSource(c.camera.source, width=c.camera.width, height=c.camera.height,
                                   fps=c.camera.fps, stall_timeout_s=c.camera.stall_timeout_s,
                                   max_backoff_s=c.camera.reopen_max_backoff_s, loop=c.camera.loop)
        try:
            await self.link.start()
        except OSError as exc:
            log.error("cannot open the MAVLink link %s: %s", c.link.url, exc)
            return 1
        self.camera.start()
        tasks: list[asyncio.Task[Any]] = []
        try:
            self.notifier.status(f"waiting for the autopilot heartbeat on {c.link.url}")
            if not await self._wait_heartbeat():
                return 0  # stopped before the autopilot appeared
            from companion.mavlink.autopilot import FlavourError

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
            self.notifier.ready(self._status_line())
            tasks = [
                asyncio.create_task(self._frame_loop(), name="frames"),
                asyncio.create_task(self._health_loop(), name="health"),
            ]
            runner = getattr(self.controller, "run", None)
            if runner is not None:
                tasks.append(asyncio.create_task(runner(), name="controller"))
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
            except asyncio.TimeoutError:
                pass
        return True

    def _wire_vehicle(self) -> None:
        from companion.mavlink.flavours import select_flavour
        from companion.mavlink.failsafe import FailsafeConfig, FailsafeMonitor

        c = self.cfg
        self.autopilot = select_flavour(self.link, c.link.flavour)
        log.info("autopilot flavour: %s", self.autopilot.name)
        f = c.failsafe
        self.monitor = FailsafeMonitor(
            FailsafeConfig(battery=f.battery, battery_level=f.battery_level, system_status=f.system_status,
                           autopilot_land=f.autopilot_land, gcs_command=f.gcs_command,
                           local_trigger=f.local_trigger, gcs_system_ids=tuple(f.gcs_system_ids),
                           local_socket=f.local_socket or None),
            self.link, self.autopilot)
        self.monitor.attach()
        self.controller = self._make_controller()
        self.monitor.subscribe(self._on_trigger)

    def _make_controller(self) -> Any:
        """The landing controller behind its async runner (commands through the autopilot
        flavour, events to the ground station as STATUSTEXT)."""
        from companion.control.landing import LandingConfig, LandingController
        from companion.control.obedience import ObedienceConfig
        from companion.control.planner import PlannerConfig
        from companion.service.landing_runner import LandingRunner

        c = self.cfg.controller
        lcfg = LandingConfig(
            planner=PlannerConfig(r0_m=self.cfg.pipeline.r0_m, radius_margin_m=c.radius_margin_m,
                                  min_track_age_s=c.min_track_age_s, min_track_hits=c.min_track_hits,
                                  zone_max_age_s=c.zone_max_age_s),
            select_timeout_s=c.select_timeout_s, hold_timeout_s=c.hold_timeout_s,
            arrive_radius_m=c.arrive_radius_m, descend_alt_m=c.descend_alt_m,
            descend_step_m=c.descend_step_m, land_abort_above_m=c.land_abort_above_m,
            hold_height_m=c.hold_height_m, max_takeover_s=c.max_takeover_s,
            max_pose_age_s=self.cfg.pipeline.max_pose_age_s, handback_action=c.handback_action,
            search_climb_m=c.search_climb_m, max_alt_m=c.max_alt_m,
            obedience=ObedienceConfig(tolerance_z_m=c.obey_tolerance_z_m, tolerance_xy_m=c.obey_tolerance_xy_m),
        )
        return LandingRunner(LandingController(lcfg), self.autopilot, self.state, self.link)

    @property
    def phase(self) -> str:
        ctl = getattr(self.controller, "controller", None)
        phase = getattr(ctl, "phase", None)
        return "MONITOR" if phase is None else str(getattr(phase, "value", phase))

    def _on_trigger(self, trigger: Any) -> None:
        log.warning("failsafe trigger: %s (%s)", trigger.reason, trigger.source.value)
        self._record_event("trigger", trigger.t, reason=trigger.reason, source=trigger.source.value)
        if self.controller is not None:
            self.controller.on_trigger(trigger)
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
            c.recorder.dir, segment_s=c.recorder.segment_s, max_mb=c.recorder.max_mb, codec=c.recorder.codec,
            fps=c.camera.fps, intrinsics=self.intrinsics, mount=self.mount,
            meta={"model": {"path": str(c.model.path), "spec": self.model.spec}, "config": c.to_dict(),
                  "autopilot": self.autopilot.name if self.autopilot else None},
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
        autopilot's own failsafe first. In LAND the autopilot is already landing by itself."""
        if self.phase not in ("SELECT", "APPROACH", "DESCEND", "HOLD") or self.autopilot is None:
            return
        action = self.cfg.controller.handback_action
        log.warning("stopping during %s: handing back to the autopilot (%s)", self.phase, action)
        try:
            from companion.mavlink.statustext import send_statustext
            from pymavlink.dialects.v20 import ardupilotmega as m

            send_statustext(self.link, f"SLZ: companion stopping; handing back ({action})",
                            m.MAV_SEVERITY_WARNING)
            # Insist within the shutdown's budget: one packet can be lost (at 20 % loss one
            # shutdown in five left the vehicle in GUIDED/OFFBOARD), so resend every 0.25 s
            # until acknowledged, five times at most (1.25 s).
            await asyncio.wait_for(self.autopilot.handback(action, timeout_s=0.25, retries=4), 1.3)
        except Exception as exc:  # timeouts, refusals: nothing more we can do on the way out
            log.error("handback on exit failed: %r", exc)

    async def _shutdown(self, tasks: list[asyncio.Task[Any]]) -> None:
        if self.controller is not None and self.link is not None:
            await self._handback_on_exit()
        if self.monitor is not None:
            try:
                await asyncio.wait_for(self.monitor.stop_local_socket(), 0.5)
            except (asyncio.TimeoutError, OSError):
                pass
        for task in tasks:
            task.cancel()
        for task in tasks:
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
        stop = getattr(self.controller, "close", None)
        if stop is not None:
            try:
                res = stop()
                if asyncio.iscoroutine(res):
                    await asyncio.wait_for(res, 1.0)
            except Exception as exc:
                log.warning("controller close: %s", exc)
        if self.camera is not None:
            await asyncio.to_thread(self.camera.stop, 1.0)
        if self.recorder is not None:
            await asyncio.to_thread(self.recorder.close, 1.0)
        if self.link is not None:
            try:
                await asyncio.wait_for(self.link.close(), 1.0)
            except (asyncio.TimeoutError, OSError):
                pass
        log.info("stopped")

    # ---- frames ------------------------------------------------------------------------------
    def _prepare(self, image: np.ndarray) -> np.ndarray:
        """Frames are brought to the calibrated resolution (the intrinsics describe that size)."""
        w, h = self.intrinsics.width, self.intrinsics.height
        if image.shape[1] != w or image.shape[0] != h:
            image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
        return image

    async def _frame_loop(self) -> None:
        assert self.camera is not None
        while not self.stop_event.is_set():
            frame = await self.camera.next_frame(timeout=0.5)
            if frame is None:
                continue
            image = self._prepare(frame.image)
            pose: Pose | None = self.state.pose_at(frame.t)
            if self.recorder is not None:
                self.recorder.add_frame(frame.index, frame.t, image, pose)
            if pose is None:
                # Stale is unsafe: without a pose at capture time the frame can't be placed on
                # the ground, and must not confirm or move any zone.
                self.counters.no_pose += 1
                continue
            self.busy_since = time.monotonic()
            try:
                result = await asyncio.to_thread(self.pipeline.process, image, frame.t, pose)
            except (FrameError, GeometryError) as exc:
                self.counters.bad += 1
                # First one visible (e.g. "camera is not above the head plane" on the ground),
                # then only now and then: a stream of identical warnings helps nobody.
                level = logging.INFO if self.counters.bad == 1 or self.counters.bad % 500 == 0 else logging.DEBUG
                log.log(level, "frame %d not usable (%d so far): %s", frame.index, self.counters.bad, exc)
                continue
            except (DensityModelError, ValueError) as exc:
                self.counters.errors += 1
                if self.counters.errors <= 10 or self.counters.errors % 100 == 0:
                    log.warning("frame %d: pipeline failed: %s", frame.index, exc)
                continue
            finally:
                self.busy_since = None
            self.counters.processed += 1
            self.last_processed_t = time.monotonic()
            self.timings.add(result.timings_ms)
            if self.controller is not None:
                self.controller.on_frame(frame.t, result.tracks, pose)
            self.last_target = result.target
            self._record_event("zones", frame.t, frame=frame.index,
                               tracks=[_track_dict(t) for t in result.tracks],
                               target=None if result.target is None else result.target.id,
                               timings_ms=result.timings_ms)

    def _record_event(self, kind: str, t: float, **data: Any) -> None:
        if self.recorder is not None:
            self.recorder.add_event(kind, t, **data)

    # ---- health ------------------------------------------------------------------------------
    def healthy(self, now: float) -> tuple[bool, str]:
        """Link alive, camera delivering, pipeline not stuck; with the reason when not."""
        if not self.link.connected:
            return False, "no autopilot heartbeat"
        assert self.camera is not None
        if not self.camera.delivering(now):
            return False, "camera not delivering"
        if self.busy_since is not None and now - self.busy_since > PIPELINE_STUCK_S:
            return False, f"pipeline stuck for {now - self.busy_since:.1f} s"
        return True, "ok"

    def _status_line(self) -> str:
        target = self.last_target
        zone = f"oldest stable zone {target.id} r={target.r:.1f} m" if target is not None else "no zone"
        return f"{self.phase}: {zone}"

    async def _health_loop(self) -> None:
        interval = self.notifier.watchdog_interval
        next_log = time.monotonic() + self.cfg.log.health_interval_s
        was_healthy = True
        last_ping = 0.0
        last_phase = self.phase
        while not self.stop_event.is_set():
            now = time.monotonic()
            phase = self.phase
            if phase != last_phase:
                log.warning("landing controller: %s -> %s", last_phase, phase)
                self._record_event("phase", now, old=last_phase, new=phase)
                last_phase = phase
            ok, why = self.healthy(now)
            if ok and interval is not None and now - last_ping >= min(interval, 1.0):
                self.notifier.watchdog()
                last_ping = now
            if ok != was_healthy:
                (log.info if ok else log.warning)("health: %s", why)
                was_healthy = ok
            self.notifier.status(self._status_line() if ok else f"unhealthy: {why}")
            if now >= next_log:
                next_log = now + self.cfg.log.health_interval_s
                self._log_health(ok, why)
            try:
                await asyncio.wait_for(self.stop_event.wait(), TICK_S)
            except asyncio.TimeoutError:
                pass

    def _log_health(self, ok: bool, why: str) -> None:
        assert self.camera is not None
        cs, fc, ls = self.camera.stats, self.counters, self.link.stats
        log.info(
            "health %s: frames camera=%d processed=%d dropped=%d corrupt=%d no_pose=%d bad=%d "
            "errors=%d stalls=%d | link rx=%d bad=%d lost=%d | timings %s%s",
            "ok" if ok else f"BAD ({why})", cs.frames, fc.processed, cs.dropped, cs.corrupt, fc.no_pose,
            fc.bad, fc.errors, cs.stalls, ls.received, ls.bad, ls.link_losses, self.timings.format() or "-",
            "" if self.recorder is None else
            f" | recorder frames={self.recorder.stats.frames} dropped={self.recorder.stats.dropped}",
        )


def _track_dict(t: Any) -> dict[str, Any]:
    return asdict(t) if is_dataclass(t) else {"id": getattr(t, "id", None)}
