"""MAVLink forwarding between the simulator's links, as the real autopilots route.

A real flight controller is a MAVLink router: what the companion computer sends on its serial
port reaches the ground station on the radio, and the ground station's commands for the
companion cross the other way. The simulator does the same, by each firmware's own rules:

- ``ArduPilotRouting`` follows ``libraries/GCS_MAVLink/MAVLink_routing.cpp`` (ArduPilot's
  ``check_and_forward``): every link learns the (system, component) pairs heard on it; a
  HEARTBEAT goes to every other link except those where its sender is known; a message without a
  target (STATUSTEXT, NAMED_VALUE_*, COMMAND_ACK's broadcast cousins) or with target system 0 goes
  to every other link where anything has been heard; a targeted one goes only to the links where
  its target was heard (its system, and its component when the target is this vehicle); one
  addressed to the autopilot alone is not forwarded; RADIO / RADIO_STATUS / ADSB_VEHICLE never
  are.
- ``Px4Routing`` follows PX4's ``Mavlink::forward_message``: nothing is forwarded unless the
  receiving link *and* the sending link have forwarding on (``MAV_X_FORWARD``; per link here,
  ``?forward=1`` on an ``--out`` URL); a message addressed to the autopilot alone is kept;
  heartbeats are forwarded (``MAV_HB_FORW_EN``, default 1); and a link gets a message only if its
  target was seen on it (system 0: anything seen there; component 0: any component of that system).

Both never send a message back on the link it came from, never learn or forward the autopilot's
own (system, component) looped back to it, and forward the received packet's bytes unchanged
(``get_msgbuf()``: a signed packet stays signed and valid, nothing is re-encoded). Packets of
message ids the dialect lacks are not forwarded: their CRC cannot be checked, so they may be
noise that framed by chance (the companion's link drops them the same way). Forwarded datagrams
go through the sending link's fault injector, as its own telemetry does.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mav

#: ArduPilot's MAVLINK_MAX_ROUTES: the routing table holds this many (system, component, link)
#: entries; later senders are not learned (a flood of forged ids cannot grow it).
MAX_ROUTES = 20

_NEVER_FORWARDED_ARDUPILOT = frozenset({
    mav.MAVLINK_MSG_ID_RADIO, mav.MAVLINK_MSG_ID_RADIO_STATUS, mav.MAVLINK_MSG_ID_ADSB_VEHICLE})


class Port(Protocol):
    """What routing needs of a link: its forwarding flag and a raw send."""

    forward: bool | None

    def send_raw(self, data: bytes) -> None: ...


@dataclass
class RoutingStats:
    forwarded: int = 0       # packets sent on another link (one per link)
    not_forwarded: int = 0   # packets received that went nowhere else
    unknown_dropped: int = 0  # packets of message ids the dialect lacks (CRC not checkable)
    loops: int = 0           # our own (system, component) heard back


_TARGET_FIELDS: dict[type, tuple[bool, bool]] = {}


def targets(msg: Any) -> tuple[int, int]:
    """(target_system, target_component) of a message, -1 for a field the message does not have."""
    cls = type(msg)
    has = _TARGET_FIELDS.get(cls)
    if has is None:
        names = getattr(cls, "fieldnames", ())
        has = _TARGET_FIELDS[cls] = ("target_system" in names, "target_component" in names)
    return (int(msg.target_system) if has[0] else -1, int(msg.target_component) if has[1] else -1)


class Routing:
    """Forwarding between ``ports`` for an autopilot that is (``system_id``, ``component_id``)."""

    def __init__(self, ports: Iterable[Port], system_id: int, component_id: int) -> None:
        self.ports = list(ports)
        self.system_id = system_id
        self.component_id = component_id
        self.routes: list[tuple[int, int, Port]] = []  # (system, component, port) heard, in order
        self.stats = RoutingStats()

    def heard(self, port: Port) -> set[tuple[int, int]]:
        """The (system, component) pairs learned on ``port``."""
        return {(s, c) for s, c, p in self.routes if p is port}

    def _learn(self, src: tuple[int, int], port: Port) -> None:
        if src[0] == 0 or len(self.routes) >= MAX_ROUTES:
            return
        for s, c, p in self.routes:
            if (s, c) == src and p is port:
                return
        self.routes.append((src[0], src[1], port))

    def on_message(self, msg: Any, port: Port) -> None:
        """A message received on ``port`` and decoded: learn its sender, forward its bytes."""
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == (self.system_id, self.component_id):
            self.stats.loops += 1
            return
        self._learn(src, port)
        if msg.get_type().startswith("UNKNOWN_"):
            self.stats.unknown_dropped += 1
            return
        out = self.destinations(msg, src, port)
        if not out:
            self.stats.not_forwarded += 1
            return
        data = bytes(msg.get_msgbuf())
        for dest in out:
            dest.send_raw(data)
        self.stats.forwarded += len(out)

    def destinations(self, msg: Any, src: tuple[int, int], port: Port) -> list[Port]:
        raise NotImplementedError


class ArduPilotRouting(Routing):
    """ArduPilot's ``MAVLink_routing::check_and_forward``: every link routes."""

    def destinations(self, msg: Any, src: tuple[int, int], port: Port) -> list[Port]:
        msg_id = msg.get_msgId()
        if msg_id in _NEVER_FORWARDED_ARDUPILOT:
            return []
        if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
            # To every other link, except those where this sender itself was heard.
            known = {id(p) for s, c, p in self.routes if (s, c) == src}
            return [p for p in self.ports if p is not port and id(p) not in known]
        ts, tc = targets(msg)
        broadcast_system = ts in (0, -1)
        broadcast_component = tc in (0, -1)
        match_system = broadcast_system or ts == self.system_id
        match_component = match_system and (broadcast_component or tc == self.component_id)
        if match_system and match_component and not broadcast_system and not broadcast_component:
            return []  # for the autopilot alone
        out: list[Port] = []
        for s, c, p in self.routes:
            if p is port or any(p is o for o in out):
                continue
            if broadcast_system or (ts == s and (broadcast_component or tc == c or not match_system)):
                out.append(p)
        return out


class Px4Routing(Routing):
    """PX4's ``Mavlink::forward_message``: only between links with forwarding on."""

    def __init__(self, ports: Iterable[Port], system_id: int, component_id: int,
                 forward_heartbeats: bool = True) -> None:
        super().__init__(ports, system_id, component_id)
        self.forward_heartbeats = forward_heartbeats  # MAV_HB_FORW_EN

    def _seen(self, port: Port, ts: int, tc: int) -> bool:
        for s, c, p in self.routes:
            if p is port and (ts == 0 or (s == ts and (tc == 0 or c == tc))):
                return True
        return False

    def destinations(self, msg: Any, src: tuple[int, int], port: Port) -> list[Port]:
        if not port.forward:
            return []
        ts, tc = (max(v, 0) for v in targets(msg))  # PX4 reads an absent target as 0
        if ts == self.system_id and tc == self.component_id:
            return []
        if msg.get_msgId() == mav.MAVLINK_MSG_ID_HEARTBEAT and not self.forward_heartbeats:
            return []
        return [p for p in self.ports if p is not port and p.forward and self._seen(p, ts, tc)]


def routing_for(flavour: str, ports: Iterable[Port], system_id: int, component_id: int) -> Routing:
    """The routing of a simulator flavour (``ardupilot`` or ``px4``)."""
    if flavour == "px4":
        return Px4Routing(ports, system_id, component_id)
    return ArduPilotRouting(ports, system_id, component_id)
