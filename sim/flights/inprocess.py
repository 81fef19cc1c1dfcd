"""The flight's service in the flight's own process, on its event loop: what a lockstep flight
(``sim.flights.lockstep``) flies with instead of ``companion run`` in a subprocess.

``companion.service.app.Service`` is built from the settings ``companion run`` would be given
(``sim.flights.spec.service_command``), and its camera source (:class:`PushCamera`) is fed each
frame the simulated camera renders, on the loop, JPEG-encoded and decoded as over MJPEG, with the
capture time the MJPEG stream's ``X-Timestamp`` carries.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import time
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np

from companion import config as config_mod
from companion.config import ConfigError
from companion.pipeline.density import DensityModelError
from companion.service import cli as service_cli
from companion.service.camera import CameraSource
from companion.service.notify import Notifier
from sim.flights.spec import FlightSpec, service_command
from sim.world.camera_server import CameraServer


class PushCamera(CameraSource):
    """The service's camera source in a lockstep flight: no reader thread; each frame is handed
    over on the loop (:meth:`push`) as the MJPEG stream would deliver it, decoded from its JPEG,
    stamped with its capture time when that is plausible (else the time it arrived)."""

    def start(self) -> PushCamera:
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()

    def push(self, jpeg: bytes, capture_time: float) -> None:
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) if jpeg else None
        if image is None:
            self.stats.corrupt += 1
            return
        if self._is_repeat(image):
            self.stats.repeated += 1
            return
        self._publish(image, *self._capture_time(capture_time, "header", time.monotonic()), jpeg=jpeg)


async def _feed(server: CameraServer, camera: PushCamera) -> None:
    """Every frame the simulated camera renders, to the service's camera, as it is rendered."""
    last: int | None = None
    while True:
        frame = await server.next_frame(last)
        last = frame.index
        camera.push(frame.jpeg, frame.capture_time)


class _QuietNotifier(Notifier):
    """No systemd here: readiness is read from ``ready_sent``, nothing is sent anywhere."""

    def __init__(self) -> None:
        super().__init__()
        self.enabled, self._sd = False, None

    @property
    def watchdog_interval(self) -> float | None:
        return None


class _Lines(logging.Handler):
    """The service's log lines, kept (and written to ``sink``) as ``companion run`` writes them."""

    def __init__(self, lines: list[str], sink: TextIO | None) -> None:
        super().__init__(logging.INFO)
        self.lines, self.sink = lines, sink
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        text = self.format(record)
        self.lines.append(text)
        if self.sink is not None:
            self.sink.write(text + "\n")
            self.sink.flush()


class InProcessService:
    """The flight's service in this process (the ``sim.flights.flight.FlightService`` of a lockstep
    flight): ``companion.service.app.Service`` built from the settings ``companion run`` would be
    given (``sim.flights.spec.service_command``), its camera fed by the simulated camera on the loop. A
    bad setting or model is a service that never becomes ready, its error in ``lines``."""

    def __init__(self, spec: FlightSpec, link_port: int, camera: CameraServer, record_dir: Path,
                 sink: TextIO | None) -> None:
        self.spec, self.link_port, self.server, self.record_dir = spec, link_port, camera, record_dir
        self.lines: list[str] = []
        self._handler = _Lines(self.lines, sink)
        self._logger = logging.getLogger("companion")
        self._task: asyncio.Task[int] | None = None
        self._feed: asyncio.Task[None] | None = None
        self.service: Any = None

    def config(self) -> config_mod.Config:
        """The settings of the command line a real-time flight starts its service with
        (``sim.flights.spec.service_command``), read by ``companion run``'s own parser and resolved as
        it resolves them; raises ConfigError."""
        argv = service_command(self.spec, self.link_port, self.server.url, self.record_dir)
        parser = argparse.ArgumentParser(prog="companion run")
        service_cli.configure(parser)
        args = parser.parse_args(argv[argv.index("run") + 1:])
        return config_mod.load(args.config, service_cli.overrides_from_args(args))

    async def start(self, timeout: float) -> bool:
        from companion.service.app import Service
        from companion.service.parts import load_landability, load_model

        self._logger.addHandler(self._handler)
        self._logger.setLevel(logging.INFO)
        try:
            cfg = self.config()
            model = load_model(cfg)
            surface = load_landability(cfg)
        except (ConfigError, DensityModelError) as exc:
            self.lines.append(f"ERROR companion: {exc}")
            return False
        c = cfg.camera
        camera = PushCamera(c.source, width=c.width, height=c.height, fps=c.fps,
                            stall_timeout_s=c.stall_timeout_s, max_backoff_s=c.reopen_max_backoff_s)
        self.service = Service(cfg, model, _QuietNotifier(), camera=camera, surface=surface)
        self._task = asyncio.create_task(self.service.run(), name="service")
        self._feed = asyncio.create_task(_feed(self.server, camera), name="camera feed")
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        while loop.time() < end:
            if self.service.notifier.ready_sent:
                return True
            if self._task.done():
                return False
            await asyncio.sleep(0.05)
        return False

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    async def stop(self) -> int | None:
        code: int | None = None
        try:
            if self._task is not None:
                if not self._task.done():
                    self.service.request_stop("the flight is over")
                try:
                    code = await asyncio.wait_for(asyncio.shield(self._task), 5.0)
                except (TimeoutError, asyncio.TimeoutError):
                    self._task.cancel()
                    with contextlib.suppress(BaseException):
                        await self._task
                    code = None
                except Exception as exc:  # the service's own failure: its exit status would be 1
                    self.lines.append(f"ERROR companion: service failed: {exc!r}")
                    code = 1
            if self._feed is not None:
                self._feed.cancel()
                with contextlib.suppress(BaseException):
                    await self._feed
        finally:
            self._logger.removeHandler(self._handler)
        return code
