"""Which landing zone to fly to: the planner, separate from the state machine that flies there.

Tracks are ``companion.pipeline.tracker.Track`` snapshots: centre ``x`` north / ``y`` east in
head-plane world NED metres from home, radius ``r`` metres, ``hits`` matched frames, ``misses``
consecutive unmatched frames, ``born_t``/``last_t`` capture times (monotonic s).

A zone is **eligible** as a new target when it is

- confirmed: matched by the latest frame (``misses == 0``) and ``hits >= min_track_hits``;
- old enough: tracked for ``min_track_age_s`` (``last_t - born_t``), so one lucky frame is not enough;
- fresh: ``now - last_t <= zone_max_age_s``;
- large: ``r >= r0_m + radius_margin_m``; or, with ``steady_s`` > 0, *steady*: every frame for
  ``steady_s`` has confirmed it with at least ``r0_m + steady_margin_m`` free (``Track.steady_s``).
  The margin is there for zones bounded by people, who walk into them; a zone whose edge has not
  moved for that long is bounded by what does not (a tree or a bench on a lawn, a crowd that keeps
  off it), and the smaller margin is enough.

The target among eligible zones is the oldest (earliest ``born_t``, then lowest id), as in the paper,
large zones before those only steady, calm zones first: with ``min_calm_s`` > 0, a zone whose ground (r0 plus a margin around its
centre) has been watched and seen free for ``min_calm_s`` (``Track.calm_s``) comes before one
that has not (a gap a walker has just left, a lawn's busy edge). With ``prefer_unwalked``, zones
equally calm are ranked before age by how long nobody has been seen on that ground since the
camera first saw it (``Track.unwalked_s``, whole seconds, longest first): a lawn nobody entered
comes before a gap walkers crossed a moment ago, also after looking away has broken both zones'
calm. The controller also waits for
that calm under the vehicle before it commits the LAND (``companion.control.landing``).
A zone already targeted is **kept** with a looser test (hysteresis, so a radius flickering around
the threshold does not make the vehicle dither): present, ``r >= r0_m``, and confirmed within
``zone_max_age_s``. A kept zone with ``misses > 0`` is *unconfirmed*: no new command goes toward it
until a frame confirms it again, and it is lost once ``zone_max_age_s`` passes. A zone seen with
less than ``r0_m`` free is *small*: the controller drops it once that has lasted its
``lose_after_frames`` frames in a row (one frame's false detection must not throw a landing away:
the network marks a patch of ground as a person in one frame now and then, while a person who
walks in is seen on every frame, so the reaction comes one frame later); gone from the tracks, it
is lost at once.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass

from companion.invariant import require
from companion.pipeline.tracker import Track

#: The least view (m around the zone centre) that can keep confirming a zone during the descent.
MIN_VIEW_M = 0.75


def seen_all_free(track: Track) -> bool:
    """On its confirming frame ``track`` was bounded by the view, not by anything seen occupied,
    with at least ``MIN_VIEW_M`` of view around its centre: everything the camera saw there was
    free (low over a zone the view is smaller than r0)."""
    return track.view_limited and track.r_view >= MIN_VIEW_M


@dataclass(frozen=True)
class PlannerConfig:
    """Zone acceptance thresholds (metres, seconds, frames)."""

    r0_m: float = 2.0
    radius_margin_m: float = 2.0
    min_track_age_s: float = 1.0
    min_track_hits: int = 3
    zone_max_age_s: float = 1.0
    #: Seconds the ground around a landing point must have been watched and seen free before the
    #: LAND (0: not required; see the module docstring).
    min_calm_s: float = 0.0
    #: Rank eligible zones by ``Track.unwalked_s`` (whole seconds, longest first) before age (off
    #: here, the paper's rule; on in the service's settings, ``controller.prefer_unwalked``).
    prefer_unwalked: bool = False
    #: A zone smaller than ``r0_m + radius_margin_m`` is still large enough once every frame for
    #: this long (s) has confirmed it with ``r0_m + steady_margin_m`` free (``Track.steady_s``; 0:
    #: never, the radius margin alone decides; off here, the paper's rule; 8 s with 0.5 m in the
    #: service's settings, ``controller.steady_s``).
    steady_s: float = 0.0
    steady_margin_m: float = 0.5

    @property
    def large_r_m(self) -> float:
        """The radius (m) a zone must have to be chosen on its size alone: r0 plus the margin."""
        return self.r0_m + self.radius_margin_m

    @property
    def steady_r_m(self) -> float:
        """The radius (m) a steady zone must keep free on every frame: r0 plus the steady margin."""
        return self.r0_m + self.steady_margin_m

    def is_steady_sized(self, track: Track) -> bool:
        """Whether ``track`` could become a steady zone by waiting: ``steady_s`` on, and
        ``r0_m + steady_margin_m`` free now (its watch, ``Track.steady_s``, aside)."""
        return self.steady_s > 0 and track.r >= self.steady_r_m

    def is_steady(self, track: Track) -> bool:
        """Whether ``track`` is a steady zone: steady-sized (``is_steady_sized``) and confirmed
        for ``steady_s`` with that much free (its ``steady_s``; NaN, not measured, is not)."""
        return self.is_steady_sized(track) and track.steady_s >= self.steady_s

    def holds_r0(self, free_m: float, all_free: bool) -> bool:
        """Whether ground ``free_m`` metres free around a point is enough to land on: r0, or,
        low down where the view is smaller than r0, ``all_free`` (everything seen there free)."""
        return free_m >= self.r0_m or all_free

    def is_calm(self, calm_s: float) -> bool:
        """Whether ground watched and seen free for ``calm_s`` seconds is calm enough (NaN, not
        measured, is not)."""
        return self.min_calm_s <= 0 or calm_s >= self.min_calm_s

    def __post_init__(self) -> None:
        for name in ("r0_m", "radius_margin_m", "min_track_age_s", "zone_max_age_s", "min_calm_s",
                     "steady_s", "steady_margin_m"):
            value = getattr(self, name)
            require(math.isfinite(value) and value >= 0, "controller", name, "must be >= 0", value)
        for name in ("r0_m", "zone_max_age_s"):
            require(getattr(self, name) > 0, "controller", name, "must be > 0", getattr(self, name))
        require(self.min_track_hits >= 1, "controller", "min_track_hits", "must be >= 1", self.min_track_hits)


class ZoneCheck(enum.Enum):
    OK = "ok"
    UNCONFIRMED = "unconfirmed"  # missed by the latest frame(s), not yet for too long
    SMALL = "small"  # confirmed by this frame, but with less than r0 free: lost if it stays so
    LOST = "lost"


class ZonePlanner:
    def __init__(self, config: PlannerConfig) -> None:
        self.config = config

    def why_not_eligible(self, track: Track, now: float) -> str | None:
        """None when ``track`` may become a target at monotonic time ``now`` (s), else the reason."""
        c = self.config
        if not all(math.isfinite(v) for v in (track.x, track.y, track.r, track.last_t, track.born_t)):
            return "has NaN"
        if track.misses != 0:
            return f"not confirmed by the latest frame ({track.misses} misses)"
        if track.hits < c.min_track_hits:
            return f"young ({track.hits} hits < {c.min_track_hits})"
        if track.last_t - track.born_t < c.min_track_age_s:
            return f"young ({track.last_t - track.born_t:.1f} s < {c.min_track_age_s:g} s)"
        if now - track.last_t > c.zone_max_age_s:
            return f"stale ({now - track.last_t:.1f} s old)"
        if track.r < c.large_r_m and not c.is_steady(track):
            return f"small (r {track.r:.1f} m < {c.large_r_m:.1f} m)"
        return None

    def choose(self, tracks: Iterable[Track], now: float, exclude: Sequence[int] = ()) -> Track | None:
        """The best eligible zone not in ``exclude`` (``_rank``), or None."""
        eligible = [t for t in tracks if t.id not in exclude and self.why_not_eligible(t, now) is None]
        if not eligible:
            return None
        return min(eligible, key=self._rank)

    def _rank(self, t: Track) -> tuple[bool, bool, int, float, int]:
        """Sort key of an eligible zone, best first: large (``r0_m + radius_margin_m``) before
        steady only, then calm, then (``prefer_unwalked``) unwalked for longer in whole seconds
        (NaN, not measured: 0), then oldest, then lowest id."""
        c = self.config
        unwalked = math.floor(t.unwalked_s) if c.prefer_unwalked and math.isfinite(t.unwalked_s) else 0
        return (t.r < c.large_r_m, not c.is_calm(t.calm_s), -unwalked, t.born_t, t.id)

    def could_become_zone(self, tracks: Iterable[Track]) -> bool:
        """Whether any zone the latest frame confirmed is at least ``r0_m`` across: something that
        may still become a landing zone (worth the SELECT's wait, ``select_empty_s``)."""
        r0 = self.config.r0_m
        return any(t.misses == 0 and math.isfinite(t.r) and t.r >= r0 for t in tracks)

    def largest_glimpse(self, tracks: Iterable[Track], exclude: Collection[int] = ()) -> Track | None:
        """The largest zone the latest frame confirmed with at least ``r0_m`` free, not in
        ``exclude``, whether or not it may be chosen yet (free ground glimpsed, for the search),
        or None."""
        leads = [t for t in tracks if t.misses == 0 and t.id not in exclude
                 and math.isfinite(t.x) and math.isfinite(t.y) and t.r >= self.config.r0_m]
        return max(leads, key=lambda t: t.r, default=None)

    def room(self, track: Track) -> float:
        """How much of ``track`` (m) must stay free around its landing point for the point to
        stay put: r0 plus the radius margin, or ``MIN_VIEW_M`` for a zone bounded by the view
        (``seen_all_free``: low down the view is smaller than r0 plus the margin)."""
        return MIN_VIEW_M if seen_all_free(track) else self.config.large_r_m

    def check_target(self, target_id: int, tracks: Iterable[Track], now: float) -> tuple[ZoneCheck, Track | None, str]:
        """Whether the zone being flown to still holds: (verdict, its latest snapshot, reason)."""
        track = next((t for t in tracks if t.id == target_id), None)
        if track is None:
            return ZoneCheck.LOST, None, "no longer tracked"
        if not all(math.isfinite(v) for v in (track.x, track.y, track.r)):
            return ZoneCheck.LOST, track, "has NaN"
        if now - track.last_t > self.config.zone_max_age_s:
            return ZoneCheck.LOST, track, f"not confirmed for {now - track.last_t:.1f} s"
        # Low over the zone the camera sees less than r0 around it; then everything it does see
        # must be free (the tracker says so with view_limited), and it must see at least 0.75 m.
        if track.r < self.config.r0_m and not seen_all_free(track):
            return ZoneCheck.SMALL, track, f"shrank to r {track.r:.1f} m < r0 {self.config.r0_m:g} m"
        if track.misses > 0:
            return ZoneCheck.UNCONFIRMED, track, f"missed by {track.misses} frame(s)"
        return ZoneCheck.OK, track, ""
