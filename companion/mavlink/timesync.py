"""TIMESYNC with the autopilot: measure the link's latency and the autopilot's clock.

Every ``period_s`` the companion sends ``TIMESYNC(tc1=0, ts1=our monotonic ns)``; ArduPilot and
PX4 answer with ``tc1`` = their boot time in ns and ``ts1`` echoed, which ``AutopilotClock``
turns into the offset between the two clocks with the latency taken out (the state subscribes
to the answers). A request from the autopilot (``tc1 = 0``; ArduPilot and PX4 send them to
measure their side of the link) is answered the same way, so the link looks alike from both ends.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from companion.mavlink.clock import AutopilotClock
from companion.mavlink.link import MavLink

#: TIMESYNC request period (s): once a second measures the link's latency and the autopilot's
#: clock drift well within the telemetry's lag limit (``clock.MAX_TELEMETRY_LAG_S``).
TIMESYNC_PERIOD_S = 1.0


async def run_timesync(link: MavLink, clock: AutopilotClock, period_s: float = TIMESYNC_PERIOD_S) -> None:
    """Request TIMESYNC every ``period_s`` while the autopilot is heard, and answer its requests.
    Runs until cancelled."""

    def answer(msg: Any, _t: float) -> None:
        if msg.tc1 == 0 and link.connected:
            link.send(link.mav.timesync_encode(time.monotonic_ns(), msg.ts1))

    unsubscribe = link.subscribe("TIMESYNC", answer)
    try:
        while True:
            if link.connected:
                link.send(link.mav.timesync_encode(0, clock.request(time.monotonic())))
            await asyncio.sleep(period_s)
    finally:
        unsubscribe()
