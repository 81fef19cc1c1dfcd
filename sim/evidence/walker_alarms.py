"""The people stage's walkers against the simulator's truth: how often the landing question is
answered wrongly.

``python -m sim.evidence.walker_alarms --seeds 2,5,8,9 [--edge-px 0,16] [--seconds 30] [--model FILE.onnx]
[--ground photo [--photos DIR]]``

With ``controller.predict_people`` the controller asks, just before it commits a landing, whether
anybody seen walking will come within ``r0`` of the landing point while the landing is committed
(docs/design.md, "People followed to touchdown"). This measures the answer on the simulator's own
frames, where the truth is known:

- for every seed with a free circle, the seed's world (its crossing walkers too, from 2 s) is
  rendered for ``--seconds`` from a camera coming down over the circle's centre from 18 m at
  1/3 m/s, no lower than 8 m (reached at 30 s), with a little sway and tilt, as a hovering
  multicopter does;
- the model runs once per frame; for each ``--edge-px`` (``PeopleParams.edge_px``) the people
  stage follows the people in those maps and, from 3 s on, on every frame the prediction is
  asked about the circle's centre for the window ``--blind-from`` to ``--horizon`` seconds ahead
  (4.5 to 8 s: the descent from 10 m at 1.5 m/s to 4 m, then the LAND at 1 m/s, committed
  below 3.5 m);
- the truth: whether anybody in the world comes within ``r0`` of the centre in that window.

Per seed and in all: **false alarms** (the prediction says somebody comes, nobody does; each
frame would hold the landing back), **alarms** when somebody does come, how many alarms a real
walker raised (a person of the world within 1 m of where the tracker puts the alarming walker
now) rather than a phantom (nobody there: a peak of the network that moves), and the walkers
followed with nobody within 1 m; and for the real walkers, the tracker's speed against theirs
over the last second (mean error, mean absolute error, how often over 1.5 times theirs). A
danger the camera cannot see (a walker outside the view) is counted as missed: that is the floor
of "The physics of the last metres", not a fault of the tracker.

``--ground photo`` (``--photos DIR``, default ``../shared/data/semantic_drone/full``) asks the same
over the photo world (docs/photo-world.md): each seed's photo scene as the flights build it, its
circle landable by the class maps, its walkers real silhouettes keeping to walkable ground, and
the photos' own people in the truth (they stand still). Each seed then also says how many of
the world's people, frame by frame, stood off walkable ground by the class maps (the crossing
world's crossers keep to it too since session 29, as in the flights).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from companion.config import SHIPPED_MODEL
from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.density import DensityModel
from companion.pipeline.people import (
    PeopleParams,
    PeopleTracker,
    Person,
    density_peaks,
    place_people,
    predicted_clearance,
)
from companion.pipeline.slz import PipelineConfig
from sim.flights.flight import build_world, crossing_walkable, photo_ground
from sim.flights.scenarios import FlightJob, parse_seeds, scenario
from sim.flights.spec import photos_folder
from sim.world.crowd import World, add_crossing_walkers
from sim.world.ground import ProceduralGround
from sim.world.photo_ground import PhotoGround
from sim.world.render import render_world

#: The head plane the service places people on (m above the ground).
HEAD_M = PipelineConfig().head_height_m
FPS = 10.0
#: Metres: a walker followed within this of a person of the world is that person.
SAME_PERSON_M = 1.0
#: Seconds: the prediction is asked from then on (the tracker needs a second to give a velocity).
ASK_FROM_S = 3.0


@dataclass
class AlarmFigure:
    """One seed, one ``edge_px``: frame counts (see the module docstring)."""

    seed: int
    world: str
    edge_px: float
    safe_frames: int = 0
    false_alarms: int = 0
    false_alarms_by_phantoms: int = 0
    danger_frames: int = 0
    alarms: int = 0
    alarms_by_real_walkers: int = 0
    walker_frames: int = 0
    phantom_walker_frames: int = 0
    #: Real walkers (see ``is_real``) whose person of the world was also there a second before:
    #: how many such frames, the sum of the tracker's speed less theirs (m/s), of its absolute
    #: value, and how many times the tracker's speed was over 1.5 times theirs.
    speed_frames: int = 0
    speed_error_sum: float = 0.0
    speed_abs_error_sum: float = 0.0
    speed_over_1_5: int = 0
    ground: str = "procedural"

    @property
    def false_alarm_rate(self) -> float:
        return self.false_alarms / self.safe_frames if self.safe_frames else math.nan

    @property
    def alarm_rate(self) -> float:
        return self.alarms / self.danger_frames if self.danger_frames else math.nan

    def add(self, other: AlarmFigure) -> None:
        for name in ("safe_frames", "false_alarms", "false_alarms_by_phantoms", "danger_frames", "alarms",
                     "alarms_by_real_walkers", "walker_frames", "phantom_walker_frames", "speed_frames",
                     "speed_error_sum", "speed_abs_error_sum", "speed_over_1_5"):
            setattr(self, name, getattr(self, name) + getattr(other, name))


@dataclass(frozen=True)
class Frame:
    """One rendered frame's density map with its capture time and pose, and the world's people
    then (ground positions, north/east metres, and their ids)."""

    t: float
    pose: Pose
    density: np.ndarray
    people: np.ndarray = field(repr=False)
    #: The world's stable person ids, one per row of ``people``.
    ids: np.ndarray = field(repr=False, default_factory=lambda: np.empty(0, np.int64))


@dataclass(frozen=True)
class Descent:
    """One seed's world seen coming down over its free circle: the world's name, the circle's
    centre (north, east m), the camera's intrinsics, the frames, and the world's people every
    0.1 s until some seconds after the last frame ((time, (N, 2) positions)). No frames for a
    world without a free circle."""

    world: str
    centre: tuple[float, float]
    intrinsics: Intrinsics
    frames: list[Frame]
    truth: list[tuple[float, np.ndarray]] = field(repr=False)
    ground: str = "procedural"
    #: Photo ground: the world's people seen in the frames (people x frames), and how many of
    #: them stood off walkable ground by the class maps; 0 and 0 on the drawn ground.
    people_frames: int = 0
    off_walkable: int = 0


def everyone(world: World) -> tuple[np.ndarray, np.ndarray]:
    """The world's people, moving and fixed in the ground (the photos' people, who count for the
    truth as everyone else), (N, 2) north/east m, and their ids (the fixed ones' negative)."""
    people, ids = world.positions().copy(), world.ids().copy()
    fixed = np.empty((0, 2)) if world.fixed_people is None else np.asarray(world.fixed_people, float).reshape(-1, 2)
    if len(fixed) == 0:
        return people, ids
    return np.vstack([people, fixed]), np.concatenate([ids, -1 - np.arange(len(fixed), dtype=np.int64)])


def fly_over_circle(model: DensityModel, seed: int, seconds: float = 30.0, horizon_s: float = 8.0,
                    photos: str | None = None) -> Descent:
    """The :class:`Descent` of ``seed``: frames for ``seconds``, the truth until ``horizon_s``
    after the last frame. ``photos``: the seed's photo world over that folder's photos instead
    of its drawn world."""
    # The scene does not depend on the flavour.
    spec = (scenario(seed, "ardupilot") if photos is None
            else FlightJob(seed, "ardupilot", ground="photo", photos=photos).spec())
    world, free, _start = build_world(spec)
    kk = Intrinsics.from_fov(640, 480, spec.hfov_deg)
    if free is None:
        return Descent(spec.world, (math.nan, math.nan), kk, [], [], spec.ground)
    if spec.world == "crossing":
        add_crossing_walkers(world, free, 2.0, spec.seed, walkable=crossing_walkable(spec, free))
    ground: ProceduralGround | PhotoGround = ProceduralGround(seed) if photos is None else photo_ground(photos)
    # The ground people walk on around the circle: as far as a 90 deg view reaches from 18 m.
    walkable = None if photos is None else photo_ground(photos).walkable((free.north, free.east), 60.0)
    frames: list[Frame] = []
    truth: list[tuple[float, np.ndarray]] = []
    seen = off = 0
    for _ in range(int(round((seconds + horizon_s) * FPS))):
        world.step(1.0 / FPS)
        t = world.t
        people, ids = everyone(world)
        truth.append((t, people))
        if t > seconds + 1e-9:
            continue
        if walkable is not None:
            moving = world.positions()
            seen += len(moving)
            off += int(np.count_nonzero(~walkable(moving)))
        height = max(18.0 - t / 3.0, 8.0)
        pose = Pose(t, free.north + 0.3 * math.sin(0.7 * t), free.east + 0.3 * math.cos(0.5 * t), -height,
                    math.radians(1.5) * math.sin(1.1 * t), math.radians(1.5) * math.cos(0.9 * t), 0.2)
        frames.append(Frame(t, pose, model(render_world(world, pose, kk, Mount(), ground)), people, ids))
    return Descent(spec.world, (free.north, free.east), kk, frames, truth, spec.ground, seen, off)


def nearest(q: Person, t: float, people: np.ndarray) -> int | None:
    """The row of the person of the world (``people``, ground north/east m) nearest to where the
    tracker puts ``q`` at time ``t`` (seen at ``q.last_t``, walking on since), if within
    ``SAME_PERSON_M``; else None."""
    if len(people) == 0:
        return None
    age = max(t - q.last_t, 0.0)
    x, y = q.x + q.vx * age, q.y + q.vy * age
    dist = np.hypot(people[:, 0] - x, people[:, 1] - y)
    k = int(np.argmin(dist))
    return k if float(dist[k]) <= SAME_PERSON_M else None


def is_real(q: Person, t: float, people: np.ndarray) -> bool:
    """Whether a person of the world stands within ``SAME_PERSON_M`` of where the tracker puts
    ``q`` at time ``t`` (``nearest``)."""
    return nearest(q, t, people) is not None


def true_speed(now: Frame, before: Frame, row: int) -> float | None:
    """The ground speed (m/s) of the person on ``row`` of ``now.people`` between ``before`` and
    ``now``, by their id; None when they were not in the world then (or without ids)."""
    if len(now.ids) != len(now.people) or len(before.ids) != len(before.people) or now.t <= before.t:
        return None
    then = np.nonzero(before.ids == now.ids[row])[0]
    if len(then) != 1:
        return None
    step = now.people[row] - before.people[int(then[0])]
    return float(np.hypot(step[0], step[1])) / (now.t - before.t)


def score(descent: Descent, threshold: float, params: PeopleParams, r0_m: float = 2.0,
          blind_from_s: float = 4.5, horizon_s: float = 8.0) -> AlarmFigure:
    """Follow the people in ``descent``'s frames with ``params`` and count the prediction's
    answers at its circle's centre against its truth (module docstring), and the tracker's
    speeds against the real walkers' own over the last second. The seed is left 0."""
    kk, truth = descent.intrinsics, descent.truth
    image_hw = (kk.height, kk.width)
    tracker = PeopleTracker(params)
    fig = AlarmFigure(0, descent.world, params.edge_px, ground=descent.ground)
    lag = int(round(FPS))  # frames: the truth's speed over the last second
    times = np.array([t for t, _ in truth])
    cn, ce = descent.centre
    for k, fr in enumerate(descent.frames):
        proj = PlaneProjection.from_pose(kk, Mount(), fr.pose, HEAD_M)
        uv, strength = density_peaks(fr.density, threshold, image_hw, params.window, params.edge_px)
        followed = tracker.update(place_people(uv, strength, proj, params.merge_m), fr.t, view=proj,
                                  image_hw=image_hw)
        if fr.t < ASK_FROM_S:
            continue
        walkers = [q for q in followed if q.speed_mps > 0]
        rows = [nearest(q, fr.t, fr.people) for q in walkers]
        fig.walker_frames += len(walkers)
        fig.phantom_walker_frames += sum(row is None for row in rows)
        for q, row in zip(walkers, rows, strict=True):
            speed = None if row is None or k < lag else true_speed(fr, descent.frames[k - lag], row)
            if speed is not None:
                fig.speed_frames += 1
                fig.speed_error_sum += q.speed_mps - speed
                fig.speed_abs_error_sum += abs(q.speed_mps - speed)
                fig.speed_over_1_5 += int(q.speed_mps > 1.5 * speed)
        window = (times >= fr.t + blind_from_s - 1e-9) & (times <= fr.t + horizon_s + 1e-9)
        if times[-1] < fr.t + horizon_s - 1e-9 or not window.any():
            continue
        true_clear = min((float(np.hypot(p[:, 0] - cn, p[:, 1] - ce).min()) if len(p) else math.inf)
                         for (_, p), w in zip(truth, window, strict=True) if w)
        clear, who = min(((predicted_clearance([q], cn, ce, fr.t, horizon_s, blind_from_s), q) for q in walkers),
                         key=lambda pair: pair[0], default=(math.inf, None))
        danger, alarm = true_clear < r0_m, clear < r0_m
        if danger:
            fig.danger_frames += 1
            fig.alarms += int(alarm)
            fig.alarms_by_real_walkers += int(alarm and who is not None and is_real(who, fr.t, fr.people))
        else:
            fig.safe_frames += 1
            fig.false_alarms += int(alarm)
            fig.false_alarms_by_phantoms += int(alarm and who is not None and not is_real(who, fr.t, fr.people))
    return fig


def _line(f: AlarmFigure, label: str) -> str:
    n = max(f.speed_frames, 1)
    return (f"{label:<22} edge {f.edge_px:>4g} px  false alarms {f.false_alarms:>4}/{f.safe_frames:<4} "
            f"({100 * f.false_alarm_rate:5.1f} %, {f.false_alarms_by_phantoms} by phantoms)  "
            f"alarms {f.alarms:>4}/{f.danger_frames:<4} ({100 * f.alarm_rate:5.1f} %, "
            f"{f.alarms_by_real_walkers} by real walkers)  phantom walkers {f.phantom_walker_frames}/{f.walker_frames}  "
            f"speed error {f.speed_error_sum / n:+.2f} m/s (mean |.| {f.speed_abs_error_sum / n:.2f}, "
            f"over 1.5x {f.speed_over_1_5}/{f.speed_frames})")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.evidence.walker_alarms", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="2,5,8,9", help="seeds with a free circle, e.g. 2,5,8,9 or 1-20")
    ap.add_argument("--edge-px", default="16", help="PeopleParams.edge_px values to compare (default 16)")
    ap.add_argument("--seconds", type=float, default=30.0, help="length of the descent in s (default 30)")
    ap.add_argument("--blind-from", type=float, default=4.5, help="start of the predicted window, s (default 4.5)")
    ap.add_argument("--horizon", type=float, default=8.0, help="end of the predicted window, s (default 8)")
    ap.add_argument("--model", type=Path, default=SHIPPED_MODEL, help="ONNX density model (default: the shipped one)")
    ap.add_argument("--ground", choices=("procedural", "photo"), default="procedural",
                    help="the drawn ground (default) or the photo world's (docs/photo-world.md)")
    ap.add_argument("--photos", type=Path, default=None,
                    help="the photos of --ground photo (default ../shared/data/semantic_drone/full)")
    ap.add_argument("--json", action="store_true", help="one JSON object per seed and edge, then the totals")
    args = ap.parse_args(argv)
    try:
        photos = photos_folder(args.ground, args.photos)
    except ValueError as e:
        print(f"error: --photos: {e}", file=sys.stderr)
        return 2
    try:
        seeds = parse_seeds(args.seeds)
        edges = [float(e) for e in args.edge_px.split(",")]
        if not all(math.isfinite(e) and e >= 0 for e in edges):
            raise ValueError(f"--edge-px must be pixels >= 0, got {args.edge_px!r}")
        if not (ASK_FROM_S < args.seconds <= 600 and 0 <= args.blind_from <= args.horizon <= 120):
            raise ValueError("need 3 < --seconds <= 600 and 0 <= --blind-from <= --horizon <= 120")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not args.model.is_file():
        print(f"error: no model at {args.model}", file=sys.stderr)
        return 2
    model = DensityModel(args.model, threads=2)
    threshold = float(model.spec.occupancy_threshold or 0.0)
    totals = {edge: AlarmFigure(0, "all", edge, ground=args.ground) for edge in edges}
    for seed in seeds:
        descent = fly_over_circle(model, seed, args.seconds, args.horizon, photos)
        if not descent.frames:
            print(f"seed {seed}: {descent.world} has no free circle, skipped", file=sys.stderr)
            continue
        if photos is not None:
            print(f"seed {seed}: {descent.off_walkable} of {descent.people_frames} people x frames stood off "
                  "walkable ground by the class maps", file=sys.stderr)
        for edge in edges:
            fig = score(descent, threshold, PeopleParams(edge_px=edge), blind_from_s=args.blind_from,
                        horizon_s=args.horizon)
            fig.seed = seed
            totals[edge].add(fig)
            print(json.dumps(asdict(fig)) if args.json else _line(fig, f"seed {seed} ({descent.world})"), flush=True)
    for fig in totals.values():
        print(json.dumps({**asdict(fig), "seed": None}) if args.json else _line(fig, "all"), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
