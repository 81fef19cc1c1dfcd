"""Autopilot flavours against a pymavlink peer: mode numbers, type masks, setpoint streams, refusals."""

from __future__ import annotations

import asyncio

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.commands import PositionTarget
from companion.mavlink.ardupilot import ArduPilotCopter
from companion.mavlink.autopilot import FlavourError
from companion.mavlink.flavours import select_flavour
from companion.mavlink.link import CommandRefused, CommandTimeout, LinkConfig, MavLink
from companion.mavlink.px4 import PX4, px4_custom_mode
from companion.mavlink.statustext import send_statustext, statustext_chunks
from tests.mavpeer import MavPeer

FAST = dict(heartbeat_period_s=0.1, heartbeat_timeout_s=0.5, command_timeout_s=0.1, command_retries=1)
TARGET = PositionTarget(47.3980118, 8.5450641, 12.5, 500.5)  # 12.5 m above a home at 488 m AMSL


async def connected(autopilot: int, custom_mode: int = 0):
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    await link.start()
    peer = MavPeer(autopilot=autopilot, custom_mode=custom_mode)
    await peer.connect_udp(link.local_address)
    peer.start_heartbeats(0.05)
    await link.wait_connected(2.0)
    return link, peer


@pytest.fixture
async def apm():
    link, peer = await connected(m.MAV_AUTOPILOT_ARDUPILOTMEGA, custom_mode=5)
    yield link, peer, select_flavour(link)
    await peer.close()
    await link.close()


@pytest.fixture
async def px4():
    link, peer = await connected(m.MAV_AUTOPILOT_PX4, custom_mode=px4_custom_mode(4, 4))
    flavour = select_flavour(link)
    flavour.warmup_s = 0.3
    yield link, peer, flavour
    await flavour.stop()
    await peer.close()
    await link.close()


async def test_flavour_is_chosen_from_the_heartbeat_and_overridable(apm):
    link, _, flavour = apm
    assert isinstance(flavour, ArduPilotCopter)
    assert isinstance(select_flavour(link, "px4"), PX4)
    with pytest.raises(FlavourError, match="auto, ardupilot or px4"):
        select_flavour(link, "inav")
    link.vehicle_autopilot = m.MAV_AUTOPILOT_GENERIC
    with pytest.raises(FlavourError, match="set link.flavour"):
        select_flavour(link)


async def test_ardupilot_mode_names_follow_the_heartbeat(apm):
    _, peer, flavour = apm
    await asyncio.sleep(0.1)
    assert flavour.mode == "LOITER"
    peer.custom_mode = 6
    await asyncio.sleep(0.15)
    assert flavour.mode == "RTL"
    assert flavour.mode_name(0, 99) == "MODE(99)"


async def test_ardupilot_goto_sets_guided_then_a_position_only_global_target(apm):
    _, peer, flavour = apm
    await flavour.goto(TARGET)
    mode_cmd = peer.commands_of(m.MAV_CMD_DO_SET_MODE)[-1]
    assert (mode_cmd.param1, mode_cmd.param2) == (m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
    sp = await peer.wait_for("SET_POSITION_TARGET_GLOBAL_INT")
    assert sp.coordinate_frame == m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT == 6
    assert sp.type_mask == 0b0000110111111000 == 3576
    assert (sp.lat_int, sp.lon_int) == (473980118, 85450641)
    assert sp.alt == pytest.approx(12.5)
    assert (sp.target_system, sp.target_component) == (1, 1)
    await flavour.goto(TARGET)  # already GUIDED: no second mode change
    assert len(peer.commands_of(m.MAV_CMD_DO_SET_MODE)) == 1


@pytest.mark.parametrize("action,mode", [("land", 9), ("rtl", 6), ("loiter", 5)])
async def test_ardupilot_mode_numbers(apm, action, mode):
    _, peer, flavour = apm
    await getattr(flavour, action)()
    assert peer.commands_of(m.MAV_CMD_DO_SET_MODE)[-1].param2 == mode
    assert peer.custom_mode == mode and flavour.commanded_mode is not None


async def test_ardupilot_handback_commands_land_or_rtl(apm):
    _, peer, flavour = apm
    await flavour.handback("RTL")
    assert peer.custom_mode == 6
    await flavour.handback("LAND")
    assert peer.custom_mode == 9
    with pytest.raises(FlavourError):
        await flavour.handback("LOITER")


async def test_a_refused_mode_change_raises_and_sends_no_target(apm):
    _, peer, flavour = apm
    peer.ack_policy[m.MAV_CMD_DO_SET_MODE] = m.MAV_RESULT_DENIED
    with pytest.raises(CommandRefused):
        await flavour.goto(TARGET)
    await asyncio.sleep(0.1)
    assert peer.of_type("SET_POSITION_TARGET_GLOBAL_INT") == []
    peer.ack_policy[m.MAV_CMD_DO_SET_MODE] = None
    with pytest.raises(CommandTimeout):
        await flavour.land()


async def test_px4_streams_setpoints_before_offboard_then_lands(px4):
    link, peer, flavour = px4
    assert flavour.mode == "MISSION"
    await flavour.goto(TARGET)
    mode_cmd = peer.commands_of(m.MAV_CMD_DO_SET_MODE)[-1]
    assert (mode_cmd.param1, mode_cmd.param2, mode_cmd.param3) == (1, 6, 0)
    # Setpoints were already arriving when OFFBOARD was asked for (PX4 refuses it otherwise).
    first_mode_index = next(i for i, (msg, _) in enumerate(peer.received) if msg.get_type() == "COMMAND_LONG"
                            and msg.command == m.MAV_CMD_DO_SET_MODE)
    before = [msg for msg, _ in peer.received[:first_mode_index] if msg.get_type() == "SET_POSITION_TARGET_GLOBAL_INT"]
    assert len(before) >= 2
    sp = before[0]
    # Frame 5 (GLOBAL_INT) with the altitude above mean sea level: PX4 converts frame 6 wrongly
    # whenever home and its estimator's origin differ in altitude (issue 19, docs/autopilot.md).
    assert sp.coordinate_frame == m.MAV_FRAME_GLOBAL_INT and sp.alt == pytest.approx(500.5)
    assert sp.type_mask == 3576 and sp.lat_int == 473980118
    # Stream rate >= 5 Hz over half a second.
    n0 = flavour.setpoints_sent
    await asyncio.sleep(0.5)
    assert flavour.setpoints_sent - n0 >= 4
    assert flavour.mode == "OFFBOARD" and peer.custom_mode == px4_custom_mode(6)
    await flavour.land()
    mode_cmd = peer.commands_of(m.MAV_CMD_DO_SET_MODE)[-1]
    assert (mode_cmd.param2, mode_cmd.param3) == (4, 6)
    assert not flavour.streaming
    await asyncio.sleep(0.1)
    assert flavour.mode == "LAND"


@pytest.mark.parametrize("action,sub,name", [("loiter", 3, "LOITER"), ("rtl", 5, "RTL")])
async def test_px4_auto_sub_modes(px4, action, sub, name):
    _, peer, flavour = px4
    await getattr(flavour, action)()
    cmd = peer.commands_of(m.MAV_CMD_DO_SET_MODE)[-1]
    assert (cmd.param2, cmd.param3) == (4, sub)
    await asyncio.sleep(0.1)
    assert flavour.mode == name


async def test_px4_refuses_a_target_without_its_altitude_above_sea_level(px4):
    _, peer, flavour = px4
    with pytest.raises(FlavourError):
        await flavour.goto(PositionTarget(47.3980118, 8.5450641, 12.5))  # no amsl_m: no home altitude
    await asyncio.sleep(0.2)
    assert not flavour.streaming and peer.of_type("SET_POSITION_TARGET_GLOBAL_INT") == []
    assert peer.commands_of(m.MAV_CMD_DO_SET_MODE) == []


async def test_px4_offboard_refused_stops_the_stream(px4):
    _, peer, flavour = px4
    peer.ack_policy[m.MAV_CMD_DO_SET_MODE] = m.MAV_RESULT_TEMPORARILY_REJECTED
    with pytest.raises(CommandRefused) as info:
        await flavour.goto(TARGET)
    assert info.value.result == m.MAV_RESULT_TEMPORARILY_REJECTED
    assert not flavour.streaming


def test_px4_rejects_slow_setpoint_rates():
    link = MavLink(LinkConfig("udpin:127.0.0.1:0"))
    with pytest.raises(FlavourError, match=">= 5 Hz"):
        PX4(link, setpoint_rate_hz=2.0)


def test_position_target_rejects_nan():
    with pytest.raises(ValueError, match="NaN"):
        PositionTarget(float("nan"), 8.0, 10.0)


def test_statustext_chunks_respect_the_50_byte_limit():
    assert statustext_chunks("short") == [b"short"]
    long = "SLZ: landing at zone 3, 12.4 m away, radius 4.1 m, descending to 10 m"
    chunks = statustext_chunks(long)
    assert all(len(c) <= 50 for c in chunks)
    # Cut at a space; the continuation repeats the prefix; the words are all there.
    assert [c.decode() for c in chunks] == ["SLZ: landing at zone 3, 12.4 m away, radius 4.1 m,",
                                            "SLZ: descending to 10 m"]
    chunks = statustext_chunks("SLZ: zone 17: landing point moved 2.0 m, 1.9 m from where people were seen")
    assert [c.decode() for c in chunks] == ["SLZ: zone 17: landing point moved 2.0 m, 1.9 m".ljust(50),
                                            "SLZ: from where people were seen"]
    assert b"".join(statustext_chunks("é" * 40)).decode() == "é" * 40


async def test_statustext_reaches_the_ground_station(apm):
    link, peer, _ = apm
    send_statustext(link, "SLZ: landing at zone 3, 12.4 m away, radius 4.1 m, altitude 25 m", m.MAV_SEVERITY_NOTICE)
    await peer.wait_for("STATUSTEXT", lambda s: s.chunk_seq == 1)
    texts = peer.of_type("STATUSTEXT")
    assert texts[0].id == texts[1].id != 0 and texts[0].severity == m.MAV_SEVERITY_NOTICE
    assert (texts[0].text + texts[1].text).startswith("SLZ: landing at zone 3")
