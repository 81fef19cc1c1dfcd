"""Failsafe trigger sources over a real link: each fires when it should and not otherwise."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import tempfile

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.ardupilot import ArduPilotCopter
from companion.mavlink.failsafe import (
    FailsafeConfig,
    FailsafeMonitor,
    TriggerSource,
    send_local_trigger,
)
from companion.mavlink.link import LinkConfig, MavLink
from tests.mavpeer import MavPeer

FAST = dict(heartbeat_period_s=0.1, heartbeat_timeout_s=0.5, command_timeout_s=0.2, command_retries=1)
ALL_ON = FailsafeConfig(battery_remaining_pct=None, gcs_system_ids=(255,))


class Rig:
    def __init__(self, link: MavLink, peer: MavPeer, monitor: FailsafeMonitor) -> None:
        self.link, self.peer, self.monitor = link, peer, monitor
        self.fired: list = []
        monitor.subscribe(self.fired.append)

    async def settle(self) -> None:
        """Round-trip a ping through the link so that every earlier packet has been handled."""
        q = self.link.queue("TIMESYNC")
        self.peer.mav.timesync_send(0, 1)
        await asyncio.wait_for(q.get(), 1.0)

    def battery(self, charge_state: int, remaining: int = 50) -> None:
        self.peer.mav.battery_status_send(
            0, 0, 0, 2500, [4000] * 3 + [65535] * 7, 1000, 0, 0, remaining, 0, charge_state
        )


@pytest.fixture
async def make_rig():
    made = []

    async def make(config: FailsafeConfig = ALL_ON, custom_mode: int = 5) -> Rig:
        link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
        await link.start()
        peer = MavPeer(custom_mode=custom_mode)
        await peer.connect_udp(link.local_address)
        peer.heartbeat()
        await link.wait_connected(2.0)
        monitor = FailsafeMonitor(config, link, ArduPilotCopter(link))
        monitor.attach()
        made.append((link, peer, monitor))
        return Rig(link, peer, monitor)

    yield make
    for link, peer, monitor in made:
        await monitor.stop_local_socket()
        await peer.close()
        await link.close()


def test_config_errors_name_the_key():
    with pytest.raises(ValueError, match="failsafe.battery_level"):
        FailsafeConfig(battery_level="flat")
    with pytest.raises(ValueError, match="battery_remaining_pct"):
        FailsafeConfig(battery_remaining_pct=150)
    with pytest.raises(ValueError, match="gcs_system_ids"):
        FailsafeConfig(gcs_system_ids=(0,))


async def test_battery_charge_state_at_the_configured_level(make_rig):
    rig = await make_rig()
    rig.battery(m.MAV_BATTERY_CHARGE_STATE_OK)
    rig.battery(m.MAV_BATTERY_CHARGE_STATE_LOW)  # below the configured "critical"
    await rig.settle()
    assert rig.fired == []
    rig.battery(m.MAV_BATTERY_CHARGE_STATE_CRITICAL)
    await rig.settle()
    assert [t.source for t in rig.fired] == [TriggerSource.BATTERY]
    assert "CRITICAL" in rig.fired[0].reason and rig.fired[0].t > 0


async def test_battery_low_level_and_switched_off(make_rig):
    low = await make_rig(dataclasses.replace(ALL_ON, battery_level="low"))
    low.battery(m.MAV_BATTERY_CHARGE_STATE_LOW)
    off = await make_rig(dataclasses.replace(ALL_ON, battery=False, battery_remaining_pct=30))
    off.battery(m.MAV_BATTERY_CHARGE_STATE_EMERGENCY, remaining=5)
    await low.settle()
    await off.settle()
    assert len(low.fired) == 1 and off.fired == []


async def test_battery_remaining_percent_threshold(make_rig):
    rig = await make_rig(dataclasses.replace(ALL_ON, battery_remaining_pct=20))
    rig.battery(m.MAV_BATTERY_CHARGE_STATE_OK, remaining=25)
    rig.battery(m.MAV_BATTERY_CHARGE_STATE_OK, remaining=-1)  # unknown
    rig.peer.mav.sys_status_send(0, 0, 0, 500, 15800, 1200, 21, 0, 0, 0, 0, 0, 0)
    await rig.settle()
    assert rig.fired == []
    rig.peer.mav.sys_status_send(0, 0, 0, 500, 15800, 1200, 19, 0, 0, 0, 0, 0, 0)
    await rig.settle()
    assert len(rig.fired) == 1 and "19%" in rig.fired[0].reason
    unset = await make_rig()
    unset.battery(m.MAV_BATTERY_CHARGE_STATE_OK, remaining=3)  # no % threshold configured
    await unset.settle()
    assert unset.fired == []


async def test_system_status_critical_or_emergency(make_rig):
    rig = await make_rig()
    rig.peer.system_status = m.MAV_STATE_STANDBY
    rig.peer.heartbeat()
    # A camera on the same system in EMERGENCY is not the autopilot.
    cam = m.MAVLink(rig.peer, srcSystem=1, srcComponent=100)
    cam.heartbeat_send(m.MAV_TYPE_CAMERA, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_EMERGENCY)
    await rig.settle()
    assert rig.fired == []
    rig.peer.system_status = m.MAV_STATE_EMERGENCY
    rig.peer.heartbeat()
    await rig.settle()
    assert [t.source for t in rig.fired] == [TriggerSource.SYSTEM_STATUS] and "EMERGENCY" in rig.fired[0].reason
    off = await make_rig(dataclasses.replace(ALL_ON, system_status=False))
    off.peer.system_status = m.MAV_STATE_CRITICAL
    off.peer.heartbeat()
    await off.settle()
    assert off.fired == []


async def test_autopilot_switching_itself_to_rtl_or_land(make_rig):
    rig = await make_rig(custom_mode=5)  # LOITER
    rig.peer.heartbeat()
    rig.peer.custom_mode = 4  # GUIDED: not a failsafe mode
    rig.peer.heartbeat()
    await rig.settle()
    assert rig.fired == []
    rig.peer.custom_mode = 6  # RTL
    rig.peer.heartbeat()
    await rig.settle()
    assert [t.source for t in rig.fired] == [TriggerSource.AUTOPILOT_MODE] and "RTL" in rig.fired[0].reason


async def test_a_land_the_companion_commanded_is_not_a_trigger(make_rig):
    rig = await make_rig(custom_mode=4)
    rig.peer.heartbeat()
    await rig.settle()
    await rig.monitor.autopilot.land()  # the peer switches to 9 and heartbeats before acking
    await rig.settle()
    assert rig.peer.custom_mode == 9 and rig.fired == []


async def test_already_in_land_at_start_and_switched_off_do_not_trigger(make_rig):
    rig = await make_rig(custom_mode=9)  # first heartbeat seen is LAND: no change observed
    rig.peer.heartbeat()
    await rig.settle()
    off = await make_rig(dataclasses.replace(ALL_ON, autopilot_land=False), custom_mode=5)
    off.peer.heartbeat()
    off.peer.custom_mode = 9
    off.peer.heartbeat()
    await asyncio.gather(rig.settle(), off.settle())
    assert rig.fired == [] and off.fired == []


async def gcs_command(rig: Rig, sysid: int, target_component: int = 191):
    gcs = m.MAVLink(rig.peer, srcSystem=sysid, srcComponent=190)
    start = len(rig.peer.received)
    gcs.command_long_send(1, target_component, m.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0)
    return await rig.peer.wait_for(
        "COMMAND_ACK", lambda a: a.command == m.MAV_CMD_USER_1 and a.target_system == sysid, timeout=1.0, start=start
    )


async def test_gcs_trigger_command_is_acked_and_fires(make_rig):
    rig = await make_rig()
    ack = await gcs_command(rig, 255)
    assert ack.result == m.MAV_RESULT_ACCEPTED and ack.target_component == 190
    assert ack.get_srcComponent() == 191
    assert [t.source for t in rig.fired] == [TriggerSource.GCS_COMMAND]


async def test_gcs_trigger_as_command_int(make_rig):
    rig = await make_rig()
    gcs = m.MAVLink(rig.peer, srcSystem=255, srcComponent=190)
    gcs.command_int_send(1, 191, 0, m.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    ack = await rig.peer.wait_for("COMMAND_ACK", lambda a: a.command == m.MAV_CMD_USER_1, timeout=1.0)
    assert ack.result == m.MAV_RESULT_ACCEPTED and [t.source for t in rig.fired] == [TriggerSource.GCS_COMMAND]


async def test_gcs_trigger_from_an_unconfigured_system_is_denied(make_rig):
    rig = await make_rig()
    ack = await gcs_command(rig, 42)
    assert ack.result == m.MAV_RESULT_DENIED and rig.fired == []
    off = await make_rig(dataclasses.replace(ALL_ON, gcs_command=False))
    ack = await gcs_command(off, 255)
    assert ack.result == m.MAV_RESULT_DENIED and off.fired == []


async def test_gcs_trigger_for_another_component_is_not_answered(make_rig):
    rig = await make_rig()
    with pytest.raises((TimeoutError, asyncio.TimeoutError)):
        await gcs_command(rig, 255, target_component=1)
    assert rig.fired == []


async def test_local_trigger_method_latch_and_reset(make_rig):
    rig = await make_rig()
    first = rig.monitor.trigger_local("bench test")
    assert first is not None and first.source == TriggerSource.LOCAL and first.reason == "bench test"
    assert rig.monitor.trigger_local("again") is None  # latched: one landing at a time
    assert len(rig.fired) == 1 and len(rig.monitor.ignored) == 1
    rig.monitor.reset()
    assert rig.monitor.trigger_local("after reset") is not None
    off = await make_rig(dataclasses.replace(ALL_ON, local_trigger=False))
    assert off.monitor.trigger_local() is None and off.fired == []


async def test_local_socket_trigger(make_rig):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "slz.sock")
        rig = await make_rig(dataclasses.replace(ALL_ON, local_socket=path))
        await rig.monitor.start_local_socket()
        assert (os.stat(path).st_mode & 0o777) == 0o660
        assert (await send_local_trigger(path, "operator")).startswith("ok")
        assert rig.fired[0].reason == "operator" and rig.fired[0].source == TriggerSource.LOCAL
        assert (await send_local_trigger(path, "twice")).startswith("ignored: already triggered")
        reader, writer = await asyncio.open_unix_connection(path)
        writer.write(b"\xff\xfegarbage\n")
        assert (await reader.readline()).startswith(b"ignored: unknown request")
        writer.close()
        assert len(rig.fired) == 1
        await rig.monitor.stop_local_socket()
        assert not os.path.exists(path)


async def test_local_socket_refuses_to_replace_a_regular_file(make_rig):
    with tempfile.NamedTemporaryFile() as f:
        rig = await make_rig(dataclasses.replace(ALL_ON, local_socket=f.name))
        with pytest.raises(ValueError, match="not a socket"):
            await rig.monitor.start_local_socket()
