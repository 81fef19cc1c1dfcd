"""PX4 multicopter behaviour: its custom_mode encoding, OFFBOARD rules and command results.

PX4 packs its mode into HEARTBEAT.custom_mode as ``main_mode << 16 | sub_mode << 24``
(``px4_custom_mode.h``: a union of reserved:16, main_mode:8, sub_mode:8). MAV_CMD_DO_SET_MODE
carries main mode in param2 and sub mode in param3. Main modes: MANUAL 1, ALTCTL 2, POSCTL 3,
AUTO 4, ACRO 5, OFFBOARD 6, STABILIZED 7; AUTO sub modes: READY 1, TAKEOFF 2, LOITER 3,
MISSION 4, RTL 5, LAND 6, PRECLAND 9.

What the companion can observe and this model reproduces:
- a refused mode change (OFFBOARD without a setpoint stream, a mode needing RC, an unknown mode)
  acks MAV_RESULT_TEMPORARILY_REJECTED, as Commander does for a denied transition;
- OFFBOARD needs setpoints (SET_POSITION_TARGET_*) streaming at more than 2 Hz for about a
  second before the switch; setpoints outside OFFBOARD only keep that stream alive;
- in OFFBOARD, no setpoint for COM_OF_LOSS_T seconds triggers the offboard-loss failsafe
  (COM_OBL_RC_ACT style: land, hold or return), shown as MAV_STATE_CRITICAL;
- NAV_TAKEOFF switches to AUTO.TAKEOFF (altitude param7 AMSL, else MIS_TAKEOFF_ALT), which ends
  in AUTO.LOITER; after landing it disarms after COM_DISARM_LAND seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.autopilot import Autopilot, AutopilotConfig, Behaviour, Setpoint
from sim.vehicle import Vehicle

MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD, MAIN_STABILIZED = (
    1, 2, 3, 4, 5, 6, 7)
SUB_READY, SUB_TAKEOFF, SUB_LOITER, SUB_MISSION, SUB_RTL, SUB_LAND = 1, 2, 3, 4, 5, 6


def px4_mode(main: int, sub: int = 0) -> int:
    """HEARTBEAT.custom_mode of a PX4 main/sub mode pair."""
    return (main << 16) | (sub << 24)


def px4_split(custom_mode: int) -> tuple[int, int]:
    """(main, sub) of a PX4 custom_mode."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


POSCTL = px4_mode(MAIN_POSCTL)
ALTCTL = px4_mode(MAIN_ALTCTL)
OFFBOARD = px4_mode(MAIN_OFFBOARD)
AUTO_TAKEOFF = px4_mode(MAIN_AUTO, SUB_TAKEOFF)
AUTO_LOITER = px4_mode(MAIN_AUTO, SUB_LOITER)
AUTO_RTL = px4_mode(MAIN_AUTO, SUB_RTL)
AUTO_LAND = px4_mode(MAIN_AUTO, SUB_LAND)

MODES: dict[int, Behaviour] = {
    POSCTL: Behaviour.MANUAL, ALTCTL: Behaviour.MANUAL, OFFBOARD: Behaviour.GUIDED,
    AUTO_TAKEOFF: Behaviour.TAKEOFF, AUTO_LOITER: Behaviour.HOLD, AUTO_RTL: Behaviour.RTL,
    AUTO_LAND: Behaviour.LAND,
}
MODE_NAMES = {POSCTL: "POSCTL", ALTCTL: "ALTCTL", OFFBOARD: "OFFBOARD",
              AUTO_TAKEOFF: "AUTO.TAKEOFF", AUTO_LOITER: "AUTO.LOITER", AUTO_RTL: "AUTO.RTL",
              AUTO_LAND: "AUTO.LAND"}
_ARMABLE = {POSCTL, ALTCTL, OFFBOARD, AUTO_TAKEOFF, AUTO_LOITER}


@dataclass
class OffboardConfig:
    """PX4's offboard rules. Seconds; ``loss_action`` is ``"land"``, ``"hold"`` or ``"rtl"``."""

    loss_timeout_s: float = 1.0   # COM_OF_LOSS_T
    max_gap_s: float = 0.5        # a gap longer than this means the stream is below 2 Hz
    warmup_s: float = 1.0         # streaming this long before OFFBOARD is accepted
    loss_action: str = "land"     # COM_OBL_RC_ACT (no RC: land / hold / return)

    def __post_init__(self) -> None:
        if self.loss_action not in ("land", "hold", "rtl"):
            raise ValueError(f"offboard loss_action must be land, hold or rtl, got {self.loss_action!r}")


class Px4Multicopter(Autopilot):
    """The PX4 multicopter flavour."""

    MAV_AUTOPILOT = mav.MAV_AUTOPILOT_PX4
    FLAVOUR = "px4"
    LAND_DISARM_S = 2.0  # COM_DISARM_LAND

    def __init__(self, vehicle: Vehicle, config: AutopilotConfig | None = None,
                 start_time: float = 0.0, offboard: OffboardConfig | None = None) -> None:
        self.offboard = offboard or OffboardConfig()
        self._stream_start: float | None = None
        self._last_setpoint_t: float | None = None
        self._last_setpoint: Setpoint | None = None
        self._offboard_failsafe = False
        super().__init__(vehicle, config, start_time)

    def initial_mode(self) -> int:
        return AUTO_LOITER if not self.vehicle.state.land_complete else POSCTL

    def behaviour_of(self, custom_mode: int) -> Behaviour | None:
        return MODES.get(custom_mode)

    def mode_for(self, behaviour: Behaviour) -> int:
        return {Behaviour.LAND: AUTO_LAND, Behaviour.RTL: AUTO_RTL, Behaviour.HOLD: AUTO_LOITER,
                Behaviour.GUIDED: OFFBOARD, Behaviour.MANUAL: POSCTL,
                Behaviour.TAKEOFF: AUTO_TAKEOFF}[behaviour]

    def mode_name(self, custom_mode: int | None = None) -> str:
        m = self.custom_mode if custom_mode is None else custom_mode
        return MODE_NAMES.get(m, hex(m))

    def mode_from_command(self, main: float, sub: float) -> int:
        main_i = int(main) if math.isfinite(main) else 0
        sub_i = int(sub) if math.isfinite(sub) else 0
        return px4_mode(main_i & 0xFF, sub_i & 0xFF)

    def base_mode_flags(self) -> int:
        flags = mav.MAV_MODE_FLAG_STABILIZE_ENABLED | mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.custom_mode in (POSCTL, ALTCTL):
            flags |= mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        else:
            flags |= mav.MAV_MODE_FLAG_AUTO_ENABLED
        return flags

    def default_rates(self) -> dict[int, float]:
        # PX4's "normal" MAVLink mode stream set (the GCS/companion UDP port).
        return {
            mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0, mav.MAVLINK_MSG_ID_ATTITUDE: 20.0,
            mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 10.0,
            mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 5.0,
            mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0, mav.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
            mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0, mav.MAVLINK_MSG_ID_DISTANCE_SENSOR: 1.0,
            mav.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0, mav.MAVLINK_MSG_ID_VFR_HUD: 4.0,
            mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
            mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS: 5.0,
        }

    def flight_sw_version(self) -> int:
        return (1 << 24) | (15 << 16) | (0 << 8) | mav.FIRMWARE_VERSION_TYPE_OFFICIAL

    def refused(self) -> int:
        return mav.MAV_RESULT_TEMPORARILY_REJECTED

    def system_status(self) -> int:
        status = super().system_status()
        if self._offboard_failsafe and status < mav.MAV_STATE_CRITICAL:
            return mav.MAV_STATE_CRITICAL
        return status

    def can_arm(self) -> bool:
        if self.custom_mode == OFFBOARD and not self.offboard_signal_ok():
            return False
        return super().can_arm() and self.custom_mode in _ARMABLE

    def arm(self) -> None:
        super().arm()
        if self.custom_mode == AUTO_TAKEOFF:
            self._start_takeoff(self.config.takeoff_alt)

    # ----- offboard -----

    def offboard_signal_ok(self) -> bool:
        """Setpoints have streamed above 2 Hz for the warm-up time and are still coming."""
        if self._stream_start is None or self._last_setpoint_t is None:
            return False
        return (self.now - self._last_setpoint_t <= self.offboard.max_gap_s
                and self._last_setpoint_t - self._stream_start >= self.offboard.warmup_s)

    def handle_setpoint(self, sp: Setpoint) -> None:
        now = self.now
        if self._last_setpoint_t is None or now - self._last_setpoint_t > self.offboard.max_gap_s:
            self._stream_start = now
        self._last_setpoint_t = now
        self._last_setpoint = sp
        if self.custom_mode != OFFBOARD:
            self.counters["setpoints_ignored"] += 1
            return
        self._follow(sp)

    def _follow(self, sp: Setpoint) -> None:
        v = self.vehicle
        if not v.state.armed:
            return
        if v.state.land_complete:
            wants_up = (sp.position is not None and sp.position[2] < -0.5) or (
                sp.position is None and sp.velocity is not None and sp.velocity[2] < -0.1)
            if not wants_up:
                return
            v.take_off(1.0)
        self.apply_setpoint(sp)

    def on_tick(self, now: float) -> None:
        if self.custom_mode != OFFBOARD or self._last_setpoint_t is None:
            return
        if now - self._last_setpoint_t > self.offboard.loss_timeout_s:
            self._offboard_failsafe = True
            self._say(mav.MAV_SEVERITY_CRITICAL, f"Offboard lost: {self.offboard.loss_action}")
            target = {"land": Behaviour.LAND, "hold": Behaviour.HOLD,
                      "rtl": Behaviour.RTL}[self.offboard.loss_action]
            self.set_mode(self.mode_for(target))

    # ----- mode changes and commands -----

    def request_mode(self, custom_mode: int) -> int:
        behaviour = self.behaviour_of(custom_mode)
        if behaviour is None:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        if custom_mode == OFFBOARD and not self.offboard_signal_ok():
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        if custom_mode == AUTO_TAKEOFF and not self.vehicle.state.land_complete:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        self._offboard_failsafe = False  # the user took over
        self.set_mode(custom_mode)
        if custom_mode == OFFBOARD and self._last_setpoint is not None:
            self._follow(self._last_setpoint)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, p, channel, msg, is_int) -> int:
        if not self.vehicle.state.land_complete:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        alt_amsl = float(p[6])
        alt = alt_amsl - self.config.home_alt if math.isfinite(alt_amsl) else self.config.takeoff_alt
        if alt <= 0.5:
            alt = self.config.takeoff_alt
        self.set_mode(AUTO_TAKEOFF)
        if self.vehicle.state.armed:
            self._start_takeoff(alt)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_reposition(self, p, channel, msg, is_int) -> int:
        if not self.flying:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        frame = int(msg.frame) if is_int else mav.MAV_FRAME_GLOBAL
        target = self._reposition_target(p, is_int, frame)
        self.set_mode(AUTO_LOITER)
        self.vehicle.fly_to(*target)
        return mav.MAV_RESULT_ACCEPTED

    def params(self) -> dict[str, float]:
        vp = self.vehicle.params
        return {
            "MAV_SYS_ID": float(self.config.system_id),
            "MPC_XY_CRUISE": vp.max_speed_xy,
            "MPC_Z_VEL_MAX_UP": vp.max_speed_up,
            "MPC_Z_VEL_MAX_DN": vp.max_speed_down,
            "MPC_LAND_SPEED": vp.land_speed,
            "MIS_TAKEOFF_ALT": self.config.takeoff_alt,
            "RTL_RETURN_ALT": self.config.rtl_alt,
            "COM_OF_LOSS_T": self.offboard.loss_timeout_s,
            "COM_DISARM_LAND": self.LAND_DISARM_S,
        }

    def set_param(self, name: str, value: float) -> None:
        vp = self.vehicle.params
        if value <= 0:
            return
        if name == "MPC_XY_CRUISE":
            vp.max_speed_xy = value
            self.vehicle.speed_xy = value
        elif name == "MPC_Z_VEL_MAX_UP":
            vp.max_speed_up = value
        elif name == "MPC_Z_VEL_MAX_DN":
            vp.max_speed_down = value
        elif name == "MPC_LAND_SPEED":
            vp.land_speed = value
        elif name == "MIS_TAKEOFF_ALT":
            self.config.takeoff_alt = value
        elif name == "RTL_RETURN_ALT":
            self.config.rtl_alt = value
        elif name == "COM_OF_LOSS_T":
            self.offboard.loss_timeout_s = value
