"""The link's settings: how to reach the flight controller and how to present ourselves
(``LinkConfig``, checked when made), the telemetry rates asked for, and the signing key's two
spellings. Kept apart from the link itself (``companion.mavlink.link``, which re-exports every
name here) so that the rules of the settings are read in one place.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.invariant import FieldError, require
from companion.mavlink.transports import TransportError, parse_peers

MAV_COMP_ID_ONBOARD_COMPUTER = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
MAV_COMP_ID_AUTOPILOT1 = mavlink2.MAV_COMP_ID_AUTOPILOT1  # 1

# Rates (Hz) of the telemetry the service needs: the pose (ATTITUDE, GLOBAL_POSITION_INT) fast
# enough to interpolate at a frame's capture time, the rest for the state and the failsafe monitor.
DEFAULT_MESSAGE_RATES_HZ: Mapping[str, float] = MappingProxyType(
    {
        "ATTITUDE": 25.0,
        "GLOBAL_POSITION_INT": 10.0,
        "HOME_POSITION": 0.5,
        "EXTENDED_SYS_STATE": 2.0,
        "SYS_STATUS": 2.0,
        "BATTERY_STATUS": 1.0,
        "DISTANCE_SENSOR": 10.0,
        "GIMBAL_DEVICE_ATTITUDE_STATUS": 10.0,
    }
)

#: The rate the service asks for the pose messages (ATTITUDE, GLOBAL_POSITION_INT), Hz: twice the
#: camera's 10 frames a second, so that a frame's capture time always lies between two samples
#: and its pose is interpolated, not held.
POSE_RATE_HZ = 20.0


def message_rates(telemetry_rate_hz: float = POSE_RATE_HZ) -> dict[str, float]:
    """The default rates with the pose messages (ATTITUDE, GLOBAL_POSITION_INT) at ``telemetry_rate_hz``."""
    rates = dict(DEFAULT_MESSAGE_RATES_HZ)
    rates["ATTITUDE"] = rates["GLOBAL_POSITION_INT"] = float(telemetry_rate_hz)
    return rates


def parse_signing_key(text: str) -> bytes:
    """A 32-byte signing key from 64 hex digits, or the SHA-256 of a passphrase (as MAVProxy does)."""
    text = text.strip()
    if not text:
        raise ValueError("the MAVLink signing key is empty")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return hashlib.sha256(text.encode()).digest()


class PeersError(FieldError, TransportError):
    """``LinkConfig.peers`` holds an entry that is no IP address or network: the transport's error
    (``parse_peers``), and a field the settings name (``link.peers``)."""


@dataclass(frozen=True)
class LinkConfig:
    """How to reach the flight controller and how to present ourselves.

    ``url``: see ``transports.parse_url``; ``peers`` its UDP allow-list of addresses or networks
    (empty: any address until the autopilot is heard, then its address alone).
    ``target_system`` None (or 0) = the first autopilot heard.
    ``signing_key``: 32 bytes (see ``parse_signing_key``) or None for no signing; with a key,
    outgoing packets are signed and unsigned incoming packets are rejected (counted as bad) unless
    ``accept_unsigned`` is True.
    """

    url: str
    system_id: int = 1
    component_id: int = MAV_COMP_ID_ONBOARD_COMPUTER
    target_system: int | None = None
    target_component: int = MAV_COMP_ID_AUTOPILOT1
    heartbeat_period_s: float = 1.0
    heartbeat_timeout_s: float = 3.0
    message_rates_hz: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_MESSAGE_RATES_HZ))
    command_timeout_s: float = 1.0
    command_retries: int = 3
    signing_key: bytes | None = None
    signing_link_id: int = 0
    accept_unsigned: bool = False
    peers: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.target_system == 0:
            object.__setattr__(self, "target_system", None)  # 0 is "any" in the service config
        # The one place these rules live (the settings name the key of a field refused here).
        for name in ("system_id", "component_id"):
            require(1 <= getattr(self, name) <= 255, "mavlink", name, "must be 1..255", getattr(self, name))
        require(self.target_system is None or 1 <= self.target_system <= 255, "mavlink", "target_system",
                "must be 0 (the first autopilot heard) or 1..255", self.target_system)
        if self.signing_key is not None and len(self.signing_key) != 32:
            raise ValueError("mavlink signing_key must be 32 bytes (use parse_signing_key)")
        if not 0 <= self.signing_link_id <= 255:
            raise ValueError(f"mavlink signing_link_id {self.signing_link_id} must be 0..255")
        for name in ("heartbeat_period_s", "heartbeat_timeout_s", "command_timeout_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"mavlink {name} must be a positive number of seconds, not {value!r}")
        if self.command_retries < 0:
            raise ValueError("mavlink command_retries must be >= 0")
        try:
            parse_peers(self.peers)
        except TransportError as exc:  # it names the bad entry
            raise PeersError("mavlink", "peers", f"must list IP addresses or networks ({exc})") from None
        for name, hz in self.message_rates_hz.items():
            if f"MAVLINK_MSG_ID_{name}" not in vars(mavlink2):
                raise ValueError(f"mavlink message_rates_hz: unknown message {name!r}")
            if not (math.isfinite(hz) and hz >= 0):
                raise ValueError(f"mavlink message_rates_hz[{name}] must be >= 0 Hz, not {hz!r}")

