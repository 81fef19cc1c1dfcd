"""The shipped systemd unit: the watchdog and restart policy the service is built for, the
hardening the audit of issue 12 asked for (each option explained), only options the target
boards' systemd knows, and ``systemd-analyze verify`` where systemd is installed."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from companion.service.app import SHUTDOWN_BUDGET_S
from companion.service.health import PIPELINE_STUCK_S

UNIT = Path(__file__).resolve().parents[3] / "systemd" / "companion.service"

#: Keys newer than the oldest systemd the unit targets (249: JetPack 6 / Ubuntu 22.04; Raspberry
#: Pi OS bookworm has 252): an older systemd ignores them with "Unknown key" and the protection or
#: policy they stand for silently does not exist there.
NEWER_THAN_249 = {"ExitType": 250, "RestartSteps": 254, "RestartMaxDelaySec": 254, "RestartMode": 254,
                  "MemoryKSM": 254, "ImportCredential": 254, "DelegateSubgroup": 254, "OpenFile": 253,
                  "SurviveFinalKillSignal": 255, "SetLoginEnvironment": 255, "PrivateUsersEx": 256,
                  "ProtectControlGroupsEx": 257, "PrivatePIDs": 257}


def _parse(text: str) -> dict[str, list[tuple[str, str]]]:
    """section -> [(key, value)] in order; repeated keys kept (DeviceAllow=, SystemCallFilter=)."""
    out: dict[str, list[tuple[str, str]]] = {}
    section = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            out.setdefault(section, [])
            continue
        key, _, value = line.partition("=")
        out[section].append((key.strip(), value.strip()))
    return out


@pytest.fixture(scope="module")
def unit() -> dict[str, list[tuple[str, str]]]:
    return _parse(UNIT.read_text())


def _values(unit: dict[str, list[tuple[str, str]]], section: str, key: str) -> list[str]:
    return [v for k, v in unit.get(section, []) if k == key]


def _one(unit: dict[str, list[tuple[str, str]]], section: str, key: str) -> str:
    values = _values(unit, section, key)
    assert len(values) == 1, f"{section}.{key}: {values}"
    return values[0]


def _seconds(value: str) -> float:
    m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*(ms|s|min)?", value)
    assert m, value
    return float(m[1]) * {"ms": 0.001, "s": 1.0, "min": 60.0, None: 1.0}[m[2]]


def _bytes(value: str) -> int:
    m = re.fullmatch(r"(\d+)([KMG]?)", value)
    assert m, value
    return int(m[1]) * {"": 1, "K": 2**10, "M": 2**20, "G": 2**30}[m[2]]


def test_restart_policy_never_leaves_the_unit_dead_but_never_retries_a_config_error(unit) -> None:
    # No start rate limit: the old 10 starts in 5 minutes left it dead after ~2.5 minutes of an
    # unplugged camera.
    assert _one(unit, "Unit", "StartLimitIntervalSec") == "0"
    assert _values(unit, "Service", "StartLimitIntervalSec") == []  # not shadowed in the wrong section
    assert _one(unit, "Service", "Restart") == "always"
    assert 0 < _seconds(_one(unit, "Service", "RestartSec")) <= 10
    assert "2" in _one(unit, "Service", "RestartPreventExitStatus").split()


def test_watchdog_policy_matches_the_service(unit) -> None:
    """Type=notify with a watchdog the health loop can feed; a stuck pipeline (the internal fault
    that stops the pings) is caught by it; a SIGTERM stop fits well inside TimeoutStopSec."""
    service = dict(unit["Service"])
    assert service["Type"] == "notify" and service["NotifyAccess"] == "main"
    watchdog = _seconds(service["WatchdogSec"])
    assert PIPELINE_STUCK_S < watchdog <= 30
    assert service["WatchdogSignal"] == "SIGTERM"  # a graceful stop hands the vehicle back first
    assert SHUTDOWN_BUDGET_S + 1.0 < _seconds(service["TimeoutStopSec"])
    header = UNIT.read_text().split("[Unit]")[0]
    assert "keeps feeding the watchdog through external" in header and "internal fault" in header


def test_hardening_the_audit_asked_for(unit) -> None:
    s = "Service"
    # Address allow-list: loopback only as shipped; integrators add the link's network.
    assert _values(unit, s, "IPAddressDeny") == ["any"]
    assert _values(unit, s, "IPAddressAllow") == ["localhost"]
    # Device policy: closed, plus cameras and the serial ports flight controllers use.
    assert _one(unit, s, "DevicePolicy") == "closed"
    allowed = {v.split()[0]: v.split()[1] for v in _values(unit, s, "DeviceAllow")}
    for cls in ("char-video4linux", "char-ttyUSB", "char-ttyACM", "char-ttyAMA", "char-ttyTHS"):
        assert allowed.get(cls) == "rw", (cls, allowed)
    assert all(mode in ("r", "rw") for mode in allowed.values())  # never mknod
    # System calls: the service set minus the privileged ones; @resources stays (onnxruntime's
    # sched_setaffinity, OpenBLAS's mbind).
    filters = _values(unit, s, "SystemCallFilter")
    assert filters[0] == "@system-service" and "~@privileged" in filters
    assert not any("@resources" in f for f in filters if f.startswith("~"))
    assert _one(unit, s, "SystemCallErrorNumber") == "EPERM"
    assert _one(unit, s, "SystemCallArchitectures") == "native"
    # journald's rate limit, high enough that the service's own rate-limited lines never reach it.
    interval = _seconds(_one(unit, s, "LogRateLimitIntervalSec"))
    burst = int(_one(unit, s, "LogRateLimitBurst"))
    assert interval >= 10 and burst / interval >= 100  # >= 100 lines/s: far above the service's few
    # What was there before stays.
    for key, value in (("NoNewPrivileges", "yes"), ("ProtectSystem", "strict"), ("ProtectHome", "yes"),
                       ("PrivateTmp", "yes"), ("ProtectKernelTunables", "yes"), ("ProtectKernelModules", "yes"),
                       ("ProtectKernelLogs", "yes"), ("ProtectControlGroups", "yes"), ("ProtectClock", "yes"),
                       ("RestrictRealtime", "yes"), ("RestrictNamespaces", "yes"), ("CapabilityBoundingSet", ""),
                       ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6"), ("User", "companion")):
        assert _one(unit, s, key) == value, key
    # Memory: a ceiling for a leak, with room above the measured ~250 MB peak.
    high, most = _bytes(_one(unit, s, "MemoryHigh")), _bytes(_one(unit, s, "MemoryMax"))
    assert 2 * 250 * 2**20 <= high < most


def test_every_policy_and_hardening_option_says_why() -> None:
    """Each of these options sits in a paragraph that opens with a comment."""
    lines = UNIT.read_text().splitlines()
    for key in ("StartLimitIntervalSec", "Restart", "RestartSec", "RestartPreventExitStatus", "WatchdogSignal",
                "TimeoutStopSec", "LogRateLimitBurst", "IPAddressAllow", "IPAddressDeny", "DevicePolicy",
                "DeviceAllow", "SystemCallFilter", "MemoryMax"):
        i = next(i for i, line in enumerate(lines) if line.startswith(f"{key}="))
        while i > 0 and lines[i - 1].strip() and not lines[i - 1].startswith("#"):
            i -= 1  # up through the paragraph's other options
        assert i > 0 and lines[i - 1].startswith("#") and len(lines[i - 1]) > 10, f"{key}= has no why-comment"


def test_only_options_the_target_boards_systemd_knows(unit) -> None:
    used = {k for entries in unit.values() for k, _ in entries}
    newer = {k: NEWER_THAN_249[k] for k in used & NEWER_THAN_249.keys()}
    assert not newer, f"options newer than systemd 249 (JetPack 6): {newer}"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_systemd_analyze_verify_accepts_the_unit(tmp_path: Path) -> None:
    """The unit as systemd reads it: no unknown key, no unparsable value. ExecStart points at this
    Python instead (verify checks that the binary exists; /opt/companion is not installed here)."""
    text = re.sub(r"(?m)^ExecStart=\S+", f"ExecStart={sys.executable}", UNIT.read_text())
    copy = tmp_path / "companion.service"
    copy.write_text(text)
    r = subprocess.run(["systemd-analyze", "verify", "--man=no", str(copy)], capture_output=True, text=True,
                       timeout=60)
    version = subprocess.run(["systemd-analyze", "--version"], capture_output=True, text=True).stdout.split("\n")[0]
    out = r.stdout + r.stderr
    assert r.returncode == 0, f"{version}:\n{out}"
    complaints = [line for line in out.splitlines() if str(copy) in line or "companion.service" in line]
    assert complaints == [], f"{version}:\n{out}"
