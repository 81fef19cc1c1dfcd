"""What the landing controller asks of the vehicle, in its own terms.

The MAVLink adapters (``companion.mavlink``) turn these into messages for each autopilot; the
controller never imports them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class PositionTarget:
    """Where to fly: WGS84 degrees, metres above home and, when home's altitude is known, the same
    altitude above mean sea level (``amsl_m`` = home AMSL + ``rel_alt_m``).

    Each flavour picks the frame its autopilot converts correctly (``docs/autopilot.md``):
    ArduPilot reads ``rel_alt_m`` (frame 6, GLOBAL_RELATIVE_ALT_INT), PX4 ``amsl_m`` (frame 5,
    GLOBAL_INT), because PX4 converts frame 6 wrongly whenever home and its estimator's origin
    differ in altitude.
    """

    lat_deg: float
    lon_deg: float
    rel_alt_m: float
    amsl_m: float | None = None

    def __post_init__(self) -> None:
        values = (self.lat_deg, self.lon_deg, self.rel_alt_m) + (() if self.amsl_m is None else (self.amsl_m,))
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"position target has a NaN or infinite value: {self!r}")
        if not (-90 <= self.lat_deg <= 90 and -180 <= self.lon_deg <= 180):
            raise ValueError(f"position target out of range: {self!r}")


@dataclass(frozen=True)
class Goto:
    """Fly to ``target`` and hold there (entering GUIDED/OFFBOARD); ``zone_id`` None = hold in place."""

    target: PositionTarget
    zone_id: int | None
    north: float
    east: float

    def repeats(self, north: float, east: float, alt: float, zone_id: int | None, within_m: float) -> bool:
        """Whether a target at (``north``, ``east``, ``alt``: NED metres from home, m above home)
        for ``zone_id`` is this one again, within ``within_m`` horizontally and vertically."""
        return (self.zone_id == zone_id and math.hypot(self.north - north, self.east - east) < within_m
                and abs(self.target.rel_alt_m - alt) < within_m)


@dataclass(frozen=True)
class Land:
    """Switch to the autopilot's LAND mode (lands where the vehicle is)."""


@dataclass(frozen=True)
class Handback:
    """Give control back to the autopilot's own failsafe: its LAND or RTL mode."""

    action: str
    reason: str


Command = Goto | Land | Handback
