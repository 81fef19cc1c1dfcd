"""Telemetry: message construction, per-link stream defaults, STATUSTEXT and reported states."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.autopilot.base import (
    AutopilotConfig,
    Behaviour,
    GeoFrame,
    MAVMessage,
    MixinBase,
    R,
    StreamSchedule,
    quaternion_from_euler,
)
from sim.vehicle.faults import Failsafe
from sim.vehicle.kinematics import Demand, Vehicle


class TelemetryMixin(MixinBase):
    """The messages the autopilot sends and the states they report (part of ``Autopilot``)."""

    # Set by ``Autopilot.__init__``.
    vehicle: Vehicle
    config: AutopilotConfig
    geo: GeoFrame
    start_time: float
    now: float
    custom_mode: int
    failsafes: set[Failsafe]
    status_text: list[tuple[int, str]]

    @property
    def time_boot_ms(self) -> int:
        return int((self.now - self.start_time) * 1000) & 0xFFFFFFFF

    def known_messages(self) -> set[int]:
        """Messages the firmware has a stream for, sent or not (no gimbal: none goes out)."""
        return self.supported_messages() | {mav.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS}

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
            d_est = d - c.alt_bias_m  # where the estimator believes the vehicle is
            lat, lon, alt = self.geo.to_global(n, e, d_est)
            hdg = int(round(math.degrees(s.yaw) * 100)) % 36000
            return mav.MAVLink_global_position_int_message(
                tb, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
                int(round(-d_est * 1000)), _i16(vn * 100), _i16(ve * 100), _i16(vd * 100), hdg)
        if msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return mav.MAVLink_local_position_ned_message(tb, n, e, d - c.alt_bias_m - self.origin_down_m(),
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
                int(round(v.battery_remaining * 100)), self.battery_time_remaining_s(), self.charge_state())
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

    def system_status(self) -> int:
        s = self.vehicle.state
        if Failsafe.BATTERY_CRITICAL in self.failsafes:
            return R.MAV_STATE_EMERGENCY
        if self.failsafes:
            return R.MAV_STATE_CRITICAL
        if not s.armed or s.land_complete:
            return R.MAV_STATE_STANDBY
        return R.MAV_STATE_ACTIVE

    def battery_time_remaining_s(self) -> int:
        """BATTERY_STATUS.time_remaining (s): the charge left at the hover current. An injected
        LOW or CRITICAL failsafe counts as the charge at that level, so the time agrees with the
        charge state (a "critical" battery with 15 minutes left would be no failsafe at all)."""
        v = self.vehicle
        remaining = v.battery_remaining
        if Failsafe.BATTERY_CRITICAL in self.failsafes:
            remaining = min(remaining, self.config.battery_critical)
        elif Failsafe.BATTERY_LOW in self.failsafes:
            remaining = min(remaining, self.config.battery_low)
        amps = max(v.state.current_a, v.params.hover_current_a)
        return max(1, int(remaining * v.params.battery_capacity_mah / 1000.0 / amps * 3600.0))

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


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x))))
