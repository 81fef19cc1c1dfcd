"""A ground station on the simulator's second link sees the companion, as through a real autopilot.

Loopback UDP in one process, seconds per test, nothing flown: the simulator (ArduPilot or PX4
flavour) with the companion's real link, command server and failsafe monitor on its first link
(``udpout``, sysid 1 / compid 191) and a pymavlink ground station (255/190) on its second
(``udpin``, the ground station "connects"). The routing rules under test are ArduPilot's
``MAVLink_routing.cpp`` and PX4's ``Mavlink::forward_message`` (``sim/vehicle/routing.py``).
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.trigger import TriggerSource
from companion.mavlink.failsafe import FailsafeConfig, FailsafeMonitor
from companion.mavlink.gcs_commands import CameraInfo, CommandServer
from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.statustext import send_statustext
from sim.flights.demo import ground_station_line
from sim.flights.flight import FlightSpec, build_scene, reserve_port
from sim.vehicle.endpoint import parse_link
from sim.vehicle.simulator import SimConfig, Simulator
from tests.mavpeer import MavPeer

pytestmark = pytest.mark.timeout(60)

FAST = dict(heartbeat_period_s=0.2, heartbeat_timeout_s=1.0, command_timeout_s=0.2, command_retries=1)


def gcs_peer(system_id: int = 255, component_id: int = 190) -> MavPeer:
    """A ground station: it answers no commands, and its heartbeat says GCS."""
    peer = MavPeer(system_id=system_id, component_id=component_id, autopilot=m.MAV_AUTOPILOT_INVALID)
    peer.default_ack = None
    peer.heartbeat = lambda: peer.mav.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)  # type: ignore[method-assign]
    return peer


def from_(msg, system: int, component: int) -> bool:
    return msg.get_srcSystem() == system and msg.get_srcComponent() == component


@dataclass
class Rig:
    sim: Simulator
    link: MavLink
    monitor: FailsafeMonitor
    server: CommandServer
    gcs: MavPeer
    fired: list


@contextlib.asynccontextmanager
async def companion_and_gcs(flavour: str, forward: tuple[str, str] = ("", "")) -> AsyncIterator[Rig]:
    """The simulator with the real companion link on link 0 and a ground station on link 1."""
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    await link.start()
    port = link.local_address[1]
    sim = Simulator(SimConfig(flavour=flavour, seed=1,
                              outputs=[f"udpout:127.0.0.1:{port}{forward[0]}", f"udpin:127.0.0.1:0{forward[1]}"]))
    await sim.start()
    gcs = gcs_peer()
    try:
        await gcs.connect_udp(sim.links[1].local_address)
        gcs.start_heartbeats(0.2)
        await link.wait_connected(5.0)
        server = CommandServer(link, camera=CameraInfo(640, 480))
        server.attach()
        monitor = FailsafeMonitor(FailsafeConfig(gcs_system_ids=(255,)), link)
        monitor.attach(server)
        fired: list = []
        monitor.subscribe(fired.append)
        # The simulator hears the ground station (its udpin link sends only once it has).
        await gcs.wait_for("HEARTBEAT", lambda h: from_(h, 1, 1), timeout=5.0)
        yield Rig(sim, link, monitor, server, gcs, fired)
    finally:
        await gcs.close()
        await sim.stop()
        await link.close()


async def trigger(rig: Rig, timeout: float = 2.0):
    start = len(rig.gcs.received)
    rig.gcs.mav.command_long_send(1, 191, m.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0)
    return await rig.gcs.wait_for("COMMAND_ACK", lambda a: a.command == m.MAV_CMD_USER_1 and from_(a, 1, 191),
                                  timeout=timeout, start=start)


async def sees_the_companion(rig: Rig) -> None:
    """HEARTBEAT, STATUSTEXT, NAMED_VALUE_FLOAT and the trigger's ACK cross the simulator."""
    hb = await rig.gcs.wait_for("HEARTBEAT", lambda h: from_(h, 1, 191), timeout=3.0)
    assert hb.type == m.MAV_TYPE_ONBOARD_CONTROLLER
    send_statustext(rig.link, "SLZ: watching the ground", m.MAV_SEVERITY_INFO)
    rig.link.send(rig.link.mav.named_value_float_encode(0, b"slz_zones", 2.0))
    text = await rig.gcs.wait_for("STATUSTEXT", lambda s: from_(s, 1, 191), timeout=2.0)
    assert text.text == "SLZ: watching the ground"
    await rig.gcs.wait_for("NAMED_VALUE_FLOAT", lambda v: from_(v, 1, 191) and v.name == "slz_zones", timeout=2.0)
    ack = await trigger(rig)
    assert ack.result == m.MAV_RESULT_ACCEPTED and ack.target_system == 255 and ack.target_component == 190
    assert [t.source for t in rig.fired] == [TriggerSource.GCS_COMMAND]


async def test_ardupilot_a_ground_station_sees_the_companion_and_triggers_it():
    async with companion_and_gcs("ardupilot") as rig:
        await sees_the_companion(rig)
        assert rig.sim.routing.stats.forwarded > 0


async def test_px4_with_forwarding_on_a_ground_station_sees_the_companion_and_triggers_it():
    async with companion_and_gcs("px4", ("?forward=1", "?forward=1")) as rig:
        await sees_the_companion(rig)


@pytest.mark.parametrize("forward", [("", ""), ("?forward=1", ""), ("", "?forward=1")])
async def test_px4_without_forwarding_on_both_links_nothing_crosses(forward):
    async with companion_and_gcs("px4", forward) as rig:
        send_statustext(rig.link, "SLZ: watching the ground", m.MAV_SEVERITY_INFO)
        with pytest.raises(TimeoutError):
            await trigger(rig, timeout=1.0)
        assert rig.fired == []
        assert not [msg for msg, _ in rig.gcs.received if from_(msg, 1, 191)]
        assert rig.sim.routing.stats.forwarded == 0


def test_forward_option_is_parsed_and_checked():
    assert parse_link("udpin:127.0.0.1:14560?forward=1") == ("udpin", ("127.0.0.1", 14560), True)
    assert parse_link("udp:127.0.0.1:14550")[2] is None
    with pytest.raises(ValueError, match="forward=0 or forward=1"):
        parse_link("udpin:127.0.0.1:14560?forward=yes")
    with pytest.raises(ValueError, match="ArduPilot routes MAVLink on every link"):
        SimConfig(flavour="ardupilot", outputs=["udpin:127.0.0.1:0?forward=0"])


# ----- the rules themselves, with three pymavlink peers -------------------------------------------


@contextlib.asynccontextmanager
async def three_peers(flavour: str = "ardupilot", opt: str = "") -> AsyncIterator[tuple[Simulator, MavPeer, MavPeer, MavPeer]]:
    """The simulator with a companion peer (1/191, link 0) and ground stations A (255/190, link 1)
    and B (254/190, link 2), each heard by the simulator before the test starts."""
    comp = MavPeer(system_id=1, component_id=191, autopilot=m.MAV_AUTOPILOT_INVALID)
    comp.default_ack = None
    port = (await comp.listen_udp())[1]
    sim = Simulator(SimConfig(flavour=flavour, seed=2, outputs=[
        f"udpout:127.0.0.1:{port}{opt}", f"udpin:127.0.0.1:0{opt}", f"udpin:127.0.0.1:0{opt}"]))
    await sim.start()
    a, b = gcs_peer(255), gcs_peer(254)
    try:
        await comp.wait_for("HEARTBEAT", lambda h: from_(h, 1, 1), timeout=5.0)
        comp.start_heartbeats(0.2)
        for peer, lk in ((a, sim.links[1]), (b, sim.links[2])):
            await peer.connect_udp(lk.local_address)
            peer.start_heartbeats(0.2)
        for peer in (comp, a, b):
            others = [p for p in (comp, a, b) if p is not peer]
            for other in others:  # every peer has heard every other one's heartbeat: routes learned
                ids = (other.mav.srcSystem, other.mav.srcComponent)
                await peer.wait_for("HEARTBEAT", lambda h, ids=ids: from_(h, *ids), timeout=5.0)
        yield sim, comp, a, b
    finally:
        for peer in (comp, a, b):
            await peer.close()
        await sim.stop()


async def settle(*peers: MavPeer, s: float = 0.4) -> None:
    await asyncio.sleep(s)


async def test_a_message_is_never_echoed_back_to_its_sender():
    async with three_peers() as (sim, comp, a, b):
        a.mav.statustext_send(m.MAV_SEVERITY_INFO, b"from A", 0, 0)
        comp.mav.statustext_send(m.MAV_SEVERITY_INFO, b"from the companion", 0, 0)
        await b.wait_for("STATUSTEXT", lambda s: s.text == "from A", timeout=2.0)
        await a.wait_for("STATUSTEXT", lambda s: s.text == "from the companion", timeout=2.0)
        await comp.wait_for("STATUSTEXT", lambda s: s.text == "from A", timeout=2.0)
        await settle()
        for peer in (comp, a, b):
            own = (peer.mav.srcSystem, peer.mav.srcComponent)
            echoed = [msg.get_type() for msg, _ in peer.received if from_(msg, *own)]
            assert echoed == [], f"{own} got its own {echoed}"


async def test_targeted_messages_go_only_to_the_link_where_the_target_was_heard():
    async with three_peers() as (sim, comp, a, b):
        # To the companion (this vehicle's system, component 191): its link only.
        a.mav.param_request_read_send(1, 191, b"SLZ_R0", -1)
        # To ground station B (another system): B's link only.
        a.mav.param_request_read_send(254, 190, b"FOR_B", -1)
        # To the autopilot alone: nobody else.
        a.mav.param_request_read_send(1, 1, b"FOR_AP", -1)
        # To a system nobody has heard: nowhere.
        a.mav.param_request_read_send(77, 1, b"NOBODY", -1)
        await comp.wait_for("PARAM_REQUEST_READ", lambda p: p.param_id == "SLZ_R0", timeout=2.0)
        await b.wait_for("PARAM_REQUEST_READ", lambda p: p.param_id == "FOR_B", timeout=2.0)
        await settle()
        got = {peer: {p.param_id for p in peer.of_type("PARAM_REQUEST_READ")} for peer in (comp, a, b)}
        assert got[comp] == {"SLZ_R0"} and got[b] == {"FOR_B"} and got[a] == set()


async def test_px4_forwards_untargeted_and_targeted_messages_only_where_seen():
    async with three_peers("px4", "?forward=1") as (sim, comp, a, b):
        a.mav.param_request_read_send(1, 191, b"SLZ_R0", -1)
        a.mav.param_request_read_send(1, 1, b"FOR_AP", -1)  # addressed to the autopilot: kept
        comp.mav.statustext_send(m.MAV_SEVERITY_INFO, b"from the companion", 0, 0)
        await comp.wait_for("PARAM_REQUEST_READ", lambda p: p.param_id == "SLZ_R0", timeout=2.0)
        await a.wait_for("STATUSTEXT", lambda s: s.text == "from the companion", timeout=2.0)
        await b.wait_for("STATUSTEXT", lambda s: s.text == "from the companion", timeout=2.0)
        await settle()
        assert {p.param_id for p in comp.of_type("PARAM_REQUEST_READ")} == {"SLZ_R0"}
        assert b.of_type("PARAM_REQUEST_READ") == []


class RecordingPeer(MavPeer):
    """A peer that keeps every datagram it sends."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        self.sent: list[bytes] = []

    def send_raw(self, data: bytes) -> None:
        self.sent.append(bytes(data))
        super().send_raw(data)


async def test_signed_packets_cross_byte_for_byte_and_garbage_does_not_cross():
    key = bytes(range(32))
    comp = RecordingPeer(system_id=1, component_id=191, autopilot=m.MAV_AUTOPILOT_INVALID, signing_key=key)
    comp.default_ack = None
    port = (await comp.listen_udp())[1]
    sim = Simulator(SimConfig(flavour="ardupilot", seed=3,
                              outputs=[f"udpout:127.0.0.1:{port}", "udpin:127.0.0.1:0"]))
    await sim.start()
    gcs = gcs_peer()
    try:
        await comp.wait_for("HEARTBEAT", timeout=5.0)
        await gcs.connect_udp(sim.links[1].local_address)
        gcs.start_heartbeats(0.2)
        await gcs.wait_for("HEARTBEAT", lambda h: from_(h, 1, 1), timeout=5.0)
        comp.heartbeat()
        comp.mav.statustext_send(m.MAV_SEVERITY_INFO, b"signed text", 0, 0)
        text = await gcs.wait_for("STATUSTEXT", lambda s: s.text == "signed text", timeout=2.0)
        sent = [d for d in comp.sent if d[7:10] == bytes([m.MAVLINK_MSG_ID_STATUSTEXT, 0, 0])]
        assert bytes(text.get_msgbuf()) == sent[-1] and sent[-1][2] & m.MAVLINK_IFLAG_SIGNED
        # Noise, a truncated packet and a well-framed packet of an id the dialect lacks: counted,
        # not forwarded, and the simulator keeps routing.
        forwarded = sim.links[1].stats.forwarded_tx  # toward the ground station
        rng = random.Random(7)
        comp.send_raw(bytes(rng.randrange(256) for _ in range(60)))
        comp.send_raw(sent[-1][:15])
        payload = b"\x01\x02\x03\x04"
        comp.send_raw(bytes([0xFD, len(payload), 0, 0, 0, 1, 191]) + (60000).to_bytes(3, "little")
                      + payload + b"\x00\x00")
        await asyncio.sleep(0.3)
        assert sim.links[1].stats.forwarded_tx == forwarded
        assert sim.routing.stats.unknown_dropped == 1
        assert sim.links[0].stats.bad_packets >= 2
        comp.mav.statustext_send(m.MAV_SEVERITY_INFO, b"still routing", 0, 0)
        await gcs.wait_for("STATUSTEXT", lambda s: s.text == "still routing", timeout=2.0)
    finally:
        await gcs.close()
        await comp.close()
        await sim.stop()


async def test_link_faults_apply_to_forwarded_traffic():
    async with three_peers() as (sim, comp, a, b):
        sim.set_link_faults(loss_tx=1.0, loss_rx=0.0, link=1)  # everything toward A is lost
        dropped = sim.links[1].faults.dropped_tx
        mark = len(a.received)
        t0 = time.monotonic()
        comp.mav.statustext_send(m.MAV_SEVERITY_INFO, b"lost on the way", 0, 0)
        await b.wait_for("STATUSTEXT", lambda s: s.text == "lost on the way", timeout=2.0)
        await settle()
        assert not [msg for msg, t in a.received[mark:] if t >= t0 and from_(msg, 1, 191)]
        assert sim.links[1].faults.dropped_tx > dropped


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
async def test_the_demo_scene_lets_a_ground_station_watch_the_companion(flavour):
    """``companion demo``'s simulator (``build_scene`` with ``gcs_port``) binds the port its
    printed line names, and forwards the companion's link to it (PX4: forwarding on both)."""
    with reserve_port() as link_port, reserve_port() as gcs_port:
        spec = FlightSpec(flavour=flavour, gcs_port=gcs_port.port)
        _world, _free, sim, _camera = build_scene(spec, link_port.port, 1)
        comp = MavPeer(system_id=1, component_id=191, autopilot=m.MAV_AUTOPILOT_INVALID)
        comp.default_ack = None
        await comp.listen_udp(link_port.port)
        gcs = gcs_peer()
        await sim.start()
        try:
            assert f"127.0.0.1:{gcs_port.port}" in ground_station_line(gcs_port.port)
            await comp.wait_for("HEARTBEAT", lambda h: from_(h, 1, 1), timeout=5.0)
            comp.start_heartbeats(0.2)
            await gcs.connect_udp(("127.0.0.1", gcs_port.port))
            gcs.start_heartbeats(0.2)
            await gcs.wait_for("HEARTBEAT", lambda h: from_(h, 1, 191), timeout=3.0)
        finally:
            await gcs.close()
            await comp.close()
            await sim.stop()
