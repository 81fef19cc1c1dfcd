"""The vehicle as the landing controller sees it: where it is, how high, in which mode."""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.geometry.camera import Pose
from companion.geometry.geodesy import GeoPoint


@dataclass(frozen=True)
class VehicleStatus:
    """The vehicle now: ``t`` when its position was sampled (our monotonic s); NED metres from
    home; ``home`` WGS84.

    ``mode`` is the flavour's mode name; ``on_ground``/``armed`` None when unknown; ``agl`` metres
    above ground from a fresh rangefinder, None without one (then heights are above home);
    ``vn``/``ve``/``vd`` velocity in NED m/s; ``latency_s`` the link's one-way latency as measured
    (TIMESYNC), 0 when not measured; ``battery_s`` the flight time the battery has left as the
    autopilot estimates it (s), None when it does not say.
    """

    t: float
    north: float
    east: float
    down: float
    home: GeoPoint
    mode: str | None = None
    armed: bool | None = None
    on_ground: bool | None = None
    agl: float | None = None
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    latency_s: float = 0.0
    battery_s: float | None = None

    @property
    def alt(self) -> float:
        """Metres above home."""
        return -self.down

    @property
    def measured_agl(self) -> float | None:
        """Metres above the ground below as the rangefinder measures it; None without a usable
        reading (none fresh, or not a number)."""
        return self.agl if self.agl is not None and math.isfinite(self.agl) else None

    @property
    def height(self) -> float:
        """Metres above the ground below: a fresh downward rangefinder if any, else above home."""
        agl = self.measured_agl
        return self.alt if agl is None else agl


def pose_usable(pose: Pose | None, t: float, max_pose_age_s: float) -> bool:
    """Whether ``pose`` can place a frame captured at ``t`` (s): present, finite, and sampled
    within ``max_pose_age_s`` of it."""
    if pose is None:
        return False
    values = (pose.t, pose.north, pose.east, pose.down, pose.roll, pose.pitch, pose.yaw)
    return all(math.isfinite(v) for v in values) and abs(pose.t - t) <= max_pose_age_s
