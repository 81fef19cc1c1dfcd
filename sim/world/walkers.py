"""Generated people motion for the simulator: walkers, groups, standing people, scripted intruders
and crossers.

Everything is on the ground in world NED metres (``north``, ``east``; origin at home). Headings are
radians from north toward east (the yaw convention of the vehicle). Speeds are in m/s, times in
seconds of the simulated clock.

A *motion source* is anything with ``step(dt)``, ``positions() -> (N, 2)``, ``headings() -> (N,)``
and ``moving() -> (N,) bool``; the :class:`~sim.world.crowd.World` composes several of them. All sources
here are deterministic for a given seed and call sequence.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

# Preferred walking speeds of adults are about 1.2-1.5 m/s (Bohannon 1997, Mohler et al. 2007);
# the brief asks for 1.0-1.6 m/s, which this normal distribution clipped to that range gives.
WALK_SPEED_MEAN = 1.3
WALK_SPEED_STD = 0.15
WALK_SPEED_RANGE = (1.0, 1.6)
#: Metres beyond a keep-out circle (and its margin) that walkers' paths around it keep: room for
#: the tangent line, so that walking it does not graze the circle.
STEER_CLEARANCE_M = 0.5
#: Where people walk: (N, 2) ground points (north, east) -> (N,) bool, True where a person can
#: walk (open ground, not a roof, water or a tree). None in a crowd's parameters: anywhere (the
#: drawn ground's crowds).
Walkable = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Bounds:
    """Axis-aligned rectangle on the ground, world NED metres."""

    north_min: float
    north_max: float
    east_min: float
    east_max: float

    @classmethod
    def around(cls, centre: tuple[float, float], half_size: float) -> Bounds:
        n, e = centre
        return cls(n - half_size, n + half_size, e - half_size, e + half_size)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return np.column_stack([rng.uniform(self.north_min, self.north_max, n),
                                rng.uniform(self.east_min, self.east_max, n)])

    def clip(self, p: np.ndarray) -> np.ndarray:
        return np.column_stack([np.clip(p[:, 0], self.north_min, self.north_max),
                                np.clip(p[:, 1], self.east_min, self.east_max)])

    def contains(self, p: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        p = np.asarray(p, float).reshape(-1, 2)
        return ((p[:, 0] >= self.north_min - tol) & (p[:, 0] <= self.north_max + tol)
                & (p[:, 1] >= self.east_min - tol) & (p[:, 1] <= self.east_max + tol))


@dataclass(frozen=True)
class Circle:
    """A circle on the ground: centre (north, east) in metres and radius in metres."""

    north: float
    east: float
    radius: float

    @property
    def centre(self) -> np.ndarray:
        return np.array([self.north, self.east])

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Distance (m) of (N, 2) points from the centre."""
        return np.hypot(p[:, 0] - self.north, p[:, 1] - self.east)


class MotionSource(Protocol):
    def step(self, dt: float) -> None: ...
    def positions(self) -> np.ndarray: ...
    def headings(self) -> np.ndarray: ...
    def moving(self) -> np.ndarray: ...


def push_out_of(p: np.ndarray, circles: list[Circle], margin: float = 0.0) -> np.ndarray:
    """Points moved radially onto the boundary of any circle (grown by ``margin``) they are in."""
    p = p.copy()
    for c in circles:
        r = c.radius + margin
        d = c.distance(p)
        inside = d < r
        if inside.any():
            v = p[inside] - c.centre
            dd = d[inside]
            # A point exactly at the centre has no direction: send it north.
            v[dd < 1e-9] = (1.0, 0.0)
            dd = np.where(dd < 1e-9, 1.0, dd)
            p[inside] = c.centre + v / dd[:, None] * (r + 1e-6)
    return p


def _sample_outside(rng: np.random.Generator, bounds: Bounds, n: int, avoid: list[Circle],
                    margin: float, walkable: Walkable | None = None) -> np.ndarray:
    """``n`` uniform points inside ``bounds`` and outside every ``avoid`` circle (+ margin), on
    ``walkable`` ground when given."""
    out = np.empty((0, 2))
    for _ in range(1000):
        p = bounds.sample(rng, max(2 * n, 16))
        ok = np.ones(len(p), bool)
        for c in avoid:
            ok &= c.distance(p) >= c.radius + margin
        if walkable is not None:
            ok &= walkable(p)
        out = np.vstack([out, p[ok]])
        if len(out) >= n:
            return out[:n]
    raise ValueError(f"cannot place {n} people in {bounds} outside {avoid}: no room left")


@dataclass
class CrowdParams:
    """What the generated crowd is made of.

    n_walkers: people walking alone toward goals. n_groups / group_size: groups of 2-4 people that
    walk together (size range inclusive). n_standing: people standing still (turning now and then).
    pause_s: range of seconds a walker waits at a goal before picking the next one.
    keep_out: circles no generated person ever enters (the guaranteed free areas).
    keep_out_margin: extra metres kept clear around each keep-out circle (a body is ~0.5 m wide).
    walkable: where people walk (:data:`Walkable`); None: anywhere. With it, people start, stand
    and pick goals on walkable ground only, and a step from walkable ground onto ground that is
    not is not taken: the walker stops there and picks another goal, as a person turns at a wall
    or a pond.
    """

    n_walkers: int = 40
    n_groups: int = 8
    group_size: tuple[int, int] = (2, 4)
    n_standing: int = 12
    pause_s: tuple[float, float] = (0.0, 4.0)
    keep_out: list[Circle] = field(default_factory=list)
    keep_out_margin: float = 0.3
    walkable: Walkable | None = None


class GeneratedCrowd:
    """Walkers with goals, groups that move together and standing people inside ``bounds``.

    Walkers head for a random goal at their own preferred speed, wait a little, pick another goal.
    A group is a leader walker plus followers keeping a fixed offset (side by side or in a short
    file) around it. People never leave ``bounds`` and never enter a keep-out circle: they walk
    around it along its tangent, and a final projection makes the guarantee exact.
    """

    def __init__(self, bounds: Bounds, params: CrowdParams = CrowdParams(), seed: int = 0) -> None:
        self.bounds = bounds
        self.params = params
        self.rng = np.random.default_rng(seed)
        rng, p = self.rng, params
        self.keep_out = list(p.keep_out)
        margin = p.keep_out_margin

        # Leaders are the lone walkers followed by the group leaders.
        sizes = [int(rng.integers(p.group_size[0], p.group_size[1] + 1)) for _ in range(p.n_groups)]
        n_lead = p.n_walkers + p.n_groups
        lo, hi = WALK_SPEED_RANGE
        self.lead_pos = _sample_outside(rng, bounds, n_lead, self.keep_out, margin + 1.5, p.walkable)
        self.lead_goal = _sample_outside(rng, bounds, n_lead, self.keep_out, margin + 1.5, p.walkable)
        speed = np.clip(rng.normal(WALK_SPEED_MEAN, WALK_SPEED_STD, n_lead), lo, hi)
        # Groups walk at the pace of their slowest: a little slower than people alone.
        speed[p.n_walkers:] = np.clip(speed[p.n_walkers:] - 0.1, lo, hi)
        self.lead_speed = speed
        self.lead_wait = rng.uniform(0.0, p.pause_s[1], n_lead) * (rng.random(n_lead) < 0.3)
        d = self.lead_goal - self.lead_pos
        self.lead_heading = np.arctan2(d[:, 1], d[:, 0])
        # Once each walker's side round a keep-out circle; walkers now take the side nearer their
        # goal, but the draw stays so that every seed draws the same world as before.
        rng.random(n_lead)

        # Followers: offsets in the leader's frame (forward, right), metres.
        fol_leader, fol_offset = [], []
        for g, size in enumerate(sizes):
            for k in range(1, size):
                side = 0.6 * ((k + 1) // 2) * (1 if k % 2 else -1)
                back = -0.7 if size > 3 and k == size - 1 else float(rng.uniform(-0.25, 0.25))
                fol_leader.append(p.n_walkers + g)
                fol_offset.append((back, side))
        self.fol_leader = np.array(fol_leader, dtype=int)
        self.fol_offset = np.array(fol_offset, dtype=float).reshape(-1, 2)
        self.fol_pos = self._follower_targets()
        if p.walkable is not None and len(self.fol_pos):
            # A follower whose slot lies off open ground starts beside its leader (on it), not on
            # the roof or the water: the rule below keeps it there only if it starts there.
            off = ~p.walkable(self.fol_pos)
            self.fol_pos[off] = self.lead_pos[self.fol_leader[off]]

        self.stand_pos = _sample_outside(rng, bounds, p.n_standing, self.keep_out, margin + 0.5, p.walkable)
        self.stand_heading = rng.uniform(-math.pi, math.pi, p.n_standing)
        self._lead_moving = np.ones(n_lead, bool)
        self._enforce()

    def __len__(self) -> int:
        return len(self.lead_pos) + len(self.fol_pos) + len(self.stand_pos)

    def _follower_targets(self) -> np.ndarray:
        if len(self.fol_leader) == 0:
            return np.empty((0, 2))
        h = self.lead_heading[self.fol_leader]
        fwd = np.column_stack([np.cos(h), np.sin(h)])
        right = np.column_stack([-np.sin(h), np.cos(h)])
        return (self.lead_pos[self.fol_leader] + fwd * self.fol_offset[:, :1]
                + right * self.fol_offset[:, 1:])

    def _enforce(self) -> None:
        m = self.params.keep_out_margin
        self.lead_pos = push_out_of(self.bounds.clip(self.lead_pos), self.keep_out, m)
        self.fol_pos = push_out_of(self.bounds.clip(self.fol_pos), self.keep_out, m)
        self.stand_pos = push_out_of(self.bounds.clip(self.stand_pos), self.keep_out, m)

    def step(self, dt: float) -> None:
        if dt <= 0:
            return
        rng, p = self.rng, self.params
        waiting = self.lead_wait > 0
        self.lead_wait = np.maximum(self.lead_wait - dt, 0.0)

        d = self.lead_goal - self.lead_pos
        dist = np.hypot(d[:, 0], d[:, 1])
        direction = d / np.maximum(dist, 1e-9)[:, None]
        direction = self._steer_around(self.lead_pos, direction, dist)
        step_len = np.minimum(self.lead_speed * dt, dist)
        move = ~waiting
        new = self.lead_pos + direction * (step_len * move)[:, None]
        off = np.zeros(len(new), bool)
        if p.walkable is not None:
            # Off open ground (a roof, water, a tree, between photos): the step is not taken and
            # the walker picks another goal. Only from walkable ground, so that nobody is stuck
            # where an edge rule (bounds, keep-out) put them.
            off = move & p.walkable(self.lead_pos) & ~p.walkable(new)
            new[off] = self.lead_pos[off]
        self.lead_pos = new
        turned = move & ~off & (step_len > 1e-6)
        # Heading turns smoothly (people do not pivot instantly); ~0.3 s time constant.
        target_h = np.arctan2(direction[:, 1], direction[:, 0])
        dh = (target_h - self.lead_heading + math.pi) % (2 * math.pi) - math.pi
        self.lead_heading = np.where(turned, self.lead_heading + dh * min(1.0, dt / 0.3),
                                     self.lead_heading)
        self._lead_moving = turned

        arrived = (move & (dist <= self.lead_speed * dt + 1e-9)) | off
        if arrived.any():
            k = int(arrived.sum())
            self.lead_goal[arrived] = _sample_outside(rng, self.bounds, k, self.keep_out,
                                                      p.keep_out_margin + 1.5, p.walkable)
            self.lead_wait[arrived] = rng.uniform(p.pause_s[0], p.pause_s[1], k)

        if len(self.fol_pos):
            target = self._follower_targets()
            # Followers close on their slot at up to 1.8 m/s, so they keep up with the leader.
            d = target - self.fol_pos
            dist = np.hypot(d[:, 0], d[:, 1])
            k = np.minimum(1.0, 1.8 * dt / np.maximum(dist, 1e-9))
            new = self.fol_pos + d * k[:, None]
            if p.walkable is not None:
                # A follower whose slot lies off open ground waits at its edge.
                stay = p.walkable(self.fol_pos) & ~p.walkable(new)
                new[stay] = self.fol_pos[stay]
            self.fol_pos = new

        # Standing people turn now and then (their shoulders change orientation).
        if len(self.stand_pos):
            turn = rng.random(len(self.stand_pos)) < 0.05 * dt
            self.stand_heading[turn] += rng.normal(0.0, 0.8, int(turn.sum()))
        self._enforce()

    def _steer_around(self, pos: np.ndarray, direction: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """Directions that walk around keep-out circles the way people walk around a lawn or a
        fenced square: whoever's straight way to the goal crosses a circle (grown by the margin
        and ``STEER_CLEARANCE_M``) heads for the tangent point on the side nearer the goal, in
        a straight line, from as far away as they are; on the circle itself they follow it.

        Straight lines that never enter the circle, rather than walking at it and turning away at
        its edge: a walker's own straight-line future then never runs through the free area
        unless they really are about to cross it. The earlier rule (head for the goal, turn only
        2 m from the edge) made every walker heading that way look, to anyone extrapolating their
        path, like someone about to cross the landing zone (docs/design.md, "People followed to
        touchdown"). ``reach``: each walker's distance to their goal (m)."""
        out = direction.copy()
        for c in self.keep_out:
            R = c.radius + self.params.keep_out_margin + STEER_CLEARANCE_M
            v = c.centre - pos  # to the centre
            dist = np.hypot(v[:, 0], v[:, 1])
            # Does the way to the goal pass within R of the centre? (The segment's nearest point.)
            along = out[:, 0] * v[:, 0] + out[:, 1] * v[:, 1]
            t = np.clip(along, 0.0, reach)
            blocked = (along > 0) & (np.hypot(v[:, 0] - t * out[:, 0], v[:, 1] - t * out[:, 1]) < R)
            if not blocked.any():
                continue
            idx = np.flatnonzero(blocked)
            u = v[idx] / np.maximum(dist[idx], 1e-9)[:, None]
            # The two tangent directions from the walker (on the circle: the two along it).
            half = np.arcsin(np.clip(R / np.maximum(dist[idx], 1e-9), 0.0, 1.0))
            cands = []
            for sgn in (1.0, -1.0):
                a = sgn * half
                cands.append(np.column_stack([u[:, 0] * np.cos(a) - u[:, 1] * np.sin(a),
                                              u[:, 0] * np.sin(a) + u[:, 1] * np.cos(a)]))
            want = out[idx]
            closer = (cands[0] * want).sum(axis=1) >= (cands[1] * want).sum(axis=1)
            out[idx] = np.where(closer[:, None], cands[0], cands[1])
        return out

    def positions(self) -> np.ndarray:
        return np.vstack([self.lead_pos, self.fol_pos, self.stand_pos])

    def headings(self) -> np.ndarray:
        fol_h = self.lead_heading[self.fol_leader] if len(self.fol_leader) else np.empty(0)
        return np.concatenate([self.lead_heading, fol_h, self.stand_heading])

    def moving(self) -> np.ndarray:
        fol_m = self._lead_moving[self.fol_leader] if len(self.fol_leader) else np.empty(0, bool)
        return np.concatenate([self._lead_moving, fol_m, np.zeros(len(self.stand_pos), bool)])


class MillingCrowd:
    """A dense crowd standing and shuffling on a jittered grid (a square, a concert, a market).

    Each person stays within ``wander`` metres of a home point on a grid of ``spacing`` metres
    with ``jitter`` metres of random displacement, shuffling at up to 0.4 m/s. The largest circle
    free of people anywhere inside the covered area is then bounded by about
    ``(spacing / sqrt(2) + jitter + wander)``.

    ``walkable`` (:data:`Walkable`; None: anywhere): where people stand. With it, a home whose
    jittered point is not walkable moves back to its grid point, else to the nearest walkable
    point of its cell, and is dropped when the cell has none (nobody stands on a roof, in a pond
    or a tree); a shuffle target off walkable
    ground is the home instead, and a step from walkable ground onto ground that is not is not
    taken, as for :class:`GeneratedCrowd`'s walkers. The bound above then holds on walkable
    ground. None draws exactly the crowd it always drew (the drawn ground's rows).
    """

    def __init__(self, bounds: Bounds, spacing: float = 2.0, jitter: float = 0.4,
                 wander: float = 0.3, seed: int = 0, keep_out: list[Circle] | None = None,
                 keep_out_margin: float = 0.3, walkable: Walkable | None = None) -> None:
        if spacing <= 0:
            raise ValueError(f"spacing must be > 0 m, got {spacing}")
        self.bounds = bounds
        self.spacing, self.jitter, self.wander = spacing, jitter, wander
        self.rng = np.random.default_rng(seed)
        n_ = np.arange(bounds.north_min + spacing / 2, bounds.north_max, spacing)
        e_ = np.arange(bounds.east_min + spacing / 2, bounds.east_max, spacing)
        gn, ge = np.meshgrid(n_, e_, indexing="ij")
        grid = np.column_stack([gn.ravel(), ge.ravel()])
        home = bounds.clip(grid + self.rng.uniform(-jitter, jitter, grid.shape))
        self.walkable = walkable
        if walkable is not None:
            # After the jitter's draw, so the stream (headings, shuffles) is drawn the same way.
            off = ~walkable(home)
            home[off] = grid[off]
            home = home[self._onto_walkable(home, walkable)]
        # Nobody's home, nor where they shuffle to, lies in a keep-out circle (free ground).
        for c in keep_out or ():
            d = np.hypot(home[:, 0] - c.north, home[:, 1] - c.east)
            home = home[d > c.radius + keep_out_margin + wander]
        self.home = home
        self.pos = self.home.copy()
        self.target = self.home.copy()
        self.heading = self.rng.uniform(-math.pi, math.pi, len(self.home))
        self._moving = np.zeros(len(self.home), bool)

    def _onto_walkable(self, home: np.ndarray, walkable: Walkable) -> np.ndarray:
        """Move each home (in place) that is not on walkable ground to the walkable point of its
        grid cell nearest to it (a 5 x 5 lattice across the cell, no random draw), so a strip of
        open ground narrower than a cell still has its people; (N,) bool, False where the cell
        holds no walkable point (the home is dropped)."""
        ok = walkable(home)
        off = np.flatnonzero(~ok)
        if len(off) == 0:
            return ok
        a = np.linspace(-0.45, 0.45, 5) * self.spacing
        lattice = np.stack(np.meshgrid(a, a, indexing="ij"), axis=-1).reshape(-1, 2)
        lattice = lattice[np.argsort(np.hypot(lattice[:, 0], lattice[:, 1]), kind="stable")]
        cand = self.bounds.clip((home[off, None, :] + lattice[None]).reshape(-1, 2)).reshape(len(off), len(lattice), 2)
        good = walkable(cand.reshape(-1, 2)).reshape(len(off), len(lattice))
        found = good.any(axis=1)
        first = np.argmax(good, axis=1)  # the nearest walkable lattice point (sorted by distance)
        home[off[found]] = cand[found, first[found]]
        ok[off[found]] = True
        return ok

    def step(self, dt: float) -> None:
        if dt <= 0:
            return
        rng = self.rng
        new_t = rng.random(len(self.pos)) < 0.1 * dt
        k = int(new_t.sum())
        if k:
            a = rng.uniform(-math.pi, math.pi, k)
            r = self.wander * np.sqrt(rng.random(k))
            target = self.home[new_t] + np.column_stack([np.cos(a), np.sin(a)]) * r[:, None]
            if self.walkable is not None:
                off = ~self.walkable(target)
                target[off] = self.home[new_t][off]
            self.target[new_t] = target
        d = self.target - self.pos
        dist = np.hypot(d[:, 0], d[:, 1])
        k = np.minimum(1.0, 0.4 * dt / np.maximum(dist, 1e-9))
        new = self.bounds.clip(self.pos + d * k[:, None])
        stay = np.zeros(len(new), bool)
        if self.walkable is not None:
            # The way to a walkable target can cut a corner of a roof or a pond: wait at its edge.
            stay = self.walkable(self.pos) & ~self.walkable(new)
            new[stay] = self.pos[stay]
        self.pos = new
        self._moving = (dist > 0.05) & ~stay
        h = np.arctan2(d[:, 1], d[:, 0])
        self.heading = np.where(self._moving, h, self.heading)

    def positions(self) -> np.ndarray:
        return self.pos.copy()

    def headings(self) -> np.ndarray:
        return self.heading.copy()

    def moving(self) -> np.ndarray:
        return self._moving.copy()


@dataclass(frozen=True)
class Intrusion:
    """People scripted to walk into ``circle`` so that the first crosses its edge at ``t_enter``.

    They come from ``approach_m`` metres outside the edge along evenly spread bearings (the first
    from ``bearing`` radians, from north toward east), walk at ``speed`` m/s, and stop at
    ``stop_fraction`` of the radius from the centre. Before they start walking they stand at
    their start point.
    """

    circle: Circle
    t_enter: float
    count: int = 1
    speed: float = 1.3
    approach_m: float = 8.0
    bearing: float = 0.0
    stop_fraction: float = 0.2


@dataclass(frozen=True)
class Crossing:
    """One person scripted to walk straight across ``circle`` and out of it again.

    They walk along the chord at ``offset_m`` from the centre (to the right of their direction
    of travel; ``|offset_m| < radius``), heading ``bearing`` (radians from north toward east), at
    ``speed`` m/s: from ``approach_m`` metres before the edge, crossing it at ``t_enter``, to
    ``approach_m`` metres beyond the far edge, where they stop. Before they start walking they
    stand at their start point.
    """

    circle: Circle
    t_enter: float
    speed: float = 1.3
    bearing: float = 0.0
    offset_m: float = 0.0
    approach_m: float = 8.0

    def __post_init__(self) -> None:
        if not abs(self.offset_m) < self.circle.radius:
            raise ValueError(f"a crossing's offset must be within the radius {self.circle.radius} m, "
                             f"got {self.offset_m}")
        if not (self.speed > 0 and math.isfinite(self.speed)):
            raise ValueError(f"a crossing's speed must be > 0 m/s, got {self.speed}")

    def path(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Start and end (north, east) of the walk, and the time it starts."""
        c = self.circle
        d = np.array([math.cos(self.bearing), math.sin(self.bearing)])
        right = np.array([-d[1], d[0]])
        half = math.sqrt(c.radius ** 2 - self.offset_m ** 2)
        mid = c.centre + self.offset_m * right
        start = mid - (half + self.approach_m) * d
        end = mid + (half + self.approach_m) * d
        return start, end, self.t_enter - self.approach_m / self.speed


class ScriptedWalkers:
    """Motion source for :class:`Intrusion` and :class:`Crossing` scripts: positions are a pure
    function of time."""

    def __init__(self, intrusions: list[Intrusion] | None = None) -> None:
        self.t = 0.0
        self.starts = np.empty((0, 2))
        self.ends = np.empty((0, 2))
        self.t_start = np.empty(0)
        self.speed = np.empty(0)
        for it in intrusions or []:
            self.add(it)

    def add(self, it: Intrusion | Crossing) -> None:
        if isinstance(it, Crossing):
            start, end, t0 = it.path()
            self.starts = np.vstack([self.starts, start[None]])
            self.ends = np.vstack([self.ends, end[None]])
            self.t_start = np.append(self.t_start, t0)
            self.speed = np.append(self.speed, it.speed)
            return
        c = it.circle
        b = it.bearing + 2 * math.pi * np.arange(it.count) / max(it.count, 1)
        u = np.column_stack([np.cos(b), np.sin(b)])
        start = c.centre + u * (c.radius + it.approach_m)
        end = c.centre + u * (c.radius * it.stop_fraction)
        self.starts = np.vstack([self.starts, start])
        self.ends = np.vstack([self.ends, end])
        self.t_start = np.concatenate([self.t_start, np.full(it.count, it.t_enter - it.approach_m / it.speed)])
        self.speed = np.concatenate([self.speed, np.full(it.count, it.speed)])

    def step(self, dt: float) -> None:
        self.t += max(dt, 0.0)

    def _progress(self) -> np.ndarray:
        length = np.hypot(*(self.ends - self.starts).T)
        walked = np.clip((self.t - self.t_start) * self.speed, 0.0, length)
        return walked / np.maximum(length, 1e-9)

    def positions(self) -> np.ndarray:
        f = self._progress()
        return self.starts + (self.ends - self.starts) * f[:, None]

    def headings(self) -> np.ndarray:
        d = self.ends - self.starts
        return np.arctan2(d[:, 1], d[:, 0])

    def moving(self) -> np.ndarray:
        f = self._progress()
        return (f > 0) & (f < 1)
