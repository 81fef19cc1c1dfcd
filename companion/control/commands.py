"""What the landing controller asks of the vehicle, in its own terms.

The MAVLink adapters (``companion.mavlink``) turn these into messages for each autopilot; the
controller never imports them. ``GotoSender`` builds the go-to targets the phase machine sends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.control.obedience import ObedienceMonitor, Sample
from companion.control.vehicle import VehicleStatus
from companion.geometry.geodesy import geo_from_ned


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


class GotoSender:
    """The go-to targets the phase machine sends (``goto``): each built from NED metres, a repeat
    of the last one (within ``min_move_m``, less than ``refresh_s`` after it) left out so as not
    to flood the link, and each told to the ``ObedienceMonitor``."""

    def __init__(self, min_move_m: float, refresh_s: float, obedience: ObedienceMonitor) -> None:
        self.min_move_m = min_move_m
        self.refresh_s = refresh_s
        self.obedience = obedience
        self.last: Goto | None = None
        self.last_t = -math.inf

    def forget(self) -> None:
        """Send the next target whatever it is (a new zone, a new phase, a command that failed)."""
        self.last = None

    def goto(self, s: VehicleStatus, north: float, east: float, alt: float, zone_id: int | None,
             now: float) -> list[Command]:
        """The command to fly to (``north``, ``east``: NED metres from home; ``alt``: m above home)
        for ``zone_id`` at ``now`` (s), or none when the vehicle already has that target."""
        last = self.last
        if last is not None and last.repeats(north, east, alt, zone_id, self.min_move_m) \
                and now - self.last_t < self.refresh_s:
            return []  # the vehicle already has this target; do not flood the link
        point = geo_from_ned(s.home, north, east, -alt)
        cmd = Goto(PositionTarget(point.lat_deg, point.lon_deg, alt, point.alt_m), zone_id, north, east)
        self.last, self.last_t = cmd, now
        # The vehicle flies on with its old target from the status's sample time until this one
        # reaches it: the status's age plus the link's latency out.
        unheard = max(0.0, now - s.t) + max(0.0, s.latency_s)
        self.obedience.target(north, east, alt, Sample.of(s), unheard)
        return [cmd]
