"""The kinematic multicopter and the autopilot logic on their own (no sockets, stepped fast)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.vehicle.ardupilot import GUIDED, LAND, LOITER, RTL, ArduPilotCopter
from sim.vehicle.autopilot import AutopilotConfig, GeoFrame, StreamSchedule
from sim.vehicle.faults import Failsafe, LinkFaults
from sim.vehicle.kinematics import Vehicle, VehicleParams
from sim.vehicle.px4 import AUTO_LAND, AUTO_LOITER, OFFBOARD, Px4Multicopter, px4_mode, px4_split

DT = 0.02


def run(vehicle: Vehicle, seconds: float, each=None) -> None:
    for _ in range(int(round(seconds / DT))):
        vehicle.step(DT)
        if each is not None:
            each(vehicle)


def test_fly_to_respects_speed_and_acceleration_limits_and_arrives() -> None:
    params = VehicleParams(max_speed_xy=5.0, max_accel_xy=2.5)
    v = Vehicle(params, position=(0.0, 0.0, -10.0))
    v.fly_to(40.0, 30.0, -10.0)
    speeds, accels, prev = [], [], v.state.velocity.copy()

    def record(veh: Vehicle) -> None:
        nonlocal prev
        speeds.append(float(np.hypot(*veh.state.velocity[:2])))
        accels.append(float(np.linalg.norm((veh.state.velocity[:2] - prev[:2]) / DT)))
        prev = veh.state.velocity.copy()

    run(v, 20.0, record)
    assert max(speeds) <= 5.0 + 1e-6
    assert max(speeds) > 4.9  # long leg: it reaches cruise speed
    assert max(accels) <= 2.5 + 1e-6
    assert np.allclose(v.state.position, [40.0, 30.0, -10.0], atol=0.05)
    assert np.linalg.norm(v.state.velocity) < 0.05


def test_attitude_follows_acceleration_nose_down_when_speeding_up_forward() -> None:
    v = Vehicle(position=(0.0, 0.0, -10.0), yaw=math.pi / 2)  # nose east
    v.fly_to(0.0, 50.0, -10.0)
    run(v, 0.5)
    assert v.state.pitch < -math.radians(5)  # accelerating forward (east): nose down
    assert abs(v.state.roll) < math.radians(1)
    assert abs(v.state.pitch) < math.radians(30)  # small-angle regime


def test_yaw_turns_at_limited_rate_toward_target() -> None:
    v = Vehicle(VehicleParams(max_yaw_rate=math.radians(45)), position=(0.0, 0.0, -5.0))
    v.fly_to(0.0, 0.0, -5.0, yaw=math.radians(90))
    run(v, 1.0)
    assert math.radians(40) < v.state.yaw < math.radians(50)
    run(v, 3.0)
    assert v.state.yaw == pytest.approx(math.radians(90), abs=0.01)


def test_land_descends_vertically_with_schedule_and_touches_down_where_it_was() -> None:
    params = VehicleParams(land_speed_high=2.0, land_speed=0.5, land_alt_low=5.0, land_detect_s=1.0)
    v = Vehicle(params, position=(12.0, -7.0, -15.0))
    v.land()
    vz = []
    run(v, 12.0, lambda veh: vz.append((veh.altitude, float(veh.state.velocity[2]))))
    high = [s for alt, s in vz if alt > 6.0 and s > 0]
    low = [s for alt, s in vz if 0.2 < alt < 4.0]
    assert max(high) == pytest.approx(2.0, abs=1e-6)
    assert max(low) <= 0.5 + 1e-6
    run(v, 20.0)
    assert v.state.on_ground and v.state.land_complete
    assert v.state.position[2] == 0.0
    assert np.allclose(v.state.position[:2], [12.0, -7.0], atol=0.05)
    assert v.touchdowns == 1


def test_land_detector_waits_before_declaring_land_complete() -> None:
    v = Vehicle(VehicleParams(land_speed=1.0, land_alt_low=1.0, land_detect_s=1.0),
                position=(0.0, 0.0, -0.5))
    v.land()
    run(v, 0.9)  # 0.7 s to reach the ground, then 0.2 s of ground contact
    assert v.state.on_ground and not v.state.land_complete
    run(v, 1.2)
    assert v.state.land_complete


def test_battery_drains_only_while_armed_and_faster_in_flight() -> None:
    flying = Vehicle(position=(0.0, 0.0, -10.0))
    run(flying, 10.0)
    idle = Vehicle()
    run(idle, 10.0)
    assert idle.battery_remaining == 1.0
    used = 1.0 - flying.battery_remaining
    # 18 A for 10 s from 5000 mAh is 1 %.
    assert used == pytest.approx(18.0 * 10 / 3600 * 1000 / 5000, rel=0.05)
    assert flying.battery_voltage < 16.8


def test_vehicle_rejects_start_underground_and_bad_params() -> None:
    with pytest.raises(ValueError):
        Vehicle(position=(0.0, 0.0, 1.0))
    with pytest.raises(ValueError):
        VehicleParams(max_speed_xy=0.0)


def test_ardupilot_land_mode_disarms_after_land_detect() -> None:
    v = Vehicle(VehicleParams(land_speed=2.0, land_alt_low=1.0), position=(0.0, 0.0, -2.0))
    ap = ArduPilotCopter(v)
    assert ap.custom_mode == LOITER  # airborne start holds position
    ap.set_mode(LAND)
    t = 0.0
    while v.state.armed and t < 10.0:
        t += DT
        v.step(DT)
        ap.tick(t)
    assert not v.state.armed
    assert 1.5 < t < 4.0  # ~1 s descent + 1 s land detector, then disarm at once


def test_failsafe_switches_mode_and_only_escalates() -> None:
    cfg = AutopilotConfig(failsafe_action={Failsafe.BATTERY_LOW: "rtl",
                                           Failsafe.BATTERY_CRITICAL: "land",
                                           Failsafe.RC_LOSS: "rtl", Failsafe.GCS_LOSS: "land"})
    v = Vehicle(position=(5.0, 5.0, -20.0))
    ap = ArduPilotCopter(v, cfg)
    ap.set_mode(GUIDED)
    ap.trigger_failsafe(Failsafe.BATTERY_LOW)
    assert ap.custom_mode == RTL
    assert v.battery_remaining <= 0.20
    ap.trigger_failsafe(Failsafe.GCS_LOSS)
    assert ap.custom_mode == LAND
    ap.trigger_failsafe(Failsafe.RC_LOSS)  # RTL would de-escalate from LAND: stays
    assert ap.custom_mode == LAND


def test_rtl_climbs_returns_and_lands_at_home() -> None:
    params = VehicleParams(max_speed_xy=10.0, max_speed_up=5.0, land_speed_high=3.0,
                           land_speed=1.0, land_alt_low=2.0, max_accel_xy=5.0)
    v = Vehicle(params, position=(30.0, -20.0, -5.0))
    ap = ArduPilotCopter(v, AutopilotConfig(rtl_alt=10.0))
    ap.set_mode(RTL)
    t, max_alt = 0.0, 0.0
    while v.state.armed and t < 60.0:
        t += DT
        v.step(DT)
        ap.tick(t)
        max_alt = max(max_alt, v.altitude)
    assert not v.state.armed
    assert max_alt == pytest.approx(10.0, abs=0.3)
    assert np.allclose(v.state.position, [0.0, 0.0, 0.0], atol=0.6)


def test_px4_custom_mode_encoding_matches_px4() -> None:
    # Values as seen in PX4 heartbeats (px4_custom_mode.h: main << 16, sub << 24).
    assert OFFBOARD == 393216
    assert AUTO_LAND == 0x06040000
    assert AUTO_LOITER == 0x03040000
    assert px4_split(AUTO_LAND) == (4, 6)
    assert px4_mode(3) == 0x030000


def test_px4_offboard_needs_a_prior_stream() -> None:
    v = Vehicle(position=(0.0, 0.0, -10.0))
    ap = Px4Multicopter(v)
    assert ap.custom_mode == AUTO_LOITER
    assert ap.request_mode(OFFBOARD) == 1  # MAV_RESULT_TEMPORARILY_REJECTED, as Commander acks
    from sim.vehicle.autopilot import Setpoint
    t = 0.0
    for _ in range(5):  # 0.4 s of 10 Hz setpoints: not yet "a while"
        t += 0.1
        ap.tick(t)
        ap.handle_setpoint(Setpoint(position=np.array([1.0, 0.0, -10.0])))
    assert ap.request_mode(OFFBOARD) == 1  # MAV_RESULT_TEMPORARILY_REJECTED, as Commander acks
    for _ in range(8):
        t += 0.1
        ap.tick(t)
        ap.handle_setpoint(Setpoint(position=np.array([1.0, 0.0, -10.0])))
    assert ap.request_mode(OFFBOARD) == 0
    assert ap.custom_mode == OFFBOARD


def test_stream_schedule_and_link_faults_validation() -> None:
    sched = StreamSchedule({0: 1.0, 30: 10.0})
    sent = {0: 0, 30: 0}
    t = 0.0
    while t < 2.0 - 1e-9:
        for msg_id in sched.due(t):
            sent[msg_id] += 1
        t += 0.01
    assert sent[0] == 2 and 19 <= sent[30] <= 21
    sched.set_interval(30, None, t)
    assert 30 not in sched.due(t + 1.0)
    assert sched.interval_us(30) == -1
    with pytest.raises(ValueError):
        LinkFaults(loss_tx=1.5)


def test_geoframe_round_trip_through_geographiclib() -> None:
    geo = GeoFrame(47.397742, 8.545594, 488.0)
    lat, lon, alt = geo.to_global(120.0, -45.0, -30.0)
    assert alt == pytest.approx(518.0)
    n, e = geo.to_local(lat, lon)
    assert (n, e) == pytest.approx((120.0, -45.0), abs=1e-6)


def test_cli_builds_the_configuration_and_rejects_bad_links() -> None:
    import argparse

    from sim.flights import standalone as cli
    from sim.vehicle.endpoint import parse_url

    parser = argparse.ArgumentParser()
    cli.configure(parser)
    args = parser.parse_args(["--flavour", "px4", "--out", "udp:127.0.0.1:14550", "--out",
                              "udpin:127.0.0.1:14560", "--start-alt", "30", "--home",
                              "40.0,-3.5,650", "--failsafe-action", "rtl"])
    cfg = cli.build_config(args)
    assert cfg.flavour == "px4" and cfg.start_position == (0.0, 0.0, -30.0)
    assert cfg.outputs == ["udp:127.0.0.1:14550", "udpin:127.0.0.1:14560"]
    assert (cfg.autopilot.home_lat, cfg.autopilot.home_alt) == (40.0, 650.0)
    assert set(cfg.autopilot.failsafe_action.values()) == {"rtl"}
    assert parse_url("udp:127.0.0.1:14550") == ("udpout", ("127.0.0.1", 14550))
    for bad in (["--out", "tcp:127.0.0.1:5760"], ["--out", "udpout:127.0.0.1:99999"],
                ["--home", "95,0,0"]):
        with pytest.raises(SystemExit):
            parser.parse_args(bad)


def test_ardupilot_velocity_target_times_out_and_gcs_failsafe_fires_on_silence() -> None:
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from sim.vehicle.autopilot import Setpoint
    v = Vehicle(position=(0.0, 0.0, -10.0))
    ap = ArduPilotCopter(v, AutopilotConfig(gcs_timeout_s=4.0))
    ap.set_mode(GUIDED)
    ap.handle_setpoint(Setpoint(velocity=np.array([2.0, 0.0, 0.0])))
    t = 0.0
    while t < 2.5:
        t += DT
        v.step(DT)
        ap.tick(t)
    assert v.state.velocity[0] == pytest.approx(2.0)
    hb = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)
    hb.pack(mavlink.MAVLink(None, 255, 190))  # from the GCS (SYSID_MYGCS 255)
    ap.handle_message(hb, channel=None)  # at t = 2.5 s: the failsafe is due at 6.5 s
    while t < 5.0:
        t += DT
        v.step(DT)
        ap.tick(t)
    assert np.linalg.norm(v.state.velocity) < 0.05  # GUID_TIMEOUT: stopped after 3 s
    assert Failsafe.GCS_LOSS not in ap.failsafes
    while t < 7.0:
        t += DT
        v.step(DT)
        ap.tick(t)
    assert Failsafe.GCS_LOSS in ap.failsafes and ap.custom_mode == LAND


def test_an_altitude_bias_is_what_px4_reports_and_flies_by_not_where_the_vehicle_is() -> None:
    """PX4 SIH's relative altitude reads -1.3 to +1.8 m on the ground (issue 62): with
    ``alt_bias_m`` the simulated PX4 believes, reports and flies altitudes that much high."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    v = Vehicle()  # on the ground at home
    ap = Px4Multicopter(v, AutopilotConfig(alt_bias_m=1.8))
    gpi = ap.build(mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
    assert gpi.relative_alt == 1800 and gpi.alt == round((488.0 + 1.8) * 1000)
    assert ap.build(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED).z == pytest.approx(-1.8)
    # A target 5 m above home in its belief is 3.2 m above the ground.
    msg = mav.MAVLink_set_position_target_global_int_message(
        0, 1, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0b0000_1111_1111_1000, int(47.397742e7),
        int(8.545594e7), 5.0, 0, 0, 0, 0, 0, 0, 0, 0)
    sp = ap._parse_setpoint(msg)
    assert sp is not None and sp.position is not None and -sp.position[2] == pytest.approx(3.2, abs=0.05)
    with pytest.raises(ValueError, match="alt_bias_m"):
        AutopilotConfig(alt_bias_m=math.nan)
