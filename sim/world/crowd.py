"""The simulated world: people on the ground that the simulated camera sees.

World frame: local NED metres, origin at home, ground at ``z = 0``; people are points
``(north, east)`` on the ground with a heading (radians from north toward east). The world has its
own clock ``t`` (seconds), advanced only by :meth:`World.step` (the simulator steps it with its
clock). The people move in fixed ticks of ``TICK_S`` whatever steps the clock is given, so the world
at time ``t`` depends on the seed and ``t`` alone, not on how a loaded machine sliced the time:
the same seed flown twice meets the same people at the same world time. A world can be
``paused`` (its clock stands still): a flight starts the clock when the service is ready, so the
people at the failsafe do not depend on how long the service took to start.

Scenario builders for the SITL tests:

- :func:`default_world`: a park-like mix of walkers, groups and standing people.
- :func:`crowd_with_free_area`: the same, with a circle that nobody ever enters
  (``world.free_areas``).
- :func:`dense_crowd`: people everywhere in a square around a point (everywhere people can stand),
  no landing circle anywhere.
- :meth:`World.add_intrusion`: people that walk into a circle at a given time (and stay).
- :meth:`World.add_crossing` / :func:`add_crossing_walkers`: people that walk across a circle and
  out again, at walking speed, at given times (the ``crossing`` scenario: a landing zone crossed
  during the descent).
- :func:`dronecrowd_world`: real trajectories from DroneCrowd (needs ``../shared``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from sim.world.walkers import (
    Bounds,
    Circle,
    Crossing,
    CrowdParams,
    GeneratedCrowd,
    Intrusion,
    MillingCrowd,
    MotionSource,
    ScriptedWalkers,
    Walkable,
)

__all__ = ["World", "Bounds", "Circle", "Crossing", "Intrusion", "default_world", "crowd_with_free_area",
           "dense_crowd", "dronecrowd_world", "largest_free_circle", "add_crossing_walkers",
           "CROSSING_SPEEDS", "CROSSING_WINDOW_S", "RUNNER_SPEEDS", "TICK_S"]

#: Walking speeds of the ``crossing`` world's walkers, m/s, drawn uniformly: adults' preferred
#: speeds are about 1.2-1.5 m/s (Bohannon 1997, Mohler et al. 2007), slower in a crowd.
CROSSING_SPEEDS = (1.0, 1.5)
#: Speeds of the crossing world's runners and cyclists (m/s, drawn uniformly; ``runners`` of
#: :func:`add_crossing_walkers`): a jogger's 2.4 m/s up to a slow cyclist's 3 m/s, the upper bound
#: the landing rules are tested against (issue 60, item 5).
RUNNER_SPEEDS = (2.4, 3.0)
#: When they cross the circle's edge, seconds after the failsafe, drawn uniformly: the companion
#: descends into its zone from about 5 s after the trigger to touchdown at 21-34 s when it lands
#: without holding (seeds 1-8 of docs/scale.md, "Measured"), and a walker at these speeds is
#: inside a 5-8 m circle for up to 7-16 s.
CROSSING_WINDOW_S = (4.0, 24.0)
#: The people's fixed time step (s). Walkers draw random numbers every step (standing people
#: turning, new goals), so steps of varying length gave varying draws and, a few seconds on,
#: different crowds from the same seed: runs of one seed were not repeatable. At walking pace a
#: tick moves a person 3 cm, about one pixel from 15 m.
TICK_S = 0.02


@dataclass
class World:
    """People from one or more motion sources, with a clock.

    sources: motion sources (see :mod:`sim.world.walkers`); their people are listed in order.
    free_areas: circles the scenario guarantees nobody enters (scripted intruders excepted).
    seed: the seed the scenario was built from (people's looks are drawn from it too).
    """

    sources: list[MotionSource] = field(default_factory=list)
    free_areas: list[Circle] = field(default_factory=list)
    seed: int = 0
    t: float = 0.0
    paused: bool = False
    #: (M, 2) people who stand still where the ground shows them (north, east m): the people of
    #: the photo ground's photos. The judge counts them (``nearest_person_distance``,
    #: ``people_within``) like everyone else; they are not in ``positions()``, which lists the
    #: people the renderer draws (these are in the ground's pixels already).
    fixed_people: np.ndarray | None = None
    _ticks: int = field(default=0, init=False, repr=False)
    _pending: float = field(default=0.0, init=False, repr=False)
    _t0: float = field(default=0.0, init=False, repr=False)

    def __post_init__(self) -> None:
        self._t0 = self.t  # a world made at a later time keeps counting from it

    def step(self, dt: float) -> None:
        """Advance the clock by ``dt`` seconds and every source by the whole ``TICK_S`` ticks
        that have passed (the rest carries over to the next step). Negative, zero or NaN does
        nothing; so does any step while ``paused``. ``t`` is the time of the last tick."""
        if not math.isfinite(dt) or dt <= 0 or self.paused:
            return
        self._pending += dt
        # The 1e-6 forgives float sums (0.3 / 0.02 is 14.999...): a tick is not lost to rounding.
        n = int(math.floor(self._pending / TICK_S + 1e-6))
        if n <= 0:
            return
        self._pending = max(0.0, self._pending - n * TICK_S)
        for _ in range(n):
            for s in self.sources:
                s.step(TICK_S)
        self._ticks += n
        # From the tick count, not a running sum, so that t is the same however it was reached.
        self.t = self._t0 + self._ticks * TICK_S

    def positions(self) -> np.ndarray:
        """(N, 2) float array of people's ground positions (north, east), metres."""
        parts = [np.asarray(s.positions(), float).reshape(-1, 2) for s in self.sources]
        return np.vstack(parts) if parts else np.empty((0, 2))

    def headings(self) -> np.ndarray:
        """(N,) facing directions, radians from north toward east."""
        parts = [np.asarray(s.headings(), float).ravel() for s in self.sources]
        return np.concatenate(parts) if parts else np.empty(0)

    def moving(self) -> np.ndarray:
        """(N,) bool, True for people walking at this instant (drawn with their legs apart)."""
        parts = [np.asarray(s.moving(), bool).ravel() for s in self.sources]
        return np.concatenate(parts) if parts else np.empty(0, bool)

    def ids(self) -> np.ndarray:
        """(N,) stable person ids (a person keeps its id, and so its looks, while others come and
        go): ``1_000_000 * source index + the source's own id`` (its list index if it has none)."""
        parts = []
        for k, s in enumerate(self.sources):
            own = s.ids() if hasattr(s, "ids") else np.arange(len(s.positions()))
            parts.append(np.asarray(own, np.int64).ravel() + 1_000_000 * k)
        return np.concatenate(parts) if parts else np.empty(0, np.int64)

    def __len__(self) -> int:
        return len(self.positions())

    def nearest_person_distance(self, point: tuple[float, float] | np.ndarray) -> float:
        """Horizontal distance (m) from ``point`` (north, east) to the nearest person; inf if none."""
        p = self._everyone()
        if len(p) == 0:
            return math.inf
        q = np.asarray(point, float).ravel()[:2]
        return float(np.min(np.hypot(p[:, 0] - q[0], p[:, 1] - q[1])))

    def people_within(self, circle: Circle) -> int:
        """How many people stand inside ``circle`` now."""
        p = self._everyone()
        return int(np.count_nonzero(circle.distance(p) < circle.radius)) if len(p) else 0

    def _everyone(self) -> np.ndarray:
        """The people who move and those fixed in the ground (:attr:`fixed_people`), (N, 2)."""
        p = self.positions()
        if self.fixed_people is None or len(self.fixed_people) == 0:
            return p
        return np.vstack([p, np.asarray(self.fixed_people, float).reshape(-1, 2)])

    def nobody_walks_at(self, point: tuple[float, float]) -> bool | None:
        """Whether ``point`` (north, east, m) is ground nobody walks into: inside a free area, or
        outside the bounds every crowd keeps to. Scripted crossers and intruders, and walkers who
        cross open ground (``crosses_open_ground``), do not count (they are the test). None when a source has no bounds to tell by (real DroneCrowd motion)."""
        q = np.asarray(point, float).reshape(1, 2)
        if any(float(c.distance(q)[0]) <= c.radius for c in self.free_areas):
            return True
        crowds = [s for s in self.sources
                  if not isinstance(s, ScriptedWalkers) and not getattr(s, "crosses_open_ground", False)]
        if any(not hasattr(s, "bounds") for s in crowds):
            return None
        return not any(bool(s.bounds.contains(q)[0]) for s in crowds)  # type: ignore[attr-defined]

    def add_source(self, source: MotionSource) -> None:
        """Add people (the source's own clock is taken as already at ``self.t``)."""
        self.sources.append(source)

    def add_intrusion(self, circle: Circle | tuple[float, float, float], t_enter: float,
                      count: int = 1, speed: float = 1.3, bearing: float = 0.0,
                      approach_m: float = 8.0) -> Intrusion:
        """People that walk into ``circle`` (north, east, radius m): the first crosses its edge at
        world time ``t_enter`` (s), all stop near its centre. Returns the script."""
        c = circle if isinstance(circle, Circle) else Circle(*map(float, circle))
        it = Intrusion(c, float(t_enter), int(count), float(speed), float(approach_m), float(bearing))
        self._scripted().add(it)
        return it

    def add_crossing(self, crossing: Crossing) -> Crossing:
        """A person who walks across a circle and out again (see :class:`sim.world.walkers.Crossing`)."""
        self._scripted().add(crossing)
        return crossing

    def _scripted(self) -> ScriptedWalkers:
        scripted = next((s for s in self.sources if isinstance(s, ScriptedWalkers)), None)
        if scripted is None:
            scripted = ScriptedWalkers()
            scripted.t = self.t
            self.sources.append(scripted)
        return scripted

    def largest_free_circle(self, centre: tuple[float, float], half_size: float,
                            cell: float = 0.1, body_radius: float = 0.0
                            ) -> tuple[float, float, float]:
        """Ground truth: the largest people-free circle in a square, see :func:`largest_free_circle`."""
        return largest_free_circle(self.positions(), centre, half_size, cell, body_radius)


def largest_free_circle(positions: np.ndarray, centre: tuple[float, float], half_size: float,
                        cell: float = 0.1, body_radius: float = 0.0) -> tuple[float, float, float]:
    """Centre (north, east) and radius (m) of the largest circle inside the square of side
    ``2 * half_size`` around ``centre`` that holds no person (people are discs of ``body_radius``).

    Computed on a ``cell``-metre grid with a distance transform, so exact to about one cell. The
    square's own edge does not bound the circle (people beyond it count, the unknown does not).
    """
    n = int(math.ceil(2 * half_size / cell))
    occ = np.full((n, n), 255, np.uint8)
    p = np.asarray(positions, float).reshape(-1, 2)
    i = np.floor((p[:, 0] - (centre[0] - half_size)) / cell).astype(int)
    j = np.floor((p[:, 1] - (centre[1] - half_size)) / cell).astype(int)
    inside = (i >= 0) & (i < n) & (j >= 0) & (j < n)
    occ[i[inside], j[inside]] = 0
    # People outside the square still limit circles near its edge: pad the grid so they count.
    pad = int(math.ceil(half_size / cell))
    big = np.full((n + 2 * pad, n + 2 * pad), 255, np.uint8)
    ib, jb = i + pad, j + pad
    ok = (ib >= 0) & (ib < n + 2 * pad) & (jb >= 0) & (jb < n + 2 * pad)
    big[ib[ok], jb[ok]] = 0
    if not (big == 0).any():
        return (float(centre[0]), float(centre[1]), math.inf)
    dist = cv2.distanceTransform(big, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[pad:pad + n, pad:pad + n]
    k = int(np.argmax(dist))
    a, b = divmod(k, n)
    r = float(dist[a, b]) * cell - body_radius
    return (centre[0] - half_size + (a + 0.5) * cell, centre[1] - half_size + (b + 0.5) * cell,
            max(r, 0.0))


#: Step (m) at which a crossing's way is checked against walkable ground, and of the bearings
#: tried (degrees) for a way that keeps to it (:func:`on_walkable_ground`).
CROSSING_CHECK_M = 0.1
CROSSING_BEARING_STEP_DEG = 5.0


def _walkable_run(walkable: Walkable, edge: np.ndarray, d: np.ndarray, length: float) -> float:
    """How far (m, up to ``length``) one walks from ``edge`` along unit direction ``d`` on
    walkable ground without a step off it (checked every :data:`CROSSING_CHECK_M`)."""
    t = np.arange(1, int(math.floor(length / CROSSING_CHECK_M + 1e-9)) + 1) * CROSSING_CHECK_M
    if len(t) == 0:
        return 0.0
    ok = walkable(edge[None, :] + t[:, None] * d[None, :])
    return float(length) if ok.all() else float(t[int(np.argmin(ok))] - CROSSING_CHECK_M)


def on_walkable_ground(crossing: Crossing, walkable: Walkable) -> Crossing:
    """``crossing`` turned to a way that keeps to walkable ground, as a person crossing open
    ground keeps to paths, paving and lawns: its start, its chord through the circle and its
    end. Bearings from the drawn one outward (every :data:`CROSSING_BEARING_STEP_DEG`, nearest
    first) are tried with the drawn offset; the first whose chord is walkable and that leaves
    the drawn ``approach_m`` of walkable ground before and beyond the circle wins. When none
    does, the one that leaves most (the nearer to the drawn bearing of equals) is taken with its
    approach shortened to what it leaves, so that the walker starts and stops on walkable
    ground, nearer the circle. Its time at the circle's edge and speed stay. When no bearing
    gives a walkable chord, the drawn crossing is kept (it is the test)."""
    c = crossing.circle
    half = math.sqrt(c.radius ** 2 - crossing.offset_m ** 2)
    n = int(round(360.0 / CROSSING_BEARING_STEP_DEG))
    best: tuple[float, float] | None = None  # (run, bearing)
    for k in [0] + [s * j for j in range(1, n // 2 + 1) for s in (1, -1)][:n - 1]:
        bearing = crossing.bearing + math.radians(k * CROSSING_BEARING_STEP_DEG)
        d = np.array([math.cos(bearing), math.sin(bearing)])
        mid = c.centre + crossing.offset_m * np.array([-d[1], d[0]])
        entry, exit_ = mid - half * d, mid + half * d
        chord = entry[None, :] + np.linspace(0.0, 1.0, max(2, int(2 * half / CROSSING_CHECK_M) + 1))[:, None] * (exit_ - entry)
        if not walkable(chord).all():
            continue
        run = min(_walkable_run(walkable, entry, -d, crossing.approach_m),
                  _walkable_run(walkable, exit_, d, crossing.approach_m))
        if run >= crossing.approach_m:
            return dataclasses.replace(crossing, bearing=bearing)
        if best is None or run > best[0]:
            best = (run, bearing)
    if best is None:
        return crossing
    return dataclasses.replace(crossing, bearing=best[1], approach_m=best[0])


def add_crossing_walkers(world: World, circle: Circle, t_from: float, seed: int,
                         count: int | None = None,
                         window: tuple[float, float] = CROSSING_WINDOW_S, runners: float = 0.0,
                         walkable: Walkable | None = None) -> list[Crossing]:
    """Walkers who cross ``circle`` (a landing zone) during the descent: ``count`` of them (2-4
    drawn when None), each at a speed drawn from :data:`CROSSING_SPEEDS`, from a bearing drawn
    all round, along a chord within half the radius of the centre, crossing the edge at world
    time ``t_from`` plus a delay drawn from ``window`` (:data:`CROSSING_WINDOW_S`), then walking
    on out of it. A wider window keeps the default's rate: the drawn count is multiplied by its
    width over the default's, rounded (at least 1). Drawn from ``seed`` alone (its own stream:
    the scene's other draws are not touched; the default window draws what it always drew).
    ``runners``: the share (0-1) of them who run or cycle instead, at a speed drawn from
    :data:`RUNNER_SPEEDS`; who does is drawn from a stream of its own, so every walker keeps its
    bearing, chord and time, and 0 draws exactly what the scenarios always drew. ``walkable``
    (:data:`Walkable`; None: anywhere, as on the drawn ground): the ground they start, cross and
    stop on (:func:`on_walkable_ground`: each drawn crossing turned to a way on it; nothing more
    is drawn, so the draws stay)."""
    lo, hi = window
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi):
        raise ValueError(f"crossing window must be 0 <= from < to seconds, not {window!r}")
    if not (math.isfinite(runners) and 0.0 <= runners <= 1.0):
        raise ValueError(f"the share of runners must be within 0-1, not {runners!r}")
    rng = np.random.default_rng([int(seed), 0xC405])
    fast = np.random.default_rng([int(seed), 0xC405, 1])
    n = int(rng.integers(2, 5)) if count is None else int(count)
    if count is None:
        n *= max(1, round((hi - lo) / (CROSSING_WINDOW_S[1] - CROSSING_WINDOW_S[0])))
    out = []
    for _ in range(n):
        speed = float(rng.uniform(*CROSSING_SPEEDS))
        bearing = float(rng.uniform(0.0, 2 * math.pi))
        offset = float(rng.uniform(-0.5, 0.5)) * circle.radius
        t_enter = t_from + float(rng.uniform(lo, hi))
        runner, run_speed = float(fast.uniform()) < runners, float(fast.uniform(*RUNNER_SPEEDS))
        speed = run_speed if runner else speed
        crossing = Crossing(circle, t_enter, speed, bearing, offset)
        if walkable is not None:
            crossing = on_walkable_ground(crossing, walkable)
        out.append(world.add_crossing(crossing))
    return out


def default_world(seed: int = 0, half_size: float = 60.0, centre: tuple[float, float] = (0.0, 0.0),
                  params: CrowdParams | None = None) -> World:
    """A park-like crowd in a square of side ``2 * half_size`` m around ``centre``: 40 walkers,
    8 groups of 2-4, 12 standing people by default."""
    bounds = Bounds.around(centre, half_size)
    return World([GeneratedCrowd(bounds, params or CrowdParams(), seed)], seed=seed)


def crowd_with_free_area(seed: int = 0, free: Circle | None = None, half_size: float = 40.0,
                         centre: tuple[float, float] = (0.0, 0.0), n_walkers: int = 60,
                         n_groups: int = 10, n_standing: int = 20, walkable: Walkable | None = None) -> World:
    """A crowd around ``centre`` that never enters the circle ``free`` (``world.free_areas[0]``).

    The default free circle is 5 m in radius, 12 m north-east of ``centre`` so that it is not
    directly under a vehicle hovering above ``centre``.
    """
    if free is None:
        free = Circle(centre[0] + 8.5, centre[1] + 8.5, 5.0)
    params = CrowdParams(n_walkers=n_walkers, n_groups=n_groups, n_standing=n_standing,
                         keep_out=[free], walkable=walkable)
    w = World([GeneratedCrowd(Bounds.around(centre, half_size), params, seed)], [free], seed)
    return w


def dense_crowd(seed: int = 0, centre: tuple[float, float] = (0.0, 0.0), half_size: float = 40.0,
                spacing: float = 2.0, n_walkers: int = 20, free: Circle | None = None,
                walkable: Walkable | None = None) -> World:
    """People everywhere in a square of side ``2 * half_size`` m around ``centre``: a milling
    crowd on a ``spacing``-metre jittered grid plus some walkers crossing it. No circle of radius
    above about ``spacing`` metres is free anywhere inside (check with
    :meth:`World.largest_free_circle`), except ``free`` when given: a circle nobody enters
    (``world.free_areas[0]``), for a search to find. ``walkable``: where the walkers walk and
    the milling crowd stands (:class:`~sim.world.walkers.MillingCrowd`); None: anywhere. With it,
    nobody stands on a roof, in water or a tree, and the bound on free circles holds on walkable
    ground."""
    bounds = Bounds.around(centre, half_size)
    keep_out = [] if free is None else [free]
    sources: list[MotionSource] = [MillingCrowd(bounds, spacing=spacing, seed=seed, keep_out=keep_out,
                                                        walkable=walkable)]
    if n_walkers:
        sources.append(GeneratedCrowd(bounds, CrowdParams(n_walkers=n_walkers, n_groups=0, n_standing=0,
                                                          keep_out=keep_out, walkable=walkable), seed + 1))
    return World(sources, keep_out, seed=seed)


def dronecrowd_world(sequence: int = 112, centre: tuple[float, float] = (0.0, 0.0),
                     metres_per_pixel: float | None = None, seed: int = 0,
                     gt_dir: str | None = None) -> World:
    """People moving as in DroneCrowd sequence ``sequence`` (real trajectories, scaled to metres,
    see :mod:`sim.world.dronecrowd`), the video's centre at ``centre``. Raises
    ``sim.world.dronecrowd.DroneCrowdUnavailable`` when the licensed trajectories are not present."""
    from sim.world.dronecrowd import DroneCrowdMotion

    return World([DroneCrowdMotion(sequence, centre, metres_per_pixel, gt_dir=gt_dir)], seed=seed)
