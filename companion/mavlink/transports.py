"""Byte transports for the MAVLink link: UDP (listen or connect), TCP client and serial.

Each transport moves raw bytes and knows nothing of MAVLink. The link gives it a ``on_data(bytes)``
callback and calls ``send(bytes)``; ``datagram`` tells the link whether one read is one whole set
of packets (UDP) so a truncated frame can be dropped at the end of the read instead of swallowing
the start of the next datagram.

URLs (the same spelling as MAVProxy / mavlink-router / MAVSDK):

- ``udpin:HOST:PORT``   listen. Until the autopilot is heard, packets go to every address heard
  from in the last 10 s; once its heartbeats pin its address (``autopilot_heard``: three of them
  while no other address claims the autopilot), datagrams from any other address are dropped
  before parsing (counted in ``foreign``) and packets go to it alone, besides the configured
  ``peers`` (a ground station sharing the port). A lost link unpins; the same address is pinned
  again on its first heartbeat, a new one needs the same evidence as at the start.
- ``udpout:HOST:PORT``  send to HOST:PORT (the flight controller or a router listens there);
  datagrams from any other address or port are dropped.

``peers`` (IP addresses or CIDR networks) is an allow-list for UDP: when given, datagrams from
addresses outside it are dropped at all times. Anyone who can reach an open port could otherwise
claim the autopilot's system id, feed a pose, or take over the link by being heard first.
- ``tcp:HOST:PORT``     TCP client; reconnects every ``reconnect_s`` seconds after a loss.
- ``tcpin:HOST:PORT``   TCP server; talks to the most recent client (a router or SITL connecting in).
- ``serial:/dev/ttyX:BAUD``  a serial port (UART, USB CDC), raw 8N1 through termios; no pyserial.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import os
import socket
import termios
import time
import tty
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from companion.logs import warn_every

log = logging.getLogger(__name__)

DataCallback = Callable[[bytes], None]
Network = ipaddress.IPv4Network | ipaddress.IPv6Network


def parse_peers(peers: Sequence[str]) -> tuple[Network, ...]:
    """IP addresses or CIDR networks (``192.168.1.10``, ``10.0.0.0/24``); TransportError if not."""
    out = []
    for p in peers:
        try:
            out.append(ipaddress.ip_network(p.strip(), strict=False))
        except ValueError as exc:
            raise TransportError(f"link peer {p!r} is not an IP address or network: {exc}") from exc
    return tuple(out)


class TransportError(ValueError):
    """A connection URL that cannot be parsed (a configuration error)."""


class TransportOpenError(TransportError, OSError):
    """A well-formed URL whose socket or device cannot be opened (also an ``OSError``)."""


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection URL. ``kind`` is udpin, udpout, tcp, tcpin or serial; ``port`` is baud for serial."""

    kind: str
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.kind}:{self.host}:{self.port}"


def parse_url(url: str) -> Endpoint:
    """Parse ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT`` or ``serial:DEV:BAUD``."""
    kind, sep, rest = url.partition(":")
    host, sep2, port_s = rest.rpartition(":")
    if not sep or not sep2 or kind not in ("udpin", "udpout", "tcp", "tcpin", "serial") or not host:
        raise TransportError(
            f"connection URL {url!r} is not one of udpin:HOST:PORT, udpout:HOST:PORT, "
            "tcp:HOST:PORT, tcpin:HOST:PORT, serial:/dev/DEVICE:BAUD"
        )
    try:
        port = int(port_s)
    except ValueError:
        raise TransportError(f"connection URL {url!r}: {port_s!r} is not a number") from None
    if kind == "serial":
        if port not in _BAUDS:
            raise TransportError(f"connection URL {url!r}: unsupported baud {port} (use one of {sorted(_BAUDS)})")
    elif not 0 <= port <= 65535:
        raise TransportError(f"connection URL {url!r}: port {port} out of range")
    return Endpoint(kind, host, port)


class Transport:
    """Base class: ``start()``, ``send(data)``, ``close()``; incoming bytes go to ``on_data``."""

    datagram = False

    def __init__(self, endpoint: Endpoint, on_data: DataCallback) -> None:
        self.endpoint = endpoint
        self._on_data = on_data
        self.bytes_sent = 0
        self.send_errors = 0
        self.foreign = 0  # datagrams dropped for their source address (UDP only)

    async def start(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def send(self, data: bytes) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    async def close(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def can_send(self) -> bool:
        """False while there is nowhere to send (UDP listen before the first packet, TCP down)."""
        return True

    @property
    def current_source(self) -> tuple[str, int] | None:
        """The address of the datagram being handed to ``on_data`` (UDP), else None."""
        return None


class _UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpTransport) -> None:
        self._owner = owner

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self._owner._received(data, addr)

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable when the peer is not up yet: normal on UDP, not fatal.
        log.debug("udp error: %s", exc)


class UdpTransport(Transport):
    """UDP in either direction: ``udpin`` binds and sends to its recent peers, ``udpout`` sends to HOST:PORT."""

    datagram = True

    PEER_TIMEOUT_S = 10.0
    #: Autopilot heartbeats from one address, with no other address sending one, that pin it.
    PIN_HEARTBEATS = 3

    #: Receive buffer asked of the kernel: a burst (or a flood) queues rather than drops the
    #: autopilot's packets while the loop is busy. Linux caps it at net.core.rmem_max.
    RCVBUF_BYTES = 4 * 1024 * 1024

    def __init__(self, endpoint: Endpoint, on_data: DataCallback, peers: Sequence[Network] = ()) -> None:
        super().__init__(endpoint, on_data)
        self._transport: asyncio.DatagramTransport | None = None
        # udpout: the one fixed destination. udpin: address -> monotonic time last heard from.
        self._fixed: tuple[str, int] | None = (endpoint.host, endpoint.port) if endpoint.kind == "udpout" else None
        self._fixed_ip: str | None = None  # udpout: the destination's address, resolved at start
        self._peers: dict[tuple[str, int], float] = {}
        self._allowed = tuple(peers)
        self._allowed_cache: dict[str, bool] = {}
        self._pinned: tuple[str, int] | None = None
        self._previous: tuple[str, int] | None = None  # the address pinned before a link loss
        self._heard: dict[tuple[str, int], deque[float]] = {}  # address -> autopilot heartbeat times
        self._current: tuple[str, int] | None = None  # the datagram being handed to on_data

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            if self.endpoint.kind == "udpin":
                self._transport, _ = await loop.create_datagram_endpoint(
                    lambda: _UdpProtocol(self), local_addr=(self.endpoint.host, self.endpoint.port)
                )
            else:
                infos = await loop.getaddrinfo(self.endpoint.host, self.endpoint.port, type=socket.SOCK_DGRAM)
                family, _, _, _, sockaddr = infos[0]
                self._fixed_ip = str(sockaddr[0])
                # Bound to loopback when the destination is (nothing else can reach the port).
                local = "127.0.0.1" if ipaddress.ip_address(self._fixed_ip).is_loopback else "0.0.0.0"
                if family == socket.AF_INET6:
                    local = "::1" if local == "127.0.0.1" else "::"
                self._transport, _ = await loop.create_datagram_endpoint(
                    lambda: _UdpProtocol(self), local_addr=(local, 0)
                )
        except OSError as exc:
            raise TransportOpenError(f"cannot open {self.endpoint}: {exc}") from exc
        sock = self._transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.RCVBUF_BYTES)
            except OSError as exc:
                log.debug("SO_RCVBUF not set: %s", exc)

    @property
    def local_address(self) -> tuple[str, int]:
        """The bound (host, port); useful with ``udpin:127.0.0.1:0`` in tests."""
        assert self._transport is not None
        return self._transport.get_extra_info("sockname")[:2]

    def _is_allowed(self, ip: str) -> bool:
        """In the ``peers`` allow-list (cached: the check runs for every datagram of a flood)."""
        ok = self._allowed_cache.get(ip)
        if ok is None:
            try:
                address = ipaddress.ip_address(ip.split("%")[0])
                ok = any(address in net for net in self._allowed)
            except ValueError:
                ok = False
            if len(self._allowed_cache) > 1024:
                self._allowed_cache.clear()  # addresses from a flood must not grow memory
            self._allowed_cache[ip] = ok
        return ok

    def _accepts(self, addr: tuple[str, int]) -> bool:
        if self._fixed is not None:
            # The autopilot or router listens at HOST:PORT and answers from that socket.
            return addr[0] == self._fixed_ip and addr[1] == self._fixed[1]
        if self._allowed and not self._is_allowed(addr[0]):
            return False
        return self._pinned is None or addr == self._pinned or bool(self._allowed)

    def _received(self, data: bytes, addr: tuple[str, int]) -> None:
        addr = (addr[0], addr[1])  # IPv6 addresses come with flow info and scope
        if not self._accepts(addr):
            self.foreign += 1
            return
        if self._fixed is None:
            self._peers[addr] = time.monotonic()
        self._current = addr
        try:
            self._on_data(data)
        finally:
            self._current = None

    @property
    def current_source(self) -> tuple[str, int] | None:
        return self._current

    def pin_current(self) -> None:
        """The datagram being handled came from the autopilot: talk to its address alone from now
        on (and to the allowed ``peers``). No effect on ``udpout``, whose peer is fixed."""
        if self._fixed is None and self._current is not None and self._pinned != self._current:
            self._pinned = self._current
            self._heard.clear()
            log.info("udp: autopilot at %s:%d; other senders are dropped", *self._pinned)

    def autopilot_heard(self, window_s: float) -> None:
        """The datagram being handled holds an autopilot heartbeat: pin its address once the
        evidence is plausible (issue 61: whoever spoke first as system 1 was pinned, and the real
        autopilot then dropped as foreign, 20 times of 20).

        The address pinned before a link loss is pinned again on its first heartbeat (the
        autopilot came back). Any other address needs ``PIN_HEARTBEATS`` heartbeats within
        ``window_s`` (s), spread over half of it at least (a burst proves nothing), while no other
        address sent one in that time: a forger who speaks
        first, once or now and then, is never pinned while the autopilot talks, and two senders
        that keep claiming the autopilot leave the link unpinned, with a warning."""
        addr = self._current
        if self._fixed is not None or addr is None or self._pinned is not None:
            return
        if addr == self._previous:
            self.pin_current()
            return
        now = time.monotonic()
        heard = self._heard
        if addr not in heard and len(heard) >= 64:
            heard.clear()  # addresses from a flood must not grow memory
        heard.setdefault(addr, deque()).append(now)
        for a in list(heard):
            times = heard[a]
            while times and now - times[0] > window_s:
                times.popleft()
            if not times:
                del heard[a]
        times = heard[addr]
        if len(heard) == 1 and len(times) >= self.PIN_HEARTBEATS and times[-1] - times[0] >= window_s / 2:
            self.pin_current()
        elif len(heard) > 1:
            warn_every(log, "two autopilots", 30.0,
                       "udp: %d addresses send autopilot heartbeats (%s): none is pinned; set link.peers "
                       "or sign the link (docs/signing.md)", len(heard),
                       ", ".join(f"{a[0]}:{a[1]}" for a in heard))

    def unpin(self) -> None:
        """The autopilot went silent: hear from any (allowed) address again. Its address is
        remembered: its next heartbeat pins it again at once."""
        if self._pinned is not None:
            self._previous = self._pinned
        self._pinned = None
        self._heard.clear()

    @property
    def pinned(self) -> tuple[str, int] | None:
        return self._pinned

    def _destinations(self) -> list[tuple[str, int]]:
        if self._fixed is not None:
            return [self._fixed]
        now = time.monotonic()
        for addr in [a for a, t in self._peers.items() if now - t > self.PEER_TIMEOUT_S]:
            del self._peers[addr]
        if self._pinned is not None:
            return [self._pinned, *(a for a in self._peers if a != self._pinned and self._allowed)]
        return list(self._peers)

    @property
    def can_send(self) -> bool:
        return self._transport is not None and bool(self._destinations())

    def send(self, data: bytes) -> None:
        if self._transport is None:
            return
        for addr in self._destinations():
            try:
                self._transport.sendto(data, addr)
                self.bytes_sent += len(data)
            except OSError as exc:
                self.send_errors += 1
                log.debug("udp send to %s failed: %s", addr, exc)

    async def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None


class _TcpStream(Transport):
    """What the TCP client and server share: they send on the one stream they talk to now
    (``_writer``; None while there is none, and then nothing is sent)."""

    def __init__(self, endpoint: Endpoint, on_data: DataCallback) -> None:
        super().__init__(endpoint, on_data)
        self._writer: asyncio.StreamWriter | None = None

    @property
    def can_send(self) -> bool:
        return self._writer is not None

    def send(self, data: bytes) -> None:
        if self._writer is None:
            return
        try:
            self._writer.write(data)
            self.bytes_sent += len(data)
        except (OSError, RuntimeError) as exc:
            self.send_errors += 1
            log.debug("tcp send failed: %s", exc)


class TcpTransport(_TcpStream):
    """TCP client that keeps reconnecting: a router or SITL restarting must not end the service."""

    def __init__(self, endpoint: Endpoint, on_data: DataCallback, reconnect_s: float = 1.0) -> None:
        super().__init__(endpoint, on_data)
        self._reconnect_s = reconnect_s
        self._task: asyncio.Task[None] | None = None
        self._connected = asyncio.Event()

    async def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name=f"tcp {self.endpoint}")

    async def wait_connected(self, timeout: float) -> None:
        await asyncio.wait_for(self._connected.wait(), timeout)

    async def _run(self) -> None:
        while True:
            try:
                reader, writer = await asyncio.open_connection(self.endpoint.host, self.endpoint.port)
            except OSError as exc:
                log.debug("tcp connect %s failed: %s", self.endpoint, exc)
                await asyncio.sleep(self._reconnect_s)
                continue
            self._writer = writer
            self._connected.set()
            log.info("tcp connected to %s:%d", self.endpoint.host, self.endpoint.port)
            try:
                while data := await reader.read(4096):
                    self._on_data(data)
            except OSError as exc:
                log.warning("tcp %s lost: %s", self.endpoint, exc)
            finally:
                self._writer = None
                self._connected.clear()
                writer.close()
            await asyncio.sleep(self._reconnect_s)

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None


class TcpServerTransport(_TcpStream):
    """TCP server: the newest client is the one we talk to; an older one is closed."""

    def __init__(self, endpoint: Endpoint, on_data: DataCallback) -> None:
        super().__init__(endpoint, on_data)
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        try:
            self._server = await asyncio.start_server(self._client, self.endpoint.host, self.endpoint.port)
        except OSError as exc:
            raise TransportOpenError(f"cannot listen on {self.endpoint}: {exc}") from exc

    @property
    def local_address(self) -> tuple[str, int]:
        assert self._server is not None
        return self._server.sockets[0].getsockname()[:2]

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._writer is not None:
            self._writer.close()
        self._writer = writer
        log.info("tcp client %s connected", writer.get_extra_info("peername"))
        try:
            while data := await reader.read(4096):
                self._on_data(data)
        except OSError as exc:
            log.warning("tcp client lost: %s", exc)
        finally:
            if self._writer is writer:
                self._writer = None
            writer.close()

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._server is not None:
            self._server.close()
            self._server = None


_BAUDS = {
    b: getattr(termios, f"B{b}")
    for b in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 921600, 1000000, 1500000, 2000000, 3000000)
    if hasattr(termios, f"B{b}")
}


class SerialTransport(Transport):
    """A serial port in raw 8N1 mode read through the event loop (``add_reader``), no thread."""

    def __init__(self, endpoint: Endpoint, on_data: DataCallback) -> None:
        super().__init__(endpoint, on_data)
        self._fd: int | None = None

    async def start(self) -> None:
        try:
            fd = os.open(self.endpoint.host, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            raise TransportOpenError(f"cannot open serial port {self.endpoint.host}: {exc}") from exc
        try:
            tty.setraw(fd)
            attrs = termios.tcgetattr(fd)
            speed = _BAUDS[self.endpoint.port]
            attrs[4] = attrs[5] = speed  # ispeed, ospeed
            attrs[2] = (attrs[2] & ~termios.CRTSCTS) | termios.CLOCAL | termios.CREAD
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except termios.error as exc:
            os.close(fd)
            raise TransportOpenError(f"{self.endpoint.host} is not a serial port: {exc}") from exc
        self._fd = fd
        asyncio.get_running_loop().add_reader(fd, self._readable)

    def _readable(self) -> None:
        assert self._fd is not None
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            # A USB adapter unplugged: stop reading; the link notices the silent autopilot.
            log.error("serial %s read failed: %s", self.endpoint.host, exc)
            asyncio.get_running_loop().remove_reader(self._fd)
            return
        if data:
            self._on_data(data)

    def send(self, data: bytes) -> None:
        if self._fd is None:
            return
        try:
            n = os.write(self._fd, data)
            self.bytes_sent += n
            if n < len(data):
                # The UART buffer is full: MAVLink tolerates loss better than latency from queueing.
                self.send_errors += 1
        except OSError as exc:
            self.send_errors += 1
            log.debug("serial write failed: %s", exc)

    async def close(self) -> None:
        if self._fd is not None:
            asyncio.get_running_loop().remove_reader(self._fd)
            os.close(self._fd)
            self._fd = None


def make_transport(url: str, on_data: DataCallback, peers: Sequence[Network] = ()) -> Transport:
    """The transport for a connection URL (not started yet); ``peers`` the UDP allow-list."""
    ep = parse_url(url)
    if ep.kind in ("udpin", "udpout"):
        return UdpTransport(ep, on_data, peers)
    if ep.kind == "tcp":
        return TcpTransport(ep, on_data)
    if ep.kind == "tcpin":
        return TcpServerTransport(ep, on_data)
    return SerialTransport(ep, on_data)
