"""Incoming messages and commands: dispatch, COMMAND_ACK results, SET_MODE, position targets.

``handle_message`` routes what a peer sends; COMMAND_LONG / COMMAND_INT go through one dispatcher
that acks every command with its MAV_RESULT; SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT are
parsed into world-frame ``Setpoint``s that the flavour's ``handle_setpoint`` applies or ignores.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.autopilot.base import (
    AutopilotConfig,
    Behaviour,
    Channel,
    GeoFrame,
    MAVMessage,
    MixinBase,
    R,
    Setpoint,
)
from sim.vehicle.kinematics import Vehicle

log = logging.getLogger(__name__)

# SET_POSITION_TARGET_* type_mask bits (POSITION_TARGET_TYPEMASK).
_IGNORE_POS = 0b111
_IGNORE_VEL = 0b111 << 3
_IGNORE_ACC = 0b111 << 6
_IGNORE_YAW = 1 << 10


class CommandsMixin(ABC, MixinBase):
    """What the autopilot does with a message from a peer (part of ``Autopilot``)."""

    # Set by ``Autopilot.__init__``.
    vehicle: Vehicle
    config: AutopilotConfig
    geo: GeoFrame
    now: float
    start_time: float
    counters: dict[str, int]

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
        elif t == "TIMESYNC":
            # As ArduPilot's and PX4's handlers: a request (tc1 = 0) is answered at once with
            # our boot time in ns and the sender's ts1 echoed; answers to requests we never
            # sent are ignored.
            if msg.tc1 == 0:
                self.counters["timesync"] += 1
                channel.send(mav.MAVLink_timesync_message(int((self.now - self.start_time) * 1e9), msg.ts1))
        elif t in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
            self._handle_param(msg, channel)
        else:
            self.counters["messages_ignored"] += 1

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
            if frame not in (R.MAV_FRAME_LOCAL_OFFSET_NED, R.MAV_FRAME_BODY_NED, R.MAV_FRAME_BODY_OFFSET_NED,
                             R.MAV_FRAME_BODY_FRD):
                pos[2] += self.config.alt_bias_m  # an altitude in the estimator's belief (alt_bias_m)
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
            north, east, down = sp.position
            v.fly_to(north, east, down, yaw=sp.yaw)
        elif sp.velocity is not None:
            vn, ve, vd = sp.velocity
            v.fly_velocity(vn, ve, vd, yaw=sp.yaw)

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

    def _cmd_set_message_interval(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
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

    def _cmd_get_message_interval(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        msg_id = int(p[0])
        if msg_id not in self.known_messages():
            return R.MAV_RESULT_DENIED
        channel.send(mav.MAVLink_message_interval_message(msg_id, channel.streams.interval_us(msg_id)))
        return R.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int | None:
        msg_id = int(p[0])
        out = self.build(msg_id)
        if out is None:
            return R.MAV_RESULT_DENIED
        # Ack first, then the message, as ArduPilot and PX4 both do.
        self._ack(channel, msg, R.MAV_RESULT_ACCEPTED)
        channel.send(out)
        return None

    def _cmd_request_capabilities(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int | None:
        self._ack(channel, msg, R.MAV_RESULT_ACCEPTED)
        channel.send(self.build(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION))
        return None

    def _cmd_get_home(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int | None:
        self._ack(channel, msg, R.MAV_RESULT_ACCEPTED)
        channel.send(self.build(mav.MAVLINK_MSG_ID_HOME_POSITION))
        return None

    def _cmd_arm_disarm(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
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

    def refused(self) -> int:
        """The result a flavour acks a refused state change with."""
        return R.MAV_RESULT_FAILED

    @abstractmethod
    def _cmd_takeoff(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int: ...

    def _cmd_land(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        return self.request_mode(self.mode_for(Behaviour.LAND))

    def _cmd_rtl(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        return self.request_mode(self.mode_for(Behaviour.RTL))

    def _cmd_set_mode(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        if not int(p[0]) & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return R.MAV_RESULT_UNSUPPORTED  # base-mode-only changes are not supported by either
        return self.request_mode(self.mode_from_command(p[1], p[2]))

    def _reposition_target(self, p: list[float], is_int: bool, frame: int) -> np.ndarray:
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
    def _cmd_reposition(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int: ...

    def _cmd_change_speed(self, p: list[float], channel: Channel, msg: MAVMessage, is_int: bool) -> int:
        speed = float(p[1])
        if not math.isfinite(speed) or speed == -1:
            return R.MAV_RESULT_ACCEPTED
        if speed <= 0:
            return R.MAV_RESULT_DENIED
        self.vehicle.speed_xy = min(speed, self.vehicle.params.max_speed_xy)
        return R.MAV_RESULT_ACCEPTED
