"""A pymavlink peer that stands in for a flight controller in the tests (the one allowed mock).

It speaks real MAVLink 2 over loopback sockets: UDP (it sends to the link's ``udpin`` address) or a
TCP server the link connects to. It sends heartbeats, answers COMMAND_LONG with a per-command
policy (a MAV_RESULT, or None for silence), follows DO_SET_MODE in its heartbeat like ArduPilot or
PX4 would, and records everything it receives for assertions.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.statustext import join_chunks


class MavPeer:
    def __init__(
        self,
        *,
        system_id: int = 1,
        component_id: int = 1,
        autopilot: int = m.MAV_AUTOPILOT_ARDUPILOTMEGA,
        custom_mode: int = 0,
        signing_key: bytes | None = None,
    ) -> None:
        self.mav = m.MAVLink(self, srcSystem=system_id, srcComponent=component_id)
        self.mav.robust_parsing = True
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
            self.mav.signing.allow_unsigned_callback = lambda *_: True
        self.autopilot = autopilot
        self.custom_mode = custom_mode
        self.base_mode = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | m.MAV_MODE_FLAG_SAFETY_ARMED
        self.system_status = m.MAV_STATE_ACTIVE
        self.ack_policy: dict[int, int | None | Callable[[Any], int | None]] = {}
        self.default_ack: int | None = m.MAV_RESULT_ACCEPTED
        self.received: list[tuple[Any, float]] = []
        self.commands: list[Any] = []  # every COMMAND_LONG, retries included
        self._udp: asyncio.DatagramTransport | None = None
        self._udp_peer: tuple[str, int] | None = None
        self._tcp_server: asyncio.Server | None = None
        self._tcp_writer: asyncio.StreamWriter | None = None
        self._hb_task: asyncio.Task[None] | None = None
        self._new = asyncio.Event()

    # -- transport ---------------------------------------------------------------------------

    def write(self, buf: bytes) -> None:  # pymavlink's file interface
        self.send_raw(bytes(buf))

    def send_raw(self, data: bytes) -> None:
        if self._udp is not None and self._udp_peer is not None:
            self._udp.sendto(data, self._udp_peer)
        elif self._tcp_writer is not None:
            self._tcp_writer.write(data)

    async def connect_udp(self, link_addr: tuple[str, int]) -> None:
        peer = self

        class Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
                peer._feed(data)

        loop = asyncio.get_running_loop()
        self._udp, _ = await loop.create_datagram_endpoint(Proto, local_addr=("127.0.0.1", 0))
        self._udp_peer = link_addr

    @property
    def udp_address(self) -> tuple[str, int]:
        assert self._udp is not None
        return self._udp.get_extra_info("sockname")[:2]

    async def listen_udp(self, port: int = 0) -> tuple[str, int]:
        """Bind a UDP socket (127.0.0.1:``port``, 0 = any) for a link in ``udpout`` mode; replies
        go to whoever wrote last."""
        peer = self

        class Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
                peer._udp_peer = addr
                peer._feed(data)

        loop = asyncio.get_running_loop()
        self._udp, _ = await loop.create_datagram_endpoint(Proto, local_addr=("127.0.0.1", port))
        return self.udp_address

    async def serve_tcp(self) -> tuple[str, int]:
        async def on_client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            self._tcp_writer = writer
            try:
                while data := await reader.read(4096):
                    self._feed(data)
            except OSError:
                pass
            finally:
                if self._tcp_writer is writer:
                    self._tcp_writer = None
                writer.close()

        self._tcp_server = await asyncio.start_server(on_client, "127.0.0.1", 0)
        return self._tcp_server.sockets[0].getsockname()[:2]

    async def drop_tcp_client(self) -> None:
        if self._tcp_writer is not None:
            self._tcp_writer.close()
            self._tcp_writer = None

    async def close(self) -> None:
        self.stop_heartbeats()
        if self._udp is not None:
            self._udp.close()
        if self._tcp_writer is not None:
            self._tcp_writer.close()
        if self._tcp_server is not None:
            self._tcp_server.close()

    # -- behaviour ---------------------------------------------------------------------------

    def heartbeat(self) -> None:
        self.mav.heartbeat_send(
            m.MAV_TYPE_QUADROTOR, self.autopilot, self.base_mode, self.custom_mode, self.system_status
        )

    def start_heartbeats(self, period_s: float = 0.1) -> None:
        async def loop() -> None:
            while True:
                self.heartbeat()
                await asyncio.sleep(period_s)

        self.stop_heartbeats()
        self._hb_task = asyncio.get_running_loop().create_task(loop())

    def stop_heartbeats(self) -> None:
        if self._hb_task is not None:
            self._hb_task.cancel()
            self._hb_task = None

    def _feed(self, data: bytes) -> None:
        for msg in self.mav.parse_buffer(data) or []:
            if msg.get_type() == "BAD_DATA":
                continue
            self.received.append((msg, time.monotonic()))
            if msg.get_type() == "COMMAND_LONG":
                self._on_command(msg)
        self._new.set()

    def _on_command(self, msg: Any) -> None:
        self.commands.append(msg)
        result = self.ack_policy.get(msg.command, self.default_ack)
        if callable(result):  # a policy that looks at the params, e.g. refuse only one mode
            result = result(msg)
        if result is None:
            return
        if result == m.MAV_RESULT_ACCEPTED and msg.command == m.MAV_CMD_DO_SET_MODE:
            if self.autopilot == m.MAV_AUTOPILOT_PX4:
                self.custom_mode = (int(msg.param2) << 16) | (int(msg.param3) << 24)
            else:
                self.custom_mode = int(msg.param2)
            self.heartbeat()
        self.mav.command_ack_send(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )

    def of_type(self, msg_type: str) -> list[Any]:
        return [msg for msg, _ in self.received if msg.get_type() == msg_type]

    def statustexts(self) -> list[tuple[int, str]]:
        """(severity, text) of every STATUSTEXT, chunks (same non-zero id) joined."""
        return join_statustexts(self.of_type("STATUSTEXT"))

    async def wait_for_text(self, needle: str, timeout: float = 2.0) -> tuple[int, str]:
        """The first (joined) STATUSTEXT containing ``needle``."""
        deadline = time.monotonic() + timeout
        while True:
            for severity, text in self.statustexts():
                if needle in text:
                    return severity, text
            if time.monotonic() > deadline:
                raise TimeoutError(f"peer: no STATUSTEXT with {needle!r}; got {self.statustexts()!r}")
            await asyncio.sleep(0.02)

    def commands_of(self, command: int) -> list[Any]:
        return [c for c in self.commands if c.command == command]

    async def wait_for(
        self, msg_type: str, predicate: Callable[[Any], bool] = lambda _m: True, timeout: float = 2.0, start: int = 0
    ) -> Any:
        """The first message of ``msg_type`` received (from index ``start``) that matches ``predicate``."""
        deadline = time.monotonic() + timeout
        while True:
            for msg, _ in self.received[start:]:
                if msg.get_type() == msg_type and predicate(msg):
                    return msg
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"peer: no {msg_type} within {timeout} s")
            self._new.clear()
            try:
                await asyncio.wait_for(self._new.wait(), remaining)
            except (TimeoutError, asyncio.TimeoutError):
                pass


def join_statustexts(messages: Iterable[Any]) -> list[tuple[int, str]]:
    """(severity, text) of each STATUSTEXT among ``messages``, in order, the chunks of a long
    text (same non-zero ``id``) joined as a ground station joins them."""
    out: list[tuple[int, list[str]]] = []
    open_ids: dict[int, int] = {}
    for msg in messages:
        if msg.get_type() != "STATUSTEXT":
            continue
        if msg.id and msg.id in open_ids:
            out[open_ids[msg.id]][1].append(msg.text)
            continue
        if msg.id:
            open_ids[msg.id] = len(out)
        out.append((int(msg.severity), [msg.text]))
    # The companion cuts chunks at spaces, pads them and repeats its prefix (statustext.py).
    return [(sev, join_chunks([c for c in chunks if c])) for sev, chunks in out]
