"""One simulated failsafe flown in shadow mode, in-process, with the status page on: what the
simulator's autopilot received from the companion (on the wire, before any decoding of intent),
what a ground station sees (STATUSTEXT, named values, heartbeat), the recording's labels, and the
status page as headless Chromium renders it with the service's real data.

One short flight serves every test here (module fixture): ArduPilot, a battery failsafe at 14 m,
the autopilot's own LAND bringing the vehicle down while the companion watches and decides.
"""

from __future__ import annotations

import asyncio
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion import config
from companion.control.events import Phase, TargetChosen
from companion.mavlink.link import MavLink
from companion.recording import RecordingReader
from companion.service.app import Service
from companion.service.gcs import CONDITIONS, PHASE_CODES
from companion.service.parts import load_model
from sim.flights.flight import FlightSpec, build_scene, reserve_port
from tests.flights.status_page import (
    check_screenshot,
    http_get,
    page_now,
    page_text,
    screenshot,
    until_while_running,
)
from tests.mavpeer import join_statustexts

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

#: What the companion may send the autopilot in shadow mode: its heartbeat, texts, numbers,
#: clock exchange, acknowledgements, requests for telemetry and reads of parameters (its descent
#: speeds); nothing that changes the vehicle's mode, position, arming or parameters.
ALLOWED_TYPES = {"HEARTBEAT", "STATUSTEXT", "NAMED_VALUE_FLOAT", "NAMED_VALUE_INT", "TIMESYNC", "COMMAND_ACK",
                 "COMMAND_LONG", "COMMAND_INT", "PARAM_REQUEST_READ", "PARAM_REQUEST_LIST"}
ALLOWED_COMMANDS = {m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAV_CMD_REQUEST_MESSAGE, m.MAV_CMD_GET_MESSAGE_INTERVAL,
                    m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, m.MAV_CMD_GET_HOME_POSITION}


@dataclass
class Flight:
    svc: Service
    code: int
    wire: list[tuple[Any, int, int]] = field(default_factory=list)  # (message, src system, src component)
    wire_t: list[float] = field(default_factory=list)  # when each arrived (monotonic s)
    modes: list[str] = field(default_factory=list)  # the simulated autopilot's modes, as they changed
    touchdown: bool = False
    dom: str | None = None  # the status page as Chromium rendered it
    dom_error: str | None = None
    page_status: dict[str, Any] | None = None  # /status.json fetched at the same moment
    mjpeg_part: bytes = b""
    #: The page's screenshot at "flight" and "landed": (the PNG or None, seconds taken, why none)
    shots: dict[str, tuple[Path | None, float, str | None]] = field(default_factory=dict)
    #: The page at "landed": (DOM or None, why none, /status.json)
    looks: dict[str, tuple[str | None, str | None, dict[str, Any]]] = field(default_factory=dict)
    record_dir: Path | None = None


async def _look(flight: Flight, port: int, when: str) -> None:
    """The page at ``when``: its DOM, /status.json and a 1280 x 900 screenshot (time to take it)."""
    assert flight.record_dir is not None
    shot = flight.record_dir.parent / f"page-{when}.png"
    took, err = await screenshot(port, shot)
    flight.shots[when] = (shot if err is None and shot.exists() else None, took, err)
    flight.looks[when] = await page_now(port)


async def _fly(record_dir: Path) -> Flight:
    # The ports stay claimed for the flight (no other flight on this machine takes them meanwhile).
    with reserve_port() as link, reserve_port(socket.SOCK_STREAM) as cam, reserve_port(socket.SOCK_STREAM) as page:
        return await _fly_on(record_dir, link.port, cam.port, page.port)


async def _fly_on(record_dir: Path, link_port: int, cam_port: int, page_port: int) -> Flight:
    spec = FlightSpec(flavour="ardupilot", world="uniform", seed=6, altitude_m=14.0, land_speed=1.0)
    _, _, sim, camera = build_scene(spec, link_port, cam_port)
    cfg = config.load(None, {"link.url": f"udpin:127.0.0.1:{link_port}", "link.flavour": "ardupilot",
                             "camera.source": camera.url, "camera.hfov_deg": spec.hfov_deg,
                             "controller.shadow": True, "live.enabled": True, "live.port": page_port,
                             "recorder.enabled": True, "recorder.dir": str(record_dir), "gcs.values_hz": 2.0})
    svc = Service(cfg, load_model(cfg), link=MavLink(config.link_config(cfg)))
    flight = Flight(svc, -1, record_dir=record_dir)

    handle = sim.autopilot.handle_message

    def on_wire(msg: Any, channel: Any) -> None:  # everything the simulated autopilot receives
        flight.wire.append((msg, msg.get_srcSystem(), msg.get_srcComponent()))
        flight.wire_t.append(time.monotonic())
        handle(msg, channel)

    sim.autopilot.handle_message = on_wire  # type: ignore[method-assign]
    sim.on_touchdown(lambda: setattr(flight, "touchdown", True))
    await sim.start()
    await camera.start()
    task = asyncio.create_task(svc.run())
    try:
        await until_while_running(
            task, lambda: (svc.gcs.ready and svc.last_result is not None and svc.controller is not None
                           and svc.controller.zone_target() is not None), 60)
        assert svc.gcs.ready and svc.controller is not None and svc.controller.zone_target() is not None, \
            "the service never saw a landing zone"
        # The page while it watches: real zones, a target, the live view.
        flight.mjpeg_part = await http_get(page_port, "/stream.mjpg", limit=4000)
        flight.dom, flight.dom_error, flight.page_status = await page_now(page_port)
        await _look(flight, page_port, "flight")
        sim.inject_failsafe("battery_critical")
        end = time.monotonic() + 60
        while not flight.touchdown and time.monotonic() < end and not task.done():
            mode = sim.truth.mode
            if not flight.modes or flight.modes[-1] != mode:
                flight.modes.append(mode)
            await asyncio.sleep(0.1)
        await asyncio.sleep(1.0)
        if flight.touchdown:  # on the ground, frames refused: the page and its live view still load
            await _look(flight, page_port, "landed")
    finally:
        svc.request_stop("test over")
        flight.code = await asyncio.wait_for(task, 10.0)
        await camera.stop()
        await sim.stop()
    return flight


@pytest.fixture(scope="module")
def flight(tmp_path_factory, model_path) -> Flight:
    return asyncio.run(_fly(tmp_path_factory.mktemp("shadow-recording")))


def from_companion(flight: Flight) -> list[Any]:
    cfg = flight.svc.cfg.link
    return [msg for msg, sys_id, comp in flight.wire if (sys_id, comp) == (cfg.system_id, cfg.component_id)]


def test_shadow_mode_sends_no_mode_or_position_command_through_a_whole_failsafe(flight):
    assert flight.code == 0
    assert flight.touchdown, f"the autopilot's LAND did not land the vehicle; modes {flight.modes}"
    sent = from_companion(flight)
    assert sent, "nothing from the companion reached the autopilot: the capture is broken"
    types = {msg.get_type() for msg in sent}
    assert types <= ALLOWED_TYPES, types - ALLOWED_TYPES
    commands = {int(msg.command) for msg in sent if msg.get_type() in ("COMMAND_LONG", "COMMAND_INT")}
    assert commands <= ALLOWED_COMMANDS, commands - ALLOWED_COMMANDS
    # The autopilot flew its own failsafe alone: never GUIDED.
    assert "GUIDED" not in flight.modes and "LAND" in flight.modes, flight.modes
    # Meanwhile the companion decided: the trigger, a target, and an end; nothing was executed.
    events = flight.svc.events
    phases = [e.phase for e in events if e.changed]
    assert phases[:1] == [Phase.SELECT] and any(isinstance(e, TargetChosen) for e in events), \
        [e.text for e in events]
    assert flight.svc.runner is not None and flight.svc.runner.executed == []
    assert flight.svc.runner.withheld, "the controller gave no command to withhold"


def statustexts(flight: Flight) -> list[tuple[int, str]]:
    return join_statustexts(from_companion(flight))


def test_the_ground_station_sees_readiness_the_shadow_decisions_and_the_numbers(flight):
    texts = statustexts(flight)
    assert (m.MAV_SEVERITY_NOTICE, "SLZ: ready, model slz-density-v4, camera 640x480") in texts, texts
    assert (m.MAV_SEVERITY_NOTICE, "SHADOW: on; the companion will command nothing") in texts
    decisions = [(sev, t) for sev, t in texts if t.startswith("SHADOW: ") and "on; the companion" not in t]
    triggers = [(sev, t) for sev, t in decisions if t.startswith("SHADOW: trigger: ")]
    assert len(triggers) == 1 and triggers[0][0] == m.MAV_SEVERITY_WARNING, decisions
    assert any(sev == m.MAV_SEVERITY_NOTICE and "landing at zone" in t for sev, t in decisions), decisions
    # Every other text is readiness or a state change (a loaded machine may well make the model
    # slow or the camera late): no decision goes out unmarked.
    told = tuple(c.split("{")[0] for cond in CONDITIONS.values() for c in (cond.bad_text, cond.good_text))
    unmarked = [t for _, t in texts if not t.startswith(("SHADOW: ", "SLZ: ready", *told))]
    assert not unmarked, unmarked
    # Each decision told is one of the controller's, told once; every text the paced outbox sent
    # arrived whole, in its order (the rest were repeats, stale news or newer news of a condition).
    said = ["SHADOW: " + e.text.removeprefix("SLZ: ") for e in flight.svc.events]
    assert all(t in said for _, t in decisions) and len({t for _, t in decisions}) == len(decisions), decisions
    assert [t for _, t in texts] == [t for _, _, t in flight.svc.gcs.outbox.sent], texts
    values: dict[str, list[float]] = {}
    for msg in from_companion(flight):
        if msg.get_type() in ("NAMED_VALUE_INT", "NAMED_VALUE_FLOAT"):
            values.setdefault(msg.name, []).append(msg.value)
    assert max(values["SLZ_ZONES"]) >= 1 and max(values["SLZ_FPS"]) > 2.0
    assert {0, 1} <= set(values["SLZ_PHASE"]) or {0, 2} <= set(values["SLZ_PHASE"]), values["SLZ_PHASE"]
    # Every phase the controller went through is plotted, however briefly it lasted (a zone right
    # under the camera passes SELECT and APPROACH within a frame, between two 1 Hz samples).
    went = {PHASE_CODES[e.phase] for e in flight.svc.events if e.changed}
    assert went <= set(values["SLZ_PHASE"]), (went, values["SLZ_PHASE"])
    assert any(r > 4.0 for r in values["SLZ_TGT_R"]), values["SLZ_TGT_R"]  # r0 + margin at least
    assert any(c == c for c in values["SLZ_CLEAR"])  # a number (not NaN) while there was a target
    states = [int(msg.system_status) for msg in from_companion(flight) if msg.get_type() == "HEARTBEAT"]
    # (Over udpin nothing reaches the autopilot before it is heard, and the service is ready
    # moments later: STANDBY before ready is tested against a peer in test_gcs.py.)
    assert m.MAV_STATE_ACTIVE in states and set(states) <= {m.MAV_STATE_STANDBY, m.MAV_STATE_ACTIVE}, states


def test_the_recording_labels_every_decision_shadow(flight):
    assert flight.record_dir is not None
    run = next(p for p in flight.record_dir.iterdir() if (p / "meta.json").is_file())
    rec = RecordingReader(run)
    assert rec.meta["shadow"] is True
    controller = list(rec.events("controller"))
    assert controller and all(e.get("shadow") is True for e in controller)
    withheld = list(rec.events("shadow_command"))
    assert withheld and withheld[0]["command"] == "Goto"


def test_the_status_page_in_headless_chromium_shows_the_phase_the_zones_and_the_live_view(flight):
    assert flight.mjpeg_part.startswith(b"HTTP/1.1 200 OK") and b"--slzframe\r\nContent-Type: image/jpeg" \
        in flight.mjpeg_part
    info = flight.svc.commands.video()  # what a ground station asking for it is told
    assert info is not None and info.uri == f"http://127.0.0.1:{flight.svc.cfg.live.port}/stream.mjpg"
    assert (info.width, info.height) == (640 + 4 + 480, 480 + 28)
    if flight.dom is None:
        pytest.skip(f"no headless browser: {flight.dom_error}")
    page = page_text(flight.dom)
    status = flight.page_status
    assert status is not None
    assert page.text.get("phase") == "MONITOR" == status["phase"], page.text
    assert page.text.get("health") == "ok"
    assert page.text.get("shadow") == "SHADOW MODE: no commands sent"
    zones = int(page.text["zone-count"])
    assert zones >= 1 and page.rows == zones + 1  # the header row and one per zone
    assert page.text["target"].startswith("#")
    assert '<img id="live" src="/stream.mjpg"' in flight.dom
    # What a pilot reads first: the height, the autopilot's mode, armed, no trigger yet, and no
    # clearance figure from 14 m (judged at 10 m: a walker's distance from up here, not the zone's).
    mode = status["vehicle"]["mode"]
    assert "m above home" in page.text["height"] and page.text["mode"] == mode and mode, page.text
    assert page.text["armed"] == "armed" and page.text["trigger"] == "none" and page.text["handback"] == "none"
    assert page.text["clearance"].startswith("n/a above 10 m"), page.text
    for key in ("people", "unlandable ground", "proposals", "zones", "target"):  # the legend
        assert f"&#9632; {key}</span>" in flight.dom or f"\u25a0 {key}</span>" in flight.dom, key


def test_the_page_loads_and_screenshots_in_flight_and_after_landing(flight):
    """Headless Chromium at 1280 x 900 takes the page's screenshot in flight and on the ground
    after landing (before the placeholder frames, one after landing never finished); on the ground
    health says why frames are not used, never "ok", and the trigger's time shows."""
    assert flight.touchdown
    for when in ("flight", "landed"):
        check_screenshot(when, *flight.shots[when])
    dom, err, status = flight.looks["landed"]
    assert dom is not None, err
    page = page_text(dom)
    assert page.text["health"] == status["health"]["reason"] != "ok", page.text
    assert status["health"]["reason"] in ("on the ground", "below the head plane"), status["health"]
    assert " s ago (" in page.text["trigger"], page.text
    assert "m above home" in page.text["height"] and page.text["mode"] == status["vehicle"]["mode"], page.text
    assert status["clearance_note"] is None or status["target"] is None


def test_the_ground_station_gets_at_most_4_texts_in_any_10_s_none_repeated_within_5_s(flight):
    """Issue 62's targets, on what reached the autopilot (and so the ground station) in a real-time
    flight: at most 4 texts from the companion in any 10 s, none repeated within 5 s, at most 2
    about the model's speed; the chunks of one text 50 ms apart."""
    cfg = flight.svc.cfg.link
    mine = [(t, msg) for (msg, sys_id, comp), t in zip(flight.wire, flight.wire_t)
            if (sys_id, comp) == (cfg.system_id, cfg.component_id) and msg.get_type() == "STATUSTEXT"]
    starts = [(t, msg) for t, msg in mine if not msg.chunk_seq]  # one per text
    assert len(starts) >= 3, starts
    texts = [(t, text) for (t, _), (_, text) in zip(starts, join_statustexts([msg for _, msg in mine]))]
    for t0, _ in texts:
        window = [text for t, text in texts if t0 <= t < t0 + 10.0 - 0.05]  # 50 ms for the loopback
        assert len(window) <= 4, window
        assert sum("model s" in text for text in window) <= 2, window
    for k, (t0, text) in enumerate(texts):
        assert not any(text == other and t - t0 < 5.0 - 0.05 for t, other in texts[k + 1:]), text
    chunked = [t for t, msg in mine if msg.chunk_seq]
    assert all(any(0.04 <= tc - t <= 1.0 for t, _ in starts) for tc in chunked), "chunks sent back to back"
