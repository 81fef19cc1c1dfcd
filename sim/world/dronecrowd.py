"""Real people motion for the simulator from the DroneCrowd head trajectories.

DroneCrowd (Wen et al., CVPR 2021) annotates every head in 300-frame, 25 fps, 1920x1080 top-down
drone videos: ``scipy.io.loadmat(f)['anno']`` is an M x 6 int array ``[frame (0-based), track_id,
x1, y1, x2, y2]`` of 20 x 20 px head boxes. The data set is licensed and lives in
``../shared/data/dronecrowd/gt`` beside the repository; nothing of it is copied here, and loading
it where it is absent raises :class:`DroneCrowdUnavailable` (the default world never needs it).

From pixels to metres (the videos carry no altitude or calibration):

1. **Camera motion.** The drone drifts, which moves every head alike. Per frame, the median
   displacement of all heads tracked in both frames is taken as the camera's motion and removed
   (sound when at least half the people do not share one walking direction; crowds of standers
   and criss-crossing walkers, as in these videos).
2. **Scale.** Each track's speed is its net displacement over 1 s windows (25 frames, which
   averages out the annotation's one-pixel jitter), median over the track. The tracks faster
   than the sequence's median are taken as *walkers*, and the median walker speed in px/s is
   set equal to a typical walking speed, 1.3 m/s (adults walk at 1.2-1.5 m/s; Bohannon 1997).
   So ``metres_per_pixel = 1.3 / median_walker_px_per_s``. On the sequences checked (1, 7, 17,
   46, 112) this gives 0.041-0.132 m/px (0.067 for 112), i.e. frames 80-250 m wide and the 20 px
   head box 0.8-2.6 m: a loose box around a head seen from a few tens of metres up to ~150 m,
   which fits the data set's high-altitude views. The figure is an estimate
   (+- 30 %: people dawdle or hurry in groups); pass ``metres_per_pixel`` to override it.

World mapping: image x (right) -> east, image y (down) -> south, image centre -> ``origin``,
optionally turned by ``rotation`` radians about down. Tracks exist only between their first and
last annotated frames (people enter and leave the view); between frames they are linearly
interpolated; annotation glitches are filtered (:func:`cleaned`). The 12 s sequence is played forward then backward (``loop="pingpong"``) so the
motion never jumps.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FPS = 25.0
FRAME_SIZE = (1920, 1080)  # width, height in pixels
WALKING_SPEED = 1.3  # m/s, see the module docstring


class DroneCrowdUnavailable(FileNotFoundError):
    """The DroneCrowd trajectories are not where they were looked for."""


def default_gt_dir() -> Path:
    """``$COMPANION_SHARED/data/dronecrowd/gt``, or ``../shared/data/dronecrowd/gt`` beside the repo."""
    shared = os.environ.get("COMPANION_SHARED")
    base = Path(shared) if shared else Path(__file__).resolve().parents[3] / "shared"
    return base / "data" / "dronecrowd" / "gt"


def sequence_path(sequence: int | str | Path, gt_dir: str | Path | None = None) -> Path:
    """The ``.mat`` file of a sequence number (e.g. 112 -> ``00112.mat``) or a given path."""
    if isinstance(sequence, (str, Path)) and (str(sequence).endswith(".mat") or os.sep in str(sequence)):
        path = Path(sequence)
    else:
        d = Path(gt_dir) if gt_dir is not None else default_gt_dir()
        if not d.is_dir():
            raise DroneCrowdUnavailable(
                f"DroneCrowd trajectories not found: {d} does not exist. They are a licensed data set "
                "kept outside the repository (../shared/data/dronecrowd/gt, or set COMPANION_SHARED); "
                "the default simulator world does not need them (sim.world.crowd.default_world).")
        if isinstance(sequence, Path):
            raise TypeError(f"a DroneCrowd sequence number must be an int or a str, got the path {sequence}")
        path = d / f"{int(sequence):05d}.mat"
    if not path.is_file():
        raise DroneCrowdUnavailable(f"DroneCrowd sequence file {path} does not exist")
    return path


@dataclass(frozen=True)
class Tracks:
    """Head tracks of one sequence in pixels: rows sorted by (track, frame).

    frame: (M,) int, 0-based. track: (M,) int ids. xy: (M, 2) float head centres (x right,
    y down) in pixels of the 1920x1080 frame.
    """

    frame: np.ndarray
    track: np.ndarray
    xy: np.ndarray
    name: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.frame.max()) + 1 if len(self.frame) else 0


def load_tracks(sequence: int | str | Path, gt_dir: str | Path | None = None) -> Tracks:
    """Read one sequence's annotation (see the module docstring for where it is looked for)."""
    import scipy.io

    path = sequence_path(sequence, gt_dir)
    try:
        anno = np.asarray(scipy.io.loadmat(str(path))["anno"], dtype=np.float64)
    except (KeyError, ValueError, OSError) as exc:
        raise ValueError(f"{path} is not a DroneCrowd annotation file ('anno' M x 6): {exc}") from exc
    if anno.ndim != 2 or anno.shape[1] < 6:
        raise ValueError(f"{path}: 'anno' has shape {anno.shape}, expected M x 6")
    order = np.lexsort((anno[:, 0], anno[:, 1]))
    a = anno[order]
    xy = np.column_stack([(a[:, 2] + a[:, 4]) / 2, (a[:, 3] + a[:, 5]) / 2])
    return Tracks(a[:, 0].astype(int), a[:, 1].astype(int), xy, path.stem)


def camera_motion(tracks: Tracks) -> np.ndarray:
    """(n_frames, 2) cumulative image displacement (px) of the camera's drift, frame 0 = (0, 0):
    per frame, the median displacement of heads tracked in both that frame and the next."""
    n = tracks.n_frames
    step = np.zeros((n, 2))
    same = (tracks.track[1:] == tracks.track[:-1]) & (tracks.frame[1:] == tracks.frame[:-1] + 1)
    d = (tracks.xy[1:] - tracks.xy[:-1])[same]
    f = tracks.frame[1:][same]
    for k in range(1, n):
        dk = d[f == k]
        if len(dk):
            step[k] = np.median(dk, axis=0)
    return np.cumsum(step, axis=0)


def stabilised(tracks: Tracks) -> Tracks:
    """The tracks with the camera's drift removed (positions in the frame-0 image)."""
    ego = camera_motion(tracks)
    return Tracks(tracks.frame, tracks.track, tracks.xy - ego[tracks.frame], tracks.name)


def cleaned(tracks: Tracks, max_step_px: float = 8.0) -> Tracks:
    """Tracks without the annotation's glitches: a 5-frame running median per track removes
    one- and two-frame spikes, and a track is split (new id) where it still jumps more than
    ``max_step_px`` between consecutive frames (an identity switch: ~0.2 % of steps in sequence
    112 jump 8-54 px, 10-100 times a walker's 1-2 px per frame)."""
    xy = tracks.xy.copy()
    new_id = tracks.track.copy()
    next_id = int(tracks.track.max()) + 1 if len(tracks.track) else 0
    ids, starts = np.unique(tracks.track, return_index=True)
    ends = np.append(starts[1:], len(tracks.track))
    for a, b in zip(starts, ends):
        if b - a >= 5:
            win = np.lib.stride_tricks.sliding_window_view(
                np.pad(xy[a:b], ((2, 2), (0, 0)), mode="edge"), 5, axis=0)
            xy[a:b] = np.median(win, axis=2)
        step = np.hypot(*np.diff(xy[a:b], axis=0).T)
        cut = np.flatnonzero(step > max_step_px)
        for c in cut:
            new_id[a + c + 1:b] = next_id
            next_id += 1
    order = np.lexsort((tracks.frame, new_id))
    return Tracks(tracks.frame[order], new_id[order], xy[order], tracks.name)


@dataclass(frozen=True)
class ScaleEstimate:
    """metres_per_pixel from the walking-speed assumption, and what it was computed from."""

    metres_per_pixel: float
    walker_speed_px_s: float  # median speed of the walkers, px/s
    n_walkers: int
    n_tracks: int


def track_speeds(tracks: Tracks, window: int = 25) -> np.ndarray:
    """Median speed (px/s) over ``window``-frame spans of every track at least that long."""
    out = []
    for tid in np.unique(tracks.track):
        m = tracks.track == tid
        f, p = tracks.frame[m], tracks.xy[m]
        if len(f) <= window:
            continue
        dt = (f[window:] - f[:-window]) / FPS
        v = np.hypot(*(p[window:] - p[:-window]).T) / dt
        out.append(float(np.median(v)))
    return np.array(out)


def estimate_scale(tracks: Tracks, walking_speed: float = WALKING_SPEED) -> ScaleEstimate:
    """Metres per pixel such that the sequence's walkers walk at ``walking_speed`` m/s (module
    docstring). ``tracks`` should be :func:`stabilised` first."""
    v = track_speeds(tracks)
    if len(v) < 3:
        raise ValueError(f"sequence {tracks.name}: too few long tracks ({len(v)}) to estimate a scale")
    walkers = v[v > max(np.median(v), 1.0)]
    if len(walkers) < 3:  # everyone stands: the fastest third are the best guess at walkers
        walkers = np.sort(v)[-max(3, len(v) // 3):]
    speed = float(np.median(walkers))
    return ScaleEstimate(walking_speed / speed, speed, len(walkers), len(v))


class DroneCrowdMotion:
    """A motion source (see :mod:`sim.world.walkers`) replaying one DroneCrowd sequence in metres.

    sequence: sequence number (e.g. 112) or a ``.mat`` path. origin: world (north, east) m of the
    image centre. metres_per_pixel: override the walking-speed estimate. rotation: radians about
    down applied to the picture (0 = image up is north). loop: ``"pingpong"`` (forward, then
    backward) or ``"once"`` (people vanish after the last frame). gt_dir: where the ``.mat``
    files are (default :func:`default_gt_dir`).
    """

    def __init__(self, sequence: int | str | Path = 112, origin: tuple[float, float] = (0.0, 0.0),
                 metres_per_pixel: float | None = None, rotation: float = 0.0,
                 loop: str = "pingpong", gt_dir: str | Path | None = None) -> None:
        if loop not in ("pingpong", "once"):
            raise ValueError(f"loop must be 'pingpong' or 'once', got {loop!r}")
        raw = load_tracks(sequence, gt_dir)
        self.tracks = cleaned(stabilised(raw))
        self.scale = estimate_scale(self.tracks)
        self.metres_per_pixel = float(metres_per_pixel or self.scale.metres_per_pixel)
        self.origin = (float(origin[0]), float(origin[1]))
        self.rotation = float(rotation)
        self.loop = loop
        self.duration = (self.tracks.n_frames - 1) / FPS
        self.t = 0.0
        ids, starts = np.unique(self.tracks.track, return_index=True)
        self.track_ids = ids
        self._start = starts
        self._end = np.append(starts[1:], len(self.tracks.track))
        self._cache_key: float | None = None
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def step(self, dt: float) -> None:
        self.t += max(float(dt), 0.0)

    def _clip_time(self) -> tuple[float, float]:
        """Sequence time (s) now and the direction of play (+1 forward, -1 backward)."""
        if self.loop == "once" or self.duration <= 0:
            return self.t, 1.0
        tau = self.t % (2 * self.duration)
        return (tau, 1.0) if tau <= self.duration else (2 * self.duration - tau, -1.0)

    def _px_to_world(self, xy: np.ndarray) -> np.ndarray:
        w, h = FRAME_SIZE
        north = -(xy[:, 1] - h / 2) * self.metres_per_pixel
        east = (xy[:, 0] - w / 2) * self.metres_per_pixel
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        return np.column_stack([self.origin[0] + c * north - s * east,
                                self.origin[1] + s * north + c * east])

    def _state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if self._cache_key == self.t and self._cache is not None:
            return self._cache
        tau, direction = self._clip_time()
        fr = tau * FPS
        pos, vel, ids = [], [], []
        tr = self.tracks
        for k, tid in enumerate(self.track_ids):
            a, b = self._start[k], self._end[k]
            f = tr.frame[a:b]
            if fr < f[0] or fr > f[-1] or (self.loop == "once" and self.t > self.duration):
                continue
            x = np.interp(fr, f, tr.xy[a:b, 0])
            y = np.interp(fr, f, tr.xy[a:b, 1])
            # Velocity over +-0.5 s, for the facing direction and the walking gait.
            f0, f1 = max(f[0], fr - 12.5), min(f[-1], fr + 12.5)
            if f1 > f0:
                vx = (np.interp(f1, f, tr.xy[a:b, 0]) - np.interp(f0, f, tr.xy[a:b, 0])) / (f1 - f0) * FPS
                vy = (np.interp(f1, f, tr.xy[a:b, 1]) - np.interp(f0, f, tr.xy[a:b, 1])) / (f1 - f0) * FPS
            else:
                vx = vy = 0.0
            pos.append((x, y))
            vel.append((vx * direction, vy * direction))
            ids.append(tid)
        if not pos:
            empty = np.empty((0, 2))
            self._cache = (empty, np.empty(0), np.empty(0, bool), np.empty(0, int))
        else:
            p = self._px_to_world(np.array(pos))
            v = self._px_to_world(np.array(vel) + np.array(FRAME_SIZE) / 2) - self._px_to_world(
                np.zeros((1, 2)) + np.array(FRAME_SIZE) / 2)
            speed = np.hypot(v[:, 0], v[:, 1])
            self._cache = (p, np.arctan2(v[:, 1], v[:, 0]), speed > 0.3, np.array(ids, int))
        self._cache_key = self.t
        return self._cache

    def positions(self) -> np.ndarray:
        """(N, 2) north, east in metres of the people in view of the original video now."""
        return self._state()[0].copy()

    def headings(self) -> np.ndarray:
        return self._state()[1].copy()

    def moving(self) -> np.ndarray:
        return self._state()[2].copy()

    def ids(self) -> np.ndarray:
        """Stable per-person ids (the data set's track ids), so looks do not jump as N changes."""
        return self._state()[3].copy()

    def speeds(self, dt: float = 0.2) -> np.ndarray:
        """(N,) current speeds in m/s over the next ``dt`` seconds (NaN for people leaving)."""
        t0 = self.t
        p0, id0 = self.positions(), self.ids()
        self.t = t0 + dt
        p1, id1 = self.positions(), self.ids()
        self.t = t0
        _, i0, i1 = np.intersect1d(id0, id1, return_indices=True)
        out = np.full(len(id0), np.nan)
        out[i0] = np.hypot(*(p1[i1] - p0[i0]).T) / dt
        return out
