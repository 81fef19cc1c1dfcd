"""Stopping the service in the middle of a takeover: a real one hands the vehicle back to the
autopilot's LAND, a shadow one (which never had it) sends nothing. The service runs in-process
against a pymavlink peer playing the autopilot, over loopback UDP."""

from __future__ import annotations

import asyncio

import cv2
import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion import config
from companion.control.events import Phase
from companion.mavlink.link import MavLink
from companion.service.app import Service
from companion.service.cli import configure, overrides_from_args
from companion.service.parts import load_model
from tests.mavpeer import MavPeer


async def stop_during_select(tmp_path, shadow: bool) -> MavPeer:
    frames = tmp_path / "frames"
    frames.mkdir(parents=True)
    cv2.imwrite(str(frames / "0000.png"), np.full((480, 640, 3), 90, np.uint8))
    peer = MavPeer(custom_mode=5)  # ArduPilot, LOITER
    host, port = await peer.listen_udp()
    cfg = config.load(None, {"link.url": f"udpout:{host}:{port}", "link.flavour": "ardupilot",
                             "camera.source": str(frames), "camera.loop": True, "controller.shadow": shadow})
    svc = Service(cfg, load_model(cfg), link=MavLink(config.link_config(cfg)))
    task = asyncio.create_task(svc.run())
    try:
        while svc.monitor is None or not svc.gcs.ready:  # the peer answers once the link has written
            if peer._udp_peer is not None:
                peer.heartbeat()
            await asyncio.sleep(0.05)
        assert svc.monitor.trigger_local("test") is not None
        while svc.phase != Phase.SELECT.value:
            await asyncio.sleep(0.02)
    finally:
        svc.request_stop("test")
        assert await asyncio.wait_for(task, 10.0) == 0
    await asyncio.sleep(0.2)
    await peer.close()
    return peer


@pytest.mark.timeout(60)
async def test_stopping_in_shadow_mode_hands_nothing_back_and_a_real_stop_does(tmp_path, model_path):
    real = await stop_during_select(tmp_path / "real", shadow=False)
    assert [c for c in real.commands if c.command == m.MAV_CMD_DO_SET_MODE], "the real service handed nothing back"
    shadow = await stop_during_select(tmp_path / "shadow", shadow=True)
    modes = [c for c in shadow.commands if c.command == m.MAV_CMD_DO_SET_MODE]
    assert modes == [] and shadow.of_type("SET_MODE") == []
    assert any(t.startswith("SHADOW: trigger: test") for _, t in shadow.statustexts()), shadow.statustexts()


def test_the_shadow_flag_sets_the_key():
    import argparse

    parser = argparse.ArgumentParser()
    configure(parser)
    assert overrides_from_args(parser.parse_args(["--shadow"]))["controller.shadow"] is True
    assert "controller.shadow" not in overrides_from_args(parser.parse_args([]))
    assert config.load(None, overrides_from_args(parser.parse_args(["--shadow"]))).controller.shadow
