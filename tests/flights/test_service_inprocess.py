"""The service driven in-process: its parts handed to it, the simulator in the same event loop.

The subprocess tests (``test_service.py``, ``test_sitl.py``) run ``companion run`` exactly as
systemd does; this one builds ``Service`` directly, hands it a link of its own, and reads its
typed events and the simulator's truth, with no process boundary or log in between.
"""

from __future__ import annotations

import asyncio
import socket
import time

import pytest

from companion import config
from companion.control.events import HandedBack, Phase, TargetChosen
from companion.mavlink.link import MavLink
from companion.service.app import Service
from companion.service.parts import load_model
from sim.flights.flight import FlightSpec, build_scene, reserve_port

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(180)]


async def _fly_in_process(flavour: str) -> tuple[Service, int, dict[str, float]]:
    with reserve_port() as link, reserve_port(socket.SOCK_STREAM) as cam:
        return await _fly_with_ports(flavour, link.port, cam.port)


async def _fly_with_ports(flavour: str, link_port: int, cam_port: int) -> tuple[Service, int, dict[str, float]]:
    spec = FlightSpec(flavour=flavour, world="uniform", seed=6, altitude_m=18.0, home_origin_offset_m=-1.5)
    world, _, sim, camera = build_scene(spec, link_port, cam_port)
    cfg = config.load(None, {"link.url": f"udpin:127.0.0.1:{link_port}", "link.flavour": flavour,
                             "camera.source": camera.url, "camera.hfov_deg": spec.hfov_deg,
                             "controller.land_agl_m": 1.0})
    model = load_model(cfg)
    svc = Service(cfg, model, link=MavLink(config.link_config(cfg)))  # a part handed in, typed
    truth: dict[str, float] = {}

    def on_touchdown() -> None:
        if "t" not in truth:
            p = sim.truth.position
            truth.update(t=time.monotonic(), clearance=world.nearest_person_distance((float(p[0]), float(p[1]))))

    sim.on_touchdown(on_touchdown)
    await sim.start()
    await camera.start()
    task = asyncio.create_task(svc.run())
    try:
        end = time.monotonic() + 60
        while svc.runner is None and time.monotonic() < end and not task.done():
            await asyncio.sleep(0.1)
        assert svc.runner is not None, "the service never wired the vehicle"
        await asyncio.sleep(3.0)  # watch the ground before the failsafe
        truth["alt0"] = truth["alt_max"] = -float(sim.truth.position[2])
        sim.inject_failsafe("battery_critical")
        end = time.monotonic() + 90
        while "t" not in truth and time.monotonic() < end and not task.done():
            truth["alt_max"] = max(truth["alt_max"], -float(sim.truth.position[2]))
            await asyncio.sleep(0.1)
        # The simulator's touchdown comes first; the companion's LANDED follows once the
        # autopilot reports it (EXTENDED_SYS_STATE / disarm), which on a loaded CI machine
        # has taken more than half a second. Wait for it, bounded.
        end = time.monotonic() + 10
        while "t" in truth and svc.phase != "LANDED" and time.monotonic() < end and not task.done():
            await asyncio.sleep(0.1)
    finally:
        svc.request_stop("test over")
        code = await asyncio.wait_for(task, 10.0)
        await camera.stop()
        await sim.stop()
    return svc, code, truth


# PX4, the one with a setpoint stream and its home below its estimator's origin; this is also
# test_sitl.py's uniform-ground flight for PX4 (that file flies it on ArduPilot).
@pytest.mark.parametrize("flavour", ["px4"])
def test_the_service_in_process_lands_on_free_ground_and_reports_every_phase(flavour, model_path):
    svc, code, truth = asyncio.run(_fly_in_process(flavour))
    assert code == 0
    changes = [e.phase for e in svc.events if e.changed]
    assert "t" in truth, changes
    assert changes[:2] == [Phase.SELECT, Phase.APPROACH] and changes[-2:] == [Phase.LAND, Phase.LANDED], changes
    assert not any(isinstance(e, HandedBack) for e in svc.events), [e.text for e in svc.events]
    assert any(isinstance(e, TargetChosen) for e in svc.events)
    assert svc.phase == "LANDED" and truth["clearance"] > 2.0
    # The last metres by the rangefinder (controller.land_agl_m) in OFFBOARD, then AUTO.LAND.
    said = [e.text for e in svc.events]
    assert any("first down to 1 m by the rangefinder" in x for x in said), said
    assert any("LAND now" in x and "above the ground by the rangefinder" in x for x in said), said
    # PX4's home 1.5 m below its estimator's origin: frame-6 targets would climb (issue 19).
    assert truth["alt_max"] - truth["alt0"] <= 1.0, truth
