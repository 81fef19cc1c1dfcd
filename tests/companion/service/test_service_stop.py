"""Stopping during a takeover with an autopilot that never acknowledges anything: the exit handback
is the last command the autopilot gets (issue 61, item 2).

The service runs in-process (its real stop path, the one SIGTERM takes) with the real model and
pipeline, against a pymavlink peer on loopback UDP that streams a hovering vehicle's telemetry and
answers no command. The trigger comes over a view with no zone, so the controller starts its search
and its first target (GUIDED / OFFBOARD) is still being resent, unanswered, when the stop comes. On
main the landing runner went on: its DO_SET_MODE kept the link's per-command lock, so the handback's
LAND waited behind it, and its retries and the next target followed the handback.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion import config
from companion.mavlink.link import MavLink
from companion.mavlink.px4 import px4_custom_mode
from companion.service.app import Service
from companion.service.freshness import HISTORY
from companion.service.parts import load_model
from tests.companion.service.test_landing_runner import Vehicle
from tests.mavpeer import MavPeer

#: What the companion sends that commands the vehicle, or asks something of it.
COMMANDS = {"COMMAND_LONG", "COMMAND_INT", "SET_MODE", "SET_POSITION_TARGET_GLOBAL_INT",
            "SET_POSITION_TARGET_LOCAL_NED", "PARAM_REQUEST_READ", "PARAM_SET"}


async def _stop_while_unanswered(tmp_path: Path, flavour: str) -> tuple[MavPeer, Service]:
    frames = tmp_path / "frames"
    frames.mkdir(parents=True)
    rng = np.random.default_rng(0)
    # Grass-like noise: frames with nothing a zone could be made of, more of them than the camera's
    # freshness history holds, so that the looped folder plays as a live camera.
    for i in range(HISTORY + 4):
        cv2.imwrite(str(frames / f"{i:04d}.png"), rng.integers(80, 120, (480, 640, 3), dtype=np.uint8))
    px4 = flavour == "px4"
    peer = MavPeer(autopilot=m.MAV_AUTOPILOT_PX4 if px4 else m.MAV_AUTOPILOT_ARDUPILOTMEGA,
                   custom_mode=px4_custom_mode(4, 3) if px4 else 5)  # loitering
    peer.default_ack = None  # answers nothing
    host, port = await peer.listen_udp()
    cfg = config.load(None, {"link.url": f"udpout:{host}:{port}", "link.flavour": flavour,
                             "camera.source": str(frames), "camera.loop": True, "camera.fps": 5.0,
                             "controller.select_timeout_s": 1.0})
    svc = Service(cfg, load_model(cfg), link=MavLink(config.link_config(cfg)))
    task = asyncio.create_task(svc.run())
    vehicle = Vehicle(peer)
    try:
        deadline = time.monotonic() + 20.0
        while svc.monitor is None or not svc.gcs.ready:  # the peer answers once the link has written
            assert time.monotonic() < deadline, "the service never got ready"
            if peer._udp_peer is not None and vehicle._task is None:
                peer.start_heartbeats(0.1)
                vehicle.start()
            await asyncio.sleep(0.05)
        while svc.counters.processed < 3:
            assert time.monotonic() < deadline, f"no frame processed: {svc.counters}"
            await asyncio.sleep(0.05)
        assert svc.monitor.trigger_local("test") is not None
        target = "SET_POSITION_TARGET_GLOBAL_INT" if px4 else "COMMAND_LONG"
        await peer.wait_for(target, lambda c: px4 or c.command == m.MAV_CMD_DO_SET_MODE, timeout=10.0)
        await asyncio.sleep(0.3)  # the takeover's first command is in flight, unanswered
        assert svc.phase in ("SEARCH", "SELECT", "APPROACH"), svc.phase
    finally:
        svc.request_stop("test")  # what SIGTERM calls
        assert await asyncio.wait_for(task, 10.0) == 0
    await asyncio.sleep(2.0)  # anything still sending would be heard by now
    vehicle.stop()
    await peer.close()
    return peer, svc


def _commands(peer: MavPeer) -> list[tuple[float, Any]]:
    return [(t, msg) for msg, t in peer.received if msg.get_type() in COMMANDS]


@pytest.mark.timeout(90)
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
async def test_the_exit_handback_is_the_last_command_sent(tmp_path: Path, flavour: str, model_path: Path) -> None:
    peer, svc = await _stop_while_unanswered(tmp_path, flavour)
    assert svc.autopilot is not None
    land = svc.autopilot.mode_params("LAND")
    sent = _commands(peer)

    def is_land(msg: Any) -> bool:
        return (msg.get_type() == "COMMAND_LONG" and msg.command == m.MAV_CMD_DO_SET_MODE
                and (msg.param2, msg.param3)[: len(land) - 1] == land[1:])

    lands = [i for i, (_, msg) in enumerate(sent) if is_land(msg)]
    # The handback went out, insisting (five attempts 0.25 s apart, none answered)...
    assert len(lands) == 5, [msg for _, msg in sent]
    # ... and nothing followed it: no retry of the takeover's mode change, no new target, no
    # parameter or message-interval request. PX4's setpoints go on only while the last LAND
    # waits for its ACK (the stream stops after the switch: stopping it first makes PX4 fire its
    # offboard-loss action), then stop.
    t_last = sent[lands[-1]][0]
    after = [(t - t_last, msg.get_type()) for t, msg in sent[lands[-1] + 1:]]
    setpoints = [dt for dt, kind in after if kind == "SET_POSITION_TARGET_GLOBAL_INT"]
    assert [kind for _, kind in after if kind != "SET_POSITION_TARGET_GLOBAL_INT"] == [], after
    assert all(dt < 0.25 + 0.1 for dt in setpoints), after
