"""The simulator flown over real MAVLink on loopback UDP with a plain pymavlink client.

The client here is written for the tests (it does not use companion.mavlink): it listens on an
ephemeral 127.0.0.1 port, the simulator sends there (``udpout``), and the client answers to the
address the datagrams come from, like a GCS does with SITL's ``--out``.
"""

from __future__ import annotations

import asyncio
import math
import random

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.ardupilot import GUIDED, LAND, LOITER, RTL
from sim.vehicle.autopilot import AutopilotConfig
from sim.vehicle.faults import Failsafe
from sim.vehicle.kinematics import VehicleParams
from sim.vehicle.px4 import AUTO_LAND, AUTO_LOITER, MAIN_AUTO, MAIN_OFFBOARD, MAIN_POSCTL, OFFBOARD, POSCTL, SUB_LAND
from sim.vehicle.simulator import SimConfig, Simulator

pytestmark = pytest.mark.sitl

HOME = (47.397742, 8.545594, 488.0)
FAST = VehicleParams(land_speed_high=2.5, land_speed=1.5, land_alt_low=1.0, land_detect_s=0.5)


class MavClient(asyncio.DatagramProtocol):
    """A minimal GCS/companion: sysid 255, records every message with its receive time."""

    def __init__(self) -> None:
        self.mav = mav.MAVLink(self, srcSystem=245, srcComponent=191)
        self.mav.robust_parsing = True
        self.rx = mav.MAVLink(None)
        self.rx.robust_parsing = True
        self.peer: tuple[str, int] | None = None
        self.transport: asyncio.DatagramTransport | None = None
        self.log: list[tuple[float, mav.MAVLink_message]] = []
        self._event = asyncio.Event()

    async def open(self) -> int:
        loop = asyncio.get_running_loop()
        await loop.create_datagram_endpoint(lambda: self, local_addr=("127.0.0.1", 0))
        return self.transport.get_extra_info("sockname")[1]

    def connection_made(self, transport) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr) -> None:
        self.peer = addr
        now = asyncio.get_running_loop().time()
        for m in self.rx.parse_buffer(data) or []:
            if m.get_type() != "BAD_DATA":
                self.log.append((now, m))
        self._event.set()

    def write(self, data: bytes) -> None:  # pymavlink's file interface
        assert self.peer is not None, "nothing received from the simulator yet"
        self.transport.sendto(data, self.peer)

    def raw(self, data: bytes) -> None:
        self.transport.sendto(data, self.peer)

    def send(self, msg) -> None:
        self.mav.send(msg)

    def close(self) -> None:
        self.transport.close()

    def mark(self) -> int:
        return len(self.log)

    async def wait(self, type_: str, cond=lambda m: True, timeout: float = 5.0, since: int = 0):
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        i = since
        while True:
            while i < len(self.log):
                m = self.log[i][1]
                i += 1
                if m.get_type() == type_ and cond(m):
                    return m
            left = end - loop.time()
            if left <= 0:
                raise TimeoutError(f"no {type_} matching within {timeout} s")
            self._event.clear()
            try:
                await asyncio.wait_for(self._event.wait(), left)
            except (TimeoutError, asyncio.TimeoutError):
                pass

    def latest(self, type_: str):
        for _, m in reversed(self.log):
            if m.get_type() == type_:
                return m
        return None

    def count(self, type_: str, t0: float, t1: float) -> int:
        return sum(1 for t, m in self.log if t0 <= t < t1 and m.get_type() == type_)

    async def command(self, cmd: int, *params: float, use_int: bool = False, frame: int = 0,
                      timeout: float = 2.0) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        since = self.mark()
        if use_int:
            self.send(mav.MAVLink_command_int_message(1, 1, frame, cmd, 0, 0, *p[:4],
                                                      int(p[4]), int(p[5]), p[6]))
        else:
            self.send(mav.MAVLink_command_long_message(1, 1, cmd, 0, *p))
        ack = await self.wait("COMMAND_ACK", lambda m: m.command == cmd, timeout, since)
        return ack.result

    async def heartbeat(self, cond=lambda m: True, timeout: float = 5.0):
        return await self.wait("HEARTBEAT", cond, timeout, self.mark())


async def fly(flavour: str, start=(0.0, 0.0, -4.0), vehicle: VehicleParams = FAST,
              autopilot: AutopilotConfig | None = None, **kw):
    client = MavClient()
    port = await client.open()
    sim = Simulator(SimConfig(flavour=flavour, outputs=[f"udpout:127.0.0.1:{port}"],
                              start_position=start, vehicle=vehicle,
                              autopilot=autopilot or AutopilotConfig(), seed=7, **kw))
    await sim.start()
    await client.wait("HEARTBEAT", timeout=3.0)
    return sim, client


@pytest.fixture
async def ardupilot():
    sim, client = await fly("ardupilot")
    yield sim, client
    await sim.stop()
    client.close()


@pytest.fixture
async def px4():
    sim, client = await fly("px4")
    yield sim, client
    await sim.stop()
    client.close()


async def test_ardupilot_heartbeat_reports_copter_mode_and_arming(ardupilot) -> None:
    sim, c = ardupilot
    hb = await c.heartbeat()
    assert hb.type == mav.MAV_TYPE_QUADROTOR
    assert hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.custom_mode == LOITER
    assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED  # started airborne
    assert hb.system_status == mav.MAV_STATE_ACTIVE
    assert hb.get_msgbuf()[0] == 0xFD and hb.get_srcSystem() == 1  # MAVLink 2 from system 1


async def test_px4_heartbeat_uses_px4_mode_encoding(px4) -> None:
    sim, c = px4
    hb = await c.heartbeat()
    assert hb.autopilot == mav.MAV_AUTOPILOT_PX4
    assert hb.custom_mode == AUTO_LOITER
    assert (hb.custom_mode >> 16) & 0xFF == MAIN_AUTO and hb.custom_mode >> 24 == 3
    assert hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert await c.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                           MAIN_AUTO, SUB_LAND) == mav.MAV_RESULT_ACCEPTED
    hb = await c.heartbeat(lambda m: m.custom_mode == AUTO_LAND, timeout=2.0)
    assert hb.custom_mode == (MAIN_AUTO << 16) | (SUB_LAND << 24)


async def test_default_rates_and_set_message_interval(ardupilot) -> None:
    sim, c = ardupilot
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    await asyncio.sleep(2.0)
    t1 = loop.time()
    assert 1 <= c.count("HEARTBEAT", t0, t1) <= 3
    assert 16 <= c.count("ATTITUDE", t0, t1) <= 24            # 10 Hz
    assert 8 <= c.count("GLOBAL_POSITION_INT", t0, t1) <= 12   # 5 Hz
    assert 3 <= c.count("EXTENDED_SYS_STATE", t0, t1) <= 5     # 2 Hz
    assert c.count("GIMBAL_DEVICE_ATTITUDE_STATUS", t0, t1) == 0  # no gimbal configured

    assert await c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE,
                           25_000) == mav.MAV_RESULT_ACCEPTED
    assert await c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_DISTANCE_SENSOR,
                           -1) == mav.MAV_RESULT_ACCEPTED
    # Known to the firmware but nothing to report without a gimbal: accepted, never sent.
    assert await c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS, 100_000) == \
        mav.MAV_RESULT_ACCEPTED
    await asyncio.sleep(0.3)
    t0 = loop.time()
    await asyncio.sleep(1.5)
    t1 = loop.time()
    assert 48 <= c.count("ATTITUDE", t0, t1) <= 72             # 40 Hz asked
    assert c.count("DISTANCE_SENSOR", t0, t1) == 0
    assert c.count("GIMBAL_DEVICE_ATTITUDE_STATUS", t0, t1) == 0
    assert await c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, 65000, 100_000) == \
        mav.MAV_RESULT_DENIED  # no such message


async def test_request_message_sends_home_position(ardupilot) -> None:
    sim, c = ardupilot
    since = c.mark()
    assert await c.command(mav.MAV_CMD_REQUEST_MESSAGE,
                           mav.MAVLINK_MSG_ID_HOME_POSITION) == mav.MAV_RESULT_ACCEPTED
    home = await c.wait("HOME_POSITION", since=since, timeout=1.0)
    assert home.latitude == round(HOME[0] * 1e7) and home.longitude == round(HOME[1] * 1e7)
    assert home.altitude == round(HOME[2] * 1000)
    assert await c.command(mav.MAV_CMD_REQUEST_MESSAGE, 9999) == mav.MAV_RESULT_DENIED
    assert await c.command(31999) == mav.MAV_RESULT_UNSUPPORTED


async def test_ardupilot_guided_position_target_flies_there_within_limits(ardupilot) -> None:
    sim, c = ardupilot
    from sim.vehicle.autopilot import GeoFrame
    lat, lon, _ = GeoFrame(*HOME).to_global(12.0, -6.0, 0.0)
    mask = 0b110111111000  # position only
    target = mav.MAVLink_set_position_target_global_int_message(
        0, 1, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mask, int(lat * 1e7), int(lon * 1e7),
        6.0, 0, 0, 0, 0, 0, 0, 0, 0)
    c.send(target)  # outside GUIDED: ignored, like ArduPilot
    await asyncio.sleep(0.5)
    assert math.hypot(*sim.truth.position[:2]) < 0.01
    assert await c.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                           GUIDED) == mav.MAV_RESULT_ACCEPTED
    since = c.mark()
    c.send(target)
    truth = await sim.wait_for(lambda t: math.dist(t.position, (12.0, -6.0, -6.0)) < 0.1, 10.0)
    gpi = [m for _, m in c.log[since:] if m.get_type() == "GLOBAL_POSITION_INT"]
    speeds = [math.hypot(m.vx, m.vy) / 100 for m in gpi]
    assert max(speeds) <= 5.0 + 0.01 and max(speeds) > 4.0
    assert max(m.vz for m in gpi) / 100 <= 1.5 + 0.01 and min(m.vz for m in gpi) / 100 >= -2.5
    assert abs(gpi[-1].relative_alt / 1000 - truth.altitude) < 0.5
    # Local NED, body-offset frame: 2 m forward of the nose (yaw 0 = north).
    here = (await sim.wait_for(lambda t: math.hypot(*t.velocity) < 0.02, 3.0)).position
    c.send(mav.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mav.MAV_FRAME_BODY_OFFSET_NED, mask, 2.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    await sim.wait_for(lambda t: math.dist(t.position, here + (2.0, 0.0, 0.0)) < 0.05, 5.0)


async def test_ardupilot_land_lands_where_it_is_and_disarms(ardupilot) -> None:
    sim, c = ardupilot
    start = sim.truth.position.copy()
    touchdowns = []
    sim.on_touchdown(lambda: touchdowns.append(sim.truth.position.copy()))
    assert await c.command(mav.MAV_CMD_NAV_LAND) == mav.MAV_RESULT_ACCEPTED
    await c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_LANDING)
    hb = await c.heartbeat(lambda m: m.custom_mode == LAND, timeout=2.0)
    await c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_ON_GROUND,
                 timeout=10.0)
    hb = await c.heartbeat(lambda m: not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED, timeout=3.0)
    assert hb.system_status == mav.MAV_STATE_STANDBY
    gpi = await c.wait("GLOBAL_POSITION_INT", since=c.mark())
    assert abs(gpi.relative_alt) < 50  # mm
    assert len(touchdowns) == 1
    assert math.dist(touchdowns[0][:2], start[:2]) < 0.05
    # Landed and disarmed: a disarm is a no-op, and a takeoff outside GUIDED fails.
    assert await c.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5) == mav.MAV_RESULT_FAILED


async def test_ardupilot_arming_rules_and_guided_takeoff() -> None:
    sim, c = await fly("ardupilot", start=(0.0, 0.0, 0.0))
    try:
        hb = await c.heartbeat()
        assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.system_status == mav.MAV_STATE_STANDBY
        assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, LAND) == mav.MAV_RESULT_ACCEPTED
        assert await c.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_FAILED
        assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, 77) == mav.MAV_RESULT_FAILED
        assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_ACCEPTED
        assert await c.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
        assert await c.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3) == \
            mav.MAV_RESULT_ACCEPTED
        await c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_TAKEOFF)
        await sim.wait_for(lambda t: abs(t.altitude - 3.0) < 0.1, 6.0)
        # In flight a plain disarm is refused.
        assert await c.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mav.MAV_RESULT_FAILED
        assert sim.truth.armed
    finally:
        await sim.stop()
        c.close()


async def _stream_setpoints(c: MavClient, north: float, down: float, hz: float, seconds: float):
    mask = 0b110111111000
    for _ in range(int(seconds * hz)):
        c.send(mav.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, mav.MAV_FRAME_LOCAL_NED, mask, north, 0, down, 0, 0, 0, 0, 0, 0, 0, 0))
        await asyncio.sleep(1.0 / hz)


async def test_px4_offboard_needs_stream_and_falls_back_on_loss(px4) -> None:
    sim, c = px4
    assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_OFFBOARD) == \
        mav.MAV_RESULT_TEMPORARILY_REJECTED
    await _stream_setpoints(c, 3.0, -4.0, 1.5, 1.4)  # below 2 Hz: not a stream
    assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_OFFBOARD) == \
        mav.MAV_RESULT_TEMPORARILY_REJECTED
    assert math.hypot(*sim.truth.position[:2]) < 0.01  # setpoints outside OFFBOARD: ignored
    stream = asyncio.create_task(_stream_setpoints(c, 3.0, -4.0, 10.0, 60.0))
    try:
        await asyncio.sleep(1.3)
        assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_OFFBOARD) == \
            mav.MAV_RESULT_ACCEPTED
        await c.heartbeat(lambda m: m.custom_mode == OFFBOARD, timeout=2.0)
        await sim.wait_for(lambda t: abs(t.position[0] - 3.0) < 0.1, 5.0)
    finally:
        stream.cancel()
    loop = asyncio.get_running_loop()
    stopped = loop.time()
    hb = await c.heartbeat(lambda m: m.custom_mode != OFFBOARD, timeout=3.0)
    fell_back_after = loop.time() - stopped
    assert hb.custom_mode == AUTO_LAND
    assert hb.system_status == mav.MAV_STATE_CRITICAL
    assert 0.9 <= fell_back_after <= 2.3  # COM_OF_LOSS_T = 1 s, plus up to one heartbeat
    await c.wait("STATUSTEXT", lambda m: "Offboard" in m.text, timeout=1.0)


@pytest.mark.parametrize("flavour,kind,mode,then,status", [
    ("ardupilot", Failsafe.BATTERY_LOW, RTL, None, mav.MAV_STATE_CRITICAL),
    ("ardupilot", Failsafe.RC_LOSS, LAND, None, mav.MAV_STATE_CRITICAL),
    # PX4 holds (AUTO.LOITER) for COM_FAIL_ACT_T = 5 s, then acts; the companion takes over
    # after the action (battery) or during the hold, which cancels the action (GCS loss).
    ("px4", Failsafe.BATTERY_CRITICAL, AUTO_LOITER, AUTO_LAND, mav.MAV_STATE_EMERGENCY),
    ("px4", Failsafe.GCS_LOSS, AUTO_LOITER, None, mav.MAV_STATE_CRITICAL),
])
async def test_failsafe_switches_mode_by_itself_and_companion_can_take_over(
        flavour, kind, mode, then, status) -> None:
    sim, c = await fly(flavour, start=(0.0, 0.0, -10.0))
    try:
        if flavour == "px4":  # out of AUTO.LOITER first, so the failsafe's hold shows
            assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_POSCTL) == \
                mav.MAV_RESULT_ACCEPTED
            await c.heartbeat(lambda m: m.custom_mode == POSCTL, timeout=2.0)
        sim.inject_failsafe(kind)
        hb = await c.heartbeat(lambda m: m.custom_mode == mode, timeout=2.0)
        assert hb.system_status == status
        if kind in (Failsafe.BATTERY_LOW, Failsafe.BATTERY_CRITICAL):
            want = (mav.MAV_BATTERY_CHARGE_STATE_LOW if kind is Failsafe.BATTERY_LOW
                    else mav.MAV_BATTERY_CHARGE_STATE_CRITICAL)
            bat = await c.wait("BATTERY_STATUS", since=c.mark(), timeout=3.0)
            assert bat.charge_state == want
            assert bat.battery_remaining <= (20 if kind is Failsafe.BATTERY_LOW else 10)
        if then is not None:
            hb = await c.heartbeat(lambda m: m.custom_mode == then, timeout=6.0)
            assert hb.system_status == status
        if flavour == "ardupilot":
            assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_ACCEPTED
            await c.heartbeat(lambda m: m.custom_mode == GUIDED, timeout=2.0)
        else:
            stream = asyncio.create_task(_stream_setpoints(c, 0.0, -10.0, 10.0, 30.0))
            try:
                await asyncio.sleep(1.2)
                assert await c.command(mav.MAV_CMD_DO_SET_MODE, 1, MAIN_OFFBOARD) == \
                    mav.MAV_RESULT_ACCEPTED
                await c.heartbeat(lambda m: m.custom_mode == OFFBOARD, timeout=2.0)
                if then is None:  # taken over during the hold: the action never comes
                    await asyncio.sleep(4.5)
                    assert sim.truth.mode == "OFFBOARD"
                    hb = await c.heartbeat(timeout=2.0)
                    assert hb.custom_mode == OFFBOARD and hb.system_status == status
            finally:
                stream.cancel()
    finally:
        await sim.stop()
        c.close()


async def test_garbage_is_counted_and_dropped_without_crashing(ardupilot) -> None:
    sim, c = ardupilot
    rng = random.Random(3)
    good = mav.MAVLink_command_long_message(1, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0,
                                           mav.MAVLINK_MSG_ID_HOME_POSITION, 0, 0, 0, 0, 0, 0)
    packed = bytearray(good.pack(mav.MAVLink(None, 245, 191)))
    bad_crc = bytes(packed[:-1] + bytes([packed[-1] ^ 0xFF]))
    c.raw(bytes(rng.randrange(256) for _ in range(300)))
    c.raw(bad_crc)
    c.raw(bytes(packed[:10]))  # truncated
    c.raw(b"\xfd")
    c.raw(b"")
    await asyncio.sleep(0.3)
    assert sim.bad_packets >= 3
    assert sim._task is not None and not sim._task.done()
    assert await c.command(mav.MAV_CMD_GET_HOME_POSITION) == mav.MAV_RESULT_ACCEPTED
    # A well-formed command with nonsense parameters gets a NACK, not an exception.
    assert await c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, float("nan"), 1000) == \
        mav.MAV_RESULT_DENIED


async def test_packet_loss_drops_about_that_share_and_latency_delays(ardupilot) -> None:
    sim, c = ardupilot
    link = sim.links[0]
    assert await c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE,
                           20_000) == mav.MAV_RESULT_ACCEPTED  # more samples, tighter share
    await asyncio.sleep(0.1)
    sim.set_link_faults(loss_tx=0.3)
    sent0, got0, dropped0 = link.stats.tx_messages, len(c.log), link.faults.dropped_tx
    await asyncio.sleep(3.0)
    sim.set_link_faults()
    await asyncio.sleep(0.1)  # let the last datagrams land
    sent, got = link.stats.tx_messages - sent0, len(c.log) - got0
    dropped = link.faults.dropped_tx - dropped0
    assert sent > 200
    assert 0.22 <= dropped / sent <= 0.38
    assert abs(got - (sent - dropped)) <= 3  # the rest all arrived (boundary messages aside)
    sim.set_link_faults(latency_tx_s=0.25)
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    assert await c.command(mav.MAV_CMD_GET_HOME_POSITION) == mav.MAV_RESULT_ACCEPTED
    assert loop.time() - t0 >= 0.25
    sim.set_link_faults()  # back to a clean link
    t0 = loop.time()
    assert await c.command(mav.MAV_CMD_GET_HOME_POSITION) == mav.MAV_RESULT_ACCEPTED
    assert loop.time() - t0 < 0.1


async def test_gimbal_status_only_with_a_gimbal_and_pose_for_the_camera() -> None:
    sim, c = await fly("ardupilot", autopilot=AutopilotConfig(gimbal_pitch=-math.pi / 2))
    try:
        g = await c.wait("GIMBAL_DEVICE_ATTITUDE_STATUS", timeout=2.0)
        w, x, y, z = g.q
        assert (w, y) == pytest.approx((math.cos(math.pi / 4), -math.sin(math.pi / 4)), abs=1e-6)
        pose = sim.pose()
        assert pose.down == pytest.approx(-4.0) and pose.gimbal is not None
        pose.validate()
    finally:
        await sim.stop()
        c.close()


async def test_udpin_link_answers_whoever_sends_to_it() -> None:
    import socket as _socket
    with _socket.socket(_socket.AF_INET, _socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    sim = Simulator(SimConfig(flavour="px4", outputs=[f"udpin:127.0.0.1:{port}"],
                              start_position=(0.0, 0.0, -3.0)))
    client = MavClient()
    await client.open()
    await sim.start()
    try:
        await asyncio.sleep(0.5)
        assert client.mark() == 0  # nobody has spoken to the port yet: nothing to send to
        client.peer = ("127.0.0.1", port)
        client.send(mav.MAVLink_heartbeat_message(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID,
                                                  0, 0, 0, 3))
        hb = await client.wait("HEARTBEAT", timeout=2.0)
        assert hb.autopilot == mav.MAV_AUTOPILOT_PX4
    finally:
        await sim.stop()
        client.close()


async def test_ardupilot_reposition_needs_guided_or_the_change_mode_flag(ardupilot) -> None:
    sim, c = ardupilot
    from sim.vehicle.autopilot import GeoFrame
    lat, lon, _ = GeoFrame(*HOME).to_global(-3.0, 2.0, 0.0)
    args = (-1, 0, 0, float("nan"), lat * 1e7, lon * 1e7, 5.0)
    frame = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    assert await c.command(mav.MAV_CMD_DO_REPOSITION, *args, use_int=True, frame=frame) == \
        mav.MAV_RESULT_DENIED  # in LOITER without MAV_DO_REPOSITION_FLAGS_CHANGE_MODE
    args = (-1, mav.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE) + args[2:]
    assert await c.command(mav.MAV_CMD_DO_REPOSITION, *args, use_int=True, frame=frame) == \
        mav.MAV_RESULT_ACCEPTED
    await c.heartbeat(lambda m: m.custom_mode == GUIDED, timeout=2.0)
    await sim.wait_for(lambda t: math.dist(t.position, (-3.0, 2.0, -5.0)) < 0.1, 6.0)
