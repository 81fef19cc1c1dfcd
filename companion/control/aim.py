"""Where in the zone: the landing point (the *aim*) and the risk map's spot.

The aim is the zone's centre when the zone is chosen, and it stays put while the zone still holds
its *room* around it: r0 plus the radius margin, or, for a zone bounded by the view (everything
seen is free), ``MIN_VIEW_M`` while the view still shows that much (``ZonePlanner.room``). Such a
zone moves with the camera, and following its centre would chase it across uniform free ground
for ever; only when the zone no longer holds its room around the aim does the aim move to the
zone's new centre.

With ``place_lookback_s`` the aim moves inside the zone to where the ground is farthest from
anybody the risk map saw within that many seconds, while the vehicle approaches the zone and
while it descends to judge it (not once judged, nor in LAND), whenever that point lies
``PLACE_GAIN_M`` farther from them than the present one. A zone's centre is the point farthest
from the people of one frame: a circle spanning a lawn and a momentary gap of the crowd beside it
has its centre at the lawn's edge, where walkers go round; what the map saw over the last seconds
shows where they go. The frame's ground view answers the ``SpotRequest`` (``ground_spot``).

These functions answer; the phase machine (``companion.control.landing``) moves the aim and says so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from companion.control.planner import ZonePlanner
from companion.control.settings import PLACE_GAIN_M
from companion.pipeline.riskmap import Spot, SpotRequest
from companion.pipeline.tracker import Track


@dataclass(frozen=True)
class Aimed:
    """The target as a frame confirms it (``track``), its landing point (``aim``: north, east m)
    and the vehicle's distance to that point (``dist``, m)."""

    track: Track
    aim: tuple[float, float]
    dist: float


class SpotSource(Protocol):
    """What a frame's ground view answers about the risk map (``SLZPipeline``'s ``GroundView``):
    where the landing point may go on that frame."""

    def spot(self, request: SpotRequest) -> Spot | None: ...


def aim_for(aim: tuple[float, float] | None, track: Track, room: float) -> tuple[float, float]:
    """The landing point over ``track`` now: the present one ``aim`` while the zone holds ``room``
    (m) around it, else the zone's centre."""
    if aim is None or track.r - math.hypot(aim[0] - track.x, aim[1] - track.y) < room:
        return (track.x, track.y)
    return aim


def spot_request(track: Track, room: float, lookback_s: float, aim: tuple[float, float]) -> SpotRequest | None:
    """Where the landing point may go over ``track`` (the part of the zone whose points keep
    ``room`` around them), away from what the map saw within ``lookback_s``; ``aim`` the present
    point. None when the zone has no such part or is not finite."""
    if not all(math.isfinite(v) for v in (track.x, track.y, track.r)):
        return None
    radius = track.r - room
    if radius <= 0:
        return None
    return SpotRequest(track.x, track.y, radius, lookback_s, aim)


def request_for(target_id: int, tracks: Sequence[Track], planner: ZonePlanner, lookback_s: float,
                aim: tuple[float, float] | None) -> SpotRequest | None:
    """What to ask a frame's ground view for the target ``target_id`` as the frame's ``tracks``
    confirm it (``spot_request``, the present landing point ``aim`` kept while the zone holds its
    room); None when the frame does not confirm it."""
    track = next((t for t in tracks if t.id == target_id and t.misses == 0), None)
    if track is None:
        return None
    room = planner.room(track)
    return spot_request(track, room, lookback_s, aim_for(aim, track, room))


def usable_spot(spot: Spot | None) -> Spot | None:
    """``spot`` when its point and clearance are finite, else None."""
    ok = spot is not None and all(math.isfinite(v) for v in (spot.x, spot.y, spot.clear_m))
    return spot if ok else None


def worth_moving(spot: Spot, track: Track, room: float) -> bool:
    """Whether the aim should move to ``spot``: ``PLACE_GAIN_M`` farther from where people were
    seen than the present point, and inside the part of ``track`` that keeps ``room`` around it
    (a spot outside it was made for another frame's zone)."""
    if spot.clear_m < was_clear(spot) + PLACE_GAIN_M:
        return False
    return not track.r - math.hypot(spot.x - track.x, spot.y - track.y) < room - 1e-6


def was_clear(spot: Spot) -> float:
    """How far the present landing point was from where people were seen (m; 0 when not measured)."""
    return spot.aim_clear_m if math.isfinite(spot.aim_clear_m) else 0.0


#: A moved landing point is told (``MoveNews``) when it has moved at least this far (m) from the
#: point last told for its zone, at most once per TELL_GAP_S (s): the point follows the risk map
#: frame by frame, and telling each step flooded the ground station (19 texts in 12 s, issue 62).
TELL_MIN_M, TELL_GAP_S = 1.0, 5.0


@dataclass
class MoveNews:
    """Which moves of the landing point the pilot is told of (``TELL_MIN_M``, ``TELL_GAP_S``):
    the point still moves on every frame that moves it; only the words wait."""

    #: zone id -> (north, east m, clearance m, when told s) of the point last told (or chosen).
    told: dict[int, tuple[float, float, float, float]]

    def tell(self, zone_id: int, was: tuple[float, float], was_clear_m: float, spot: Spot,
             now: float) -> tuple[float, float] | None:
        """(distance moved m, clearance then m) to tell for ``zone_id``'s point moving from
        ``was`` (clear by ``was_clear_m``) to ``spot`` at ``now``, or None to say nothing yet."""
        north, east, clear, t = self.told.setdefault(zone_id, (was[0], was[1], was_clear_m, -math.inf))
        moved = math.hypot(spot.x - north, spot.y - east)
        if moved < TELL_MIN_M or now - t < TELL_GAP_S:
            return None
        self.told[zone_id] = (spot.x, spot.y, spot.clear_m, now)
        return moved, clear
