"""People on the ground, tracked over frames in the world and predicted to touchdown (issue 11).

The zones say where the ground is free *now*; what a landing needs is where people will be when
the vehicle touches down, seconds later. This stage finds each person in the density map, places
them on the head plane in the world (local NED metres from home), follows them from frame to
frame with a constant-velocity Kalman filter, and answers: how close to a landing point will
anybody seen so far come before touchdown, walking as they are seen walking?

- **Detection**: a person is a local maximum of the density map (``window`` cells square) above
  the occupancy threshold, at least ``edge_px`` from the image's border; its pixel (the cell's
  centre at the map's stride) goes to the head plane through the frame's projection. Two maxima
  closer than ``merge_m`` are one person. Why the border is left out: there the network sees a
  person, or a patch of ground it mistakes for one, a part at a time, and the peak slides as the
  view moves, so the tracker followed it as somebody walking at the camera's pace (measured on
  the simulator's rendered frames: the most common "walker" with nobody there). Occupancy is not
  affected: the border is as occupied as the network says; only who is *followed* starts inside.
- **Tracking**: all people are filtered at once (vectorised numpy: a crowd in view is a hundred
  people, and the post-density budget is a few milliseconds), associated to detections by the
  Hungarian method (``scipy.optimize.linear_sum_assignment``) within ``gate_m`` plus how far a
  walker gets since the last frame. Unmatched detections start people; a person the camera still
  looks at but has not matched for ``max_missed_s`` is dropped, one out of view after
  ``memory_s``.
- **Prediction**: a person seen for ``min_hits`` frames moves on at the filter's velocity when that
  velocity is clear of its own uncertainty (twice its standard deviation), else is taken to stand
  still: noise must not make a standing person "walk" into every zone. The clearance of a point is
  the least distance to any person's predicted path until the horizon, less twice the position's
  standard deviation.

What this cannot know is a person the camera never saw, or one who changes course: walking speed
times the time the camera cannot see the ground around the landing point is a floor no prediction
removes (docs/design.md, "The physics of the last metres").

Units: metres, seconds (capture time), metres per second. Pure numpy/OpenCV/scipy, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from companion.geometry.camera import GeometryError, PlaneProjection
from companion.pipeline.occupancy import occupied_mask


class PeopleError(GeometryError):
    """A frame the people tracker cannot take (a non-finite time, or time going back): the frame
    is dropped and counted, as the risk map's are, and the people stay as they were."""


@dataclass(frozen=True)
class PeopleParams:
    """See the module docstring. window: side of the local-maximum window (density cells, odd).
    merge_m: detections closer than this are one person. gate_m: association distance at no
    elapsed time; walk_speed_mps widens it with the time since the person was last matched.
    meas_std_m: a detection's position error. accel_std: the filter's process noise (m/s^2).
    max_missed_s / memory_s: how long a person not matched is kept in view / out of view.
    min_hits: matched frames before a person's velocity is used (10, about a second: a person
    coming into the view is seen a part at a time, and the first frames' peaks move over them).
    edge_px: peaks closer than this to the image's border (input pixels) are nobody to follow
    (module docstring). 16 px (four cells of a stride-4 map) is about 0.6 m on the ground from
    20 m with a 70 degree 640 px camera: a person walking in is followed that much later."""

    window: int = 3
    merge_m: float = 0.4
    gate_m: float = 1.0
    walk_speed_mps: float = 1.5
    meas_std_m: float = 0.25
    accel_std: float = 1.0
    max_missed_s: float = 0.6
    memory_s: float = 5.0
    min_hits: int = 10
    edge_px: float = 16.0

    def __post_init__(self) -> None:
        if int(self.window) != self.window or self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"people window must be an odd integer >= 1, got {self.window!r}")
        for name in ("merge_m", "gate_m", "walk_speed_mps", "meas_std_m", "accel_std", "max_missed_s", "memory_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"people {name} must be a positive number, got {v!r}")
        if self.min_hits < 1:
            raise ValueError(f"people min_hits must be >= 1, got {self.min_hits!r}")
        if not (math.isfinite(self.edge_px) and self.edge_px >= 0):
            raise ValueError(f"people edge_px must be a number of pixels >= 0, got {self.edge_px!r}")


@dataclass(frozen=True)
class Person:
    """One person followed on the ground. x, y: head-plane position (m, world north/east) at
    ``last_t``; vx, vy: velocity (m/s) as used for prediction (0 while not established);
    pos_std_m: position standard deviation (m); hits: frames matched; last_t: the capture time of
    the last frame that saw them (s)."""

    id: int
    x: float
    y: float
    vx: float
    vy: float
    pos_std_m: float
    hits: int
    last_t: float

    @property
    def speed_mps(self) -> float:
        return math.hypot(self.vx, self.vy)


def density_peaks(density: np.ndarray, threshold: float, image_hw: tuple[int, int],
                  window: int = 3, edge_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The people in one frame's density map, in image pixels: its local maxima (``window`` cells
    square) among the cells the occupancy stage marks occupied (``occupied_mask``: above
    ``min(D) + threshold``), as ((N, 2) pixel centres, (N,) peak values), leaving out those whose
    centre is within ``edge_px`` of the image's border. NaN or infinite density is no person (the
    occupancy stage already marks it occupied)."""
    d = np.asarray(density, dtype=np.float32)
    none = (np.zeros((0, 2)), np.zeros(0))
    if d.ndim != 2 or d.size == 0:
        return none
    finite = np.isfinite(d)
    if not finite.any():
        return none
    above = occupied_mask(d, max(float(threshold), 0.0)) & finite
    d = np.where(finite, d, -np.inf).astype(np.float32)
    peaks = (d >= cv2.dilate(d, np.ones((window, window), np.uint8))) & above
    rows, cols = np.nonzero(peaks)
    h, w = image_hw
    sy, sx = h / d.shape[0], w / d.shape[1]
    uv = np.column_stack([(cols + 0.5) * sx - 0.5, (rows + 0.5) * sy - 0.5]).astype(float)
    strength = d[rows, cols].astype(float)
    if edge_px > 0 and len(uv):
        inside = (uv[:, 0] >= edge_px) & (uv[:, 0] < w - edge_px) & (uv[:, 1] >= edge_px) & (uv[:, 1] < h - edge_px)
        uv, strength = uv[inside], strength[inside]
    return uv, strength


def place_people(uv: np.ndarray, strength: np.ndarray, proj: PlaneProjection, merge_m: float = 0.4) -> np.ndarray:
    """(N, 2) head-plane points (m) of the peaks at ideal (undistorted) pixels ``uv``: points that
    do not project (above the horizon) are dropped, and of two closer than ``merge_m`` (a plateau,
    a double peak of one person) the stronger is kept."""
    if len(uv) == 0:
        return np.zeros((0, 2))
    xy = proj.image_to_plane(np.asarray(uv, dtype=float))
    ok = np.isfinite(xy).all(axis=1)
    xy, strength = xy[ok], np.asarray(strength, dtype=float)[ok]
    if len(xy) < 2:
        return np.asarray(xy, dtype=float)
    xy = xy[np.argsort(-strength, kind="stable")]
    # Greedy, strongest first: a point is dropped when a stronger point that is kept lies within
    # merge_m. Most peaks have no neighbour that close (a crowd is a hundred isolated heads), so
    # only the points of a close pair (found with a k-d tree) go through the loop.
    pairs = cKDTree(xy).query_pairs(merge_m * (1.0 - 1e-9), output_type="ndarray")
    keep = np.ones(len(xy), dtype=bool)
    if len(pairs):
        stronger: dict[int, list[int]] = {int(i): [] for i in np.unique(pairs)}
        for a, b in pairs.tolist():
            stronger[max(a, b)].append(min(a, b))
        for i in sorted(stronger):
            if keep[stronger[i]].any():
                keep[i] = False
    return np.asarray(xy[keep], dtype=float)


def associate(tracks: np.ndarray, points: np.ndarray, gate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Matched (track rows, point rows): the assignment that matches the most tracks ((N, 2) m) to
    points ((M, 2) m) each within its track's ``gate`` ((N,) m), and of those the least total
    distance (Hungarian, ``scipy.optimize.linear_sum_assignment``). The pairs within the gates come
    from a k-d tree, not an N x M matrix: a crowd is hundreds of people, mostly one track near one
    head, and the Hungarian method runs only on those with a choice to make."""
    n, m = len(tracks), len(points)
    none = (np.zeros(0, dtype=int), np.zeros(0, dtype=int))
    if n == 0 or m == 0:
        return none
    gmax = float(np.max(gate))
    if not math.isfinite(gmax) or gmax < 0:
        return none
    sparse = cKDTree(tracks).sparse_distance_matrix(cKDTree(points), gmax, output_type="ndarray")
    i, j, dist = sparse["i"], sparse["j"], sparse["v"]
    ok = dist <= gate[i]
    i, j, dist = i[ok], j[ok], dist[ok]
    if not len(i):
        return none
    # A pair whose track and point are in no other pair is a match with nothing to choose; the
    # Hungarian method runs once, on the tracks and points left (the same optimum: the isolated
    # pairs are independent of the rest).
    single = (np.bincount(i, minlength=n)[i] == 1) & (np.bincount(j, minlength=m)[j] == 1)
    rows, cols = [i[single]], [j[single]]
    if not single.all():
        rest = ~single
        ti, ui = np.unique(i[rest], return_inverse=True)
        pj, vj = np.unique(j[rest], return_inverse=True)
        big = 1e6
        cost = np.full((len(ti), len(pj)), big)
        cost[ui, vj] = dist[rest]
        r, c = linear_sum_assignment(cost)
        good = cost[r, c] < big
        rows.append(ti[r[good]])
        cols.append(pj[c[good]])
    return np.concatenate(rows).astype(int), np.concatenate(cols).astype(int)


class PeopleTracker:
    """Constant-velocity Kalman filters over everyone at once (state x, y, vx, vy per person)."""

    def __init__(self, params: PeopleParams = PeopleParams()) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._x = np.zeros((0, 4))  # state
        self._P = np.zeros((0, 4, 4))  # covariance
        self._ids = np.zeros(0, dtype=int)
        self._hits = np.zeros(0, dtype=int)
        self._last = np.zeros(0)  # last matched capture time
        self._std = np.zeros(0)  # position standard deviation at the last match (m)
        self._t: float | None = None
        self._next_id = 1

    def __len__(self) -> int:
        return len(self._ids)

    def update(self, points: np.ndarray, t: float,
               view: PlaneProjection | None = None, image_hw: tuple[int, int] | None = None) -> list[Person]:
        """Advance to capture time ``t`` (s) with this frame's detections ((N, 2) plane metres).
        ``view`` and ``image_hw``: the frame's projection and size, to tell people the camera
        looks at (dropped after ``max_missed_s`` unmatched) from people out of view (kept for
        ``memory_s``). Times going back are refused with PeopleError (the frame is dropped)."""
        p = self.params
        if not math.isfinite(t):
            raise PeopleError(f"frame time must be finite, got {t!r}")
        if self._t is not None and t < self._t:
            raise PeopleError(f"frame time went back from {self._t} to {t}")
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(axis=1)]
        dt = 0.0 if self._t is None else t - self._t
        self._t = t
        self._predict(dt)
        n = len(self._ids)
        matched_tracks = np.zeros(n, dtype=bool)
        used = np.zeros(len(pts), dtype=bool)
        if n and len(pts):
            gate = p.gate_m + p.walk_speed_mps * np.maximum(t - self._last, 0.0)
            rows, cols = associate(self._x[:, :2], pts, gate)
            self._correct(rows, pts[cols])
            self._std[rows] = np.sqrt(np.maximum(self._P[rows, 0, 0], self._P[rows, 1, 1]))
            self._hits[rows] += 1
            self._last[rows] = t
            matched_tracks[rows] = True
            used[cols] = True
        # Forget people: matched long ago while the camera looks where they should be, or out of
        # view for longer than the memory.
        if n:
            looked = np.zeros(n, dtype=bool)
            if view is not None and image_hw is not None:
                uv = view.plane_to_image(self._x[:, :2])
                h, w = image_hw
                looked = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & \
                    (uv[:, 1] >= 0) & (uv[:, 1] < h)
            unseen = t - self._last
            alive = matched_tracks | np.where(looked, unseen <= p.max_missed_s, unseen <= p.memory_s)
            self._keep(alive)
        new = pts[~used]
        if len(new):
            k = len(new)
            x = np.zeros((k, 4))
            x[:, :2] = new
            P = np.zeros((k, 4, 4))
            P[:, 0, 0] = P[:, 1, 1] = p.meas_std_m ** 2
            P[:, 2, 2] = P[:, 3, 3] = p.walk_speed_mps ** 2  # any walking direction and pace
            self._x = np.concatenate([self._x, x])
            self._P = np.concatenate([self._P, P])
            self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + k)])
            self._hits = np.concatenate([self._hits, np.ones(k, dtype=int)])
            self._last = np.concatenate([self._last, np.full(k, t)])
            self._std = np.concatenate([self._std, np.full(k, p.meas_std_m)])
            self._next_id += k
        return self.people()

    def people(self) -> list[Person]:
        """Everyone followed now, with the velocity used for prediction (see the module docstring)."""
        p = self.params
        v = self._x[:, 2:]
        v_std = np.sqrt(np.maximum(self._P[:, 2, 2], self._P[:, 3, 3]))
        moving = (self._hits >= p.min_hits) & (np.hypot(v[:, 0], v[:, 1]) > 2 * v_std)
        v_used = np.where(moving[:, None], v, 0.0)
        # Where they were when last seen (the filter's state is predicted to the latest frame,
        # but a person not matched since is reported as seen: the prediction moves them on).
        age = np.maximum((self._t or 0.0) - self._last, 0.0)
        seen_xy = self._x[:, :2] - self._x[:, 2:] * age[:, None]
        # tolist() converts to Python numbers in one call (a crowd is hundreds of people a frame).
        return list(map(Person, self._ids.tolist(), seen_xy[:, 0].tolist(), seen_xy[:, 1].tolist(),
                        v_used[:, 0].tolist(), v_used[:, 1].tolist(), self._std.tolist(), self._hits.tolist(),
                        self._last.tolist()))

    # -- the filter ------------------------------------------------------------------------

    def _predict(self, dt: float) -> None:
        if not len(self._ids) or dt <= 0:
            return
        F = np.eye(4)
        F[0, 2] = F[1, 3] = dt
        q = self.params.accel_std ** 2
        g = np.array([0.5 * dt * dt, dt])
        Q1 = q * np.outer(g, g)  # white acceleration, per axis
        Q = np.zeros((4, 4))
        Q[np.ix_([0, 2], [0, 2])] = Q1
        Q[np.ix_([1, 3], [1, 3])] = Q1
        self._x = self._x @ F.T
        self._P = F @ self._P @ F.T + Q

    def _correct(self, rows: np.ndarray, z: np.ndarray) -> None:
        if not len(rows):
            return
        # The measurement is the position (H = [I 0]): S = P_pp + R, K = P[:, :2]^T S^-1, written
        # out instead of multiplied through H (hundreds of people a frame).
        P = self._P[rows]
        S = P[:, :2, :2] + np.eye(2) * self.params.meas_std_m ** 2
        K = P[:, :, :2] @ np.linalg.inv(S)
        y = z - self._x[rows][:, :2]
        self._x[rows] = self._x[rows] + np.einsum("nij,nj->ni", K, y)
        self._P[rows] = P - K @ P[:, :2, :]

    def _keep(self, alive: np.ndarray) -> None:
        self._x, self._P = self._x[alive], self._P[alive]
        self._ids, self._hits, self._last = self._ids[alive], self._hits[alive], self._last[alive]
        self._std = self._std[alive]


def predicted_clearance(people: list[Person], x: float, y: float, t: float, horizon_s: float,
                        from_s: float = 0.0) -> float:
    """The least distance (m) anybody in ``people`` comes to the point (x, y) between times
    ``t + from_s`` and ``t + horizon_s`` (s), each moving on at their predicted velocity from
    where they were last seen, less twice their position's standard deviation at that sighting;
    inf with nobody (or an empty window). Never negative."""
    if not people or horizon_s < from_s:
        return math.inf
    a = np.array([[q.x, q.y, q.vx, q.vy, q.pos_std_m, q.last_t] for q in people], dtype=float)
    age = np.maximum(t - a[:, 5], 0.0)
    # Position now (moved on since it was last seen), and its offset from the point.
    dx = a[:, 0] + a[:, 2] * age - x
    dy = a[:, 1] + a[:, 3] * age - y
    vv = a[:, 2] ** 2 + a[:, 3] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(vv > 0, -(dx * a[:, 2] + dy * a[:, 3]) / vv, 0.0)
    tau = np.clip(tau, max(from_s, 0.0), max(horizon_s, 0.0))
    d = np.hypot(dx + a[:, 2] * tau, dy + a[:, 3] * tau) - 2.0 * a[:, 4]
    return float(max(0.0, d.min()))
