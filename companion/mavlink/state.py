"""Vehicle state from MAVLink telemetry, each part with its time, and the pose at any instant.

``VehicleState.update(msg, t)`` takes one message and its receive time (``time.monotonic()``
seconds); ``attach(link)`` subscribes it to a ``MavLink``. ATTITUDE and GLOBAL_POSITION_INT are
placed in time by the autopilot's own ``time_boot_ms``, mapped onto our clock by
``clock.AutopilotClock`` (TIMESYNC where answered): their ``t`` is when the autopilot sampled them,
not when they arrived. A sample that arrives too late, or is not newer than the last of its stream,
is counted and dropped (``rejected``; ``clock.stats`` says why). Frames: local NED metres from home
(HOME_POSITION, through geographiclib), ground at ``z = 0``; angles in radians as in ATTITUDE
(aerospace Z-Y-X, yaw from north). Messages with NaN or out-of-range values (angles past +-pi,
altitudes past 20 km, speeds past 100 m/s, latitudes past +-90) are counted in ``rejected`` and
dropped so they never reach the pose.

``pose_at(t)`` interpolates, on the autopilot's clock, between the two ATTITUDE samples and the
two GLOBAL_POSITION_INT samples around ``t`` (attitude by quaternion slerp, so yaw wraps correctly
across +-pi). Past the newest sample it holds that sample for at most ``max_extrapolation_s`` and
then says so: the pose's ``t`` is the newest sample's time, its true age, never the time asked for.
``covers(t)`` tells a caller whether the samples after ``t`` have arrived, so that it can wait for
them rather than hold. It returns None when ``t`` is outside the buffered samples (beyond the
extrapolation allowance), when home or position is unknown, or when the samples around ``t`` are
too far apart to trust.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as m
from scipy.spatial.transform import Rotation, Slerp

from companion.geometry.camera import Pose, rotation_from_euler, rotation_from_quaternion
from companion.geometry.geodesy import GeodesyError, GeoPoint, ned_from_geo
from companion.logs import warn_every
from companion.mavlink.clock import AutopilotClock, Verdict

log = logging.getLogger(__name__)


class StateError(ValueError):
    """A telemetry value that cannot be used (NaN, out of range)."""


@dataclass(frozen=True)
class Attitude:
    """ATTITUDE: radians, yaw from north (-pi..pi); ``t`` sample time on our clock (s);
    ``time_boot_ms`` as sent; ``boot_s`` the autopilot's time (s, unwrapped); ``arrival`` receive time."""

    t: float
    time_boot_ms: int
    roll: float
    pitch: float
    yaw: float
    boot_s: float = math.nan
    arrival: float = math.nan


@dataclass(frozen=True)
class GlobalPosition:
    """GLOBAL_POSITION_INT: WGS84 degrees, AMSL and above-home metres, NED velocity m/s, heading rad;
    times as in ``Attitude``."""

    t: float
    time_boot_ms: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    relative_alt_m: float
    vn: float
    ve: float
    vd: float
    heading: float | None  # None when the autopilot does not know it (UINT16_MAX)
    boot_s: float = math.nan
    arrival: float = math.nan


@dataclass(frozen=True)
class Home:
    """HOME_POSITION: WGS84 degrees and AMSL metres; the origin of the local NED world frame."""

    t: float
    point: GeoPoint


@dataclass(frozen=True)
class Heartbeat:
    """HEARTBEAT of the autopilot: mode (base and custom), armed, MAV_STATE system status."""

    t: float
    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int
    system_status: int

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED)


@dataclass(frozen=True)
class Battery:
    """Battery: ``remaining_pct`` 0..100 or None if unknown; ``charge_state`` MAV_BATTERY_CHARGE_STATE
    (None from SYS_STATUS, which has none); ``voltage_v`` None if unknown."""

    t: float
    source: str  # "SYS_STATUS" or "BATTERY_STATUS"
    battery_id: int
    remaining_pct: float | None
    voltage_v: float | None
    charge_state: int | None
    time_remaining_s: float | None = None  # BATTERY_STATUS.time_remaining; None when 0 (not given)


#: A rangefinder reading older than this (s) is no height above ground: the vehicle may have moved
#: a metre and more since (the controller's low descent comes down at 1.5 m/s).
RANGEFINDER_MAX_AGE_S = 0.5
#: DISTANCE_SENSOR.orientation of a rangefinder facing down (25), the only one that measures height.
DOWNWARD_ORIENTATION: int = m.MAV_SENSOR_ROTATION_PITCH_270


def downward_range_m(current_cm: int, min_cm: int, max_cm: int) -> float | None:
    """A downward DISTANCE_SENSOR's fields (``DOWNWARD_ORIENTATION``; callers skip the others,
    which leave the height as it was) as metres above the ground, or None outside the sensor's
    own valid range. One rule for the live state and for replay, which reads the recorded
    messages. A sensor whose range is empty or beyond any rangefinder's (``MAX_RANGEFINDER_CM``)
    gives None: replay believes no more of it than the live state does."""
    if min_cm >= max_cm or max_cm > MAX_RANGEFINDER_CM or current_cm > MAX_RANGEFINDER_CM:
        return None
    return current_cm / 100.0 if min_cm <= current_cm <= max_cm else None


@dataclass(frozen=True)
class Rangefinder:
    """DISTANCE_SENSOR facing down: metres above ground, when within the sensor's valid range."""

    t: float
    distance_m: float


@dataclass(frozen=True)
class GimbalAttitude:
    """GIMBAL_DEVICE_ATTITUDE_STATUS: quaternion (w, x, y, z) and flags as sent; see ``R_body_from_cam``."""

    t: float
    q: tuple[float, float, float, float]
    flags: int

    @property
    def yaw_in_earth_frame(self) -> bool:
        if self.flags & m.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME:
            return True
        if self.flags & m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME:
            return False
        return bool(self.flags & m.GIMBAL_DEVICE_FLAGS_YAW_LOCK)


@dataclass(frozen=True)
class LandedState:
    """EXTENDED_SYS_STATE.landed_state (MAV_LANDED_STATE)."""

    t: float
    landed_state: int

    @property
    def on_ground(self) -> bool:
        return self.landed_state == m.MAV_LANDED_STATE_ON_GROUND


#: Limits past which telemetry is corrupt or forged: 20 km altitude, 100 m/s.
MAX_ALT_MM = 20_000_000
MAX_SPEED_CMS = 10_000
#: The longest range (cm) a downward rangefinder on a multicopter measures: long-range lidars
#: (LightWare SF30/D) reach 200 m; a reading or a range beyond 250 m is no rangefinder's.
MAX_RANGEFINDER_CM = 25_000


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def R_body_from_gimbal(gimbal: GimbalAttitude, roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The camera FRD frame in the body frame, from a gimbal attitude and the body attitude (rad).

    MAVLink gimbal quaternions have roll and pitch relative to the horizon; yaw is either absolute
    (earth frame) or relative to the vehicle's heading (vehicle frame), as the flags say.
    """
    R_q = rotation_from_quaternion(gimbal.q)
    R_world_from_body = rotation_from_euler(roll, pitch, yaw)
    R_world_from_cam = R_q if gimbal.yaw_in_earth_frame else rotation_from_euler(0.0, 0.0, yaw) @ R_q
    return R_world_from_body.T @ R_world_from_cam


#: The service's limit (s) on how far a frame's pose may be from its capture time and still be
#: used for decisions: the telemetry comes at 20 Hz (``link.POSE_RATE_HZ``), so a quarter of a
#: second is several samples missed; the landing controller refuses older poses, and the pose
#: held past the newest sample is given no longer than this.
MAX_POSE_AGE_S = 0.25


class VehicleState:
    """The latest telemetry of one vehicle and a short history of its pose for interpolation.

    ``history_s`` of ATTITUDE and position samples are kept; ``max_gap_s`` is the widest gap
    between two samples that ``pose_at`` interpolates across; ``max_extrapolation_s`` is how far
    past the newest sample ``pose_at`` may still answer (with the newest sample, and its age).
    ``clock`` places samples in time (a default ``AutopilotClock`` when not given).
    """

    def __init__(
        self,
        *,
        history_s: float = 5.0,
        max_gap_s: float = 0.5,
        max_extrapolation_s: float = 0.1,
        autopilot_component: int = m.MAV_COMP_ID_AUTOPILOT1,
        clock: AutopilotClock | None = None,
    ) -> None:
        self.history_s = history_s
        self.max_gap_s = max_gap_s
        self.max_extrapolation_s = max_extrapolation_s
        self.autopilot_component = autopilot_component
        self.clock = clock if clock is not None else AutopilotClock()
        self.attitude: Attitude | None = None
        self.position: GlobalPosition | None = None
        self.home: Home | None = None
        self.heartbeat: Heartbeat | None = None
        self.battery: Battery | None = None  # the newest of SYS_STATUS / BATTERY_STATUS
        self.battery_status: Battery | None = None  # BATTERY_STATUS only (has the charge state)
        self.sys_status_battery: Battery | None = None
        self.rangefinder: Rangefinder | None = None
        self.gimbal: GimbalAttitude | None = None
        self.landed: LandedState | None = None
        self.rejected = 0  # messages dropped for NaN / out-of-range values
        self._att: deque[Attitude] = deque()
        self._pos: deque[GlobalPosition] = deque()

    # -- input -------------------------------------------------------------------------------

    def attach(self, link: Any) -> None:
        """Subscribe to the vehicle's messages on a ``MavLink``."""
        for name in self.HANDLED:
            link.subscribe(name, self.update)

    HANDLED = (
        "HEARTBEAT",
        "ATTITUDE",
        "GLOBAL_POSITION_INT",
        "HOME_POSITION",
        "EXTENDED_SYS_STATE",
        "SYS_STATUS",
        "BATTERY_STATUS",
        "DISTANCE_SENSOR",
        "GIMBAL_DEVICE_ATTITUDE_STATUS",
        "TIMESYNC",
    )

    def update(self, msg: Any, t: float) -> None:
        """Take one message received at monotonic time ``t`` (s). Bad values are counted and dropped."""
        handler = getattr(self, "_on_" + msg.get_type().lower(), None)
        if handler is None:
            return
        try:
            handler(msg, t)
        except (StateError, GeodesyError) as exc:
            self.rejected += 1
            # One line per kind and 10 s, with the count: a flood of bad telemetry must not
            # push the trigger's lines out of journald's rate limit.
            warn_every(log, f"dropped {msg.get_type()}", 10.0, "dropped %s: %s", msg.get_type(), exc)

    def _on_heartbeat(self, msg: Any, t: float) -> None:
        if msg.get_srcComponent() != self.autopilot_component or msg.autopilot == m.MAV_AUTOPILOT_INVALID:
            return  # a camera, gimbal or companion on the same system, not the autopilot
        self.heartbeat = Heartbeat(t, msg.autopilot, msg.type, msg.base_mode, msg.custom_mode, msg.system_status)

    def _on_attitude(self, msg: Any, t: float) -> None:
        if not _finite(msg.roll, msg.pitch, msg.yaw):
            raise StateError(f"ATTITUDE has NaN: roll={msg.roll} pitch={msg.pitch} yaw={msg.yaw}")
        # Finite but absurd (roll 1e30) is as unusable as NaN: angles are within +-pi (2 pi for
        # yaw, which some autopilots send 0..2 pi).
        if abs(msg.roll) > math.pi + 1e-3 or abs(msg.pitch) > math.pi / 2 + 1e-3 or abs(msg.yaw) > 2 * math.pi + 1e-3:
            raise StateError(f"ATTITUDE out of range: roll={msg.roll} pitch={msg.pitch} yaw={msg.yaw}")
        t_sample, boot_s = self._stamp("ATTITUDE", msg.time_boot_ms, t)
        att = Attitude(t_sample, msg.time_boot_ms, msg.roll, msg.pitch, msg.yaw, boot_s, t)
        self.attitude = att
        self._append(self._att, att)

    def _on_global_position_int(self, msg: Any, t: float) -> None:
        if msg.lat == 0 and msg.lon == 0:
            raise StateError("GLOBAL_POSITION_INT without a fix (0, 0)")
        point = GeoPoint(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)  # validates the range
        # Altitudes beyond anything a multicopter reaches (the int32 fields allow 2,147 km) and
        # speeds beyond 100 m/s are corrupt or forged, not a pose to project frames with.
        if abs(msg.alt) > MAX_ALT_MM or abs(msg.relative_alt) > MAX_ALT_MM or \
                max(abs(msg.vx), abs(msg.vy), abs(msg.vz)) > MAX_SPEED_CMS:
            raise StateError(f"GLOBAL_POSITION_INT out of range: alt={msg.alt} mm "
                             f"relative_alt={msg.relative_alt} mm v=({msg.vx}, {msg.vy}, {msg.vz}) cm/s")
        hdg = None if msg.hdg == 65535 else math.radians(msg.hdg / 100.0)
        t_sample, boot_s = self._stamp("GLOBAL_POSITION_INT", msg.time_boot_ms, t)
        pos = GlobalPosition(
            t_sample, msg.time_boot_ms, point.lat_deg, point.lon_deg, point.alt_m, msg.relative_alt * 1e-3,
            msg.vx / 100.0, msg.vy / 100.0, msg.vz / 100.0, hdg, boot_s, t,
        )
        self.position = pos
        self._append(self._pos, pos)

    def _on_home_position(self, msg: Any, t: float) -> None:
        if msg.latitude == 0 and msg.longitude == 0:
            raise StateError("HOME_POSITION at (0, 0): home not set")
        if abs(msg.altitude) > MAX_ALT_MM:  # home is the ground frames are projected onto
            raise StateError(f"HOME_POSITION altitude {msg.altitude} mm is out of range")
        self.home = Home(t, GeoPoint(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3))

    def _on_extended_sys_state(self, msg: Any, t: float) -> None:
        self.landed = LandedState(t, msg.landed_state)

    def _on_sys_status(self, msg: Any, t: float) -> None:
        remaining = None if msg.battery_remaining < 0 else float(msg.battery_remaining)
        voltage = None if msg.voltage_battery == 65535 else msg.voltage_battery / 1000.0
        self.sys_status_battery = Battery(t, "SYS_STATUS", 0, remaining, voltage, None)
        self.battery = self.sys_status_battery

    def _on_battery_status(self, msg: Any, t: float) -> None:
        remaining = None if msg.battery_remaining < 0 else float(msg.battery_remaining)
        cells = [v for v in msg.voltages if v != 65535]
        voltage = sum(cells) / 1000.0 if cells else None
        left = float(getattr(msg, "time_remaining", 0) or 0)
        self.battery_status = Battery(t, "BATTERY_STATUS", msg.id, remaining, voltage, msg.charge_state,
                                      left if left > 0 else None)
        self.battery = self.battery_status

    def _on_distance_sensor(self, msg: Any, t: float) -> None:
        if msg.orientation != DOWNWARD_ORIENTATION:
            return  # only a downward rangefinder measures height above ground
        if msg.min_distance >= msg.max_distance or msg.max_distance > MAX_RANGEFINDER_CM \
                or msg.current_distance > MAX_RANGEFINDER_CM:
            # A sensor that claims a range no rangefinder on a multicopter has, or an empty one, is
            # corrupt or forged: counted and dropped, and the height it gave before is kept no
            # longer than RANGEFINDER_MAX_AGE_S.
            raise StateError(f"DISTANCE_SENSOR implausible: current={msg.current_distance} cm "
                             f"min={msg.min_distance} cm max={msg.max_distance} cm")
        d = downward_range_m(msg.current_distance, msg.min_distance, msg.max_distance)
        # Out of range: no height above ground rather than a wrong one.
        self.rangefinder = None if d is None else Rangefinder(t, d)

    def _on_gimbal_device_attitude_status(self, msg: Any, t: float) -> None:
        q = tuple(float(v) for v in msg.q)
        if not _finite(*q) or abs(math.sqrt(sum(v * v for v in q)) - 1.0) > 0.1:
            raise StateError(f"gimbal quaternion {q} is not a unit quaternion")
        self.gimbal = GimbalAttitude(t, q, msg.flags)  # type: ignore[arg-type]

    def _on_timesync(self, msg: Any, t: float) -> None:
        if msg.tc1 != 0:  # an answer to our request (tc1 = 0 is the autopilot asking us)
            self.clock.on_timesync(msg.tc1, msg.ts1, t)

    def _stamp(self, stream: str, time_boot_ms: int, arrival: float) -> tuple[float, float]:
        """(sample time on our clock, autopilot time) of a pose sample, or StateError if it is
        late or not newer than its stream's last one. A confirmed autopilot reboot clears the
        history: its samples are on a clock that no longer exists."""
        stamp = self.clock.stamp(stream, time_boot_ms / 1000.0, arrival)
        if stamp.verdict is Verdict.LATE:
            raise StateError(f"{stream} arrived {stamp.lag_s:.2f} s after it was sampled "
                             f"(limit {self.clock.max_lag_s:g} s)")
        if stamp.verdict is Verdict.BACKWARDS:
            raise StateError(f"{stream} time_boot_ms {time_boot_ms} is not newer than the last sample")
        if stamp.verdict is Verdict.AHEAD:
            raise StateError(f"{stream} time_boot_ms {time_boot_ms} is {-stamp.lag_s:.2f} s ahead of the "
                             "autopilot's clock (unconfirmed: a forgery or a jump the next samples confirm)")
        if stamp.verdict is Verdict.REBOOT:
            # Rate-limited: however a reboot is claimed, the warning must not flood the journal.
            warn_every(log, "autopilot reboot", 10.0, "autopilot clock restarted (reboot?): pose history cleared")
        if stamp.verdict is Verdict.RESET:
            warn_every(log, "clock reset", 10.0, "autopilot clock: the first estimate was an outlier (a forged "
                       "first sample?); the streams agree on another: pose history cleared")
        if stamp.verdict in (Verdict.REBOOT, Verdict.RESET):
            self._att.clear()
            self._pos.clear()
        return stamp.t, stamp.boot_s

    def _append(self, buf: deque[Any], sample: Any) -> None:
        # The clock only lets through samples newer than their stream's last: boot_s increases.
        buf.append(sample)
        while buf and sample.boot_s - buf[0].boot_s > self.history_s:
            buf.popleft()

    # -- derived -----------------------------------------------------------------------------

    @property
    def mode(self) -> tuple[int, int] | None:
        """(base_mode, custom_mode) of the last autopilot heartbeat, or None."""
        return None if self.heartbeat is None else (self.heartbeat.base_mode, self.heartbeat.custom_mode)

    @property
    def armed(self) -> bool | None:
        return None if self.heartbeat is None else self.heartbeat.armed

    def altitude_above_home(self) -> float | None:
        """Metres above home from the latest position (GLOBAL_POSITION_INT.relative_alt)."""
        return None if self.position is None else self.position.relative_alt_m

    def altitude_above_ground(self, now: float, max_age_s: float = RANGEFINDER_MAX_AGE_S) -> float | None:
        """Metres above ground from a fresh downward rangefinder, else None (not measured)."""
        rf = self.rangefinder
        if rf is None or now - rf.t > max_age_s:
            return None
        return rf.distance_m

    def local_ned(self, position: GlobalPosition | None = None) -> tuple[float, float, float] | None:
        """(north, east, down) metres of a position (default the latest) from home, or None."""
        position = position or self.position
        if position is None or self.home is None:
            return None
        n, e, _ = ned_from_geo(self.home.point, GeoPoint(position.lat_deg, position.lon_deg, position.alt_m))
        # relative_alt is the autopilot's own height above home: consistent with the alt it flies.
        return n, e, -position.relative_alt_m

    def is_fresh(self, now: float, max_age_s: float) -> bool:
        """True when attitude, position and home are known and attitude/position are younger than ``max_age_s``."""
        return (
            self.attitude is not None
            and self.position is not None
            and self.home is not None
            and now - self.attitude.t <= max_age_s
            and now - self.position.t <= max_age_s
        )

    def covers(self, t: float) -> bool:
        """True when an ATTITUDE and a position sample at or after our time ``t`` have arrived:
        ``pose_at(t)`` then interpolates rather than holds, and waiting longer cannot improve it."""
        b = self.clock.to_boot(t) if math.isfinite(t) else None
        return (b is not None and bool(self._att) and bool(self._pos)
                and self._att[-1].boot_s >= b and self._pos[-1].boot_s >= b)

    def pose_at(self, t: float) -> Pose | None:
        """The pose at our monotonic time ``t`` (s), or None if it cannot be trusted.

        Interpolated on the autopilot's clock. Past the newest sample (within
        ``max_extrapolation_s``) the newest sample is held and the pose's ``t`` is that sample's
        time, so that its age shows.
        """
        if self.home is None or not math.isfinite(t):
            return None
        b = self.clock.to_boot(t)
        if b is None:
            return None
        att = self._bracket(self._att, b)
        pos = self._bracket(self._pos, b)
        if att is None or pos is None:
            return None
        roll, pitch, yaw = self._interp_attitude(att, b)
        n0, e0, d0 = self.local_ned(pos[0])  # type: ignore[misc]
        n1, e1, d1 = self.local_ned(pos[1])  # type: ignore[misc]
        f = self._fraction(pos[0].boot_s, pos[1].boot_s, b)
        # The time the pose truly describes: t when both are bracketed, else the older held sample.
        held = [pair[1].boot_s for pair in (att, pos) if pair[1].boot_s < b]
        t_pose = t if not held else t - (b - min(held))
        gimbal = None
        if self.gimbal is not None and abs(self.gimbal.t - t) <= self.max_gap_s:
            gimbal = R_body_from_gimbal(self.gimbal, roll, pitch, yaw)
        return Pose(
            t_pose,
            n0 + f * (n1 - n0),
            e0 + f * (e1 - e0),
            d0 + f * (d1 - d0),
            roll,
            pitch,
            yaw,
            gimbal,
        )

    def _bracket(self, buf: deque[Any], b: float) -> tuple[Any, Any] | None:
        """The samples around autopilot time ``b`` (s), the newest twice when ``b`` is past it."""
        if not buf or b < buf[0].boot_s:
            return None
        i = bisect.bisect_right(buf, b, key=lambda s: s.boot_s)
        if i == len(buf):
            last = buf[-1]
            return (last, last) if b - last.boot_s <= self.max_extrapolation_s else None
        a, c = buf[i - 1], buf[i]
        if c.boot_s - a.boot_s > self.max_gap_s:
            return None  # a telemetry gap: do not invent what happened in between
        return a, c

    @staticmethod
    def _fraction(t0: float, t1: float, t: float) -> float:
        return 0.0 if t1 <= t0 else min(1.0, max(0.0, (t - t0) / (t1 - t0)))

    def _interp_attitude(self, pair: tuple[Attitude, Attitude], b: float) -> tuple[float, float, float]:
        a, c = pair
        if a is c or c.boot_s <= a.boot_s:
            return a.roll, a.pitch, a.yaw
        rots = Rotation.from_euler("ZYX", [[a.yaw, a.pitch, a.roll], [c.yaw, c.pitch, c.roll]])
        yaw, pitch, roll = Slerp([a.boot_s, c.boot_s], rots)([b]).as_euler("ZYX")[0]
        return float(roll), float(pitch), float(yaw)
