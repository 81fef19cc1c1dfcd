"""The stop: every part stopped in order within ``SHUTDOWN_BUDGET_S``, the vehicle handed back to
the autopilot first when the companion has it."""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.statustext import send_statustext
from companion.service.wiring import ServiceParts

log = logging.getLogger("companion.service")

#: SIGTERM to exit (s): the promise is 2 s (the unit's TimeoutStopSec=5 is the backstop). Every
#: shutdown step gets at most what is left of it (and at least SHUTDOWN_STEP_MIN_S).
SHUTDOWN_BUDGET_S = 1.8
SHUTDOWN_STEP_MIN_S = 0.05


class Shutdown(ServiceParts):
    """The shutdown sequence and the handback on exit."""

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
