"""The crossing world's crossers keep to walkable ground when the world says where it lies (the
photo ground's class maps, issue 59): they start, cross and stop on it, at the time and speed
drawn; on the drawn ground (no walkable map) they are drawn as they always were. The maps here
are real ``WalkableMap`` masks laid out by hand, so these run without ``../shared``."""

from __future__ import annotations

import math

import numpy as np

from sim.world.crowd import World, add_crossing_walkers, on_walkable_ground
from sim.world.photo_ground import WalkableMap
from sim.world.walkers import Circle, Crossing

RES = 0.1
HALF = 30.0


def _map(open_ground) -> WalkableMap:
    """A 60 m square around (0, 0) at 0.1 m/px, walkable where ``open_ground(north, east)``."""
    c = -HALF + (np.arange(int(2 * HALF / RES)) + 0.5) * RES
    nn, ee = np.meshgrid(c, c, indexing="ij")
    return WalkableMap(-HALF, -HALF, RES, open_ground(nn, ee))


def _positions_over(world: World, seconds: float = 60.0, step: float = 0.1) -> np.ndarray:
    out = []
    for _ in range(int(round(seconds / step))):
        world.step(step)
        out.append(world.positions())
    return np.vstack(out)


def test_crossers_start_cross_and_stop_on_walkable_ground_at_their_drawn_time() -> None:
    """A square in a street running north-south (walls east and west of it): every drawn
    crossing is turned to run along the street, never through the walls, and meets the circle's
    edge when it was drawn to, at its drawn speed."""
    circle = Circle(0.0, 0.0, 6.0)
    walkable = _map(lambda n, e: (np.hypot(n, e) <= 7.0) | (np.abs(e) <= 4.0))
    for seed in range(1, 9):
        drawn = add_crossing_walkers(World(seed=seed), circle, 0.0, seed)
        world = World(seed=seed)
        kept = add_crossing_walkers(world, circle, 0.0, seed, walkable=walkable)
        assert len(kept) == len(drawn)
        for a, b in zip(drawn, kept):
            assert (b.t_enter, b.speed, b.offset_m, b.approach_m) == (a.t_enter, a.speed, a.offset_m, 8.0)
            start, end, _t0 = b.path()
            assert walkable(np.array([start, end])).all()
        assert walkable(_positions_over(world)).all()
    # Drawn anywhere, some of them walk through the walls: the map is what keeps them off.
    off = [~walkable(_positions_over(_world_with(seed, circle))) for seed in range(1, 9)]
    assert np.concatenate(off).mean() > 0.1


def _world_with(seed: int, circle: Circle) -> World:
    world = World(seed=seed)
    add_crossing_walkers(world, circle, 0.0, seed)
    return world


def test_on_open_ground_a_crossing_is_kept_as_drawn() -> None:
    circle = Circle(2.0, -3.0, 5.0)
    everywhere = _map(lambda n, e: np.ones_like(n, bool))
    drawn = add_crossing_walkers(World(seed=3), circle, 1.0, 3)
    assert add_crossing_walkers(World(seed=3), circle, 1.0, 3, walkable=everywhere) == drawn


def test_with_little_walkable_ground_around_the_circle_the_approach_is_shortened_not_off_it() -> None:
    """A landable disc 2 m wider than the circle in ground nobody walks on (a square between
    buildings): the crossers start and stop on its rim, 2 m out, and still cross at their time."""
    circle = Circle(0.0, 0.0, 6.0)
    walkable = _map(lambda n, e: np.hypot(n, e) <= 8.0)
    crossing = Crossing(circle, t_enter=10.0, speed=1.2, bearing=0.7, offset_m=-1.5)
    turned = on_walkable_ground(crossing, walkable)
    assert 1.5 < turned.approach_m < 8.0
    assert (turned.t_enter, turned.speed, turned.offset_m) == (10.0, 1.2, -1.5)
    start, end, t0 = turned.path()
    assert walkable(np.array([start, end])).all()
    assert t0 == 10.0 - turned.approach_m / 1.2  # at the edge when it was drawn to be
    world = World(seed=1)
    world.add_crossing(turned)
    assert walkable(_positions_over(world, 30.0)).all()
    assert world.people_within(circle) == 0  # and out again


def test_without_any_walkable_way_across_the_drawn_crossing_is_kept() -> None:
    """The crossers are the test: a circle no walkable chord crosses still gets them."""
    circle = Circle(0.0, 0.0, 6.0)
    nowhere = _map(lambda n, e: np.zeros_like(n, bool))
    crossing = Crossing(circle, t_enter=5.0, speed=1.3, bearing=2.0, offset_m=1.0)
    assert on_walkable_ground(crossing, nowhere) == crossing


def test_the_turn_is_the_nearest_bearing_that_keeps_to_walkable_ground() -> None:
    """A street running east-west: a crossing drawn heading north-ish turns to the nearer of east
    and west, not to any bearing that would do."""
    circle = Circle(0.0, 0.0, 5.0)
    walkable = _map(lambda n, e: (np.hypot(n, e) <= 6.0) | (np.abs(n) <= 2.0))
    turned = on_walkable_ground(Crossing(circle, 5.0, 1.3, bearing=math.radians(60.0)), walkable)
    assert turned.approach_m == 8.0
    assert abs(math.degrees(turned.bearing) - 90.0) <= 10.0
