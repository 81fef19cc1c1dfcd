"""The status page before take-off (issue 62 item 2): the vehicle on the ground, armed or not,
the service up. Headless Chromium at 1280 x 900 must finish its screenshot (a live view that sent
nothing from the ground kept a browser loading forever) and the page must say why frames are not
used, never "ok"; then the vehicle takes off and the same page reads ok with the live figure.
One simulated ArduPilot vehicle starting on the ground, the service in-process in shadow mode."""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path

import pytest

from companion import config
from companion.mavlink.link import MavLink
from companion.service.app import Service
from companion.service.parts import load_model
from sim.flights.flight import FlightSpec, build_scene, reserve_port
from tests.flights.status_page import check_screenshot, page_now, page_text, screenshot, until_while_running

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]


async def _ground_then_air(tmp: Path) -> dict:
    out: dict = {}
    with reserve_port() as link, reserve_port(socket.SOCK_STREAM) as cam, reserve_port(socket.SOCK_STREAM) as page:
        spec = FlightSpec(flavour="ardupilot", world="uniform", seed=6, altitude_m=0.0)
        _, _, sim, camera = build_scene(spec, link.port, cam.port)
        cfg = config.load(None, {"link.url": f"udpin:127.0.0.1:{link.port}", "link.flavour": "ardupilot",
                                 "camera.source": camera.url, "camera.hfov_deg": spec.hfov_deg,
                                 "controller.shadow": True, "live.enabled": True, "live.port": page.port})
        svc = Service(cfg, load_model(cfg), link=MavLink(config.link_config(cfg)))
        await sim.start()
        await camera.start()
        task = asyncio.create_task(svc.run())
        try:
            await until_while_running(
                task, lambda: svc.gcs.ready and svc.health(time.monotonic()).reason == "on the ground", 60)
            out["ground_health"] = svc.health(time.monotonic()).reason
            out["ground_shot"] = await screenshot(page.port, tmp / "page-ground.png")
            out["ground"] = await page_now(page.port)
            sim.take_off(14.0)
            await until_while_running(
                task, lambda: (svc.health(time.monotonic()).ok and svc.last_result is not None
                               and (svc.state.altitude_above_home() or 0.0) > 12.0), 90)
            out["air_shot"] = await screenshot(page.port, tmp / "page-air.png")
            out["air"] = await page_now(page.port)
        finally:
            svc.request_stop("test over")
            out["code"] = await asyncio.wait_for(task, 10.0)
            await camera.stop()
            await sim.stop()
    return out


def test_the_page_before_take_off_says_on_the_ground_and_screenshots(tmp_path, model_path):
    out = asyncio.run(_ground_then_air(tmp_path))
    assert out["code"] == 0
    assert out["ground_health"] == "on the ground", out["ground_health"]
    for when in ("ground", "air"):
        took, err = out[f"{when}_shot"]
        check_screenshot(when, tmp_path / f"page-{when}.png", took, err)
    dom, err, status = out["ground"]
    assert dom is not None, err
    page = page_text(dom)
    assert page.text["health"] == "on the ground" == status["health"]["reason"], page.text
    assert status["health"]["standby"] and not status["health"]["ok"]
    assert page.text["trigger"] == "none" and page.text["handback"] == "none"
    assert page.text["mode"] == status["vehicle"]["mode"] and page.text["mode"] not in ("", "-"), page.text
    assert page.text["height"].startswith("0.") or page.text["height"].startswith("-0."), page.text
    dom, err, status = out["air"]
    assert dom is not None, err
    page = page_text(dom)
    assert page.text["health"] == "ok" and page.text["armed"] == "armed", page.text
    assert status["vehicle"]["height_m"] > 12.0
