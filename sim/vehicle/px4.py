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
  in AUTO.LOITER;
- the land detector disarms COM_DISARM_LAND seconds after touchdown in ANY mode once the vehicle
  has flown since arming ("Disarmed by landing"); the heartbeat keeps the mode it was in (e.g.
  OFFBOARD). Armed on the ground without a flight it disarms after COM_DISARM_PRFLT
  (``idle_disarm_s``). Failsafes (offboard loss included) only act while armed;
- the local frame is the EKF origin's, ``AutopilotConfig.origin_alt_offset_m`` = home_alt -
  ref_alt below home (LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED,
  HOME_POSITION x/y/z). SET_POSITION_TARGET_GLOBAL_INT is converted as mavlink_receiver.cpp
  does (1.15, unchanged in 1.16/1.17): frame GLOBAL_INT (5) ``z = ref_alt - alt`` and
  GLOBAL_TERRAIN_ALT_INT (11) ``z = ref_alt - (alt + terrain_alt)``, both correct, but
  GLOBAL_RELATIVE_ALT_INT (6) ``z = (home_alt - alt) - ref_alt``, off by ``+2 * (home_alt -
  ref_alt)`` in z (down): the target comes out that much too low, or too high when home is
  below the origin (SIH: home 1.48 m below, targets ~3 m too high); any other frame is
  discarded (counted ``setpoints_invalid``);
- POSITION_TARGET_GLOBAL_INT (1 Hz) carries the navigator's target in AUTO modes in flight only:
  never in OFFBOARD (the navigator's triplet is invalid there), POSCTL/ALTCTL, or on the ground;
- while disarmed HOME_POSITION wanders with the pre-arming estimate (a seeded random walk of a
  few centimetres to decimetres); at arming home is the configured one and stays fixed. Only the
  report wanders: the world frame, GLOBAL_POSITION_INT relative_alt and every conversion use the
  configured home;
- failsafes go through PX4's failsafe framework: battery LOW is a warning only (STATUSTEXT,
  BATTERY_STATUS charge_state LOW, no mode change); battery CRITICAL, RC loss and GCS loss
  switch to AUTO.LOITER (hold) at once and to their action (``failsafe_action``, AUTO.LAND by
  default) after COM_FAIL_ACT_T seconds. A mode change the user asks for during that hold
  (DO_SET_MODE / SET_MODE / NAV_LAND / NAV_RTL / DO_REPOSITION) cancels the action; the
  failsafe stays latched in system_status. Offboard loss acts at once (COM_OF_LOSS_T is its
  delay).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.autopilot import Autopilot, AutopilotConfig, Behaviour, Channel, MAVMessage, Setpoint
from sim.vehicle.faults import Failsafe
from sim.vehicle.kinematics import Vehicle

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


@dataclass
class Px4FailsafeConfig:
    """PX4's failsafe framework timing, seconds."""

    action_delay_s: float = 5.0   # COM_FAIL_ACT_T: hold this long before the failsafe action

    def __post_init__(self) -> None:
        if not (math.isfinite(self.action_delay_s) and self.action_delay_s >= 0.0):
            raise ValueError(f"action_delay_s must be >= 0 seconds, got {self.action_delay_s!r}")


@dataclass
class _PendingAction:
    """A failsafe action waiting out COM_FAIL_ACT_T in hold: due at ``due`` (simulator s)."""

    kinds: set[Failsafe]
    due: float
    target: Behaviour


class HomeWander:
    """The pre-arming home estimate's drift: a seeded, mean-reverting random walk in world NED m.

    The walk takes one step every ``step_s`` seconds of simulator time since start, generated
    lazily and in order, so a seed gives the same sequence however often it is read. The
    stationary spread is about ``sigma / sqrt(1 - decay**2)``: ~10 cm horizontally and ~20 cm
    vertically with the defaults, the centimetres-to-decimetres PX4 SIH shows before arming.
    """

    def __init__(self, seed: int | None, step_s: float = 1.0, sigma_xy_m: float = 0.06,
                 sigma_z_m: float = 0.12, decay: float = 0.8) -> None:
        self._rng = np.random.default_rng(seed)
        self.step_s = step_s
        self._sigma = np.array([sigma_xy_m, sigma_xy_m, sigma_z_m])
        self._decay = decay
        self._index = -1
        self._offset = np.zeros(3)

    def at(self, t: float) -> np.ndarray:
        """The offset (north, east, down m) at ``t`` seconds after start."""
        index = max(0, int(t // self.step_s))
        while self._index < index:
            self._offset = self._offset * self._decay + self._rng.normal(0.0, self._sigma)
            self._index += 1
        return self._offset.copy()


class Px4Multicopter(Autopilot):
    """The PX4 multicopter flavour."""

    MAV_AUTOPILOT = mav.MAV_AUTOPILOT_PX4
    FLAVOUR = "px4"
    LAND_DISARM_S = 2.0  # COM_DISARM_LAND
    LANDED_DISARM_TEXT = "Disarmed by landing"
    IDLE_DISARM_TEXT = "Disarmed by auto preflight disarming"

    def __init__(self, vehicle: Vehicle, config: AutopilotConfig | None = None,
                 start_time: float = 0.0, offboard: OffboardConfig | None = None,
                 failsafe: Px4FailsafeConfig | None = None, seed: int | None = None) -> None:
        self.offboard = offboard or OffboardConfig()
        self.failsafe_config = failsafe or Px4FailsafeConfig()
        self._stream_start: float | None = None
        self._last_setpoint_t: float | None = None
        self._last_setpoint: Setpoint | None = None
        self._offboard_failsafe = False
        self._pending: _PendingAction | None = None
        self._home_wander = HomeWander(seed)
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

    # ----- frames -----

    def origin_down_m(self) -> float:
        # The EKF origin is origin_alt_offset_m below home: world down = home_alt - AMSL.
        return self.config.origin_alt_offset_m

    def global_target_down(self, frame: int, alt: float) -> float | None:
        """World down (m) of a SET_POSITION_TARGET_GLOBAL_INT altitude, as PX4 converts it.

        mavlink_receiver.cpp computes the local z (origin ref_alt AMSL) and only for frames 5, 6
        and 11; world down = z_local + origin_down_m(). Frame 6 uses (home_alt - alt) - ref_alt
        where ref_alt - home_alt - alt is right, so it lands 2 * (home_alt - ref_alt) off.
        """
        c = self.config
        ref_alt = c.home_alt - c.origin_alt_offset_m
        if frame == mav.MAV_FRAME_GLOBAL_INT:
            z_local = ref_alt - alt
        elif frame == mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT:
            z_local = (c.home_alt - alt) - ref_alt  # PX4's formula, wrong unless home = origin
        elif frame == mav.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT:
            z_local = ref_alt - (alt + c.home_alt)  # terrain: flat at home's height here
        else:
            return None  # PX4 exact-matches 5 / 6 / 11 and drops the rest
        return z_local + self.origin_down_m()

    def reported_home(self) -> tuple[float, float, float]:
        if self.vehicle.state.armed:
            return 0.0, 0.0, 0.0  # set at arming: the configured home, fixed while armed
        n, e, d = self._home_wander.at(self.now - self.start_time)
        return float(n), float(e), float(d)

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
            mav.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT: 1.0,
            mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS: 5.0,
        }

    def supported_messages(self) -> set[int]:
        return super().supported_messages() | {mav.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT}

    def build(self, msg_id: int) -> MAVMessage | None:
        if msg_id == mav.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT:
            return self._navigator_target()
        return super().build(msg_id)

    def _navigator_target(self) -> MAVMessage | None:
        """POSITION_TARGET_GLOBAL_INT: the navigator's current target, AUTO modes in flight only.

        PX4 sends it from position_setpoint_triplet.current, which the navigator invalidates
        outside its own (AUTO) modes: nothing in OFFBOARD or POSCTL, nothing on the ground.
        """
        if not self.flying or self.behaviour in (Behaviour.GUIDED, Behaviour.MANUAL):
            return None
        v, s = self.vehicle, self.vehicle.state
        lat, lon, alt = self.geo.to_global(*(float(x) for x in v.target_position))
        yaw = v.target_yaw if v.target_yaw is not None else s.yaw
        vn, ve, vd = (float(x) for x in s.velocity)
        return mav.MAVLink_position_target_global_int_message(
            self.time_boot_ms, mav.MAV_FRAME_GLOBAL_INT, 0, int(round(lat * 1e7)),
            int(round(lon * 1e7)), alt, vn, ve, vd, 0.0, 0.0, 0.0, yaw, 0.0)

    def flight_sw_version(self) -> int:
        return (1 << 24) | (15 << 16) | (0 << 8) | mav.FIRMWARE_VERSION_TYPE_OFFICIAL

    def refused(self) -> int:
        return mav.MAV_RESULT_TEMPORARILY_REJECTED

    def system_status(self) -> int:
        status = super().system_status()
        if self.failsafes == {Failsafe.BATTERY_LOW} and not self._offboard_failsafe:
            # A low battery is only a warning to PX4 (no failsafe state): the heartbeat stays
            # ACTIVE, so a companion triggering on CRITICAL/EMERGENCY does not act on it.
            s = self.vehicle.state
            return mav.MAV_STATE_ACTIVE if s.armed and not s.land_complete else mav.MAV_STATE_STANDBY
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
        self._run_pending_failsafe(now)
        # PX4's failsafe framework only acts while armed: disarmed by landing in OFFBOARD with the
        # stream stopped, the heartbeat stays OFFBOARD.
        if (self.custom_mode != OFFBOARD or self._last_setpoint_t is None
                or not self.vehicle.state.armed):
            return
        if now - self._last_setpoint_t > self.offboard.loss_timeout_s:
            self._offboard_failsafe = True
            self._say(mav.MAV_SEVERITY_CRITICAL, f"Offboard lost: {self.offboard.loss_action}")
            target = {"land": Behaviour.LAND, "hold": Behaviour.HOLD,
                      "rtl": Behaviour.RTL}[self.offboard.loss_action]
            self.set_mode(self.mode_for(target))

    # ----- failsafes (PX4's failsafe framework) -----

    def disarms_when_landed(self, behaviour: Behaviour) -> bool:
        # Commander: COM_DISARM_LAND after a takeoff in any mode, else COM_DISARM_PRFLT.
        return self._has_flown

    def react_to_failsafe(self, kind: Failsafe) -> None:
        """Battery low: warn only. Others: hold now, the action after COM_FAIL_ACT_T."""
        if kind is Failsafe.BATTERY_LOW:
            self._say(mav.MAV_SEVERITY_WARNING, "Low battery level! Return advised")
            return
        target = self.failsafe_target(kind)
        delay = self.failsafe_config.action_delay_s
        if target is None or delay <= 0.0:
            super().react_to_failsafe(kind)  # nothing to change, or act at once (COM_FAIL_ACT_T 0)
            return
        action = self.config.failsafe_action.get(kind, "land")
        pending = self._pending
        if pending is None:
            pending = self._pending = _PendingAction({kind}, self.now + delay, target)
            self.set_mode(AUTO_LOITER)
        else:
            # Another failsafe during the hold joins it (same deadline); land outranks return.
            pending.kinds.add(kind)
            if target is Behaviour.LAND:
                pending.target = Behaviour.LAND
        left = pending.due - self.now
        self._say(mav.MAV_SEVERITY_CRITICAL,
                  f"Failsafe {kind.value}: hold, {action.upper()} in {left:.0f} s")

    def _run_pending_failsafe(self, now: float) -> None:
        p = self._pending
        if p is None or now < p.due:
            return
        self._pending = None
        if not self.flying or self.behaviour is Behaviour.LAND or self.behaviour is p.target:
            return
        name = "LAND" if p.target is Behaviour.LAND else "RTL"
        kinds = "+".join(sorted(k.value for k in p.kinds))
        self._say(mav.MAV_SEVERITY_CRITICAL, f"Failsafe {kinds}: {name}")
        self.set_mode(self.mode_for(p.target))

    def _user_takeover(self) -> None:
        """A mode change the user asked for: it cancels a failsafe action still on hold."""
        if self._pending is not None:
            self._say(mav.MAV_SEVERITY_WARNING, "Failsafe action cancelled: user took over")
            self._pending = None
        self._offboard_failsafe = False

    def clear_failsafe(self, kind: Failsafe) -> None:
        super().clear_failsafe(kind)
        p = self._pending
        if p is not None:
            p.kinds.discard(kind)
            if not p.kinds:
                self._pending = None  # the condition went away during the hold: stay in hold

    def disarm(self) -> None:
        super().disarm()
        self._pending = None

    # ----- mode changes and commands -----

    def request_mode(self, custom_mode: int) -> int:
        behaviour = self.behaviour_of(custom_mode)
        if behaviour is None:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        if custom_mode == OFFBOARD and not self.offboard_signal_ok():
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        if custom_mode == AUTO_TAKEOFF and not self.vehicle.state.land_complete:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        self._user_takeover()
        self.set_mode(custom_mode)
        if custom_mode == OFFBOARD and self._last_setpoint is not None:
            self._follow(self._last_setpoint)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
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

    def _cmd_reposition(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        if not self.flying:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        frame = int(msg.frame) if is_int else mav.MAV_FRAME_GLOBAL
        target = self._reposition_target(p, is_int, frame)
        self._user_takeover()  # Commander takes a reposition as the user's mode intention
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
            "COM_FAIL_ACT_T": self.failsafe_config.action_delay_s,
        }

    def set_param(self, name: str, value: float) -> None:
        vp = self.vehicle.params
        if name == "COM_FAIL_ACT_T":
            if value >= 0:  # 0 is valid: act at once, no hold
                self.failsafe_config.action_delay_s = value
            return
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
