"""A kinematic multicopter: position, velocity, attitude and battery stepped in time, no I/O.

Frames (docs/design.md): world = local NED metres, origin at home, ground at ``z = 0`` (so altitude
above home is ``-down``); body = FRD; angles in radians; times in seconds.

The model is what a position controller makes of a multicopter seen from outside: the vehicle
follows a position or velocity demand with speed and acceleration limits, tilts in proportion to
its horizontal acceleration (small angles), turns its nose at a limited yaw rate, touches down on
the ground plane and drains a battery while the motors turn. The autopilot logic (modes, MAVLink)
sits on top in ``sim.vehicle.autopilot`` and only talks to this class through its demand methods.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

GRAVITY = 9.80665  # m/s^2
TOUCHDOWN_SPEED = 0.3  # m/s, the slowest descent onto a position target on the ground


class Demand(Enum):
    """What the controller is asked to follow."""

    IDLE = "idle"          # motors off or spinning on the ground, no movement
    HOLD = "hold"          # keep the current position (loiter)
    POSITION = "position"  # fly to ``target_position``
    VELOCITY = "velocity"  # follow ``target_velocity``
    LAND = "land"          # descend vertically where it is, land-speed schedule


@dataclass
class VehicleParams:
    """Limits and physical constants, named after the ArduPilot parameters they mirror.

    Speeds in m/s, accelerations in m/s^2, heights in metres, yaw rate in rad/s, capacity in mAh,
    current in A.
    """

    max_speed_xy: float = 5.0         # WPNAV_SPEED
    max_speed_up: float = 2.5         # WPNAV_SPEED_UP
    max_speed_down: float = 1.5       # WPNAV_SPEED_DN
    max_accel_xy: float = 2.5         # WPNAV_ACCEL
    max_accel_z: float = 2.5          # PILOT_ACCEL_Z
    attitude_tc: float = 0.15         # ATC_INPUT_TC: time constant of the tilt response (s)
    max_yaw_rate: float = math.radians(90.0)
    land_speed_high: float = 1.5      # LAND_SPEED_HIGH (0 = WPNAV_SPEED_DN), above land_alt_low
    land_speed: float = 0.5           # LAND_SPEED, the final descent
    land_alt_low: float = 10.0        # LAND_ALT_LOW
    land_detect_s: float = 1.0        # on the ground this long before "land complete"
    battery_capacity_mah: float = 5000.0
    battery_cells: int = 4
    hover_current_a: float = 18.0
    idle_current_a: float = 0.5
    position_gain: float = 2.0        # 1/s, P gain of the position loop (PSC_POSXY_P-like)

    def __post_init__(self) -> None:
        for name in ("max_speed_xy", "max_speed_up", "max_speed_down", "max_accel_xy",
                     "max_accel_z", "max_yaw_rate", "land_speed", "battery_capacity_mah",
                     "position_gain"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"vehicle parameter {name} must be > 0, got {value!r}")


@dataclass
class VehicleState:
    """The true state. Position/velocity in world NED (m, m/s), attitude in radians."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    yaw_rate: float = 0.0
    armed: bool = False
    on_ground: bool = True
    land_complete: bool = True
    consumed_mah: float = 0.0
    current_a: float = 0.0


def _limit_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v if n <= limit or n == 0.0 else v * (limit / n)


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def sqrt_controller(error: float, gain: float, accel: float) -> float:
    """Speed toward a target that can still stop in time: linear near it, sqrt(2 a d) far away.

    The same shape as ArduPilot's ``sqrt_controller``, so approach and stop look like a real
    position controller rather than a bang-bang jump.
    """
    linear_dist = accel / (gain * gain)
    if abs(error) <= linear_dist:
        return error * gain
    return math.copysign(math.sqrt(2.0 * accel * (abs(error) - linear_dist / 2.0)), error)


class Vehicle:
    """The kinematic multicopter. Call the demand methods, then ``step(dt)``."""

    def __init__(self, params: VehicleParams | None = None,
                 position: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw: float = 0.0,
                 battery_remaining: float = 1.0) -> None:
        self.params = params or VehicleParams()
        self.state = VehicleState(position=np.array(position, dtype=float), yaw=float(yaw))
        if self.state.position[2] > 0.0:
            raise ValueError("the vehicle cannot start below the ground (down > 0)")
        airborne = bool(self.state.position[2] < 0.0)
        self.state.armed = airborne
        self.state.on_ground = not airborne
        self.state.land_complete = not airborne
        self.state.consumed_mah = (1.0 - battery_remaining) * self.params.battery_capacity_mah
        self.demand = Demand.HOLD if airborne else Demand.IDLE
        self.target_position = self.state.position.copy()
        self.target_velocity = np.zeros(3)
        self.target_yaw: float | None = None
        self.speed_xy = self.params.max_speed_xy  # DO_CHANGE_SPEED can lower it
        self._ground_time = 0.0
        self._land_complete_time = 0.0
        self.touchdowns = 0

    # ----- demands (what the autopilot asks for) -----

    def hold(self) -> None:
        """Stop and keep the current position (targets the stopping point, not a jerk)."""
        if self.state.armed and not self.state.land_complete:
            self.demand = Demand.HOLD
            self.target_position = self.stopping_point()

    def stopping_point(self) -> np.ndarray:
        """Where braking at the acceleration limits from the current velocity ends (world NED m)."""
        p, s = self.params, self.state
        v_xy, v_z = s.velocity[:2], float(s.velocity[2])
        point = s.position.copy()
        point[:2] += v_xy * float(np.linalg.norm(v_xy)) / (2.0 * p.max_accel_xy)
        point[2] = min(point[2] + v_z * abs(v_z) / (2.0 * p.max_accel_z), 0.0)
        return point

    def fly_to(self, north: float, east: float, down: float, yaw: float | None = None) -> None:
        """Fly to a world NED point (m); ``down`` is clamped to stay above the ground."""
        self.demand = Demand.POSITION
        self.target_position = np.array([north, east, min(down, 0.0)], dtype=float)
        if yaw is not None:
            self.target_yaw = yaw

    def fly_velocity(self, vn: float, ve: float, vd: float, yaw: float | None = None) -> None:
        """Follow a world NED velocity (m/s), limited to the speed limits."""
        self.demand = Demand.VELOCITY
        self.target_velocity = np.array([vn, ve, vd], dtype=float)
        if yaw is not None:
            self.target_yaw = yaw

    def land(self) -> None:
        """Descend vertically where it is with the land speed schedule, then touch down."""
        if self.demand is not Demand.LAND:
            self.target_position = self.state.position.copy()
        self.demand = Demand.LAND

    def take_off(self, altitude: float) -> None:
        """Climb vertically to ``altitude`` metres above home (needs to be armed)."""
        if not self.state.armed:
            raise RuntimeError("take-off needs the motors armed")
        p = self.state.position
        self.state.land_complete = False
        self.state.on_ground = False
        self._ground_time = 0.0
        self.fly_to(float(p[0]), float(p[1]), -abs(altitude))

    def arm(self) -> None:
        self.state.armed = True
        self._ground_time = 0.0
        self._land_complete_time = 0.0
        self.demand = Demand.IDLE

    def disarm(self) -> None:
        self.state.armed = False
        self.demand = Demand.IDLE
        self.state.velocity[:] = 0.0

    # ----- derived quantities -----

    @property
    def altitude(self) -> float:
        """Height above home (= above the flat ground), metres."""
        return -float(self.state.position[2])

    @property
    def battery_remaining(self) -> float:
        """Remaining charge as a fraction 0..1."""
        p = self.params
        return max(0.0, 1.0 - self.state.consumed_mah / p.battery_capacity_mah)

    @property
    def battery_voltage(self) -> float:
        """Pack voltage (V) from a crude linear cell curve, 3.5 V empty to 4.2 V full."""
        cell = 3.5 + 0.7 * self.battery_remaining
        return cell * self.params.battery_cells - 0.01 * self.state.current_a

    def set_battery_remaining(self, fraction: float) -> None:
        """Jump the charge (failsafe injection); fraction in 0..1."""
        fraction = min(1.0, max(0.0, float(fraction)))
        self.state.consumed_mah = (1.0 - fraction) * self.params.battery_capacity_mah

    # ----- physics -----

    def _desired_velocity(self) -> np.ndarray:
        p, s = self.params, self.state
        if self.demand is Demand.VELOCITY:
            v = self.target_velocity.copy()
        elif self.demand in (Demand.POSITION, Demand.HOLD):
            err = self.target_position - s.position
            dist_xy = float(math.hypot(err[0], err[1]))
            v = np.zeros(3)
            if dist_xy > 1e-6:
                speed = sqrt_controller(dist_xy, p.position_gain, p.max_accel_xy)
                v[:2] = err[:2] / dist_xy * speed
            v[2] = sqrt_controller(float(err[2]), p.position_gain, p.max_accel_z)
            if self.target_position[2] >= 0.0:
                # A target on the ground is reached by touching it: keep a touchdown speed
                # rather than creep toward z = 0 forever (the linear end of the approach is
                # exponential), as a real vehicle settles onto the ground and its land detector
                # fires.
                v[2] = max(v[2], min(TOUCHDOWN_SPEED, p.land_speed))
        elif self.demand is Demand.LAND:
            # Hold the horizontal position the landing started at; descend by the schedule.
            err = self.target_position - s.position
            v = np.zeros(3)
            v[:2] = err[:2] * p.position_gain
            high = p.land_speed_high if p.land_speed_high > 0 else p.max_speed_down
            v[2] = high if self.altitude > p.land_alt_low else p.land_speed
        else:
            return np.zeros(3)
        v[:2] = _limit_norm(v[:2], self.speed_xy)
        if self.demand is not Demand.LAND:  # LAND_SPEED_HIGH is not capped by WPNAV_SPEED_DN
            v[2] = min(max(v[2], -p.max_speed_up), p.max_speed_down)
        return v

    def step(self, dt: float) -> None:
        """Advance the state by ``dt`` seconds."""
        if not (dt > 0.0 and math.isfinite(dt)):
            return
        p, s = self.params, self.state
        flying = s.armed and not s.land_complete
        v_des = self._desired_velocity() if flying else np.zeros(3)
        dv = v_des - s.velocity
        dv[:2] = _limit_norm(dv[:2], p.max_accel_xy * dt)
        dv[2] = min(max(dv[2], -p.max_accel_z * dt), p.max_accel_z * dt)
        s.acceleration = dv / dt
        s.velocity = s.velocity + dv
        s.position = s.position + s.velocity * dt

        if s.position[2] >= 0.0:
            # The ground stops the descent: clamp, kill vertical and horizontal motion (skids).
            if not s.on_ground and flying:
                self.touchdowns += 1
            s.position[2] = 0.0
            s.velocity[:] = 0.0
            s.acceleration[:] = 0.0
            s.on_ground = True
        elif s.on_ground and s.position[2] < -0.05:
            s.on_ground = False
        self._update_land_detector(dt)
        self._update_attitude(dt)
        self._update_battery(dt)

    def _update_land_detector(self, dt: float) -> None:
        p, s = self.params, self.state
        climbing = self.demand in (Demand.POSITION, Demand.VELOCITY) and (
            (self.demand is Demand.POSITION and self.target_position[2] < -0.1)
            or (self.demand is Demand.VELOCITY and self.target_velocity[2] < -0.05))
        if s.on_ground and s.armed and not climbing:
            self._ground_time += dt
            if not s.land_complete and self._ground_time >= p.land_detect_s:
                s.land_complete = True
                self._land_complete_time = 0.0
            if s.land_complete:
                self._land_complete_time += dt
        else:
            self._ground_time = 0.0
            if s.armed and not s.on_ground:
                s.land_complete = False

    @property
    def landed_for_s(self) -> float:
        """Seconds since the land detector fired (0 while flying)."""
        return self._land_complete_time if self.state.land_complete else 0.0

    def _update_attitude(self, dt: float) -> None:
        p, s = self.params, self.state
        if self.target_yaw is not None and s.armed and not s.land_complete:
            err = _wrap_pi(self.target_yaw - s.yaw)
            rate = max(-p.max_yaw_rate, min(p.max_yaw_rate, 2.0 * err))
        else:
            rate = 0.0
        s.yaw_rate = rate
        s.yaw = _wrap_pi(s.yaw + rate * dt)
        if s.on_ground:
            s.roll = s.pitch = 0.0
            return
        # Thrust tilts toward the horizontal acceleration: a forward acceleration needs the nose
        # down (negative pitch), a rightward one the right side down (positive roll).
        cy, sy = math.cos(s.yaw), math.sin(s.yaw)
        a_fwd = cy * s.acceleration[0] + sy * s.acceleration[1]
        a_right = -sy * s.acceleration[0] + cy * s.acceleration[1]
        pitch = -math.atan2(a_fwd, GRAVITY)
        roll = math.atan2(a_right * math.cos(pitch), GRAVITY)
        # The attitude controller follows the demanded tilt with a lag (ArduPilot ATC_INPUT_TC):
        # the velocity model's acceleration steps would otherwise make the camera jump by
        # degrees between two telemetry samples, which no real airframe does.
        k = min(1.0, dt / p.attitude_tc) if p.attitude_tc > 0 else 1.0
        s.pitch += (pitch - s.pitch) * k
        s.roll += (roll - s.roll) * k

    def _update_battery(self, dt: float) -> None:
        p, s = self.params, self.state
        if not s.armed:
            s.current_a = 0.0
        elif s.land_complete:
            s.current_a = p.idle_current_a
        else:
            # Faster flight and climbing draw more, a crude but monotonic model.
            speed = float(np.linalg.norm(s.velocity))
            s.current_a = p.hover_current_a * (1.0 + 0.02 * speed * speed / 4.0
                                                + 0.1 * max(0.0, -s.velocity[2]))
        s.consumed_mah += s.current_a * dt * 1000.0 / 3600.0
