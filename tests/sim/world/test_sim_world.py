"""The simulated world's people: realistic motion, bounds, determinism and the SITL scenarios."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.world.crowd import World, crowd_with_free_area, default_world, dense_crowd, largest_free_circle
from sim.world.walkers import WALK_SPEED_RANGE, Bounds, Circle, CrowdParams, GeneratedCrowd

DT = 0.1


def _run(world: World, seconds: float, dt: float = DT) -> list[np.ndarray]:
    out = [world.positions()]
    for _ in range(int(round(seconds / dt))):
        world.step(dt)
        out.append(world.positions())
    return out


def test_walkers_move_at_walking_speeds_and_stay_in_bounds() -> None:
    bounds = Bounds.around((5.0, -3.0), 30.0)
    crowd = GeneratedCrowd(bounds, CrowdParams(n_walkers=50, n_groups=0, n_standing=0,
                                               pause_s=(0.0, 0.0)), seed=4)
    world = World([crowd])
    traj = np.stack(_run(world, 30.0))  # (T, N, 2)
    speeds = np.hypot(*np.diff(traj, axis=0).transpose(2, 0, 1)) / DT  # (T-1, N)
    lo, hi = WALK_SPEED_RANGE
    assert speeds.max() <= hi + 1e-6
    # While walking (not at a goal or turning), each walker holds its own preferred speed.
    per_walker = np.median(speeds, axis=0)
    assert per_walker.min() >= lo - 1e-6
    assert 1.15 <= float(np.median(per_walker)) <= 1.45
    assert bounds.contains(traj.reshape(-1, 2)).all()
    # They go places: most have covered well over 10 m net in 30 s.
    net = np.hypot(*(traj[-1] - traj[0]).T)
    assert np.mean(net > 10.0) > 0.5


def test_groups_walk_together_and_standing_people_stand() -> None:
    params = CrowdParams(n_walkers=0, n_groups=6, group_size=(3, 3), n_standing=5)
    crowd = GeneratedCrowd(Bounds.around((0.0, 0.0), 40.0), params, seed=1)
    world = World([crowd])
    start = world.positions()
    _run(world, 20.0)
    pos = world.positions()
    n_lead, n_fol = 6, 12
    leaders = pos[:n_lead]
    followers = pos[n_lead:n_lead + n_fol]
    gap = np.hypot(*(followers - leaders[crowd.fol_leader]).T)
    assert gap.max() < 2.0  # still with their group after 20 s
    moved_leaders = np.hypot(*(leaders - start[:n_lead]).T)
    assert moved_leaders.max() > 5.0
    standing = pos[n_lead + n_fol:]
    assert np.allclose(standing, start[n_lead + n_fol:])
    assert not world.moving()[n_lead + n_fol:].any()


def test_same_seed_same_world_other_seed_other_world() -> None:
    a, b, c = default_world(seed=7), default_world(seed=7), default_world(seed=8)
    for w in (a, b, c):
        _run(w, 5.0)
    assert np.array_equal(a.positions(), b.positions())
    assert np.array_equal(a.headings(), b.headings())
    assert a.t == pytest.approx(5.0)
    pa, pc = a.positions(), c.positions()
    assert pa.shape != pc.shape or not np.allclose(pa, pc)


def test_the_same_seed_meets_the_same_crowd_however_its_time_was_sliced() -> None:
    # A loaded machine steps the world at uneven intervals: the crowd at a world time must not
    # depend on them (walkers draw random numbers every step; uneven steps used to give another
    # crowd from the same seed within seconds, and runs of one seed were not repeatable).
    def uneven_steps(total: float) -> list[float]:
        rng, left, steps = np.random.default_rng(0), total, []
        while left > 1e-9:
            steps.append(min(left, float(rng.uniform(0.001, 0.3))))
            left -= steps[-1]
        return steps

    even = crowd_with_free_area(seed=5)
    uneven = crowd_with_free_area(seed=5)
    for _ in range(600):
        even.step(0.05)
    for dt in uneven_steps(30.0):
        uneven.step(dt)
    assert even.t == pytest.approx(30.0) and uneven.t == pytest.approx(30.0)
    np.testing.assert_array_equal(even.positions(), uneven.positions())
    np.testing.assert_array_equal(even.headings(), uneven.headings())
    # The old way (each source stepped by whatever dt came) gives another crowd: the test has teeth.
    raw = crowd_with_free_area(seed=5)
    for dt in uneven_steps(30.0):
        for s in raw.sources:
            s.step(dt)
    assert np.abs(raw.positions() - even.positions()).max() > 1.0


def test_a_world_made_at_a_later_time_counts_on_from_it() -> None:
    world = World(t=12.0)
    world.step(0.5)
    assert world.t == pytest.approx(12.5)


def test_a_paused_world_stands_still() -> None:
    world = crowd_with_free_area(seed=2)
    before = world.positions().copy()
    world.paused = True
    world.step(5.0)
    assert world.t == 0.0
    np.testing.assert_array_equal(world.positions(), before)
    world.paused = False
    world.step(0.5)
    assert world.t == pytest.approx(0.5)
    assert np.abs(world.positions() - before).max() > 0.1


def test_free_area_stays_free_for_minutes() -> None:
    world = crowd_with_free_area(seed=3)
    (free,) = world.free_areas
    for _ in range(1200):  # 2 minutes
        world.step(DT)
        assert world.people_within(free) == 0
    # The crowd is around it, not somewhere else: people within 10 m of its edge.
    d = free.distance(world.positions())
    assert np.count_nonzero(d < free.radius + 10.0) >= 5
    assert world.nearest_person_distance(free.centre) >= free.radius


def test_free_area_at_a_given_place() -> None:
    free = Circle(-6.0, 4.0, 3.0)
    world = crowd_with_free_area(seed=5, free=free, half_size=20.0, n_walkers=80)
    _run(world, 30.0)
    assert world.free_areas == [free]
    assert world.nearest_person_distance((free.north, free.east)) >= 3.0


def test_dense_crowd_has_no_landing_circle_anywhere() -> None:
    world = dense_crowd(seed=2, centre=(10.0, -5.0), half_size=30.0, spacing=2.0)
    _run(world, 10.0)
    n, e, r = world.largest_free_circle((10.0, -5.0), 25.0)
    assert r < 2.5, f"a free circle of {r:.2f} m at ({n:.1f}, {e:.1f}) in the dense crowd"
    # ... while the sparse default world has room.
    sparse = default_world(seed=2)
    assert sparse.largest_free_circle((0.0, 0.0), 25.0)[2] > 5.0


def _pond(p: np.ndarray) -> np.ndarray:
    """Walkable ground: everywhere but a pond of 8 m radius at (10, -5) and a strip of roofs
    north of 18 m (world north, east)."""
    p = np.asarray(p, float).reshape(-1, 2)
    return (np.hypot(p[:, 0] - 10.0, p[:, 1] + 5.0) > 8.0) & (p[:, 0] < 18.0)


def test_a_dense_crowd_stands_where_people_stand_and_packs_the_rest() -> None:
    """Issue 59: on the photo ground the milling crowd keeps off roofs and water, as the walkers
    do: nobody stands, shuffles or walks there for a minute, and the walkable ground is still
    packed (no circle of room anywhere on it)."""
    world = dense_crowd(seed=2, centre=(10.0, -5.0), half_size=30.0, spacing=2.0, walkable=_pond)
    everywhere = dense_crowd(seed=2, centre=(10.0, -5.0), half_size=30.0, spacing=2.0)
    assert len(world.sources[0].positions()) < 0.8 * len(everywhere.sources[0].positions())
    for _ in range(600):
        world.step(DT)
        assert _pond(world.positions()).all()
    walkable_pts = np.array([[n, e] for n in np.arange(-15.0, 16.0, 1.0) for e in np.arange(-30.0, 21.0, 1.0)])
    people = world.positions()
    for q in walkable_pts[_pond(walkable_pts)]:
        if _pond(q + np.array([[2.0, 0.0], [-2.0, 0.0], [0.0, 2.0], [0.0, -2.0]])).all():
            # Ground with walkable room around it has somebody within about a spacing.
            assert np.min(np.hypot(*(people - q).T)) < 2.5, q


def test_a_path_narrower_than_the_crowds_grid_still_has_its_people() -> None:
    """A 1 m wide path between roofs, off every grid point: the homes of the cells it crosses move
    onto it (the nearest walkable point of the cell), so the path is as packed as open ground."""
    def path(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, float).reshape(-1, 2)
        return np.abs(p[:, 1] - 0.3) < 0.5

    world = dense_crowd(seed=3, centre=(0.0, 0.0), half_size=10.0, spacing=2.0, n_walkers=0, walkable=path)
    assert len(world) >= 10 and path(world.positions()).all()
    for _ in range(300):
        world.step(DT)
    people = world.positions()
    assert path(people).all()
    for n in np.arange(-9.0, 9.5, 0.5):
        assert np.min(np.hypot(people[:, 0] - n, people[:, 1] - 0.3)) < 1.5, n


def test_a_dense_crowd_anywhere_is_drawn_as_it_always_was() -> None:
    """Walkable ground everywhere draws exactly the crowd of no walkable map: the option draws no
    random number of its own, so the drawn ground's worlds (walkable None) keep their people and
    the yardstick's rows."""
    free = Circle(25.0, 10.0, 6.5)
    a = dense_crowd(seed=4, centre=(10.0, 0.0), half_size=45.0, free=free)
    b = dense_crowd(seed=4, centre=(10.0, 0.0), half_size=45.0, free=free,
                    walkable=lambda p: np.ones(len(np.asarray(p).reshape(-1, 2)), bool))
    for _ in range(300):
        a.step(DT)
        b.step(DT)
    np.testing.assert_array_equal(a.positions(), b.positions())
    np.testing.assert_array_equal(a.headings(), b.headings())
    np.testing.assert_array_equal(a.moving(), b.moving())


def test_people_walk_into_a_circle_at_the_given_time() -> None:
    world = crowd_with_free_area(seed=9)
    (free,) = world.free_areas
    world.add_intrusion(free, t_enter=12.0, count=3, bearing=0.5)
    inside_at = None
    while world.t < 25.0:
        world.step(DT)
        if inside_at is None and world.people_within(free) > 0:
            inside_at = world.t
    assert inside_at == pytest.approx(12.0, abs=2 * DT)
    assert world.people_within(free) == 3
    assert world.nearest_person_distance(free.centre) <= 0.25 * free.radius


def test_nearest_person_distance() -> None:
    world = World()
    assert world.nearest_person_distance((0.0, 0.0)) == math.inf
    world.add_intrusion(Circle(0.0, 0.0, 2.0), t_enter=100.0, approach_m=3.0)  # stands 5 m north
    assert world.nearest_person_distance((0.0, 0.0)) == pytest.approx(5.0)
    assert world.nearest_person_distance(np.array([5.0, 4.0])) == pytest.approx(4.0)


def test_largest_free_circle_ground_truth() -> None:
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    n, e, r = largest_free_circle(pts, (5.0, 5.0), 5.0, cell=0.05)
    assert (n, e) == pytest.approx((5.0, 5.0), abs=0.1)
    assert r == pytest.approx(math.sqrt(50), abs=0.1)


def test_a_dense_crowd_can_keep_one_free_circle_out_of_the_first_view() -> None:
    """The search scenarios (``dense_beyond``): people everywhere but one circle nobody enters,
    for minutes, with the crowd packed right up to its edge."""
    free = Circle(35.0, 10.0, 6.5)
    world = dense_crowd(seed=4, centre=(10.0, 0.0), half_size=45.0, spacing=2.0, free=free)
    assert world.free_areas == [free]
    for _ in range(600):  # a minute
        world.step(DT)
        assert world.people_within(free) == 0
    d = free.distance(world.positions())
    assert np.count_nonzero(d < free.radius + 3.0) >= 20
    # Nowhere else within 20 m of the start is there room to land.
    assert world.largest_free_circle((10.0, 0.0), 18.0)[2] < 2.5


@pytest.mark.parametrize("seed", [1, 3, 9])
def test_walkers_go_around_the_free_area_on_paths_that_never_cross_it(seed: int) -> None:
    """People walk around a free area on straight tangent paths, as round a lawn, not at it and
    then away at its edge: the straight-line extrapolation of how anyone is moving (what a
    tracker predicts) never runs through the middle of the free area. Before, walkers headed for
    goals beyond it and turned 2 m from its edge, so extrapolated paths crossed it all the time."""
    world = crowd_with_free_area(seed=seed)
    (free,) = world.free_areas
    prev = world.positions()
    worst = np.inf
    for _ in range(600):  # 1 minute
        world.step(DT)
        now = world.positions()
        if len(now) == len(prev):
            v = (now - prev) / DT
            moving = np.hypot(v[:, 0], v[:, 1]) > 0.3
            rel = free.centre - now[moving]
            vm = v[moving]
            vv = np.maximum((vm ** 2).sum(axis=1), 1e-12)
            # The closest approach to the centre over the next 5 s of straight walking.
            tau = np.clip((rel * vm).sum(axis=1) / vv, 0.0, 5.0)
            d = np.hypot(rel[:, 0] - vm[:, 0] * tau, rel[:, 1] - vm[:, 1] * tau)
            if len(d):
                worst = min(worst, float(d.min()))
        prev = now
    # r_0 (2 m) around the centre is what a landing needs: nobody's extrapolated path comes
    # within it (the closest are group members catching up with their group, at up to 1.8 m/s).
    assert worst >= 2.5
