"""The running service's parts and what every concern of it reads from them.

``ServiceParts`` builds the parts from the settings unless given (a test drives the service
in-process by handing it a link, a camera or a pipeline of its own: real ones, pointed at the
simulator) and holds the views of them that the frame loop, the reports and the shutdown share:
the landing controller, its phase, the health verdict, the live view's caption. The concerns are
mixins on it (``frame_loop``, ``reports``, ``shutdown``); ``companion.service.app.Service`` puts
them together with the start-up and the controller's events.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as m

from companion import config as settings
from companion.config import Config
from companion.control.events import Event, Phase
from companion.control.landing import LandingController
from companion.mavlink.autopilot import Autopilot
from companion.mavlink.failsafe import TRIGGER_COMMAND, FailsafeMonitor
from companion.mavlink.gcs_commands import CommandServer, Reply, VideoStream, VideoStreamProvider
from companion.mavlink.link import MavLink
from companion.mavlink.state import MAX_POSE_AGE_S, VehicleState
from companion.pipeline.density import DensityModel
from companion.pipeline.landability import UnlandableMap
from companion.pipeline.slz import FrameResult, SLZPipeline
from companion.pipeline.tracker import Track
from companion.recording import FlightRecorder
from companion.replay.live_figure import CAPTION_PX
from companion.service.camera import CameraSource
from companion.service.frame_use import FrameUse
from companion.service.gcs import GroundStation
from companion.service.health import PIPELINE_STUCK_S, FrameCounters, Health, StageTimings, assess
from companion.service.landing_runner import LandingRunner
from companion.service.notify import Notifier
from companion.service.parts import build_camera, build_pipeline
from companion.service.web import LiveView, WebServer, live_video_stream

log = logging.getLogger("companion.service")

#: Decisions kept for the status page.
DECISIONS_KEPT = 20


class ServiceParts:
    """The parts of one running service. The parts that depend on the autopilot (flavour,
    failsafe monitor, landing runner) stay None until its first heartbeat says which autopilot it
    is (``Service._wire_vehicle``)."""

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

    @staticmethod
    def _trigger_before_wiring(msg: Any, t: float, broadcast: bool) -> Reply | None:
        """The trigger before the autopilot is heard: nobody could fly the landing yet."""
        return None if broadcast else Reply(m.MAV_RESULT_DENIED, "SLZ: trigger refused: no autopilot yet")

    def live_video_stream(self) -> VideoStream | None:
        """The live view as VIDEO_STREAM_INFORMATION announces it, None while it is off or could
        not start: the provider of the ground station's camera protocol (``self.commands``)."""
        if self.live is None or self.web is None:
            return None
        w, h = self.intrinsics.width, self.intrinsics.height
        # The figure: the frame and its square head-plane view side by side, under the caption.
        return live_video_stream(self.cfg.live, w + 4 + h, h + CAPTION_PX)

    @property
    def controller(self) -> LandingController | None:
        return None if self.runner is None else self.runner.controller

    @property
    def phase(self) -> str:
        return Phase.MONITOR.value if self.controller is None else self.controller.phase.value

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

    def _caption(self, result: FrameResult | None, target: Track | None) -> str:
        shadow = "SHADOW  " if self.shadow else ""
        aim = "no target" if target is None else f"target #{target.id} r {target.r:.1f} m"
        zones = "" if result is None else f"zones {len(result.tracks)}  "
        return (f"{shadow}{self.phase}  {zones}{aim}  "
                f"{time.strftime('%H:%M:%S')}")

    def _record_event(self, kind: str, t: float, **data: Any) -> None:
        if self.recorder is not None:
            self.recorder.add_event(kind, t, **data)
