"""The simulator's MAVLink over UDP, like SITL's ``--out`` / ``--serial`` ports.

Each ``UdpLink`` is one port with its own codec state (sequence numbers), its own telemetry rates
(``StreamSchedule``: MAV_CMD_SET_MESSAGE_INTERVAL is per link on both firmwares) and its own
fault injector. Two kinds:

- ``udpout:HOST:PORT`` sends to a fixed address from an ephemeral port and reads whatever the
  peer sends back (SITL ``--out``; the companion and MAVSDK listen on 14550 / 14540);
- ``udpin:HOST:PORT`` binds and answers every peer that has sent to it (a GCS "connects").

A URL may end in ``?forward=1`` (or ``?forward=0``): whether the link forwards MAVLink between
itself and the other links, PX4's per-link ``MAV_X_FORWARD`` (``sim.vehicle.routing``; the PX4 flavour
forwards only between links marked so, the ArduPilot flavour routes on every link).

Bad input is counted and dropped: a datagram that does not decode to valid MAVLink increments
``bad_packets``, never raises.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.autopilot import StreamSchedule
from sim.vehicle.faults import FaultInjector, LinkFaults

log = logging.getLogger(__name__)

Address = tuple[str, int]


class _Writer:
    """File-like sink for the pymavlink codec: every write is one datagram."""

    def __init__(self, link: UdpLink) -> None:
        self._link = link

    def write(self, data: bytes) -> None:
        self._link._write(bytes(data))


def parse_url(url: str) -> tuple[str, Address]:
    """``udpout:127.0.0.1:14550`` / ``udp:...`` (= udpout) / ``udpin:0.0.0.0:14560`` -> (kind, addr)."""
    kind, address, _forward = parse_link(url)
    return kind, address


def parse_link(url: str) -> tuple[str, Address, bool | None]:
    """(kind, address, forward) of a link URL; ``forward`` is None when the URL does not say.

    ``udpin:127.0.0.1:14560?forward=1``: the options after ``?`` are ``forward=0|1`` only.
    """
    base, _, query = url.partition("?")
    forward: bool | None = None
    if query:
        for item in query.split("&"):
            key, _, value = item.partition("=")
            if key != "forward" or value not in ("0", "1"):
                raise ValueError(f"link {url!r}: the only option is forward=0 or forward=1, got {item!r}")
            forward = value == "1"
    try:
        kind, host, port_s = base.split(":")
        port = int(port_s)
    except ValueError:
        raise ValueError(f"link {url!r} is not KIND:HOST:PORT (udpout:127.0.0.1:14550)") from None
    kind = {"udp": "udpout", "udpout": "udpout", "udpin": "udpin"}.get(kind.lower(), "")
    if not kind:
        raise ValueError(f"link {url!r}: kind must be udpout (or udp) or udpin")
    if not 0 <= port <= 65535:
        raise ValueError(f"link {url!r}: port {port} out of range")
    return kind, (host, port), forward


@dataclass
class LinkStats:
    rx_datagrams: int = 0
    rx_messages: int = 0
    bad_packets: int = 0
    tx_messages: int = 0
    forwarded_tx: int = 0  # packets another link received that this one sent on (sim.vehicle.routing)


class UdpLink(asyncio.DatagramProtocol):
    """One MAVLink UDP port of the simulator."""

    MAX_PEERS = 8

    def __init__(self, url: str, system_id: int, component_id: int,
                 streams: StreamSchedule,
                 on_message: Callable[[mav.MAVLink_message, UdpLink], None],
                 faults: LinkFaults | None = None, seed: int | None = None) -> None:
        self.url = url
        self.kind, self.address, self.forward = parse_link(url)
        self.streams = streams
        self.stats = LinkStats()
        self.faults = FaultInjector(faults, seed)
        self._on_message = on_message
        self._mav = mav.MAVLink(_Writer(self), srcSystem=system_id, srcComponent=component_id)
        self._mav.robust_parsing = True
        self._rx = mav.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._rx.robust_parsing = True
        self._transport: asyncio.DatagramTransport | None = None
        self.peers: list[Address] = [self.address] if self.kind == "udpout" else []

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        if self.kind == "udpout":
            await loop.create_datagram_endpoint(lambda: self, local_addr=(self.address[0], 0))
        else:
            await loop.create_datagram_endpoint(lambda: self, local_addr=self.address)

    @property
    def local_address(self) -> Address | None:
        if self._transport is None:
            return None
        return self._transport.get_extra_info("sockname")[:2]

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    # ----- asyncio protocol -----

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self.faults.incoming(data, lambda d: self._receive(d, addr))

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable while nobody listens on a udpout port: normal, keep sending.
        log.debug("%s: %s", self.url, exc)

    # ----- receive path -----

    def _receive(self, data: bytes, addr: Address) -> None:
        self.stats.rx_datagrams += 1
        if self.kind == "udpin" and addr not in self.peers:
            self.peers.append(addr)
            del self.peers[:-self.MAX_PEERS]
        try:
            msgs = self._rx.parse_buffer(data) or []
        except Exception:  # pymavlink raises its own MAVError and struct errors on some garbage
            msgs = []
            self.stats.bad_packets += 1
        else:
            if any(m.get_type() == "BAD_DATA" for m in msgs):
                self.stats.bad_packets += 1
        # A UDP datagram carries whole packets: a truncated tail is garbage, not a prefix.
        if len(self._rx.buf) - self._rx.buf_index > 0:
            if not any(m.get_type() == "BAD_DATA" for m in msgs):
                self.stats.bad_packets += 1
            self._rx.buf = bytearray()
            self._rx.buf_index = 0
            self._rx.expected_length = mav.HEADER_LEN_V1 + 2
            self._rx.have_prefix_error = False
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                continue
            self.stats.rx_messages += 1
            try:
                self._on_message(m, self)
            except Exception:
                # A message the handlers choke on must not take the vehicle down with it.
                log.exception("%s: handling %s failed", self.url, m.get_type())
                self.stats.bad_packets += 1

    # ----- send path -----

    def send(self, msg: mav.MAVLink_message) -> None:
        """Encode and send one message to the link's peers (through the fault injector)."""
        if self._transport is None or not self.peers:
            return
        self.stats.tx_messages += 1
        self._mav.send(msg)

    def send_raw(self, data: bytes) -> None:
        """Send a packet another link received, byte for byte (routing: a signature stays valid)."""
        if self._transport is None or not self.peers:
            return
        self.stats.forwarded_tx += 1
        self._write(data)

    def _write(self, data: bytes) -> None:
        for peer in list(self.peers):
            self.faults.outgoing(data, functools.partial(self._sendto, peer=peer))

    def _sendto(self, data: bytes, peer: Address) -> None:
        if self._transport is not None:
            self._transport.sendto(data, peer)


@dataclass
class Endpoint:
    """All links of the simulator."""

    links: list[UdpLink] = field(default_factory=list)

    async def open(self) -> None:
        for link in self.links:
            await link.open()

    def close(self) -> None:
        for link in self.links:
            link.close()

    @property
    def bad_packets(self) -> int:
        return sum(link.stats.bad_packets for link in self.links)

    def set_faults(self, faults: LinkFaults) -> None:
        for link in self.links:
            link.faults.faults = faults
