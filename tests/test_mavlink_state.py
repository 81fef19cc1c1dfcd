"""Vehicle state: every telemetry message parsed over a real link; pose interpolation; staleness."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.geometry.geodesy import GeoPoint, geo_from_ned
from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.state import VehicleState
from tests.mavpeer import MavPeer

HOME = GeoPoint(47.397742, 8.545594, 488.0)
ENC = m.MAVLink(None, 1, 1)


def gpi(t_ms: int, north: float, east: float, up: float):
    p = geo_from_ned(HOME, north, east, -up)
    return m.MAVLink_global_position_int_message(
        t_ms, round(p.lat_deg * 1e7), round(p.lon_deg * 1e7), round(p.alt_m * 1e3), round(up * 1e3), 100, -50, 0, 9000
    )


def home_msg():
    return m.MAVLink_home_position_message(
        round(HOME.lat_deg * 1e7), round(HOME.lon_deg * 1e7), round(HOME.alt_m * 1e3), 0, 0, 0, [1, 0, 0, 0], 0, 0, 0
    )


def att(t_ms: int, roll: float, pitch: float, yaw: float):
    return m.MAVLink_attitude_message(t_ms, roll, pitch, yaw, 0, 0, 0)


def with_header(msg):
    """Give a locally built message the source ids a received one has."""
    msg.pack(ENC)
    return msg


async def test_every_message_type_is_parsed_into_the_state_over_the_link():
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, heartbeat_period_s=0.1))
    await link.start()
    peer = MavPeer(autopilot=m.MAV_AUTOPILOT_ARDUPILOTMEGA, custom_mode=4)
    state = VehicleState()
    state.attach(link)
    try:
        await peer.connect_udp(link.local_address)
        peer.heartbeat()
        await link.wait_connected(2.0)
        peer.mav.send(home_msg())
        peer.mav.send(att(1000, 0.1, -0.05, 1.5))
        peer.mav.send(gpi(1000, 12.0, -7.0, 25.0))
        peer.mav.extended_sys_state_send(m.MAV_VTOL_STATE_UNDEFINED, m.MAV_LANDED_STATE_IN_AIR)
        peer.mav.sys_status_send(0, 0, 0, 500, 15800, 1200, 63, 0, 0, 0, 0, 0, 0)
        peer.mav.battery_status_send(
            0, 0, 0, 2500, [4000, 4000, 3900] + [65535] * 7, 1200, 100, 100, 40, 600, m.MAV_BATTERY_CHARGE_STATE_LOW
        )
        peer.mav.distance_sensor_send(1000, 20, 4000, 2480, 0, 0, m.MAV_SENSOR_ROTATION_PITCH_270, 0)
        q = [math.cos(-math.pi / 4), 0.0, math.sin(-math.pi / 4), 0.0]  # pitched 90 deg down
        peer.mav.gimbal_device_attitude_status_send(1, 191, 1000, m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, q, 0, 0, 0, 0)
        for _ in range(200):
            if state.gimbal is not None:
                break
            await asyncio.sleep(0.01)
        assert state.heartbeat.custom_mode == 4 and state.armed is True
        assert state.heartbeat.system_status == m.MAV_STATE_ACTIVE
        assert state.home.point.lat_deg == pytest.approx(HOME.lat_deg, abs=1e-7)
        assert state.attitude.yaw == pytest.approx(1.5)
        assert state.position.relative_alt_m == pytest.approx(25.0)
        n, e, d = state.local_ned()
        assert (n, e, d) == pytest.approx((12.0, -7.0, -25.0), abs=0.02)
        assert state.altitude_above_home() == pytest.approx(25.0)
        assert state.landed.landed_state == m.MAV_LANDED_STATE_IN_AIR and not state.landed.on_ground
        assert state.sys_status_battery.remaining_pct == 63 and state.sys_status_battery.voltage_v == pytest.approx(15.8)
        assert state.battery_status.charge_state == m.MAV_BATTERY_CHARGE_STATE_LOW
        assert state.battery_status.remaining_pct == 40 and state.battery_status.voltage_v == pytest.approx(11.9)
        assert state.altitude_above_ground(state.rangefinder.t) == pytest.approx(24.8)
        assert state.gimbal.q == pytest.approx(tuple(q))
        for part in (state.heartbeat, state.home, state.attitude, state.position, state.landed, state.battery, state.gimbal):
            assert part.t > 0  # each has its monotonic receive time
    finally:
        await peer.close()
        await link.close()


def test_heartbeats_of_other_components_do_not_set_the_mode():
    state = VehicleState()
    cam = m.MAVLink(None, 1, 100)
    hb = m.MAVLink_heartbeat_message(m.MAV_TYPE_CAMERA, m.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    hb.pack(cam)
    state.update(hb, 1.0)
    assert state.heartbeat is None


def test_pose_interpolates_between_samples_and_wraps_yaw():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0.0, 0.0, math.radians(170)), 10.0)
    s.update(att(100, 0.2, -0.1, math.radians(-170)), 10.1)
    s.update(gpi(0, 0.0, 0.0, 20.0), 10.0)
    s.update(gpi(100, 10.0, 4.0, 30.0), 10.1)
    pose = s.pose_at(10.05)
    assert pose is not None and pose.t == 10.05
    assert abs(abs(pose.yaw) - math.pi) < 0.01  # slerp: halfway from 170 to -170 deg is 180, not 0
    assert pose.roll == pytest.approx(0.1, abs=0.01) and pose.pitch == pytest.approx(-0.05, abs=0.01)
    assert (pose.north, pose.east, pose.down) == pytest.approx((5.0, 2.0, -25.0), abs=0.02)


def test_pose_is_none_outside_the_samples_across_gaps_and_without_home():
    s = VehicleState(max_gap_s=0.5, max_extrapolation_s=0.1)
    s.update(att(0, 0, 0, 0), 10.0)
    s.update(gpi(0, 0, 0, 20), 10.0)
    assert s.pose_at(10.0) is None  # no home yet: no world frame
    s.update(home_msg(), 10.0)
    assert s.pose_at(10.0) is not None
    assert s.pose_at(10.05) is not None  # small extrapolation allowance
    assert s.pose_at(10.2) is None  # too far past the newest sample
    assert s.pose_at(9.9) is None  # before the history
    s.update(att(2000, 0, 0, 0), 12.0)
    s.update(gpi(2000, 0, 0, 20), 12.0)
    assert s.pose_at(11.0) is None  # 2 s telemetry gap around t
    assert s.pose_at(float("nan")) is None


def test_fresh_only_with_recent_attitude_position_and_home():
    s = VehicleState()
    assert not s.is_fresh(10.0, 0.5)
    s.update(home_msg(), 9.0)
    s.update(att(0, 0, 0, 0), 10.0)
    s.update(gpi(0, 0, 0, 20), 10.0)
    assert s.is_fresh(10.3, 0.5)
    assert not s.is_fresh(10.6, 0.5)


def test_nan_and_out_of_range_values_are_counted_and_dropped():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0, 0, 0), 1.0)
    s.update(att(10, float("nan"), 0, 0), 1.01)
    assert s.attitude.t == 1.0 and s.rejected == 1
    bad = m.MAVLink_global_position_int_message(0, 95 * 10**7, 0, 0, 0, 0, 0, 0, 0)
    s.update(bad, 1.0)
    no_fix = m.MAVLink_global_position_int_message(0, 0, 0, 0, 0, 0, 0, 0, 0)
    s.update(no_fix, 1.0)
    s.update(m.MAVLink_home_position_message(0, 0, 0, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0), 1.0)
    q_bad = m.MAVLink_gimbal_device_attitude_status_message(1, 191, 0, 0, [float("nan"), 0, 0, 0], 0, 0, 0, 0)
    s.update(q_bad, 1.0)
    assert s.position is None and s.gimbal is None and s.home.point.lat_deg == pytest.approx(HOME.lat_deg)
    assert s.rejected == 5


def test_rangefinder_out_of_range_or_not_downward_gives_no_height():
    s = VehicleState()
    s.update(m.MAVLink_distance_sensor_message(0, 20, 4000, 5000, 0, 0, m.MAV_SENSOR_ROTATION_PITCH_270, 0), 1.0)
    assert s.altitude_above_ground(1.0) is None
    s.update(m.MAVLink_distance_sensor_message(0, 20, 4000, 300, 0, 0, m.MAV_SENSOR_ROTATION_NONE, 0), 1.0)
    assert s.altitude_above_ground(1.0) is None
    s.update(m.MAVLink_distance_sensor_message(0, 20, 4000, 300, 0, 0, m.MAV_SENSOR_ROTATION_PITCH_270, 0), 1.0)
    assert s.altitude_above_ground(1.2) == pytest.approx(3.0)
    assert s.altitude_above_ground(2.0) is None  # stale


def test_gimbal_pointing_down_gives_the_camera_rotation_in_the_body_frame():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0.0, 0.0, 1.0), 1.0)
    s.update(gpi(0, 0, 0, 20), 1.0)
    half = -math.pi / 4  # pitch -90 deg about the camera's right axis
    for flags in (m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, m.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME):
        yaw_half = 0.0 if flags == m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME else 0.5  # earth: yaw 1 rad too
        qz = [math.cos(yaw_half), 0, 0, math.sin(yaw_half)]
        qy = [math.cos(half), 0, math.sin(half), 0]
        w1, x1, y1, z1 = qz
        w2, x2, y2, z2 = qy
        q = [w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
             w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2]
        s.update(m.MAVLink_gimbal_device_attitude_status_message(1, 191, 0, flags, q, 0, 0, 0, 0), 1.0)
        pose = s.pose_at(1.0)
        # The camera's forward axis points straight down in the body frame of a level vehicle.
        assert pose.gimbal @ np.array([1.0, 0, 0]) == pytest.approx([0, 0, 1], abs=1e-9)


def test_finite_but_absurd_telemetry_is_counted_and_dropped():
    s = VehicleState()
    s.update(home_msg(), 0.0)
    s.update(att(0, 0.1, -0.2, 3.0), 1.0)
    s.update(gpi(0, 5.0, 5.0, 20.0), 1.0)
    good_att, good_pos = s.attitude, s.position
    s.update(att(10, 1e30, 0, 0), 1.01)           # roll 1e30 rad
    s.update(att(20, 0, 2.0, 0), 1.02)            # pitch past the vertical
    huge = m.MAVLink_global_position_int_message(0, 473977420, 85455940, 488000, 2_147_000_000, 0, 0, 0, 0)
    s.update(huge, 1.03)                          # 2,147 km above home
    fast = m.MAVLink_global_position_int_message(0, 473977420, 85455940, 508000, 20000, 32000, 0, 0, 0)
    s.update(fast, 1.04)                          # 320 m/s
    assert s.rejected == 4
    assert s.attitude is good_att and s.position is good_pos
    pose = s.pose_at(1.0)
    assert pose is not None and pose.roll == pytest.approx(0.1) and -pose.down == pytest.approx(20.0, abs=0.01)
