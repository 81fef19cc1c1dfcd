"""systemd notification (``Type=notify``): readiness, watchdog, status and stopping.

A thin layer over :mod:`sdnotify` that also reads ``WATCHDOG_USEC`` so the main loop knows how
often to feed the watchdog. Without ``NOTIFY_SOCKET`` (not under systemd) every call is a no-op,
so the same code runs from a shell, in tests and as a daemon.

The service sends ``READY=1`` once the model is loaded and the first autopilot heartbeat arrived,
``WATCHDOG=1`` from its main loop unless it has an internal fault (a pipeline call stuck, or an
event loop too blocked to send them: a restart may cure those), ``STATUS=...`` lines for
``systemctl status`` (external faults, a camera not delivering or no autopilot heartbeat, show up
there as ``degraded: ...`` while the pings go on: restarting cannot fix them and the service
reconnects by itself; see :mod:`companion.service.health`), and ``STOPPING=1`` when it begins to
shut down.
"""

from __future__ import annotations

import logging
import os

import sdnotify

log = logging.getLogger(__name__)


class Notifier:
    """Sends sd_notify messages to ``$NOTIFY_SOCKET`` (or nothing when it is unset)."""

    def __init__(self) -> None:
        self.enabled = bool(os.environ.get("NOTIFY_SOCKET"))
        self._sd = sdnotify.SystemdNotifier() if self.enabled else None
        if self._sd is not None and self._sd.socket is not None:
            # A full notify queue must never stall the event loop: a lost status line is
            # harmless, a blocked main loop is not (sdnotify ignores the send error).
            self._sd.socket.setblocking(False)
        self.ready_sent = False
        self.stopping_sent = False
        self.last_status = ""

    @property
    def watchdog_interval(self) -> float | None:
        """Seconds between WATCHDOG=1 pings: half of ``WATCHDOG_USEC`` (None when no watchdog)."""
        usec = os.environ.get("WATCHDOG_USEC")
        pid = os.environ.get("WATCHDOG_PID")
        if not usec or (pid and pid.isdigit() and int(pid) != os.getpid()):
            return None
        try:
            return max(int(usec) / 2e6, 0.05)
        except ValueError:
            log.warning("WATCHDOG_USEC=%r is not a number; watchdog pings at 1 s", usec)
            return 1.0

    def _send(self, msg: str) -> None:
        if self._sd is not None:
            self._sd.notify(msg)

    def ready(self, status: str = "") -> None:
        if not self.ready_sent:
            self.ready_sent = True
            self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> None:
        self._send("WATCHDOG=1")

    def status(self, text: str) -> None:
        """``STATUS=`` shown by ``systemctl status``; sent only when it changes."""
        text = text.replace("\n", " ")
        if text != self.last_status:
            self.last_status = text
            self._send(f"STATUS={text}")

    def stopping(self, status: str = "stopping") -> None:
        if not self.stopping_sent:
            self.stopping_sent = True
            self._send(f"STOPPING=1\nSTATUS={status}")
