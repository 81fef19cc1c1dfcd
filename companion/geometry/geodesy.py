"""Local NED <-> WGS84 around home, through geographiclib's geodesics (no hand formulas).

North/east are the distance along the WGS84 geodesic from home and its azimuth; over the few
hundred metres a landing covers this agrees with a tangent-plane (ENU/NED) projection to
millimetres. Down is minus the height above home's altitude (metres), ground at ``z = 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from geographiclib.geodesic import Geodesic

_WGS84 = Geodesic.WGS84


class GeodesyError(ValueError):
    """A latitude/longitude/altitude that is not a finite point on Earth."""


@dataclass(frozen=True)
class GeoPoint:
    """WGS84 latitude and longitude in degrees, altitude in metres (AMSL unless said otherwise)."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.lat_deg, self.lon_deg, self.alt_m)):
            raise GeodesyError(f"geographic point has a NaN or infinite value: {self!r}")
        if not (-90.0 <= self.lat_deg <= 90.0 and -180.0 <= self.lon_deg <= 180.0):
            raise GeodesyError(f"latitude/longitude out of range: {self.lat_deg}, {self.lon_deg}")


def ned_from_geo(home: GeoPoint, point: GeoPoint) -> tuple[float, float, float]:
    """``(north, east, down)`` metres of ``point`` from ``home`` (down = home alt - point alt)."""
    g = _WGS84.Inverse(home.lat_deg, home.lon_deg, point.lat_deg, point.lon_deg)
    azi = math.radians(g["azi1"])
    s = g["s12"]
    return s * math.cos(azi), s * math.sin(azi), home.alt_m - point.alt_m


def geo_from_ned(home: GeoPoint, north: float, east: float, down: float = 0.0) -> GeoPoint:
    """The WGS84 point ``north``/``east`` metres from ``home``, ``-down`` metres above it."""
    if not all(math.isfinite(v) for v in (north, east, down)):
        raise GeodesyError(f"NED offset has a NaN or infinite value: {(north, east, down)!r}")
    s = math.hypot(north, east)
    if s == 0.0:
        return GeoPoint(home.lat_deg, home.lon_deg, home.alt_m - down)
    g = _WGS84.Direct(home.lat_deg, home.lon_deg, math.degrees(math.atan2(east, north)), s)
    return GeoPoint(g["lat2"], g["lon2"], home.alt_m - down)
