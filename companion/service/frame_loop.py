"""The frame loop: the newest camera frame, paired with the pose at its capture time, recorded,
through the pipeline in a worker thread, and its zones to the landing controller (the module
docstring of ``companion.service.app`` tells the whole story)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from dataclasses import asdict

import cv2
import numpy as np

from companion.geometry.camera import GeometryError, Pose
from companion.pipeline.density import DensityModelError, FrameError
from companion.pipeline.tracker import Track
from companion.service.camera import Frame
from companion.service.frame_use import UNUSABLE, geometry_reason, pose_reason
from companion.service.web import Snapshot
from companion.service.wiring import ServiceParts

log = logging.getLogger("companion.service")

#: How often a frame waiting for its telemetry checks again (s).
POSE_POLL_S = 0.01


class FrameLoop(ServiceParts):
    """The frames, from the camera to the controller."""

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
