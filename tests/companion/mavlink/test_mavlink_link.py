"""The MAVLink link against a pymavlink peer on loopback sockets."""

from __future__ import annotations

import asyncio
import os
import tempfile

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.link import (
    CommandRefused,
    CommandTimeout,
    LinkConfig,
    MavLink,
    message_rates,
    parse_signing_key,
)
from companion.mavlink.transports import TransportError, parse_url
from tests.mavpeer import MavPeer

FAST = dict(heartbeat_period_s=0.1, heartbeat_timeout_s=0.4, command_timeout_s=0.15, command_retries=2)


async def until(pred, timeout: float = 2.0) -> None:
    for _ in range(int(timeout / 0.01)):
        if pred():
            return
        await asyncio.sleep(0.01)
    raise AssertionError("condition not reached in time")


@pytest.fixture
async def pair():
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={"ATTITUDE": 20.0, "SYS_STATUS": 2.0}, **FAST))
    await link.start()
    peer = MavPeer()
    await peer.connect_udp(link.local_address)
    peer.start_heartbeats(0.05)
    await link.wait_connected(2.0)
    yield link, peer
    await peer.close()
    await link.close()


def test_parse_url_accepts_the_four_kinds_and_names_bad_ones():
    assert parse_url("udpin:0.0.0.0:14550").kind == "udpin"
    assert parse_url("udpout:10.0.0.2:14555").port == 14555
    assert parse_url("tcp:localhost:5760").host == "localhost"
    assert parse_url("tcpin:0.0.0.0:5760").kind == "tcpin"
    assert parse_url("serial:/dev/ttyAMA0:921600").host == "/dev/ttyAMA0"
    for bad in ("udp:1.2.3.4:5", "tcp:host", "serial:/dev/ttyS0:12345", "udpin:h:99999", "tcp:h:port"):
        with pytest.raises(TransportError, match="connection URL"):
            parse_url(bad)


def test_message_rates_put_the_pose_at_the_telemetry_rate():
    rates = message_rates(40.0)
    assert rates["ATTITUDE"] == rates["GLOBAL_POSITION_INT"] == 40.0 and rates["BATTERY_STATUS"] == 1.0


def test_config_errors_name_the_key():
    assert LinkConfig("udpin:127.0.0.1:0", target_system=0).target_system is None  # 0 = first heard
    with pytest.raises(ValueError, match="system_id"):
        LinkConfig("udpin:127.0.0.1:0", system_id=0)
    with pytest.raises(ValueError, match="message_rates_hz: unknown message 'ATTITUDEX'"):
        LinkConfig("udpin:127.0.0.1:0", message_rates_hz={"ATTITUDEX": 1.0})
    with pytest.raises(ValueError, match="signing_key"):
        LinkConfig("udpin:127.0.0.1:0", signing_key=b"short")


async def test_identifies_as_onboard_computer_and_requests_intervals(pair):
    link, peer = pair
    hb = await peer.wait_for("HEARTBEAT")
    assert hb.type == m.MAV_TYPE_ONBOARD_CONTROLLER
    assert hb.autopilot == m.MAV_AUTOPILOT_INVALID
    assert hb.get_srcComponent() == 191 and hb.get_srcSystem() == 1
    await peer.wait_for("COMMAND_LONG", lambda c: c.param1 == m.MAVLINK_MSG_ID_SYS_STATUS)
    reqs = peer.commands_of(m.MAV_CMD_SET_MESSAGE_INTERVAL)
    by_id = {int(c.param1): c.param2 for c in reqs}
    assert by_id[m.MAVLINK_MSG_ID_ATTITUDE] == pytest.approx(50_000)  # 20 Hz in microseconds
    assert by_id[m.MAVLINK_MSG_ID_SYS_STATUS] == pytest.approx(500_000)
    assert all(c.target_system == 1 and c.target_component == 1 for c in reqs)
    await until(lambda: link.intervals_acked.get("SYS_STATUS") == m.MAV_RESULT_ACCEPTED)
    assert link.vehicle_autopilot == m.MAV_AUTOPILOT_ARDUPILOTMEGA


async def test_subscribers_get_messages_by_type_with_receive_time(pair):
    link, peer = pair
    got = []
    unsubscribe = link.subscribe("ATTITUDE", lambda msg, t: got.append((msg, t)))
    q = link.queue("ATTITUDE")
    peer.mav.attitude_send(1000, 0.1, -0.2, 3.0, 0, 0, 0)
    msg, t = await asyncio.wait_for(q.get(), 1.0)
    assert msg.roll == pytest.approx(0.1) and msg.yaw == pytest.approx(3.0)
    assert got and got[0][1] == t
    unsubscribe()
    peer.mav.attitude_send(1100, 0.1, -0.2, 3.0, 0, 0, 0)
    await asyncio.wait_for(q.get(), 1.0)
    assert len(got) == 1


async def test_a_crashing_subscriber_is_counted_and_the_link_keeps_going(pair):
    link, peer = pair

    def boom(msg, t):
        raise RuntimeError("subscriber bug")

    link.subscribe("ATTITUDE", boom)
    q = link.queue("ATTITUDE")
    peer.mav.attitude_send(1000, 0, 0, 0, 0, 0, 0)
    await asyncio.wait_for(q.get(), 1.0)
    assert link.stats.handler_errors == 1


async def test_garbage_truncated_and_bad_crc_are_counted_not_fatal(pair):
    link, peer = pair
    q = link.queue("ATTITUDE")
    good = m.MAVLink_attitude_message(1, 0.5, 0, 0, 0, 0, 0).pack(m.MAVLink(None, 1, 1))
    bad_before = link.stats.bad
    peer.send_raw(os.urandom(7).replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00"))  # garbage
    peer.send_raw(good[:-5])  # truncated frame, alone in its datagram
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    peer.send_raw(bytes(bad_crc))
    peer.send_raw(b"\xfd\xff\x00\x00\x00")  # header promising 255 bytes that never come
    await until(lambda: link.stats.bad >= bad_before + 4)
    peer.mav.attitude_send(2000, 0.25, 0, 0, 0, 0, 0)
    msg, _ = await asyncio.wait_for(q.get(), 1.0)
    assert msg.roll == pytest.approx(0.25)  # the link still parses good packets afterwards
    assert link.stats.bad == bad_before + 4


async def test_sequence_gaps_are_counted_as_dropped(pair):
    link, peer = pair
    q = link.queue("ATTITUDE")
    peer.mav.attitude_send(1, 0, 0, 0, 0, 0, 0)
    await asyncio.wait_for(q.get(), 1.0)
    before = link.stats.dropped
    peer.mav.seq = (peer.mav.seq + 5) % 256  # as if 5 packets were lost on the way
    peer.mav.attitude_send(2, 0, 0, 0, 0, 0, 0)
    await asyncio.wait_for(q.get(), 1.0)
    assert link.stats.dropped == before + 5


async def test_command_acked(pair):
    link, peer = pair
    result = await link.command_long(m.MAV_CMD_DO_SET_MODE, (1, 4))
    assert result == m.MAV_RESULT_ACCEPTED
    assert peer.commands_of(m.MAV_CMD_DO_SET_MODE)[-1].confirmation == 0


@pytest.mark.parametrize(
    "result", [m.MAV_RESULT_DENIED, m.MAV_RESULT_FAILED, m.MAV_RESULT_UNSUPPORTED, m.MAV_RESULT_TEMPORARILY_REJECTED]
)
async def test_command_refused_raises_with_the_result(pair, result):
    link, peer = pair
    peer.ack_policy[m.MAV_CMD_DO_SET_MODE] = result
    with pytest.raises(CommandRefused) as info:
        await link.command_long(m.MAV_CMD_DO_SET_MODE, (1, 4))
    assert info.value.result == result
    assert "MAV_CMD_DO_SET_MODE refused" in str(info.value)


async def test_command_times_out_after_retries_with_confirmation_incremented(pair):
    link, peer = pair
    peer.ack_policy[m.MAV_CMD_DO_SET_MODE] = None
    with pytest.raises(CommandTimeout, match="3 attempts"):
        await link.command_long(m.MAV_CMD_DO_SET_MODE, (1, 4))
    assert [c.confirmation for c in peer.commands_of(m.MAV_CMD_DO_SET_MODE)] == [0, 1, 2]


async def test_link_loss_is_noticed_and_recovery_re_requests_intervals(pair):
    link, peer = pair
    changes = []
    link.on_link_change(changes.append)
    await until(lambda: link.intervals_acked.get("SYS_STATUS") == m.MAV_RESULT_ACCEPTED)
    n_requests = len(peer.commands_of(m.MAV_CMD_SET_MESSAGE_INTERVAL))
    peer.stop_heartbeats()
    await until(lambda: not link.connected, timeout=2.0)
    assert changes == [False] and link.stats.link_losses == 1
    peer.start_heartbeats(0.05)
    await until(lambda: link.connected)
    await until(lambda: len(peer.commands_of(m.MAV_CMD_SET_MESSAGE_INTERVAL)) >= n_requests + 2)
    assert changes == [False, True]


async def test_a_gcs_heartbeat_does_not_keep_the_link_alive(pair):
    link, peer = pair
    peer.stop_heartbeats()
    gcs = m.MAVLink(peer, srcSystem=255, srcComponent=190)
    for _ in range(8):
        gcs.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        await asyncio.sleep(0.1)
    assert not link.connected


async def test_tcp_transport_and_reconnect():
    peer = MavPeer()
    host, port = await peer.serve_tcp()
    link = MavLink(LinkConfig(f"tcp:{host}:{port}", message_rates_hz={}, **FAST))
    link.transport._reconnect_s = 0.05  # type: ignore[attr-defined]
    await link.start()
    try:
        await link.transport.wait_connected(2.0)  # type: ignore[attr-defined]
        peer.start_heartbeats(0.05)
        await link.wait_connected(2.0)
        await peer.wait_for("HEARTBEAT", lambda h: h.get_srcComponent() == 191)
        await peer.drop_tcp_client()
        await until(lambda: not link.transport.can_send)
        await until(lambda: link.transport.can_send)  # reconnected by itself
        assert await link.command_long(m.MAV_CMD_DO_SET_MODE, (1, 4)) == m.MAV_RESULT_ACCEPTED
    finally:
        await peer.close()
        await link.close()


async def test_tcpin_transport():
    link = MavLink(LinkConfig("tcpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    await link.start()
    host, port = link.local_address
    reader, writer = await asyncio.open_connection(host, port)
    try:
        fc = m.MAVLink(writer, srcSystem=1, srcComponent=1)
        fc.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
        await link.wait_connected(2.0)
        parser = m.MAVLink(None)
        for _ in range(20):
            msgs = parser.parse_buffer(await asyncio.wait_for(reader.read(4096), 1.0)) or []
            if any(x.get_type() == "HEARTBEAT" and x.get_srcComponent() == 191 for x in msgs):
                break
        else:
            raise AssertionError("no heartbeat from the link over tcpin")
    finally:
        writer.close()
        await link.close()


async def test_udpin_talks_to_a_ground_station_in_its_peers_as_well_as_the_autopilot():
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, peers=("127.0.0.1/32",), **FAST))
    await link.start()
    peer = MavPeer()
    gcs = MavPeer(system_id=255, component_id=190)
    try:
        await peer.connect_udp(link.local_address)
        peer.start_heartbeats(0.05)
        await link.wait_connected(2.0)
        await gcs.connect_udp(link.local_address)
        gcs.heartbeat()  # a ground station on the same port must not steal the autopilot's replies
        await gcs.wait_for("HEARTBEAT", lambda h: h.get_srcComponent() == 191)
        start = len(peer.received)
        assert await link.command_long(m.MAV_CMD_DO_SET_MODE, (1, 4)) == m.MAV_RESULT_ACCEPTED
        await peer.wait_for("HEARTBEAT", lambda h: h.get_srcComponent() == 191, start=start)
        assert link.transport.foreign == 0
    finally:
        await gcs.close()
        await peer.close()
        await link.close()


async def test_udpout_transport():
    peer = MavPeer()
    host, port = await peer.listen_udp()
    link = MavLink(LinkConfig(f"udpout:{host}:{port}", message_rates_hz={}, **FAST))
    await link.start()
    try:
        await peer.wait_for("HEARTBEAT")  # we speak first: the FC learns our address from it
        peer.start_heartbeats(0.05)
        await link.wait_connected(2.0)
    finally:
        await peer.close()
        await link.close()


async def test_serial_transport_over_a_pty():
    master, slave = os.openpty()
    os.set_blocking(master, False)
    link = MavLink(LinkConfig(f"serial:{os.ttyname(slave)}:57600", message_rates_hz={}, **FAST))
    await link.start()
    q = link.queue("HEARTBEAT")
    try:
        fc = m.MAVLink(None, srcSystem=1, srcComponent=1)
        hb = m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_PX4, 0, 0, 4, 3)
        os.write(master, hb.pack(fc))
        msg, _ = await asyncio.wait_for(q.get(), 2.0)
        assert msg.autopilot == m.MAV_AUTOPILOT_PX4
        await link.wait_connected(1.0)
        await asyncio.sleep(0.15)
        parser = m.MAVLink(None)
        parser.robust_parsing = True
        out = parser.parse_buffer(os.read(master, 4096)) or []
        assert any(x.get_type() == "HEARTBEAT" and x.get_srcComponent() == 191 for x in out)
    finally:
        await link.close()
        os.close(master)
        os.close(slave)


async def test_serial_open_errors_are_clear():
    link = MavLink(LinkConfig("serial:/nonexistent/ttyX:57600", **FAST))
    with pytest.raises(OSError, match="cannot open serial port /nonexistent/ttyX"):
        await link.start()
    with tempfile.NamedTemporaryFile() as f:  # a regular file is not a serial port
        with pytest.raises(TransportError, match="is not a serial port"):
            await MavLink(LinkConfig(f"serial:{f.name}:57600", **FAST)).start()
    busy = MavLink(LinkConfig("udpin:127.0.0.1:0", **FAST))
    await busy.start()
    try:
        host, port = busy.local_address
        with pytest.raises(OSError, match="cannot open udpin"):
            await MavLink(LinkConfig(f"udpin:{host}:{port}", **FAST)).start()
    finally:
        await busy.close()


async def test_one_forged_packet_with_a_far_future_timestamp_does_not_lock_out_the_genuine_stream():
    # pymavlink stores a stream's timestamp before verifying the signature: one keyless packet
    # stamped ten years ahead made every genuine packet "old" and the link never recovered.
    key = parse_signing_key("correct horse battery staple")
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, signing_key=key, **FAST))
    await link.start()
    genuine = MavPeer(signing_key=key)
    forger = MavPeer(signing_key=parse_signing_key("not the key"))  # same system, component, link id
    forger.mav.signing.timestamp += 10 * 365 * 86400 * 100_000  # ten years ahead, in 10 us units
    try:
        await genuine.connect_udp(link.local_address)
        genuine.start_heartbeats(0.05)
        await link.wait_connected(2.0)
        # From the autopilot's own address (a compromised router on the path, say): any other
        # address is dropped before the signature is even looked at.
        forger._udp, forger._udp_peer = genuine._udp, genuine._udp_peer
        rejected = link.stats.unsigned_rejected
        forger.heartbeat()
        await until(lambda: link.stats.unsigned_rejected > rejected)
        before = link.stats.received
        await asyncio.sleep(FAST["heartbeat_timeout_s"] * 2)
        # The genuine stream goes on being accepted (30 heartbeats in 1.5 s at 20 Hz, say) and the
        # link never drops.
        assert link.stats.received - before >= 10
        assert link.connected and link.stats.link_losses == 0
    finally:
        await genuine.close()
        await link.close()


async def test_signing_accepts_only_signed_packets():
    key = parse_signing_key("correct horse battery staple")
    assert len(key) == 32 and parse_signing_key("ab" * 32) == bytes.fromhex("ab" * 32)
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, signing_key=key, signing_link_id=3, **FAST))
    await link.start()
    signed_peer = MavPeer(signing_key=key)
    unsigned_peer = MavPeer(system_id=1)
    wrong_key_peer = MavPeer(signing_key=parse_signing_key("wrong"))
    try:
        for p in (unsigned_peer, wrong_key_peer):
            await p.connect_udp(link.local_address)
            p.heartbeat()
        await until(lambda: link.stats.unsigned_rejected == 2)
        assert not link.connected and link.stats.received == 0
        await signed_peer.connect_udp(link.local_address)
        signed_peer.start_heartbeats(0.05)
        await link.wait_connected(2.0)
        # Our packets are signed with our link id: the incompat flag is set and the peer verifies them.
        hb = await signed_peer.wait_for("HEARTBEAT")
        assert hb.get_signed() and hb.get_link_id() == 3
    finally:
        for p in (signed_peer, unsigned_peer, wrong_key_peer):
            await p.close()
        await link.close()
