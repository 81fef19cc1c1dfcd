"""sd_notify messages reach a real Unix datagram socket bound by the test (as systemd's would)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from companion.service.notify import Notifier


@pytest.fixture()
def notify_socket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(1.0)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    yield sock
    sock.close()


def _recv(sock: socket.socket) -> str:
    return sock.recv(4096).decode()


def test_messages_arrive(notify_socket: socket.socket, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    n = Notifier()
    assert n.enabled and n.watchdog_interval == pytest.approx(2.0)
    n.ready("link up")
    n.ready("again")  # READY is sent once
    n.watchdog()
    n.status("zones 3")
    n.status("zones 3")  # unchanged status is not re-sent
    n.stopping()
    got = [_recv(notify_socket) for _ in range(4)]
    assert got == ["READY=1\nSTATUS=link up", "WATCHDOG=1", "STATUS=zones 3", "STOPPING=1\nSTATUS=stopping"]
    notify_socket.settimeout(0.1)
    with pytest.raises(socket.timeout):
        _recv(notify_socket)


def test_watchdog_for_another_pid_is_ignored(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert Notifier().watchdog_interval is None


def test_without_systemd_everything_is_a_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    n = Notifier()
    n.ready()
    n.watchdog()
    n.stopping()
    assert not n.enabled and n.watchdog_interval is None


def test_unit_file_has_what_integrators_expect() -> None:
    unit = (Path(__file__).resolve().parents[3] / "systemd" / "companion.service").read_text()
    lines = {line.split("=", 1)[0]: line.split("=", 1)[1] for line in unit.splitlines()
             if "=" in line and not line.startswith("#")}
    assert lines["Type"] == "notify"
    assert int(lines["WatchdogSec"]) > 0
    assert lines["WatchdogSignal"] == "SIGTERM"  # graceful: hands the vehicle back first
    assert lines["Restart"] == "always"  # never left dead; the full policy: tests/companion/service/test_systemd_unit.py
    assert lines["User"] == "companion"
    assert lines["ExecStart"].endswith("companion run --config /etc/companion/companion.toml")
    assert lines["ProtectSystem"] == "strict" and lines["NoNewPrivileges"] == "yes"
    assert lines["CapabilityBoundingSet"] == ""
    assert lines["RestrictAddressFamilies"] == "AF_UNIX AF_INET AF_INET6"
    assert set(lines["SupplementaryGroups"].split()) == {"video", "dialout"}
    assert "/var/lib/companion" in lines["ReadWritePaths"]
    for key in ("ProtectHome", "PrivateTmp"):
        assert lines[key] == "yes"
