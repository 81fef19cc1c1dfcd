"""The MAVLink link: pymavlink's codec over an asyncio transport, as an onboard computer.

``MavLink`` owns one connection to the flight controller. It

- identifies as an onboard computer: component 191 (``MAV_COMP_ID_ONBOARD_COMPUTER``),
  ``MAV_TYPE_ONBOARD_CONTROLLER``, a heartbeat every ``heartbeat_period_s``;
- uses the vehicle's system id by default (``system_id=1``): MAVLink groups the components of one
  vehicle under one system id, and both ArduPilot and PX4 route and accept commands from a
  companion that shares it. Set it to the vehicle's ``SYSID_THISMAV`` / ``MAV_SYS_ID``;
- finds the vehicle from the first autopilot heartbeat (or ``target_system`` when configured) and
  asks for the telemetry it needs with ``MAV_CMD_SET_MESSAGE_INTERVAL``, again after every link
  recovery (an autopilot that rebooted forgets the rates);
- declares the link lost when the autopilot's heartbeat is silent for ``heartbeat_timeout_s``;
- counts packets received, bad (CRC, parse, signature, truncated) and dropped (sequence gaps);
- optionally signs (MAVLink 2 signing) and then accepts only signed packets unless told otherwise;
- sends ``COMMAND_LONG`` and waits for the ``COMMAND_ACK``, retrying with ``confirmation``
  incremented (``command_long``);
- hands received messages to subscribers by type: callbacks ``(msg, t)`` or asyncio queues.

Times ``t`` given to subscribers are the receive time on ``time.monotonic()`` in seconds.
Its settings (``LinkConfig``, the telemetry rates, the signing key's spellings) live in
``link_config`` and are imported from here too.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.logs import warn_every
from companion.mavlink.link_config import DEFAULT_MESSAGE_RATES_HZ as DEFAULT_MESSAGE_RATES_HZ
from companion.mavlink.link_config import MAV_COMP_ID_AUTOPILOT1 as MAV_COMP_ID_AUTOPILOT1
from companion.mavlink.link_config import MAV_COMP_ID_ONBOARD_COMPUTER as MAV_COMP_ID_ONBOARD_COMPUTER
from companion.mavlink.link_config import POSE_RATE_HZ as POSE_RATE_HZ
from companion.mavlink.link_config import LinkConfig as LinkConfig
from companion.mavlink.link_config import PeersError as PeersError
from companion.mavlink.link_config import message_rates as message_rates
from companion.mavlink.link_config import parse_signing_key as parse_signing_key
from companion.mavlink.transports import (
    TcpServerTransport,
    Transport,
    UdpTransport,
    make_transport,
    parse_peers,
)

if sys.version_info >= (3, 11):
    from asyncio import timeout as _timeout
else:  # Python 3.10 (JetPack 6): the package asyncio.timeout was taken from
    from async_timeout import timeout as _timeout

log = logging.getLogger(__name__)

mav = mavlink2  # the dialect module: constants and message classes, re-exported for users

Message = Any  # pymavlink's MAVLink_message subclasses; they carry no useful static types
MessageCallback = Callable[[Message, float], None]

# MAVLink 2 signing timestamps count 10 us units since 2015-01-01 00:00:00 UTC.
_SIGNING_EPOCH = 1420070400


class CommandError(RuntimeError):
    """A command the vehicle did not carry out (base class)."""

    def __init__(self, command: int, message: str) -> None:
        super().__init__(message)
        self.command = command


class CommandRefused(CommandError):
    """The vehicle answered with a result other than ACCEPTED (``result`` is the MAV_RESULT)."""

    def __init__(self, command: int, result: int) -> None:
        self.result = result
        super().__init__(command, f"{command_name(command)} refused: {result_name(result)}")


class CommandTimeout(CommandError):
    """No COMMAND_ACK arrived after all retries."""

    def __init__(self, command: int, attempts: int, timeout_s: float) -> None:
        super().__init__(
            command, f"{command_name(command)}: no COMMAND_ACK after {attempts} attempts of {timeout_s:g} s"
        )


def command_name(command: int) -> str:
    entry = mavlink2.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else f"MAV_CMD {command}"


def result_name(result: int) -> str:
    entry = mavlink2.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"



@dataclass
class LinkStats:
    """Counters since start. ``received`` counts decoded packets of known messages only; ``bad``
    counts each corruption once (a wrong length byte and the stray bytes it leaves are one) and
    includes ``unsigned_rejected`` (unsigned or wrongly signed frames on a signed link, unknown
    message ids included); ``dropped`` = sequence gaps of the vehicle's components, per sender."""

    received: int = 0
    bad: int = 0
    dropped: int = 0
    sent: int = 0
    unsigned_rejected: int = 0
    handler_errors: int = 0
    link_losses: int = 0
    unknown: int = 0  # well-framed packets of message ids this dialect lacks (CRC not checkable)


class _Writer:
    """The file-like object pymavlink's ``MAVLink.send`` writes to."""

    def __init__(self, link: MavLink) -> None:
        self._link = link

    def write(self, buf: bytes) -> None:
        self._link._write(bytes(buf))


class _VerifyFirstMAVLink(mavlink2.MAVLink):
    """pymavlink's codec with signatures checked before a stream's timestamp is stored.

    pymavlink (2.4.x) records a packet's signing timestamp for its stream *before* it verifies
    the signature, so one keyless packet with a far-future timestamp made every later genuine
    packet of that stream "old": the link went down and never recovered (issue 12, item 3). Here
    the signature is verified first; only an authentic packet moves the stream's timestamp.
    """

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        signing = self.signing
        assert signing.secret_key is not None
        h = hashlib.new("sha256")
        h.update(signing.secret_key)
        h.update(msgbuf[:-6])
        if h.digest()[:6] != msgbuf[-6:]:
            return False  # forged or corrupt: it must not touch any stream's state
        tlow, thigh = self.mav_sign_unpacker.unpack(msgbuf[-12:-6])
        timestamp = tlow + (thigh << 32)
        stream_key = (msgbuf[-13], srcSystem, srcComponent)
        last = signing.stream_timestamps.get(stream_key)
        if last is not None:
            if timestamp <= last:
                return False  # a replay of an old packet
        elif timestamp + 6000 * 1000 < signing.timestamp:
            return False  # a new stream more than a minute behind us
        signing.stream_timestamps[stream_key] = timestamp
        signing.timestamp = max(signing.timestamp, timestamp)
        return True


class MavLink:
    """One MAVLink connection to a flight controller. Use ``async with MavLink(cfg) as link``."""

    def __init__(self, config: LinkConfig) -> None:
        self.config = config
        self.stats = LinkStats()
        self._mav = _VerifyFirstMAVLink(_Writer(self), srcSystem=config.system_id, srcComponent=config.component_id)
        self._mav.robust_parsing = True
        if config.signing_key is not None:
            signing = self._mav.signing
            signing.secret_key = config.signing_key
            signing.link_id = config.signing_link_id
            signing.sign_outgoing = True
            signing.timestamp = int((time.time() - _SIGNING_EPOCH) * 1e5)
            if config.accept_unsigned:
                signing.allow_unsigned_callback = lambda _mav, _msgid: True
        self._transport: Transport = make_transport(config.url, self._on_data, parse_peers(config.peers))
        self._subs: dict[str, list[MessageCallback]] = defaultdict(list)
        self._any_source_subs: dict[str, list[MessageCallback]] = defaultdict(list)
        self._seq: dict[tuple[Any, int, int], int] = {}  # (sender address, system, component) -> seq
        self._bad_run = False  # the bytes being parsed follow a bad frame (one corruption, one count)
        self._tasks: list[asyncio.Task[Any]] = []
        self._interval_task: asyncio.Task[None] | None = None
        self._requests_stopped = False
        self._command_locks: dict[int, asyncio.Lock] = defaultdict(asyncio.Lock)
        self._link_callbacks: list[Callable[[bool], None]] = []
        self.vehicle_system: int | None = config.target_system
        self.vehicle_autopilot: int | None = None  # MAV_AUTOPILOT of the vehicle's heartbeat
        self.vehicle_type: int | None = None
        self.last_heartbeat_t: float | None = None
        self.last_heartbeat: Message | None = None  # the autopilot's latest HEARTBEAT
        #: MAV_STATE our own HEARTBEAT reports (the service sets it from its health; see
        #: ``companion.service.gcs``); ACTIVE for a link used on its own.
        self.system_status: int = mavlink2.MAV_STATE_ACTIVE
        self.connected = False
        self.intervals_acked: dict[str, int] = {}  # message name -> MAV_RESULT of the last request

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Open the transport and start the heartbeat and link watchdog tasks."""
        await self._transport.start()
        self._tasks = [
            asyncio.create_task(self._heartbeat_loop(), name="mavlink heartbeat"),
            asyncio.create_task(self._watchdog_loop(), name="mavlink watchdog"),
        ]

    async def close(self) -> None:
        tasks = self._tasks + ([self._interval_task] if self._interval_task else [])
        for task in tasks:
            task.cancel()
        for task in tasks:
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks = []
        await self._transport.close()

    def stop_requests(self) -> None:
        """Send no more requests of the link's own (message intervals), now or at a later link-up:
        a stopping service calls it so that its exit handback is the last command sent."""
        self._requests_stopped = True
        if self._interval_task is not None:
            self._interval_task.cancel()

    async def __aenter__(self) -> MavLink:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def transport(self) -> Transport:
        return self._transport

    @property
    def local_address(self) -> tuple[str, int]:
        """The bound address of a listening link (``udpin:...:0``, ``tcpin:...:0``)."""
        if not isinstance(self._transport, (UdpTransport, TcpServerTransport)):
            raise TypeError("local_address is only defined for udpin/tcpin links")
        return self._transport.local_address

    # -- subscriptions -----------------------------------------------------------------------

    def subscribe(self, msg_type: str, callback: MessageCallback, *, any_source: bool = False) -> Callable[[], None]:
        """Call ``callback(msg, t)`` for each message of ``msg_type`` (``"*"`` = all types).

        By default only messages from the vehicle (its system id, any component but ours) are
        delivered; ``any_source=True`` delivers messages from every system (e.g. a ground station's
        commands). Returns a function that unsubscribes. A callback that raises is logged and
        counted in ``stats.handler_errors``; it never stops the link.
        """
        table = self._any_source_subs if any_source else self._subs
        table[msg_type].append(callback)

        def unsubscribe() -> None:
            if callback in table[msg_type]:
                table[msg_type].remove(callback)

        return unsubscribe

    def queue(self, msg_type: str, maxsize: int = 100, *, any_source: bool = False) -> asyncio.Queue[tuple[Message, float]]:
        """An asyncio queue of ``(msg, t)``; when full the oldest entry is dropped (fresh beats complete)."""
        q: asyncio.Queue[tuple[Message, float]] = asyncio.Queue(maxsize)

        def put(msg: Message, t: float) -> None:
            if q.full():
                q.get_nowait()
            q.put_nowait((msg, t))

        self.subscribe(msg_type, put, any_source=any_source)
        return q

    def on_link_change(self, callback: Callable[[bool], None]) -> None:
        """Call ``callback(connected)`` when the autopilot's heartbeat appears or times out."""
        self._link_callbacks.append(callback)

    async def wait_connected(self, timeout: float) -> None:
        """Wait until the autopilot's heartbeat has been heard (raises TimeoutError)."""
        deadline = time.monotonic() + timeout
        while not self.connected:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no autopilot heartbeat on {self.config.url} within {timeout:g} s")
            await asyncio.sleep(0.01)

    # -- sending -----------------------------------------------------------------------------

    @property
    def mav(self) -> Any:
        """pymavlink's MAVLink object: ``link.mav.xxx_encode(...)`` builds messages for ``send``."""
        return self._mav

    def send(self, msg: Message) -> None:
        """Send one message (sequence number and signature added). Dropped while nowhere to send."""
        if not self._transport.can_send:
            return
        self._mav.send(msg)

    def _write(self, buf: bytes) -> None:
        self.stats.sent += 1
        self._transport.send(buf)

    @property
    def target_system(self) -> int:
        """The vehicle's system id (the configured one, else the one heard, else our own)."""
        return self.vehicle_system if self.vehicle_system is not None else self.config.system_id

    async def command_long(
        self,
        command: int,
        params: tuple[float, ...] = (),
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
        target_component: int | None = None,
    ) -> int:
        """Send ``COMMAND_LONG`` and return MAV_RESULT_ACCEPTED, or raise ``CommandError``.

        Up to ``retries`` resends after ``timeout_s`` each, with ``confirmation`` incremented as the
        protocol asks. ``IN_PROGRESS`` extends the wait. Any other result raises ``CommandRefused``.
        """
        timeout_s = self.config.command_timeout_s if timeout_s is None else timeout_s
        retries = self.config.command_retries if retries is None else retries
        p = tuple(float(v) for v in params) + (0.0,) * (7 - len(params))
        if len(p) != 7:
            raise ValueError(f"COMMAND_LONG takes 7 params, got {len(params)}")
        async with self._command_locks[command]:
            loop = asyncio.get_running_loop()
            acks: asyncio.Queue[int] = asyncio.Queue()

            def on_ack(msg: Message, _t: float) -> None:
                if msg.command != command:
                    return
                # An ack meant for another component (a GCS on the same vehicle) is not ours.
                ts, tc = getattr(msg, "target_system", 0), getattr(msg, "target_component", 0)
                if ts not in (0, self.config.system_id) or tc not in (0, self.config.component_id):
                    return
                acks.put_nowait(msg.result)

            unsubscribe = self.subscribe("COMMAND_ACK", on_ack)
            try:
                for attempt in range(retries + 1):
                    self.send(
                        self._mav.command_long_encode(
                            self.target_system,
                            self.config.target_component if target_component is None else target_component,
                            command,
                            attempt,  # confirmation
                            *p,
                        )
                    )
                    deadline = loop.time() + timeout_s
                    while (remaining := deadline - loop.time()) > 0:
                        try:
                            # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a
                            # cancellation that races with the ack, leaving the caller running.
                            async with _timeout(remaining):
                                result = await acks.get()
                        except (TimeoutError, asyncio.TimeoutError):  # one class from 3.11 on
                            break
                        if result == mavlink2.MAV_RESULT_ACCEPTED:
                            return result
                        if result == mavlink2.MAV_RESULT_IN_PROGRESS:
                            deadline = loop.time() + timeout_s
                            continue
                        log.warning("%s refused by the vehicle: %s", command_name(command), result_name(result))
                        raise CommandRefused(command, result)
                    log.debug("%s: no ack (attempt %d)", command_name(command), attempt + 1)
                raise CommandTimeout(command, retries + 1, timeout_s)
            finally:
                unsubscribe()

    async def set_message_interval(self, msg_name: str, rate_hz: float) -> int:
        """Ask the vehicle to stream ``msg_name`` at ``rate_hz`` (0 = stop). Returns MAV_RESULT."""
        msg_id = getattr(mavlink2, f"MAVLINK_MSG_ID_{msg_name}")
        interval_us = -1.0 if rate_hz == 0 else 1e6 / rate_hz
        return await self.command_long(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, interval_us))

    async def request_intervals(self) -> dict[str, int]:
        """Request every configured rate; a refusal is logged, not fatal (not every FC has a gimbal)."""
        for name, hz in self.config.message_rates_hz.items():
            try:
                self.intervals_acked[name] = await self.set_message_interval(name, hz)
            except CommandRefused as exc:
                self.intervals_acked[name] = exc.result
                log.info("rate for %s not set: %s", name, result_name(exc.result))
            except CommandTimeout as exc:
                self.intervals_acked[name] = -1
                log.warning("%s", exc)
        return dict(self.intervals_acked)

    # -- receiving ---------------------------------------------------------------------------

    def _on_data(self, data: bytes) -> None:
        t = time.monotonic()
        if self._transport.datagram:
            self._bad_run = False
        try:
            msgs = self._mav.parse_buffer(data) or []
        except Exception as exc:  # robust_parsing should catch all; a codec bug must not kill the link
            log.warning("MAVLink parser error: %s", exc)
            self.stats.bad += 1
            self._reset_parser()
            return
        for msg in msgs:
            self._handle(msg, t)
        if self._transport.datagram and self._mav.buf_len() > 0:
            # A datagram ended inside a frame: it was truncated; it must not eat the next datagram.
            if not self._bad_run:
                self.stats.bad += 1
            log.debug("dropped %d bytes of a truncated frame", self._mav.buf_len())
            self._reset_parser()
        if self._transport.datagram:
            self._bad_run = False  # the next datagram starts clean

    def _reset_parser(self) -> None:
        self._mav.buf = bytearray()
        self._mav.buf_index = 0
        self._mav.expected_length = mavlink2.HEADER_LEN_V1 + 2

    def _handle(self, msg: Message, t: float) -> None:
        msg_type = msg.get_type()
        if msg_type == "BAD_DATA":
            if "signature" in str(getattr(msg, "reason", "")):
                # A whole frame, refused for its signature: each one counts.
                self.stats.bad += 1
                self.stats.unsigned_rejected += 1
                self._bad_run = False
            elif not self._bad_run:
                # One corruption (a wrong length byte) yields a CRC error, then stray bytes and a
                # truncated tail: counted once, until a good frame parses.
                self.stats.bad += 1
                self._bad_run = True
            log.debug("bad MAVLink data: %s", getattr(msg, "reason", "?"))
            return
        self._bad_run = False
        if msg_type.startswith("UNKNOWN_"):
            if not self._signature_accepted(msg):
                self.stats.bad += 1
                self.stats.unsigned_rejected += 1
                return
            # A message id this dialect lacks: its CRC cannot be checked (no CRC_EXTRA), so it
            # may be random bytes that framed by chance. Not received, and its sequence number
            # must not count as a gap in the sender's stream.
            self.stats.unknown += 1
            return
        self.stats.received += 1
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        self._count_gap(src, msg.get_seq())
        if msg_type == "HEARTBEAT":
            self._on_heartbeat(msg, t)
        from_vehicle = src[0] == self.vehicle_system and src[1] != self.config.component_id
        if from_vehicle:
            self._dispatch(self._subs, msg_type, msg, t)
        self._dispatch(self._any_source_subs, msg_type, msg, t)

    def _count_gap(self, src: tuple[int, int], seq: int) -> None:
        """Sequence gaps of the vehicle's components, per sender address and (system, component):
        other systems (a ground station, a flood claiming other ids) have their own counters,
        which say nothing of the autopilot's link, and are not counted in ``dropped``."""
        key = (self._transport.current_source, *src)
        last = self._seq.get(key)
        if last is not None and src[0] == self.vehicle_system:
            gap = (seq - last - 1) % 256
            # A gap of > 128 is more likely a peer restart than 128+ lost packets in a row.
            if 0 < gap < 128:
                self.stats.dropped += gap
        if last is None and len(self._seq) >= 1024:
            self._seq.clear()  # senders from a flood must not grow memory
        self._seq[key] = seq

    def _signature_accepted(self, msg: Message) -> bool:
        """For a frame pymavlink did not check (an unknown message id): on a signed link that
        refuses unsigned packets, only a frame with a valid signature passes."""
        signing = self._mav.signing
        if signing.secret_key is None or self.config.accept_unsigned:
            return True
        buf = bytearray(getattr(msg, "_msgbuf", b""))
        if len(buf) < 10 + 2 + 13 or buf[0] != mavlink2.PROTOCOL_MARKER_V2 or not buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED:
            return False
        return bool(self._mav.check_signature(buf, buf[5], buf[6]))

    def _dispatch(self, table: dict[str, list[MessageCallback]], msg_type: str, msg: Message, t: float) -> None:
        for callback in (*table.get(msg_type, ()), *table.get("*", ())):
            try:
                callback(msg, t)
            except Exception:
                self.stats.handler_errors += 1
                log.exception("handler for %s failed", msg_type)

    def is_autopilot_heartbeat(self, msg: Message) -> bool:
        """True for a heartbeat from the vehicle's autopilot component (not a GCS, camera, gimbal)."""
        if msg.autopilot == mavlink2.MAV_AUTOPILOT_INVALID:
            return False
        if msg.get_srcComponent() != self.config.target_component:
            return False
        return self.vehicle_system is None or msg.get_srcSystem() == self.vehicle_system

    def _on_heartbeat(self, msg: Message, t: float) -> None:
        if not self.is_autopilot_heartbeat(msg):
            if (msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID and self.vehicle_system is not None
                    and msg.get_srcComponent() == self.config.target_component):
                # Most often a vehicle whose SYSID_THISMAV / MAV_SYS_ID is not the configured one:
                # say so rather than wait in silence (and never take it: it may be an impostor).
                warn_every(log, ("other autopilot", msg.get_srcSystem()), 30.0,
                           "ignored an autopilot heartbeat from system %d: link.target_system is %d "
                           "(set it to the vehicle's SYSID_THISMAV / MAV_SYS_ID)",
                           msg.get_srcSystem(), self.vehicle_system)
            return
        if self.vehicle_system is None:
            self.vehicle_system = msg.get_srcSystem()
            log.info("vehicle found: system %d", self.vehicle_system)
        self.vehicle_autopilot = msg.autopilot
        self.vehicle_type = msg.type
        self.last_heartbeat_t = t
        self.last_heartbeat = msg
        if isinstance(self._transport, UdpTransport):
            # Its address alone is heard once the heartbeats make it plausible (not on one packet).
            self._transport.autopilot_heard(self.config.heartbeat_timeout_s)
        if not self.connected:
            self.connected = True
            log.info("autopilot heartbeat: link up (system %d)", self.vehicle_system)
            self._seq.clear()  # a rebooted autopilot restarts its sequence
            if not self._requests_stopped:
                self._interval_task = asyncio.get_running_loop().create_task(self._request_intervals_safe())
            self._notify_link(True)

    async def _request_intervals_safe(self) -> None:
        try:
            await self.request_intervals()
        except Exception:
            log.exception("requesting message intervals failed")

    def _notify_link(self, connected: bool) -> None:
        for callback in self._link_callbacks:
            try:
                callback(connected)
            except Exception:
                self.stats.handler_errors += 1
                log.exception("link-change callback failed")

    # -- periodic tasks ----------------------------------------------------------------------

    async def _heartbeat_loop(self) -> None:
        while True:
            self.send(
                self._mav.heartbeat_encode(
                    mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                    mavlink2.MAV_AUTOPILOT_INVALID,
                    0,
                    0,
                    self.system_status,
                )
            )
            await asyncio.sleep(self.config.heartbeat_period_s)

    async def _watchdog_loop(self) -> None:
        period = min(0.1, self.config.heartbeat_timeout_s / 4)
        while True:
            await asyncio.sleep(period)
            if self.connected and self.last_heartbeat_t is not None:
                if time.monotonic() - self.last_heartbeat_t > self.config.heartbeat_timeout_s:
                    self.connected = False
                    self.stats.link_losses += 1
                    if isinstance(self._transport, UdpTransport):
                        self._transport.unpin()  # a restarted autopilot or router may come back elsewhere
                    if self._interval_task is not None:
                        self._interval_task.cancel()
                    log.warning(
                        "autopilot heartbeat lost for %.1f s: link down", time.monotonic() - self.last_heartbeat_t
                    )
                    self._notify_link(False)
