"""Step 5 of the pipeline: tracking landing zones over time (docs/design.md, the paper's section IV).

One constant-velocity Kalman filter per zone, state ``(x, y, r, dx, dy, dr)`` in head-plane metres
and metres per second, measurement ``(x, y, r)``. Proposals are assigned to tracks by the
Hungarian algorithm on circle IoU with a minimum-IoU gate. A track missed more than ``mu_1``
consecutive frames is deleted; a proposal seen (matched frame to frame) for ``mu_2`` consecutive
frames starts a track while fewer than ``max_tracks`` exist. The oldest stable track is the landing
target.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from scipy.optimize import linear_sum_assignment

from companion.pipeline.circles import Circle, iou_matrix

# Frames further apart than this are not extrapolated: a stalled camera must not let the filter
# coast zones a long way on an old velocity.
MAX_DT = 2.0
MIN_DT = 1e-3
# A zone is confirmed by a view that is smaller than the zone only if the view still reaches this
# far (m) around its centre: a camera that sees next to nothing confirms nothing.
_MIN_VIEW = 0.75
#: The zones' motion models (``TrackerParams.motion``).
MOTIONS = ("velocity", "position")
#: The service's zones, on posed frames in the world frame, are ground: no velocity, and a centre
#: and radius that wander ``GROUND_SIGMA_V`` m per square-root second (about 1 s of lag at 10
#: frames a second; docs/design.md, "Zones are ground"). The velocity model, the paper's, lost in
#: flight (docs/measurements.md) and stays for frames without a pose (the evaluation).
GROUND_MOTION = "position"
GROUND_SIGMA_V = 0.1


@dataclass(frozen=True)
class TrackerParams:
    """sigma_a: process noise scale of the constant-velocity model (m^2/s^4, as ``Q = sigma_a *
    [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]``). r_std: measurement standard deviation of x, y
    and r in metres (R = diag(r_std^2)). min_iou: assignments below this IoU are refused.
    mu_1: a track missed more than this many consecutive frames is deleted. mu_2: consecutive
    frames a proposal must be seen before it becomes a track. max_tracks: N_p.
    motion: "velocity", the paper's constant-velocity model (zones on a plane that moves with
    the camera), or "position": a zone is a piece of ground, its centre and radius only wander
    (a random walk of ``sigma_v`` m per square-root second) and it has no velocity to coast on.
    In the world frame (posed frames) the velocity let a zone slide with its proposals as the
    view moved, and keep sliding: 12-13 m in 4 s into the crowd (docs/design.md, "Zones are
    ground")."""

    sigma_a: float = 0.5
    r_std: tuple[float, float, float] = (0.3, 0.3, 0.3)
    min_iou: float = 0.3
    mu_1: int = 3
    mu_2: int = 3
    max_tracks: int = 5
    motion: str = "velocity"
    sigma_v: float = 0.3

    def __post_init__(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"tracker motion must be one of {MOTIONS}, got {self.motion!r}")
        if not (math.isfinite(self.sigma_v) and self.sigma_v > 0):
            raise ValueError(f"tracker sigma_v must be > 0, got {self.sigma_v!r}")
        if not (math.isfinite(self.sigma_a) and self.sigma_a > 0):
            raise ValueError(f"tracker sigma_a must be > 0, got {self.sigma_a!r}")
        if len(self.r_std) != 3 or not all(math.isfinite(s) and s > 0 for s in self.r_std):
            raise ValueError(f"tracker r_std must be three numbers > 0, got {self.r_std!r}")
        if not 0.0 <= self.min_iou < 1.0:
            raise ValueError(f"tracker min_iou must be in [0, 1), got {self.min_iou!r}")
        for name in ("mu_1", "mu_2", "max_tracks"):
            v = getattr(self, name)
            if int(v) != v or v < (1 if name != "mu_1" else 0):
                raise ValueError(f"tracker {name} must be a positive integer, got {v!r}")


@dataclass(frozen=True)
class Track:
    """A snapshot of one tracked landing zone.

    x, y: filtered centre in head-plane metres (world north/east when poses are known).
    r: radius in metres that is free about (x, y) on the frame that last confirmed the track,
       never larger than the filtered radius: smoothing must not widen a zone into ground the
       camera saw occupied. Measured on that frame's free grid when the tracker is given a
       clearance function, else bounded by the confirming proposal.
    r_filtered: the filter's own radius estimate.
    age: frames since the track was born; hits: frames it was matched; misses: consecutive
    frames without a match (0 = confirmed by the latest frame).
    view_limited: on the confirming frame, ``r`` was bounded by the edge of the camera's view,
    not by anything seen occupied: everything the camera saw within ``r_view`` metres of the
    centre was free (low over a zone, the view is smaller than the zone).
    r_view: how far the view reached from the centre on the confirming frame (m).
    edge: what bounds the zone on the latest frame, set by the pipeline
    (``companion.pipeline.edges``: "people", "surface" or "view"; "" when not judged).
    born_t, last_t: capture times (s) of the birth and of the last confirming frame.
    calm_s: on the confirming frame, how long the ground within r0 plus a margin of the centre
    had been watched and seen free (s, set by the pipeline from its risk map,
    ``riskmap.GroundRiskMap.calm_s``); NaN when not measured (a frame without a pose).
    unwalked_s: on the confirming frame, how long nobody had been seen within r0 plus the calm
    margin of the centre since the camera first saw all of it (s, ``GroundRiskMap.unwalked_s``);
    NaN when not measured.
    steady_s: how long (s, from the first to the latest confirming frame) every frame has
    confirmed the zone with the same ground free: the tracker's steady radius
    (``ZoneTracker.update``'s ``steady_r``) round where that run of frames began, inside the
    zone's free circle. A zone bounded by things that do not move into it (a tree, a bench, a
    crowd that keeps off a lawn) rather than by people walking past. A frame that missed the
    zone, saw less free, or a centre that drifted off that ground (a gap travelling with its
    crowd) starts it again at 0; NaN when not measured (no steady radius given).
    """

    id: int
    x: float
    y: float
    r: float
    r_filtered: float
    age: int
    hits: int
    misses: int
    born_t: float
    last_t: float
    view_limited: bool = False
    r_view: float = math.inf
    edge: str = ""
    calm_s: float = math.nan
    unwalked_s: float = math.nan
    steady_s: float = math.nan

    @property
    def confirmed(self) -> bool:
        return self.misses == 0

    def circle(self) -> Circle:
        return Circle(self.x, self.y, self.r)


def _cp_matrices(dt: float, sigma_v: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant position: (x, y, r) a random walk of sigma_v m per square-root second; the
    velocity half of the state stays zero (no process noise, zero initial covariance)."""
    Q = np.zeros((6, 6))
    Q[0:3, 0:3] = sigma_v**2 * dt * np.eye(3)
    return np.eye(6), Q


_DIAG3 = (np.arange(3), np.arange(3))


def _cv_matrices(dt: float, sigma_a: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant velocity: F moves (x, y, r) by dt times their rates; Q is sigma_a times the
    discrete white-noise acceleration blocks [[dt^4/4, dt^3/2], [dt^3/2, dt^2]] on each axis
    (written entry by entry: ``np.block`` cost more than the filter's own step)."""
    F = np.eye(6)
    F[0:3, 3:6][_DIAG3] = dt
    Q = np.zeros((6, 6))
    Q[0:3, 0:3][_DIAG3] = sigma_a * (dt**4 / 4)
    Q[0:3, 3:6][_DIAG3] = Q[3:6, 0:3][_DIAG3] = sigma_a * (dt**3 / 2)
    Q[3:6, 3:6][_DIAG3] = sigma_a * dt**2
    return F, Q


@functools.cache
def _kalman_filter() -> Any:
    """filterpy's ``KalmanFilter`` class. Imported on first use, not with this module: the
    package's ``__init__`` imports its EKF and statistics, and with them ``scipy.stats`` (about
    0.8 s on the development machine), which every ``companion`` command paid for through
    ``companion.config`` before it could even say a key was wrong. A ``ZoneTracker`` imports it
    when it is made, so the service pays at start-up, never at its first zone."""
    from filterpy.kalman import KalmanFilter

    return KalmanFilter


class _ZoneFilter:
    """One zone's Kalman filter and bookkeeping."""

    def __init__(self, track_id: int, z: Circle, t: float, params: TrackerParams, hits: int):
        kf = _kalman_filter()(dim_x=6, dim_z=3)
        kf.x = np.array([z.x, z.y, z.r, 0.0, 0.0, 0.0])
        kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        kf.R = np.diag(np.square(params.r_std))
        # Position known to the measurement's accuracy; velocity unknown (a zone drifts at most
        # at walking pace, ~2 m/s), or, for a zone that is ground, known to be zero.
        self.still = params.motion == "position"
        kf.P = np.diag([*np.square(params.r_std), *((0.0,) * 3 if self.still else (4.0,) * 3)])
        self.kf = kf
        self.id = track_id
        self.age = 0
        self.hits = hits
        self.misses = 0
        self.born_t = t
        self.last_t = t
        self.last_z = z
        self.clear: float | None = None
        self.view: float = math.inf
        # Capture time of the first frame of the present run of frames that confirmed the zone
        # with the steady radius free (None: no such run, or not measured).
        self.steady_since: float | None = None
        # Where that run began (filtered centre, m): the ground it must keep free.
        self.steady_at: tuple[float, float] | None = None
        self.steady_measured = False

    def predict(self, dt: float, params: TrackerParams) -> None:
        F, Q = _cp_matrices(dt, params.sigma_v) if self.still else _cv_matrices(dt, params.sigma_a)
        self.kf.predict(F=F, Q=Q)
        self._guard_radius()

    def update(self, z: Circle, t: float) -> None:
        self.kf.update(np.array([z.x, z.y, z.r]))
        self._guard_radius()
        self.hits += 1
        self.misses = 0
        self.last_t = t
        self.last_z = z
        self.clear = None

    def _guard_radius(self) -> None:
        if self.kf.x[2] < 0:
            self.kf.x[2] = 0.0
            self.kf.x[5] = max(self.kf.x[5], 0.0)

    def mark_steady(self, steady_r: float | None) -> None:
        """After a confirming frame: go on with the steady run while the disc of ``steady_r``
        round where the run began is still inside the zone's free circle (the snapshot's centre
        and radius), else end it, and begin another here if the zone has ``steady_r`` free (None:
        not measured).

        The same ground, not a free circle of that size: a gap in a walking crowd travels with
        the crowd and keeps its size while the people round it move, and a free circle that is
        always somewhere else says nothing of what walks into any one place of it. A zone bounded
        by a tree or a bench stays where it is."""
        if steady_r is None:
            self.steady_measured, self.steady_since, self.steady_at = False, None, None
            return
        self.steady_measured = True
        x, y = float(self.kf.x[0]), float(self.kf.x[1])
        safe = self._safe_radius()
        if self.steady_since is not None and self.steady_at is not None:
            ax, ay = self.steady_at
            if safe - math.hypot(x - ax, y - ay) >= steady_r:
                return
        if safe >= steady_r:
            self.steady_since, self.steady_at = self.last_t, (x, y)
        else:
            self.steady_since, self.steady_at = None, None

    def _safe_radius(self) -> float:
        x, y, r = (float(v) for v in self.kf.x[:3])
        z = self.last_z
        bound = self.clear if self.clear is not None else z.r - math.hypot(x - z.x, y - z.y)
        return max(0.0, min(r, bound))

    def circle(self) -> np.ndarray:
        x: np.ndarray = self.kf.x  # filterpy is untyped
        return np.array(x[:3], copy=True)  # not .copy(): typed ndarray for mypy at Python 3.10

    def snapshot(self) -> Track:
        x, y, r = (float(v) for v in self.kf.x[:3])
        safe = self._safe_radius()
        limited = self.clear is not None and self.clear >= self.view - 1e-6
        if not self.steady_measured:
            steady = math.nan
        else:
            steady = 0.0 if self.steady_since is None else self.last_t - self.steady_since
        return Track(self.id, x, y, safe, r, self.age, self.hits, self.misses,
                     self.born_t, self.last_t, limited, self.view, steady_s=steady)


@dataclass
class _Candidate:
    circle: Circle
    count: int


def _assign(a: np.ndarray, b: np.ndarray, min_iou: float) -> tuple[list[tuple[int, int]],
                                                                     list[int], list[int]]:
    """Hungarian assignment on IoU; pairs under ``min_iou`` are left unmatched."""
    if len(a) == 0 or len(b) == 0:
        return [], list(range(len(a))), list(range(len(b)))
    iou = iou_matrix(a, b)
    rows, cols = linear_sum_assignment(-iou)
    pairs = [(int(r), int(c)) for r, c in zip(rows, cols) if iou[r, c] >= max(min_iou, 1e-9)]
    ma = {p[0] for p in pairs}
    mb = {p[1] for p in pairs}
    return pairs, [i for i in range(len(a)) if i not in ma], [j for j in range(len(b)) if j not in mb]


class Clearance(Protocol):
    """One frame's measure of the ground (``slz.FrameClearance``): for a plane point (x, y; m),
    how far the ground around it is free and how far the view reaches (m)."""

    def at(self, x: float, y: float) -> tuple[float, float]: ...


class ZoneTracker:
    """Tracks landing zones from per-frame proposals. Call ``update`` once per processed frame."""

    def __init__(self, params: TrackerParams = TrackerParams()):
        _kalman_filter()  # the import's cost now, at start-up, not at the first zone
        self.params = params
        self._filters: list[_ZoneFilter] = []
        self._candidates: list[_Candidate] = []
        self._ids = itertools.count(1)
        self._t: float | None = None
        self.born = 0
        self.ended = 0

    def reset(self) -> None:
        """Forget every zone (for example after the plane frame changed)."""
        self.ended += len(self._filters)
        self._filters.clear()
        self._candidates.clear()
        self._t = None

    def update(self, proposals: list[Circle], t: float, clearance: Clearance | None = None,
               r_min: float | None = None, steady_r: float | None = None) -> list[Track]:
        """Advance to capture time ``t`` (s) with this frame's proposals; returns the tracks.

        clearance: for a plane point, (free radius, view radius) in metres on this frame: how far
        the ground is free and seen around it, and how far the view reaches. When given, each
        confirmed track's radius is measured at its filtered centre, and a track that no
        proposal matched is still confirmed when the ground under it is free on this frame for at
        least ``r_min`` metres (or, when the view is smaller than that, for all the view shows).
        Proposals are the largest circles, which jump about as people move and as the footprint
        changes; the ground under a zone is what decides whether it still holds.

        steady_r: measure each track's ``steady_s`` against this free radius (m; None: not
        measured, NaN).
        """
        if not math.isfinite(t):
            raise ValueError(f"frame time must be finite, got {t!r}")
        p = self.params
        dt = MIN_DT if self._t is None else min(max(t - self._t, MIN_DT), MAX_DT)
        self._t = t
        for f in self._filters:
            f.predict(dt, p)
            f.age += 1

        props = np.array([c.as_array() for c in proposals], dtype=float).reshape(-1, 3)
        preds = np.array([f.circle() for f in self._filters], dtype=float).reshape(-1, 3)
        pairs, missed, unmatched = _assign(preds, props, p.min_iou)
        for fi, pi in pairs:
            f = self._filters[fi]
            f.update(proposals[pi], t)
            if clearance is not None:
                f.clear, f.view = clearance.at(float(f.kf.x[0]), float(f.kf.x[1]))
            f.mark_steady(steady_r)
        for fi in missed:
            f = self._filters[fi]
            if clearance is not None and r_min is not None:
                x, y = float(f.kf.x[0]), float(f.kf.x[1])
                clear, view = clearance.at(x, y)
                if clear >= r_min or (clear >= view - 1e-6 and view >= _MIN_VIEW):
                    f.update(Circle(x, y, clear), t)
                    f.clear, f.view = clear, view
                    f.mark_steady(steady_r)
                    continue
            f.misses += 1
            f.steady_since, f.steady_at = None, None
        alive = [f for f in self._filters if f.misses <= p.mu_1]
        self.ended += len(self._filters) - len(alive)
        self._filters = alive

        self._births([proposals[i] for i in unmatched], t, steady_r)
        return self.tracks()

    def _births(self, unmatched: list[Circle], t: float, steady_r: float | None = None) -> None:
        p = self.params
        cand = np.array([c.circle.as_array() for c in self._candidates]).reshape(-1, 3)
        new = np.array([c.as_array() for c in unmatched]).reshape(-1, 3)
        pairs, _, fresh = _assign(cand, new, p.min_iou)
        kept: list[_Candidate] = [
            _Candidate(unmatched[ni], self._candidates[ci].count + 1) for ci, ni in pairs
        ]
        kept += [_Candidate(unmatched[ni], 1) for ni in fresh]
        # Larger zones first, so that when the track budget is short the biggest is born.
        kept.sort(key=lambda c: (-c.count, -c.circle.r))
        self._candidates = []
        for c in kept:
            if c.count >= p.mu_2 and len(self._filters) < p.max_tracks:
                born = _ZoneFilter(next(self._ids), c.circle, t, p, hits=c.count)
                born.mark_steady(steady_r)
                self._filters.append(born)
                self.born += 1
            else:
                self._candidates.append(c)

    def tracks(self) -> list[Track]:
        return [f.snapshot() for f in self._filters]
