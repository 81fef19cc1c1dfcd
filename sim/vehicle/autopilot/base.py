"""Shared types of the simulated autopilot: behaviours, links, stream rates, config, frames.

Units and frames are those of the package (see ``sim.vehicle.autopilot``): world = local NED metres from
home, ground ``z = 0``; MAVLink units are converted at the message boundary only; times are
seconds of the simulator clock. The mixin modules (``modes``, ``commands``, ``params``,
``telemetry``, ``failsafes``) take their shared types from here and never import each other;
what they call on one another through ``self`` is declared here too (``AutopilotHost``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Protocol, TypeAlias

import numpy as np
from geographiclib.geodesic import Geodesic
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.faults import Failsafe

MAVMessage: TypeAlias = mav.MAVLink_message  # pymavlink is untyped: an alias of Any to mypy

R = mav  # short alias for enum constants


class Behaviour(Enum):
    """What a flight mode makes the vehicle do (flavour modes map onto these)."""

    MANUAL = "manual"    # STABILIZE / ALT_HOLD / POSCTL with sticks centred: hold where it is
    HOLD = "hold"        # LOITER / AUTO.LOITER
    GUIDED = "guided"    # GUIDED / OFFBOARD: follow the companion's targets
    TAKEOFF = "takeoff"  # AUTO.TAKEOFF
    LAND = "land"        # LAND / AUTO.LAND: vertical descent where it is
    RTL = "rtl"          # RTL / AUTO.RTL: climb, return, land


class Channel(Protocol):
    """The link a message came on: replies go back on it and it owns its stream rates."""

    streams: StreamSchedule

    def send(self, msg: MAVMessage) -> None: ...


@dataclass
class StreamSchedule:
    """Per-link telemetry rates, as ``SRx_*`` / ``MAV_CMD_SET_MESSAGE_INTERVAL`` keep them per link.

    ``intervals`` maps message id to period in seconds (``None`` = disabled).
    """

    defaults: dict[int, float]
    intervals: dict[int, float | None] = field(default_factory=dict)
    _next: dict[int, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for msg_id, hz in self.defaults.items():
            self.intervals[msg_id] = 1.0 / hz if hz > 0 else None

    def set_interval(self, msg_id: int, interval_s: float | None, now: float) -> None:
        self.intervals[msg_id] = interval_s
        self._next[msg_id] = now  # the first one goes out at once, like the firmwares do

    def reset(self, msg_id: int, now: float) -> None:
        hz = self.defaults.get(msg_id, 0.0)
        self.set_interval(msg_id, 1.0 / hz if hz > 0 else None, now)

    def interval_us(self, msg_id: int) -> int:
        """MESSAGE_INTERVAL encoding: -1 disabled, else microseconds."""
        iv = self.intervals.get(msg_id)
        return -1 if iv is None else int(round(iv * 1e6))

    def due(self, now: float) -> list[int]:
        out = []
        for msg_id, iv in self.intervals.items():
            if iv is None:
                continue
            t = self._next.get(msg_id)
            if t is None or now >= t:
                out.append(msg_id)
                # Catch up without bursts after a stall: never schedule into the past.
                self._next[msg_id] = max(now, (t if t is not None else now) + iv)
        return out


@dataclass
class AutopilotConfig:
    """Identity, home and failsafe set-up of the simulated autopilot.

    Home: WGS84 degrees and metres AMSL. Heights in metres above home. Battery thresholds as
    remaining fractions 0..1. ``failsafe_action`` maps a failsafe to ``"land"`` or ``"rtl"``
    (PX4 only warns on battery low, whatever its entry says).

    ``origin_alt_offset_m`` is ``home_alt - ref_alt`` in metres, where ``ref_alt`` is the AMSL
    altitude of the estimator's (EKF) local origin: the origin sits at ``home_alt -
    origin_alt_offset_m`` AMSL, horizontally at home. Negative = home below the origin. Only the
    PX4 flavour uses it (its local frame and its MAV_FRAME_GLOBAL_RELATIVE_ALT_INT conversion,
    which is wrong by ``2 * origin_alt_offset_m``); ArduPilot converts correctly and its local
    frame stays at home in this model.
    """

    system_id: int = 1
    component_id: int = 1
    home_lat: float = 47.397742
    home_lon: float = 8.545594
    home_alt: float = 488.0
    rtl_alt: float = 15.0
    takeoff_alt: float = 2.5
    battery_low: float = 0.20
    battery_critical: float = 0.10
    failsafe_action: dict[Failsafe, str] = field(default_factory=lambda: {
        Failsafe.BATTERY_LOW: "rtl", Failsafe.BATTERY_CRITICAL: "land",
        Failsafe.RC_LOSS: "land", Failsafe.GCS_LOSS: "land"})
    idle_disarm_s: float = 10.0       # DISARM_DELAY / COM_DISARM_PRFLT: armed but never took off
    rangefinder_max_m: float = 40.0
    rangefinder_min_m: float = 0.2
    gimbal_pitch: float | None = None  # radians, earth-frame stabilised; None = no gimbal
    gcs_system_id: int = 255           # SYSID_MYGCS: whose heartbeats count for the GCS failsafe
    gcs_timeout_s: float | None = None  # FS_GCS_TIMEOUT; None = FS_GCS_ENABLE 0 (the default)
    telemetry_rates: dict[int, float] | None = None  # overrides of the flavour's default rates
    origin_alt_offset_m: float = 0.0   # home_alt - EKF origin alt AMSL (m); PX4 only, see above
    #: The estimator's altitude error (m): the autopilot believes it is this much higher than it
    #: is, reports its altitude so (GLOBAL_POSITION_INT alt and relative_alt, LOCAL_POSITION_NED z)
    #: and flies altitude targets in that belief (a target of 5 m above home puts the vehicle 5 m
    #: less the bias above the ground). PX4 1.15.4 SIH's relative altitude on the ground reads
    #: -1.3 to +1.8 m (issue 62). Its rangefinder, if any, still measures the ground truly.
    alt_bias_m: float = 0.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.origin_alt_offset_m):
            raise ValueError(f"origin_alt_offset_m must be finite, got {self.origin_alt_offset_m}")
        if not math.isfinite(self.alt_bias_m):
            raise ValueError(f"alt_bias_m must be finite, got {self.alt_bias_m}")
        for kind, action in self.failsafe_action.items():
            if action not in ("land", "rtl"):
                raise ValueError(f"failsafe action for {kind.value} must be 'land' or 'rtl'")


class GeoFrame:
    """Conversions between world NED metres (origin home) and WGS84, through geographiclib."""

    def __init__(self, lat: float, lon: float, alt: float) -> None:
        self.lat, self.lon, self.alt = lat, lon, alt
        self._geod = Geodesic.WGS84

    def to_global(self, north: float, east: float, down: float) -> tuple[float, float, float]:
        """(lat deg, lon deg, alt m AMSL) of a world NED point."""
        dist = math.hypot(north, east)
        if dist < 1e-9:
            return self.lat, self.lon, self.alt - down
        azi = math.degrees(math.atan2(east, north))
        g = self._geod.Direct(self.lat, self.lon, azi, dist)
        return g["lat2"], g["lon2"], self.alt - down

    def to_local(self, lat: float, lon: float) -> tuple[float, float]:
        """(north m, east m) of a WGS84 point relative to home."""
        g = self._geod.Inverse(self.lat, self.lon, lat, lon)
        azi = math.radians(g["azi1"])
        return g["s12"] * math.cos(azi), g["s12"] * math.sin(azi)


@dataclass
class Setpoint:
    """A parsed position target: any of position (world NED m), velocity (m/s), yaw (rad)."""

    position: np.ndarray | None = None
    velocity: np.ndarray | None = None
    yaw: float | None = None


class AutopilotHost(Protocol):
    """What the mixins call through ``self`` on one another and on the flavour.

    ``Autopilot`` (``core``) combines the mixins and declares the flavour hooks; ``sim.vehicle.ardupilot``
    and ``sim.vehicle.px4`` fill them in. Each mixin declares the state it reads itself; what it uses of
    a sibling mixin or of the flavour is declared here, once, with its real signature.
    """

    # ----- the flavour: class constants and hooks (``core.Autopilot``, ``sim.vehicle.ardupilot``, ``sim.vehicle.px4``)

    FLAVOUR: str
    MAV_AUTOPILOT: int

    def behaviour_of(self, custom_mode: int) -> Behaviour | None: ...

    def mode_for(self, behaviour: Behaviour) -> int: ...

    def mode_name(self, custom_mode: int | None = None) -> str: ...

    def mode_from_command(self, main: float, sub: float) -> int: ...

    def request_mode(self, custom_mode: int) -> int: ...

    def base_mode_flags(self) -> int: ...

    def default_rates(self) -> dict[int, float]: ...

    def handle_setpoint(self, sp: Setpoint) -> None: ...

    def origin_down_m(self) -> float: ...

    def global_target_down(self, frame: int, alt: float) -> float | None: ...

    # ----- ``modes``

    @property
    def behaviour(self) -> Behaviour: ...

    @property
    def flying(self) -> bool: ...

    def set_mode(self, custom_mode: int) -> None: ...

    def arm(self) -> None: ...

    def disarm(self) -> None: ...

    def can_arm(self) -> bool: ...

    # ----- ``telemetry``

    def known_messages(self) -> set[int]: ...

    def build(self, msg_id: int) -> MAVMessage | None: ...

    def _say(self, severity: int, text: str) -> None: ...

    # ----- ``params`` and ``failsafes``

    def _handle_param(self, msg: MAVMessage, channel: Channel) -> None: ...

    def on_peer_heartbeat(self, msg: MAVMessage) -> None: ...


if TYPE_CHECKING:
    # To the type checker each mixin is an ``AutopilotHost``, so that it may call what a sibling
    # or the flavour provides; at run time a mixin is a plain class and ``Autopilot`` brings the
    # parts together.
    MixinBase = AutopilotHost
else:
    MixinBase = object



def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the Z-Y-X Euler rotation, MAVLink order."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)
