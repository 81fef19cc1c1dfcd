"""Failsafe monitor: turns telemetry, a ground-station command or a local request into a Trigger.

Sources, each switchable in ``FailsafeConfig``:

- ``battery``: BATTERY_STATUS.charge_state at or past ``battery_level`` (low, critical,
  emergency; FAILED counts too), or, when ``battery_remaining_pct`` is set, a remaining charge
  (BATTERY_STATUS or SYS_STATUS) below it.
- ``system_status``: the autopilot's heartbeat ``system_status`` CRITICAL or EMERGENCY.
- ``autopilot_land``: the autopilot switching itself into LAND or RTL (its own failsafe fired),
  seen as a mode change in its heartbeat, unless the companion asked for that mode.
- ``gcs_command``: ``COMMAND_LONG`` (or ``COMMAND_INT``) ``MAV_CMD_USER_1`` (31010) addressed to our system and
  component (191). Accepted (``MAV_RESULT_ACCEPTED``) only from ``gcs_system_ids``; any other
  sender, or this source switched off, gets ``MAV_RESULT_DENIED`` and a STATUSTEXT saying why.
  Params are ignored. A USER_1 broadcast to component 0 is not a trigger (USER_1 is user-defined:
  another component may own it) and gets no answer. With a ``CommandServer``
  (``attach(commands)``) the server acks it; alone, the monitor acks it itself.
- ``local_trigger``: ``trigger_local(reason)`` (the service wires SIGUSR1 to it) and, when
  ``local_socket`` is a path, a Unix stream socket taking the line ``trigger [reason]``; it
  answers ``ok`` or ``ignored: <why>`` (``send_local_trigger`` is the client).

The first trigger is latched (``triggered``) and handed to subscribers once; later ones are logged
and ignored until ``reset()``. The monitor only reports; it never commands the vehicle.
"""

from __future__ import annotations

import asyncio
import logging
import os
import stat
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.trigger import Trigger, TriggerSource
from companion.invariant import require
from companion.mavlink.autopilot import Autopilot
from companion.mavlink.gcs_commands import CommandServer, Reply, send_reply
from companion.mavlink.link import MavLink
from companion.mavlink.statustext import send_statustext

log = logging.getLogger(__name__)

TRIGGER_COMMAND = m.MAV_CMD_USER_1  # 31010

BATTERY_LEVELS = {
    "low": m.MAV_BATTERY_CHARGE_STATE_LOW,
    "critical": m.MAV_BATTERY_CHARGE_STATE_CRITICAL,
    "emergency": m.MAV_BATTERY_CHARGE_STATE_EMERGENCY,
}


@dataclass(frozen=True)
class FailsafeConfig:
    battery: bool = True
    battery_level: str = "critical"
    battery_remaining_pct: float | None = None
    system_status: bool = True
    autopilot_land: bool = True
    gcs_command: bool = True
    gcs_system_ids: tuple[int, ...] = (255,)
    local_trigger: bool = True
    local_socket: str | None = None

    def __post_init__(self) -> None:
        # The one place this rule lives (the settings name the key of a field refused here).
        require(self.battery_level in BATTERY_LEVELS, "failsafe", "battery_level",
                f"must be one of {', '.join(map(repr, BATTERY_LEVELS))}", self.battery_level)
        if self.battery_remaining_pct is not None and not 0 <= self.battery_remaining_pct <= 100:
            raise ValueError(f"failsafe.battery_remaining_pct must be 0..100, not {self.battery_remaining_pct!r}")
        require(all(1 <= s <= 255 for s in self.gcs_system_ids), "failsafe", "gcs_system_ids",
                "must list system ids 1..255", list(self.gcs_system_ids))


class FailsafeMonitor:
    """Watches the link for the configured trigger sources; ``subscribe`` to get the ``Trigger``."""

    def __init__(
        self,
        config: FailsafeConfig,
        link: MavLink,
        autopilot: Autopilot | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.link = link
        self.autopilot = autopilot
        self._clock = clock
        self.triggered: Trigger | None = None
        self.ignored: list[Trigger] = []  # triggers after the latched one, for the logs
        self._callbacks: list[Callable[[Trigger], None]] = []
        self._last_mode: str | None = None
        self._server: asyncio.AbstractServer | None = None

    def attach(self, commands: CommandServer | None = None) -> None:
        """Subscribe to the link: vehicle telemetry, and the trigger command from every system
        (through ``commands``, which answers every command, when given)."""
        for name in ("HEARTBEAT", "BATTERY_STATUS", "SYS_STATUS"):
            self.link.subscribe(name, self.handle)
        if commands is not None:
            commands.register(TRIGGER_COMMAND, self.trigger_command)
            return
        self.link.subscribe("COMMAND_LONG", self._on_command_long, any_source=True)
        self.link.subscribe("COMMAND_INT", self._on_command_long, any_source=True)  # same fields we use

    def subscribe(self, callback: Callable[[Trigger], None]) -> None:
        self._callbacks.append(callback)

    def reset(self) -> None:
        """Re-arm after a landing was handled (or handed back)."""
        self.triggered = None

    # -- sources -----------------------------------------------------------------------------

    def handle(self, msg: Any, t: float) -> None:
        """One telemetry message from the vehicle received at monotonic ``t`` (s)."""
        kind = msg.get_type()
        if kind == "BATTERY_STATUS":
            self._on_battery(msg, t)
        elif kind == "SYS_STATUS":
            self._on_remaining(msg.battery_remaining, "SYS_STATUS", t)
        elif kind == "HEARTBEAT" and self.link.is_autopilot_heartbeat(msg):
            self._on_heartbeat(msg, t)

    def _on_battery(self, msg: Any, t: float) -> None:
        if not self.config.battery:
            return
        level = BATTERY_LEVELS[self.config.battery_level]
        if level <= msg.charge_state <= m.MAV_BATTERY_CHARGE_STATE_FAILED:
            name = m.enums["MAV_BATTERY_CHARGE_STATE"][msg.charge_state].name.removeprefix("MAV_BATTERY_CHARGE_STATE_")
            self._fire(TriggerSource.BATTERY, f"battery {msg.id} charge state {name}", t)
            return
        self._on_remaining(msg.battery_remaining, f"battery {msg.id}", t)

    def _on_remaining(self, remaining: int, what: str, t: float) -> None:
        limit = self.config.battery_remaining_pct
        if not self.config.battery or limit is None or remaining < 0:  # -1 = unknown
            return
        if remaining < limit:
            self._fire(TriggerSource.BATTERY, f"{what} at {remaining}% (< {limit:g}%)", t)

    def _on_heartbeat(self, msg: Any, t: float) -> None:
        if self.config.system_status and msg.system_status in (m.MAV_STATE_CRITICAL, m.MAV_STATE_EMERGENCY):
            name = m.enums["MAV_STATE"][msg.system_status].name.removeprefix("MAV_STATE_")
            self._fire(TriggerSource.SYSTEM_STATUS, f"autopilot system status {name}", t)
        if self.autopilot is None:
            return
        mode = self.autopilot.mode_name(msg.base_mode, msg.custom_mode)
        previous, self._last_mode = self._last_mode, mode
        if (
            self.config.autopilot_land
            and previous is not None
            and mode != previous
            and mode in self.autopilot.FAILSAFE_MODES
            and mode != self.autopilot.commanded_mode
        ):
            self._fire(TriggerSource.AUTOPILOT_MODE, f"autopilot switched itself to {mode}", t)

    def _on_command_long(self, msg: Any, t: float) -> None:
        """The trigger without a ``CommandServer``: answer USER_1 addressed to us, ignore the rest."""
        if msg.command != TRIGGER_COMMAND:
            return
        if msg.target_system != self.link.config.system_id or msg.target_component != self.link.config.component_id:
            return  # for another component (or everyone): not ours to answer
        reply = self.trigger_command(msg, t, False)
        if reply is not None:
            send_reply(self.link, msg, reply)
            if reply.text:
                send_statustext(self.link, reply.text, reply.severity)
            if reply.then is not None:
                reply.then()

    def trigger_command(self, msg: Any, t: float, broadcast: bool) -> Reply | None:
        """``MAV_CMD_USER_1`` addressed to us, received at monotonic ``t`` (s): fire and accept, or
        deny saying why. A broadcast one is not a trigger (None: no answer)."""
        if broadcast:
            return None
        sender = msg.get_srcSystem()
        if not self.config.gcs_command:
            log.warning("trigger command from system %d denied: gcs_command is off", sender)
            return Reply(m.MAV_RESULT_DENIED, "SLZ: trigger refused: gcs_command off")
        if sender not in self.config.gcs_system_ids:
            log.warning("trigger command from system %d denied: not in gcs_system_ids %s", sender, self.config.gcs_system_ids)
            return Reply(m.MAV_RESULT_DENIED, f"SLZ: trigger refused: system {sender} not a GCS")
        reason = f"ground station (system {sender}) asked to land"
        return Reply(m.MAV_RESULT_ACCEPTED, then=lambda: self._fire(TriggerSource.GCS_COMMAND, reason, t))

    def trigger_local(self, reason: str = "local request") -> Trigger | None:
        """Trigger from this machine (signal, CLI). Returns the trigger, or None if switched off."""
        if not self.config.local_trigger:
            log.warning("local trigger ignored: local_trigger is off")
            return None
        return self._fire(TriggerSource.LOCAL, reason, self._clock())

    # -- local socket ------------------------------------------------------------------------

    async def start_local_socket(self) -> None:
        """Listen on ``config.local_socket`` (mode 0660) if set. A stale socket file is replaced."""
        path = self.config.local_socket
        if not path:
            return
        if os.path.exists(path):
            if not stat.S_ISSOCK(os.stat(path).st_mode):
                raise ValueError(f"failsafe.local_socket {path!r} exists and is not a socket")
            os.unlink(path)
        self._server = await asyncio.start_unix_server(self._serve_client, path)
        os.chmod(path, 0o660)

    async def stop_local_socket(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
            if self.config.local_socket and os.path.exists(self.config.local_socket):
                os.unlink(self.config.local_socket)

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            line = (await asyncio.wait_for(reader.readline(), 5.0)).decode("utf-8", "replace").strip()
            word, _, reason = line.partition(" ")
            if word != "trigger":
                answer = f"ignored: unknown request {word[:40]!r} (use: trigger [reason])"
            elif not self.config.local_trigger:
                answer = "ignored: local_trigger is off"
            elif self.triggered is not None:
                self.trigger_local(reason[:200] or "local socket")
                answer = f"ignored: already triggered ({self.triggered.reason})"
            else:
                self.trigger_local(reason[:200] or "local socket")
                answer = "ok"
            writer.write((answer + "\n").encode())
            await writer.drain()
        except (TimeoutError, asyncio.TimeoutError, OSError) as exc:
            log.debug("local trigger client: %s", exc)
        finally:
            writer.close()

    # -- output ------------------------------------------------------------------------------

    def _fire(self, source: TriggerSource, reason: str, t: float) -> Trigger | None:
        trigger = Trigger(reason, source, t)
        if self.triggered is not None:
            self.ignored.append(trigger)
            log.debug("trigger %s ignored: already triggered by %s", reason, self.triggered.reason)
            return None
        self.triggered = trigger
        log.warning("failsafe trigger: %s", reason)
        for callback in self._callbacks:
            try:
                callback(trigger)
            except Exception:
                log.exception("trigger callback failed")
        return trigger


async def send_local_trigger(path: str, reason: str = "local request", timeout_s: float = 5.0) -> str:
    """Client for the local socket (the CLI uses it): returns the service's answer line."""
    reader, writer = await asyncio.wait_for(asyncio.open_unix_connection(path), timeout_s)
    try:
        writer.write(f"trigger {reason}\n".encode())
        await writer.drain()
        return (await asyncio.wait_for(reader.readline(), timeout_s)).decode().strip()
    finally:
        writer.close()
