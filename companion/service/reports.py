"""What the service tells, and to whom: systemd and the log (the health loop), the ground station
(STATUSTEXT of readiness, the numbers at ``gcs.values_hz``) and the status page."""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import numpy as np

from companion.control.events import Phase
from companion.pipeline.tracker import Track
from companion.service.gcs import PHASE_CODES
from companion.service.health import FaultLog
from companion.service.pilot_view import clearance_note, vehicle_fields
from companion.service.web import WebServer, stream_uri
from companion.service.wiring import ServiceParts

log = logging.getLogger("companion.service")

#: Main-loop tick for watchdog and health checks (s).
TICK_S = 0.25


class Reports(ServiceParts):
    """The health loop, the ground station's values and the status page."""

    # ---- health ------------------------------------------------------------------------------
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

    # ---- ground station and status page ------------------------------------------------------
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

    def _target_numbers(self) -> tuple[Track | None, float | None]:
        """The target (flown to, or the one it would fly to now) and its least clearance at
        touchdown if it committed now: the controller's own figure (``DescentProfile`` with the
        autopilot's descent speeds, as replay computes ``clearance_m``)."""
        c = self.controller
        target = None if c is None else c.zone_target()
        return target, None if c is None or target is None else c.touchdown_clearance(target)

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
