"""The real PX4's frame-6 fly-away, reproduced end to end: the companion's runner, its real PX4
flavour and MAVLink link, against the simulated PX4 with its home 1.5 m below its estimator's
origin (as in PX4's SIH), over loopback UDP in one process.

With frame 6 (what the companion sent before issue 19) PX4 reads every target about 3 m too high:
the vehicle climbs, and the obedience monitor hands it back to LAND within 3 s. With frame 5 (what
it sends now) the same vehicle flies to the zone and lands under the companion.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.commands import PositionTarget
from companion.control.landing import LandingConfig, LandingController, Phase
from companion.control.planner import PlannerConfig
from companion.control.trigger import Trigger, TriggerSource
from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.px4 import PX4
from companion.mavlink.state import VehicleState
from companion.pipeline.tracker import Track
from companion.service.landing_runner import LandingRunner
from sim.flights.flight import free_port
from sim.vehicle.autopilot import AutopilotConfig
from sim.vehicle.simulator import SimConfig, Simulator

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]

OFFSET_M = -1.5  # home_alt - origin_alt: home 1.5 m below the estimator's origin
ZONE = (8.0, 6.0)  # north, east of the start; a free lawn, radius 6 m


class Frame6PX4(PX4):
    """The PX4 flavour as it was before issue 19: frame 6, altitude above home."""

    TARGET_FRAME = m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT

    def target_altitude(self, target: PositionTarget) -> float:
        return target.rel_alt_m


@contextlib.asynccontextmanager
async def companion_on_px4(flavour_cls: type[PX4]) -> AsyncIterator[tuple[Simulator, LandingRunner]]:
    port = free_port()
    sim = Simulator(SimConfig(flavour="px4", outputs=[f"udpout:127.0.0.1:{port}"],
                              start_position=(0.0, 0.0, -20.0),
                              autopilot=AutopilotConfig(origin_alt_offset_m=OFFSET_M), seed=1))
    link = MavLink(LinkConfig(f"udpin:127.0.0.1:{port}"))
    await link.start()
    await sim.start()
    tasks: list[asyncio.Task[None]] = []
    try:
        await link.wait_connected(5.0)
        state = VehicleState()
        state.attach(link)
        flavour = flavour_cls(link)
        config = LandingConfig(planner=PlannerConfig(r0_m=2.0, radius_margin_m=2.0))
        runner = LandingRunner(LandingController(config), flavour, state, link, tick_hz=10)
        tasks.append(asyncio.create_task(runner.run()))
        deadline = time.monotonic() + 5.0
        while not (state.is_fresh(time.monotonic(), 0.3) and state.home is not None):
            assert time.monotonic() < deadline, "no telemetry from the simulator"
            await asyncio.sleep(0.05)

        async def frames() -> None:  # the zone, confirmed by a fresh frame every 0.1 s
            while True:
                t = time.monotonic() - 0.03
                track = Track(id=1, x=ZONE[0], y=ZONE[1], r=6.0, r_filtered=6.0, age=100, hits=100,
                              misses=0, born_t=t - 10.0, last_t=t)
                runner.on_frame(t, [track], state.pose_at(t))
                await asyncio.sleep(0.1)
        tasks.append(asyncio.create_task(frames()))
        yield sim, runner
    finally:
        for task in tasks:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await link.close()
        await sim.stop()


async def fly(runner: LandingRunner, sim: Simulator, until, timeout: float) -> list[tuple[float, float]]:
    """Trigger, then record (time, true altitude) until ``until()`` or the timeout."""
    trace = [(time.monotonic(), sim.truth.altitude)]
    runner.on_trigger(Trigger("battery critical", TriggerSource.BATTERY, time.monotonic()))
    end = time.monotonic() + timeout
    while not until() and time.monotonic() < end:
        await asyncio.sleep(0.05)
        trace.append((time.monotonic(), sim.truth.altitude))
    return trace


async def test_frame_6_targets_make_the_offset_px4_climb_and_the_companion_hands_back_within_3_s():
    async with companion_on_px4(Frame6PX4) as (sim, runner):
        ctl = runner.controller
        trace = await fly(runner, sim, lambda: ctl.phase == Phase.HANDBACK, timeout=30.0)
        assert ctl.phase == Phase.HANDBACK
        t_back = trace[-1][0]
        alt0 = trace[0][1]
        climbing = next(t for t, alt in trace if alt > alt0 + 0.1)  # PX4 read the target too high
        assert t_back - climbing <= 3.0
        handbacks = [c for c, _ in runner.executed if type(c).__name__ == "Handback"]
        assert handbacks and handbacks[-1].action == "LAND"
        assert "climbing" in handbacks[-1].reason or "not reaching" in handbacks[-1].reason
        print(f"frame 6: climbing from {alt0:.1f} m, handed back {t_back - climbing:.2f} s later, "
              f"highest {max(alt for _, alt in trace):.1f} m: {handbacks[-1].reason}")
        assert max(alt for _, alt in trace) < alt0 + 3.5  # it would have gone on; it was stopped
        await sim.wait_for(lambda tr: tr.mode == "AUTO.LAND", 3.0)


async def test_frame_5_targets_land_the_offset_px4_under_the_companion():
    async with companion_on_px4(PX4) as (sim, runner):
        ctl = runner.controller
        trace = await fly(runner, sim, lambda: ctl.phase in (Phase.LANDED, Phase.HANDBACK), timeout=60.0)
        assert ctl.phase == Phase.LANDED, [str(c) for c, _ in runner.executed][-5:]
        truth = sim.truth
        assert truth.landed
        assert abs(truth.position[0] - ZONE[0]) < 1.5 and abs(truth.position[1] - ZONE[1]) < 1.5
        print(f"frame 5: landed {truth.position[0] - ZONE[0]:+.2f} / {truth.position[1] - ZONE[1]:+.2f} m "
              f"from the zone centre, {trace[-1][0] - trace[0][0]:.1f} s after the trigger, highest "
              f"{max(alt for _, alt in trace):.1f} m from {trace[0][1]:.1f} m")
        assert max(alt for _, alt in trace) <= trace[0][1] + 0.5
