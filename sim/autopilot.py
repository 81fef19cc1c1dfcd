"""What an autopilot does on top of the vehicle: modes, commands, telemetry, failsafes.

``Autopilot`` holds the behaviour common to ArduPilot Copter (``sim.ardupilot``) and PX4
(``sim.px4``): telemetry message construction, message-interval scheduling per link, the command
dispatcher with its COMMAND_ACK results, position-target parsing, return-to-launch and landing
sequences, and failsafes. Each flavour maps its own ``custom_mode`` numbers onto a small set of
``Behaviour``s and decides which commands it accepts in which state, as its firmware does.

Units: world = local NED metres from home, ground ``z = 0``; MAVLink fields in their own units
(degE7, mm, cm/s, cdeg) are converted at the message boundary only. Times are seconds of the
simulator clock, ``time_boot_ms`` counts from the simulator start.

The autopilot's own local frame (LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED in
MAV_FRAME_LOCAL_NED, HOME_POSITION x/y/z) has its origin at the estimator's origin, which a flavour
may put ``origin_down_m()`` metres below home (world down); horizontally it is home. In that frame
``z_local = world_down - origin_down_m()``. ArduPilot's is home here (0); PX4's is
``AutopilotConfig.origin_alt_offset_m``.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from enum import Enum
from typing import Callable, Protocol

import numpy as np
from geographiclib.geodesic import Geodesic
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.faults import Failsafe
from sim.vehicle import Demand, Vehicle

log = logging.getLogger(__name__)

MAVMessage = mav.MAVLink_message


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

    streams: "StreamSchedule"

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

    def __post_init__(self) -> None:
        if not math.isfinite(self.origin_alt_offset_m):
            raise ValueError(f"origin_alt_offset_m must be finite, got {self.origin_alt_offset_m}")
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


# SET_POSITION_TARGET_* type_mask bits (POSITION_TARGET_TYPEMASK).
_IGNORE_POS = 0b111
_IGNORE_VEL = 0b111 << 3
_IGNORE_ACC = 0b111 << 6
_IGNORE_YAW = 1 << 10

R = mav  # short alias for enum constants below


def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the Z-Y-X Euler rotation, MAVLink order."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


class Autopilot(ABC):
    """The flavour-independent part of a simulated autopilot. ``tick(now)`` every physics step."""

    MAV_AUTOPILOT: int = R.MAV_AUTOPILOT_GENERIC
    FLAVOUR: str = "generic"
    LAND_DISARM_S: float = 0.0  # after the land detector fires (see ``disarms_when_landed``)
    LANDED_DISARM_TEXT: str = "Disarming: landed"
    IDLE_DISARM_TEXT: str = "Disarming: auto disarm while landed"

    def __init__(self, vehicle: Vehicle, config: AutopilotConfig | None = None,
                 start_time: float = 0.0) -> None:
        self.vehicle = vehicle
        self.config = config or AutopilotConfig()
        self.geo = GeoFrame(self.config.home_lat, self.config.home_lon, self.config.home_alt)
        self.start_time = start_time
        self.now = start_time
        self.custom_mode = self.initial_mode()
        self.failsafes: set[Failsafe] = set()
        self.counters: dict[str, int] = {
            "commands": 0, "commands_unsupported": 0, "setpoints": 0,
            "setpoints_ignored": 0, "setpoints_invalid": 0, "messages_ignored": 0,
        }
        self._rtl_phase = ""
        self._armed_on_ground_since: float | None = None
        # Airborne since the last arming: the land detector's disarm applies only after a flight.
        self._has_flown = vehicle.state.armed and not vehicle.state.land_complete
        self.on_mode_change: list[Callable[[int, int], None]] = []
        self.on_touchdown: list[Callable[[], None]] = []
        self._was_landed = vehicle.state.land_complete
        self._last_gcs_heartbeat: float | None = None  # the GCS failsafe arms on the first one
        self.status_text: list[tuple[int, str]] = []  # pending STATUSTEXT (severity, text)

    # ----- flavour hooks -----

    @abstractmethod
    def initial_mode(self) -> int: ...

    @abstractmethod
    def behaviour_of(self, custom_mode: int) -> Behaviour | None:
        """The behaviour of a flavour mode number, None when the firmware has no such mode."""

    @abstractmethod
    def mode_for(self, behaviour: Behaviour) -> int:
        """The flavour mode number the autopilot itself switches to for a behaviour."""

    def mode_name(self, custom_mode: int | None = None) -> str:
        """Human name of a mode number (the current one by default)."""
        return str(self.custom_mode if custom_mode is None else custom_mode)

    @abstractmethod
    def base_mode_flags(self) -> int:
        """HEARTBEAT base_mode without SAFETY_ARMED."""

    @abstractmethod
    def default_rates(self) -> dict[int, float]:
        """Default telemetry rates in Hz per message id on a new link."""

    @abstractmethod
    def handle_setpoint(self, sp: Setpoint) -> None:
        """A parsed SET_POSITION_TARGET_*: apply or ignore as the flavour does."""

    @abstractmethod
    def request_mode(self, custom_mode: int) -> int:
        """A mode change asked over MAVLink; returns the MAV_RESULT to ack with."""

    def mode_from_command(self, main: float, sub: float) -> int:
        """The custom_mode that MAV_CMD_DO_SET_MODE param2/param3 name (flavour encoding)."""
        return int(main)

    def origin_down_m(self) -> float:
        """World down (m) of the local frame's origin (the estimator's origin); 0 = at home."""
        return 0.0

    def global_target_down(self, frame: int, alt: float) -> float | None:
        """World down (m) of a SET_POSITION_TARGET_GLOBAL_INT altitude in ``frame``.

        ``alt`` is metres AMSL (GLOBAL), above home (RELATIVE_ALT) or above terrain (TERRAIN_ALT;
        the terrain is flat at home's height here). None: the firmware discards that frame.
        """
        if frame in (R.MAV_FRAME_GLOBAL_INT, R.MAV_FRAME_GLOBAL):
            return self.config.home_alt - alt
        if frame in (R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, R.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                     R.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT, R.MAV_FRAME_GLOBAL_TERRAIN_ALT):
            return -alt
        return None

    def disarms_when_landed(self, behaviour: Behaviour) -> bool:
        """Whether the land detector disarms (after LAND_DISARM_S) in this behaviour.

        Otherwise an armed vehicle on the ground disarms after ``idle_disarm_s``.
        """
        return behaviour in (Behaviour.LAND, Behaviour.RTL)

    # ----- state -----

    @property
    def behaviour(self) -> Behaviour:
        b = self.behaviour_of(self.custom_mode)
        assert b is not None
        return b

    @property
    def time_boot_ms(self) -> int:
        return int((self.now - self.start_time) * 1000) & 0xFFFFFFFF

    @property
    def flying(self) -> bool:
        s = self.vehicle.state
        return s.armed and not s.land_complete

    def set_mode(self, custom_mode: int) -> None:
        """Switch mode and start its behaviour (no checks: callers have done them)."""
        old = self.custom_mode
        self.custom_mode = custom_mode
        self._enter(self.behaviour)
        if old != custom_mode:
            log.info("%s mode %s -> %s", self.FLAVOUR, self.mode_name(old), self.mode_name(custom_mode))
            for cb in list(self.on_mode_change):
                cb(old, custom_mode)

    def _enter(self, b: Behaviour) -> None:
        v = self.vehicle
        if b is Behaviour.LAND:
            if self.flying:
                v.land()
        elif b is Behaviour.RTL:
            self._rtl_phase = "climb"
            if self.flying:
                v.fly_to(*v.state.position[:2], min(v.state.position[2], -self.config.rtl_alt))
        elif b in (Behaviour.HOLD, Behaviour.MANUAL, Behaviour.GUIDED):
            if self.flying:
                v.hold()
        elif b is Behaviour.TAKEOFF:
            self._start_takeoff(self.config.takeoff_alt)

    def _start_takeoff(self, altitude: float) -> bool:
        v = self.vehicle
        if not v.state.armed:
            return False
        if v.state.land_complete:
            v.take_off(altitude)
        else:
            v.fly_to(*v.state.position[:2], -abs(altitude))
        return True

    def arm(self) -> None:
        self.vehicle.arm()
        self._armed_on_ground_since = self.now
        self._has_flown = False

    def disarm(self) -> None:
        self.vehicle.disarm()
        self._armed_on_ground_since = None

    # ----- the periodic step -----

    def tick(self, now: float) -> None:
        """Run mode logic, failsafe detection and auto-disarm at simulator time ``now`` (s)."""
        self.now = now
        v, s = self.vehicle, self.vehicle.state
        b = self.behaviour
        if b is Behaviour.RTL and self.flying:
            self._run_rtl()
        if b is Behaviour.TAKEOFF and self.flying and v.demand is Demand.POSITION:
            if abs(s.position[2] - v.target_position[2]) < 0.3:
                self.set_mode(self.mode_for(Behaviour.HOLD))
        remaining = v.battery_remaining
        if remaining <= self.config.battery_critical and Failsafe.BATTERY_CRITICAL not in self.failsafes:
            self.trigger_failsafe(Failsafe.BATTERY_CRITICAL)
        elif remaining <= self.config.battery_low and Failsafe.BATTERY_LOW not in self.failsafes:
            self.trigger_failsafe(Failsafe.BATTERY_LOW)
        landed = s.land_complete
        if landed and not self._was_landed and s.armed:
            for cb in list(self.on_touchdown):
                cb()
        self._was_landed = landed
        if s.armed and not landed:
            self._has_flown = True
        if s.armed and landed:
            by_landing = self.disarms_when_landed(b)
            if by_landing and v.landed_for_s >= self.LAND_DISARM_S:
                self.disarm()
                self._say(R.MAV_SEVERITY_INFO, self.LANDED_DISARM_TEXT)
            elif self._armed_on_ground_since is not None and not by_landing:
                if now - self._armed_on_ground_since >= self.config.idle_disarm_s:
                    self.disarm()
                    self._say(R.MAV_SEVERITY_INFO, self.IDLE_DISARM_TEXT)
        if not landed:
            self._armed_on_ground_since = now if s.armed else None
        timeout = self.config.gcs_timeout_s
        if (timeout is not None and self._last_gcs_heartbeat is not None and self.flying
                and now - self._last_gcs_heartbeat > timeout):
            self.trigger_failsafe(Failsafe.GCS_LOSS)
        self.on_tick(now)

    def on_tick(self, now: float) -> None:
        """Flavour-specific periodic logic (offboard loss on PX4)."""

    def _run_rtl(self) -> None:
        v, s = self.vehicle, self.vehicle.state
        if self._rtl_phase == "climb":
            if s.position[2] <= v.target_position[2] + 0.3:
                self._rtl_phase = "return"
                v.fly_to(0.0, 0.0, float(v.target_position[2]))
        elif self._rtl_phase == "return":
            if math.hypot(*s.position[:2]) < 0.5 and float(np.linalg.norm(s.velocity)) < 0.3:
                self._rtl_phase = "land"
                v.land()

    # ----- failsafes -----

    def trigger_failsafe(self, kind: Failsafe) -> None:
        """Raise a failsafe as the firmware would: flag it (latched), then ``react_to_failsafe``."""
        if kind in self.failsafes:
            return
        self.failsafes.add(kind)
        if kind is Failsafe.BATTERY_LOW:
            self.vehicle.set_battery_remaining(min(self.vehicle.battery_remaining,
                                                   self.config.battery_low))
        elif kind is Failsafe.BATTERY_CRITICAL:
            self.vehicle.set_battery_remaining(min(self.vehicle.battery_remaining,
                                                   self.config.battery_critical))
        self.react_to_failsafe(kind)

    def react_to_failsafe(self, kind: Failsafe) -> None:
        """What the firmware does about a new failsafe: tell the GCS, switch mode at once."""
        action = self.config.failsafe_action.get(kind, "land")
        self._say(R.MAV_SEVERITY_CRITICAL, f"Failsafe {kind.value}: {action.upper()}")
        target = self.failsafe_target(kind)
        if target is not None:
            self.set_mode(self.mode_for(target))

    def failsafe_target(self, kind: Failsafe) -> Behaviour | None:
        """The behaviour ``kind``'s action switches to now; None when it changes nothing."""
        if not self.flying:
            return None
        action = self.config.failsafe_action.get(kind, "land")
        target = Behaviour.RTL if action == "rtl" else Behaviour.LAND
        # A failsafe never de-escalates: already landing stays landing.
        if self.behaviour is Behaviour.LAND or self.behaviour is target:
            return None
        return target

    def clear_failsafe(self, kind: Failsafe) -> None:
        """The condition went away (RC back, GCS back); the mode stays as it is, like the firmwares."""
        self.failsafes.discard(kind)
        if kind is Failsafe.GCS_LOSS and self._last_gcs_heartbeat is not None:
            self._last_gcs_heartbeat = self.now

    def system_status(self) -> int:
        s = self.vehicle.state
        if Failsafe.BATTERY_CRITICAL in self.failsafes:
            return R.MAV_STATE_EMERGENCY
        if self.failsafes:
            return R.MAV_STATE_CRITICAL
        if not s.armed or s.land_complete:
            return R.MAV_STATE_STANDBY
        return R.MAV_STATE_ACTIVE

    def charge_state(self) -> int:
        remaining = self.vehicle.battery_remaining
        if remaining <= 0.02:
            return R.MAV_BATTERY_CHARGE_STATE_EMERGENCY
        if remaining <= self.config.battery_critical or Failsafe.BATTERY_CRITICAL in self.failsafes:
            return R.MAV_BATTERY_CHARGE_STATE_CRITICAL
        if remaining <= self.config.battery_low or Failsafe.BATTERY_LOW in self.failsafes:
            return R.MAV_BATTERY_CHARGE_STATE_LOW
        return R.MAV_BATTERY_CHARGE_STATE_OK

    def landed_state(self) -> int:
        s, v = self.vehicle.state, self.vehicle
        if not s.armed or s.land_complete:
            return R.MAV_LANDED_STATE_ON_GROUND
        if v.demand is Demand.LAND:
            return R.MAV_LANDED_STATE_LANDING
        if self.behaviour is Behaviour.TAKEOFF or (
                v.demand is Demand.POSITION and v.altitude < 1.0 and v.target_position[2] < -1.0):
            return R.MAV_LANDED_STATE_TAKEOFF
        return R.MAV_LANDED_STATE_IN_AIR

    def _say(self, severity: int, text: str) -> None:
        self.status_text.append((severity, text))

    # ----- incoming messages -----

    def handle_message(self, msg: MAVMessage, channel: Channel) -> None:
        """Act on one decoded message from a peer; replies go back on ``channel``."""
        t = msg.get_type()
        if t in ("COMMAND_LONG", "COMMAND_INT"):
            if msg.target_system not in (0, self.config.system_id):
                return
            if msg.target_component not in (0, self.config.component_id):
                return
            self._handle_command(msg, channel)
        elif t in ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT"):
            if msg.target_system not in (0, self.config.system_id):
                return
            self.counters["setpoints"] += 1
            sp = self._parse_setpoint(msg)
            if sp is None:
                self.counters["setpoints_invalid"] += 1
                return
            self.handle_setpoint(sp)
        elif t == "SET_MODE":
            if msg.target_system not in (0, self.config.system_id):
                return
            # SET_MODE has no ack; the heartbeat tells the sender whether it worked.
            if msg.base_mode & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                self.request_mode(int(msg.custom_mode))
        elif t in ("HEARTBEAT",):
            self.on_peer_heartbeat(msg)
        elif t in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
            self._handle_param(msg, channel)
        else:
            self.counters["messages_ignored"] += 1

    def on_peer_heartbeat(self, msg: MAVMessage) -> None:
        """A heartbeat from a peer: the GCS's ones feed the GCS failsafe, others are ignored."""
        if msg.get_srcSystem() == self.config.gcs_system_id:
            self._last_gcs_heartbeat = self.now

    def _parse_setpoint(self, msg: MAVMessage) -> Setpoint | None:
        mask = int(msg.type_mask)
        sp = Setpoint()
        s = self.vehicle.state
        pos_bits = mask & _IGNORE_POS
        vel_bits = mask & _IGNORE_VEL
        if pos_bits not in (0, _IGNORE_POS):
            return None  # partial position targets are rejected by both firmwares
        if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            frame = int(msg.coordinate_frame)
            pos = np.array([msg.x, msg.y, msg.z], dtype=float)
            vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
            if frame == R.MAV_FRAME_LOCAL_NED:
                pos[2] += self.origin_down_m()  # local frame (estimator origin) -> world
            elif frame == R.MAV_FRAME_LOCAL_OFFSET_NED:
                pos = pos + s.position
            elif frame in (R.MAV_FRAME_BODY_NED, R.MAV_FRAME_BODY_OFFSET_NED, R.MAV_FRAME_BODY_FRD):
                cy, sy = math.cos(s.yaw), math.sin(s.yaw)
                rot = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
                pos = rot @ pos + s.position
                vel = rot @ vel
            else:
                return None
        else:
            frame = int(msg.coordinate_frame)
            down = self.global_target_down(frame, float(msg.alt))
            if down is None:
                return None
            north, east = (0.0, 0.0)
            if pos_bits == 0:
                north, east = self.geo.to_local(msg.lat_int / 1e7, msg.lon_int / 1e7)
            pos = np.array([north, east, down])
            vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if pos_bits == 0:
            if not np.all(np.isfinite(pos)):
                return None
            sp.position = pos
        if vel_bits != _IGNORE_VEL:
            if not np.all(np.isfinite(vel)):
                return None
            sp.velocity = np.where([(mask >> (3 + i)) & 1 for i in range(3)], 0.0, vel)
        if sp.position is None and sp.velocity is None:
            return None
        if not (mask & _IGNORE_YAW) and math.isfinite(float(msg.yaw)):
            sp.yaw = float(msg.yaw)
        return sp

    def apply_setpoint(self, sp: Setpoint) -> None:
        """Steer the vehicle with a setpoint (the caller checked the mode)."""
        v = self.vehicle
        if sp.position is not None:
            v.fly_to(*sp.position, yaw=sp.yaw)
        elif sp.velocity is not None:
            v.fly_velocity(*sp.velocity, yaw=sp.yaw)

    # ----- commands -----

    def _ack(self, channel: Channel, msg: MAVMessage, result: int) -> None:
        channel.send(mav.MAVLink_command_ack_message(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _handle_command(self, msg: MAVMessage, channel: Channel) -> None:
        self.counters["commands"] += 1
        cmd = int(msg.command)
        is_int = msg.get_type() == "COMMAND_INT"
        p = [msg.param1, msg.param2, msg.param3, msg.param4]
        if is_int:
            p += [msg.x, msg.y, msg.z]
        else:
            p += [msg.param5, msg.param6, msg.param7]
        handler = {
            R.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            R.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_message_interval,
            R.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._cmd_request_capabilities,
            R.MAV_CMD_GET_HOME_POSITION: self._cmd_get_home,
            R.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            R.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            R.MAV_CMD_NAV_LAND: self._cmd_land,
            R.MAV_CMD_NAV_RETURN_TO_LAUNCH: self._cmd_rtl,
            R.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            R.MAV_CMD_DO_REPOSITION: self._cmd_reposition,
            R.MAV_CMD_DO_CHANGE_SPEED: self._cmd_change_speed,
        }.get(cmd)
        if handler is None:
            self.counters["commands_unsupported"] += 1
            self._ack(channel, msg, R.MAV_RESULT_UNSUPPORTED)
            return
        try:
            result = handler(p, channel, msg, is_int)
        except (ValueError, TypeError, OverflowError) as exc:
            # Nonsense parameters (NaN where a number is needed...) get a clean refusal.
            log.debug("command %d refused: %s", cmd, exc)
            result = R.MAV_RESULT_DENIED
        if result is not None:
            self._ack(channel, msg, result)

    def known_messages(self) -> set[int]:
        """Messages the firmware has a stream for, sent or not (no gimbal: none goes out)."""
        return self.supported_messages() | {mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS}

    def _cmd_set_message_interval(self, p, channel, msg, is_int) -> int:
        msg_id, interval_us = int(p[0]), float(p[1])
        if msg_id not in self.known_messages():
            return R.MAV_RESULT_DENIED
        if interval_us < 0:
            channel.streams.set_interval(msg_id, None, self.now)
        elif interval_us == 0:
            channel.streams.reset(msg_id, self.now)
        else:
            channel.streams.set_interval(msg_id, interval_us / 1e6, self.now)
        return R.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, p, channel, msg, is_int) -> int:
        msg_id = int(p[0])
        if msg_id not in self.known_messages():
            return R.MAV_RESULT_DENIED
        channel.send(mav.MAVLink_message_interval_message(msg_id, channel.streams.interval_us(msg_id)))
        return R.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, p, channel, msg, is_int) -> int | None:
        msg_id = int(p[0])
        out = self.build(msg_id)
        if out is None:
            return R.MAV_RESULT_DENIED
        # Ack first, then the message, as ArduPilot and PX4 both do.
        self._ack(channel, msg, R.MAV_RESULT_ACCEPTED)
        channel.send(out)
        return None

    def _cmd_request_capabilities(self, p, channel, msg, is_int) -> int | None:
        self._ack(channel, msg, R.MAV_RESULT_ACCEPTED)
        channel.send(self.build(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION))
        return None

    def _cmd_get_home(self, p, channel, msg, is_int) -> int | None:
        self._ack(channel, msg, R.MAV_RESULT_ACCEPTED)
        channel.send(self.build(mav.MAVLINK_MSG_ID_HOME_POSITION))
        return None

    def _cmd_arm_disarm(self, p, channel, msg, is_int) -> int:
        force = int(p[1]) == 21196
        if p[0] >= 0.5:
            if self.vehicle.state.armed:
                return R.MAV_RESULT_ACCEPTED
            if not self.can_arm() and not force:
                return self.refused()
            self.arm()
            return R.MAV_RESULT_ACCEPTED
        if not self.vehicle.state.armed:
            return R.MAV_RESULT_ACCEPTED
        if self.flying and not force:
            return self.refused()
        self.disarm()
        return R.MAV_RESULT_ACCEPTED

    def can_arm(self) -> bool:
        return self.vehicle.state.land_complete and Failsafe.BATTERY_CRITICAL not in self.failsafes

    def refused(self) -> int:
        """The result a flavour acks a refused state change with."""
        return R.MAV_RESULT_FAILED

    @abstractmethod
    def _cmd_takeoff(self, p, channel, msg, is_int) -> int: ...

    def _cmd_land(self, p, channel, msg, is_int) -> int:
        return self.request_mode(self.mode_for(Behaviour.LAND))

    def _cmd_rtl(self, p, channel, msg, is_int) -> int:
        return self.request_mode(self.mode_for(Behaviour.RTL))

    def _cmd_set_mode(self, p, channel, msg, is_int) -> int:
        if not int(p[0]) & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return R.MAV_RESULT_UNSUPPORTED  # base-mode-only changes are not supported by either
        return self.request_mode(self.mode_from_command(p[1], p[2]))

    def _reposition_target(self, p, is_int: bool, frame: int) -> np.ndarray:
        s = self.vehicle.state
        target = s.position.copy()
        lat = p[4] / 1e7 if is_int else p[4]
        lon = p[5] / 1e7 if is_int else p[5]
        if math.isfinite(lat) and math.isfinite(lon) and not (lat == 0 and lon == 0):
            target[0], target[1] = self.geo.to_local(lat, lon)
        if math.isfinite(p[6]):
            rel = frame in (R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
            target[2] = -p[6] if rel else self.config.home_alt - p[6]
        target[2] = min(target[2], 0.0)
        return target

    @abstractmethod
    def _cmd_reposition(self, p, channel, msg, is_int) -> int: ...

    def _cmd_change_speed(self, p, channel, msg, is_int) -> int:
        speed = float(p[1])
        if not math.isfinite(speed) or speed == -1:
            return R.MAV_RESULT_ACCEPTED
        if speed <= 0:
            return R.MAV_RESULT_DENIED
        self.vehicle.speed_xy = min(speed, self.vehicle.params.max_speed_xy)
        return R.MAV_RESULT_ACCEPTED

    # ----- parameters (a handful, enough for MAVSDK and GCS look-ups) -----

    def params(self) -> dict[str, float]:
        return {}

    def _handle_param(self, msg: MAVMessage, channel: Channel) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        table = self.params()
        names = sorted(table)
        t = msg.get_type()

        def value(name: str) -> MAVMessage:
            return mav.MAVLink_param_value_message(name.encode(), float(table[name]),
                                                   R.MAV_PARAM_TYPE_REAL32, len(names),
                                                   names.index(name))
        if t == "PARAM_REQUEST_LIST":
            for name in names:
                channel.send(value(name))
        elif t == "PARAM_REQUEST_READ":
            name = _param_name(msg.param_id)
            if msg.param_index >= 0 and msg.param_index < len(names):
                name = names[msg.param_index]
            if name in table:
                channel.send(value(name))
        elif t == "PARAM_SET":
            name = _param_name(msg.param_id)
            if name in table and math.isfinite(msg.param_value):
                self.set_param(name, float(msg.param_value))
                table = self.params()
                channel.send(value(name))

    def set_param(self, name: str, value: float) -> None:
        """Apply a parameter write (flavours map names onto their config)."""

    # ----- telemetry -----

    def supported_messages(self) -> set[int]:
        ids = {
            mav.MAVLINK_MSG_ID_HEARTBEAT, mav.MAVLINK_MSG_ID_ATTITUDE,
            mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
            mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_HOME_POSITION,
            mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mav.MAVLINK_MSG_ID_SYS_STATUS,
            mav.MAVLINK_MSG_ID_BATTERY_STATUS, mav.MAVLINK_MSG_ID_DISTANCE_SENSOR,
            mav.MAVLINK_MSG_ID_GPS_RAW_INT, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
            mav.MAVLINK_MSG_ID_VFR_HUD,
        }
        if self.config.gimbal_pitch is not None:
            ids.add(mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS)
        return ids

    def stream_defaults(self) -> dict[int, float]:
        rates = dict(self.default_rates())
        if self.config.gimbal_pitch is None:
            rates.pop(mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS, None)
        if self.config.telemetry_rates:
            rates.update(self.config.telemetry_rates)
        return rates

    def new_streams(self) -> StreamSchedule:
        return StreamSchedule(self.stream_defaults())

    def pending_status_text(self) -> list[MAVMessage]:
        out = [mav.MAVLink_statustext_message(sev, text.encode()[:50])
               for sev, text in self.status_text]
        self.status_text.clear()
        return out

    def autopilot_version(self) -> MAVMessage:
        caps = (R.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | R.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | R.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | R.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                | R.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT)
        return mav.MAVLink_autopilot_version_message(
            caps, self.flight_sw_version(), 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0,
            0x5349_4D00 + self.config.system_id)

    def flight_sw_version(self) -> int:
        return 0

    def reported_home(self) -> tuple[float, float, float]:
        """Where HOME_POSITION says home is, world NED metres (the configured home: origin)."""
        return 0.0, 0.0, 0.0

    def build(self, msg_id: int) -> MAVMessage | None:
        """The current telemetry message ``msg_id``, or None if this autopilot does not send it."""
        if msg_id not in self.supported_messages():
            return None
        v, s, c = self.vehicle, self.vehicle.state, self.config
        tb = self.time_boot_ms
        n, e, d = (float(x) for x in s.position)
        vn, ve, vd = (float(x) for x in s.velocity)
        if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
            base = self.base_mode_flags() | R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if s.armed:
                base |= R.MAV_MODE_FLAG_SAFETY_ARMED
            return mav.MAVLink_heartbeat_message(R.MAV_TYPE_QUADROTOR, self.MAV_AUTOPILOT, base,
                                                 self.custom_mode, self.system_status(), 3)
        if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE:
            return mav.MAVLink_attitude_message(tb, s.roll, s.pitch, s.yaw, 0.0, 0.0, s.yaw_rate)
        if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            q = quaternion_from_euler(s.roll, s.pitch, s.yaw)
            return mav.MAVLink_attitude_quaternion_message(tb, *q, 0.0, 0.0, s.yaw_rate)
        if msg_id == mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            lat, lon, alt = self.geo.to_global(n, e, d)
            hdg = int(round(math.degrees(s.yaw) * 100)) % 36000
            return mav.MAVLink_global_position_int_message(
                tb, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
                int(round(-d * 1000)), _i16(vn * 100), _i16(ve * 100), _i16(vd * 100), hdg)
        if msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return mav.MAVLink_local_position_ned_message(tb, n, e, d - self.origin_down_m(),
                                                          vn, ve, vd)
        if msg_id == mav.MAVLINK_MSG_ID_HOME_POSITION:
            hn, he, hd = self.reported_home()
            lat, lon, alt = self.geo.to_global(hn, he, hd)
            return mav.MAVLink_home_position_message(
                int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
                hn, he, hd - self.origin_down_m(), [1.0, 0.0, 0.0, 0.0],
                0.0, 0.0, 0.0, int((self.now - self.start_time) * 1e6))
        if msg_id == mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return mav.MAVLink_extended_sys_state_message(R.MAV_VTOL_STATE_UNDEFINED,
                                                          self.landed_state())
        if msg_id == mav.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = (R.MAV_SYS_STATUS_SENSOR_3D_GYRO | R.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                       | R.MAV_SYS_STATUS_SENSOR_3D_MAG | R.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
                       | R.MAV_SYS_STATUS_SENSOR_GPS | R.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
                       | R.MAV_SYS_STATUS_SENSOR_BATTERY | R.MAV_SYS_STATUS_SENSOR_LASER_POSITION)
            health = sensors
            if Failsafe.RC_LOSS in self.failsafes:
                health &= ~R.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
            if self.failsafes & {Failsafe.BATTERY_LOW, Failsafe.BATTERY_CRITICAL}:
                health &= ~R.MAV_SYS_STATUS_SENSOR_BATTERY
            return mav.MAVLink_sys_status_message(
                sensors, sensors, health, 250, int(v.battery_voltage * 1000),
                int(s.current_a * 100), int(round(v.battery_remaining * 100)), 0, 0, 0, 0, 0, 0)
        if msg_id == mav.MAVLINK_MSG_ID_BATTERY_STATUS:
            cells = [65535] * 10
            cell_mv = int(v.battery_voltage / v.params.battery_cells * 1000)
            for i in range(min(v.params.battery_cells, 10)):
                cells[i] = cell_mv
            return mav.MAVLink_battery_status_message(
                0, R.MAV_BATTERY_FUNCTION_ALL, R.MAV_BATTERY_TYPE_LIPO, 32767, cells,
                int(s.current_a * 100), int(s.consumed_mah), -1,
                int(round(v.battery_remaining * 100)), 0, self.charge_state())
        if msg_id == mav.MAVLINK_MSG_ID_DISTANCE_SENSOR:
            tilt = max(math.cos(s.roll) * math.cos(s.pitch), 0.2)
            rng = v.altitude / tilt
            rng = min(max(rng, c.rangefinder_min_m), c.rangefinder_max_m + 0.01)
            return mav.MAVLink_distance_sensor_message(
                tb, int(c.rangefinder_min_m * 100), int(c.rangefinder_max_m * 100),
                int(round(rng * 100)), R.MAV_DISTANCE_SENSOR_LASER, 0,
                R.MAV_SENSOR_ROTATION_PITCH_270, 255)
        if msg_id == mav.MAVLINK_MSG_ID_GPS_RAW_INT:
            lat, lon, alt = self.geo.to_global(n, e, d)
            gs = math.hypot(vn, ve)
            cog = int(round(math.degrees(math.atan2(ve, vn)) * 100)) % 36000 if gs > 0.2 else 65535
            return mav.MAVLink_gps_raw_int_message(
                int((self.now - self.start_time) * 1e6), R.GPS_FIX_TYPE_3D_FIX,
                int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
                80, 120, int(gs * 100), cog, 16)
        if msg_id == mav.MAVLINK_MSG_ID_VFR_HUD:
            return mav.MAVLink_vfr_hud_message(
                math.hypot(vn, ve), math.hypot(vn, ve), int(math.degrees(s.yaw)) % 360,
                int(min(100, s.current_a / v.params.hover_current_a * 50)), -d, -vd)
        if msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self.autopilot_version()
        if msg_id == mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS:
            # Roll and pitch stabilised in the earth frame, yaw follows the vehicle.
            q = quaternion_from_euler(0.0, float(c.gimbal_pitch or 0.0), 0.0)
            flags = (R.GIMBAL_DEVICE_FLAGS_ROLL_LOCK | R.GIMBAL_DEVICE_FLAGS_PITCH_LOCK
                     | R.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME)
            return mav.MAVLink_gimbal_device_attitude_status_message(
                0, 0, tb, flags, list(q), 0.0, 0.0, 0.0, 0, 0.0, 0.0, 1)
        return None


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x))))


def _param_name(raw: bytes | str) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return raw.split("\x00", 1)[0]
