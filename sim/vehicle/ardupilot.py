"""ArduPilot Copter behaviour: its mode numbers, command results and GUIDED target rules.

What the companion can observe of ArduPilot Copter 4.5 and what this model does:
- custom_mode is the Copter mode number (STABILIZE 0, ALT_HOLD 2, GUIDED 4, LOITER 5, RTL 6,
  LAND 9, POSHOLD 16, BRAKE 17); an unknown number or a refused change acks MAV_RESULT_FAILED.
- position targets (SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT) are obeyed only in GUIDED and
  only in flight; elsewhere they are silently ignored, as the firmware does.
- NAV_TAKEOFF works only in GUIDED, armed and landed (altitude param7 relative to home).
- LAND descends where the vehicle is and disarms as soon as the land detector fires.
- a failsafe switches to LAND or RTL by itself and the heartbeat shows MAV_STATE_CRITICAL; with
  FS_OPTIONS "continue in GUIDED" style set-up the companion may take over with GUIDED again.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.autopilot import Autopilot, Behaviour, Channel, MAVMessage, Setpoint
from sim.vehicle.kinematics import Demand

STABILIZE, ALT_HOLD, GUIDED, LOITER, RTL, LAND, POSHOLD, BRAKE = 0, 2, 4, 5, 6, 9, 16, 17

MODES: dict[int, Behaviour] = {
    STABILIZE: Behaviour.MANUAL, ALT_HOLD: Behaviour.MANUAL, GUIDED: Behaviour.GUIDED,
    LOITER: Behaviour.HOLD, RTL: Behaviour.RTL, LAND: Behaviour.LAND, POSHOLD: Behaviour.HOLD,
    BRAKE: Behaviour.HOLD,
}
MODE_NAMES = {STABILIZE: "STABILIZE", ALT_HOLD: "ALT_HOLD", GUIDED: "GUIDED", LOITER: "LOITER",
              RTL: "RTL", LAND: "LAND", POSHOLD: "POSHOLD", BRAKE: "BRAKE"}
_ARMABLE = {STABILIZE, ALT_HOLD, GUIDED, LOITER, POSHOLD}
# Copter sets GUIDED_ENABLED in base_mode for its navigating modes.
_GUIDED_FLAG_MODES = {GUIDED, LOITER, RTL, POSHOLD, BRAKE}


class ArduPilotCopter(Autopilot):
    """The ArduPilot Copter flavour."""

    MAV_AUTOPILOT = mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    FLAVOUR = "ardupilot"
    GUID_TIMEOUT_S = 3.0  # velocity targets older than this stop the vehicle (GUID_TIMEOUT)
    _last_velocity_target: float | None = None

    def initial_mode(self) -> int:
        return LOITER if not self.vehicle.state.land_complete else STABILIZE

    def behaviour_of(self, custom_mode: int) -> Behaviour | None:
        return MODES.get(custom_mode)

    def mode_for(self, behaviour: Behaviour) -> int:
        return {Behaviour.LAND: LAND, Behaviour.RTL: RTL, Behaviour.HOLD: LOITER,
                Behaviour.GUIDED: GUIDED, Behaviour.MANUAL: STABILIZE,
                Behaviour.TAKEOFF: GUIDED}[behaviour]

    def mode_name(self, custom_mode: int | None = None) -> str:
        m = self.custom_mode if custom_mode is None else custom_mode
        return MODE_NAMES.get(m, str(m))

    def base_mode_flags(self) -> int:
        flags = mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.custom_mode in _GUIDED_FLAG_MODES:
            flags |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        return flags

    def default_rates(self) -> dict[int, float]:
        # Roughly the SRx_* stream rates a companion port is set up with.
        return {
            mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0, mav.MAVLINK_MSG_ID_ATTITUDE: 10.0,
            mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 5.0,
            mav.MAVLINK_MSG_ID_SYS_STATUS: 2.0, mav.MAVLINK_MSG_ID_BATTERY_STATUS: 2.0,
            mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0, mav.MAVLINK_MSG_ID_DISTANCE_SENSOR: 2.0,
            mav.MAVLINK_MSG_ID_GPS_RAW_INT: 2.0, mav.MAVLINK_MSG_ID_VFR_HUD: 4.0,
            mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS: 10.0,
        }

    def flight_sw_version(self) -> int:
        return (4 << 24) | (5 << 16) | (7 << 8) | mav.FIRMWARE_VERSION_TYPE_OFFICIAL

    def system_status(self) -> int:
        # Copter reports CRITICAL for any failsafe (vehicle_system_status), never EMERGENCY.
        if self.failsafes:
            return mav.MAV_STATE_CRITICAL
        return super().system_status()

    def can_arm(self) -> bool:
        return super().can_arm() and self.custom_mode in _ARMABLE

    def request_mode(self, custom_mode: int) -> int:
        if self.behaviour_of(custom_mode) is None:
            return mav.MAV_RESULT_FAILED
        self.set_mode(custom_mode)
        return mav.MAV_RESULT_ACCEPTED

    def handle_setpoint(self, sp: Setpoint) -> None:
        if self.behaviour is not Behaviour.GUIDED or not self.flying:
            self.counters["setpoints_ignored"] += 1
            return
        self._last_velocity_target = self.now if sp.position is None else None
        self.apply_setpoint(sp)

    def on_tick(self, now: float) -> None:
        t = self._last_velocity_target
        if t is not None and now - t > self.GUID_TIMEOUT_S:
            self._last_velocity_target = None
            if self.behaviour is Behaviour.GUIDED and self.vehicle.demand is Demand.VELOCITY:
                self.vehicle.hold()

    def _cmd_takeoff(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        alt = float(p[6])
        if (self.custom_mode != GUIDED or not self.vehicle.state.armed
                or not self.vehicle.state.land_complete or not math.isfinite(alt) or alt <= 0):
            return mav.MAV_RESULT_FAILED
        self._start_takeoff(alt)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_reposition(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        change_mode = int(p[1]) & mav.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE if math.isfinite(p[1]) else 0
        if self.custom_mode != GUIDED and not change_mode:
            return mav.MAV_RESULT_DENIED
        if not self.flying:
            return mav.MAV_RESULT_FAILED
        frame = int(msg.frame) if is_int else mav.MAV_FRAME_GLOBAL
        target = self._reposition_target(p, is_int, frame)
        if self.custom_mode != GUIDED:
            self.set_mode(GUIDED)
        self.vehicle.fly_to(*target)
        return mav.MAV_RESULT_ACCEPTED

    def params(self) -> dict[str, float]:
        vp = self.vehicle.params
        return {
            "SYSID_THISMAV": float(self.config.system_id),
            "WPNAV_SPEED": vp.max_speed_xy * 100.0,
            "WPNAV_SPEED_UP": vp.max_speed_up * 100.0,
            "WPNAV_SPEED_DN": vp.max_speed_down * 100.0,
            "LAND_SPEED": vp.land_speed * 100.0,
            "LAND_SPEED_HIGH": vp.land_speed_high * 100.0,
            "RTL_ALT": self.config.rtl_alt * 100.0,
            "DISARM_DELAY": self.config.idle_disarm_s,
            "FS_OPTIONS": 0.0,
        }

    def set_param(self, name: str, value: float) -> None:
        vp = self.vehicle.params
        if value <= 0 and name not in ("FS_OPTIONS", "DISARM_DELAY"):
            return
        if name == "WPNAV_SPEED":
            vp.max_speed_xy = value / 100.0
            self.vehicle.speed_xy = vp.max_speed_xy
        elif name == "WPNAV_SPEED_UP":
            vp.max_speed_up = value / 100.0
        elif name == "WPNAV_SPEED_DN":
            vp.max_speed_down = value / 100.0
        elif name == "LAND_SPEED":
            vp.land_speed = value / 100.0
        elif name == "LAND_SPEED_HIGH":
            vp.land_speed_high = value / 100.0
        elif name == "RTL_ALT":
            self.config.rtl_alt = value / 100.0
        elif name == "DISARM_DELAY":
            self.config.idle_disarm_s = max(0.0, value)
