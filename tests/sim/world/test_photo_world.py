"""The photo world (issue 59): real nadir photos as the simulator's ground, their class maps the
truth, their people counted by the judge, walkers drawn as real silhouettes and some crossing open
ground. Needs ``../shared`` (the held-out full-size semantic-drone photos); skips without it."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from companion.evaluation.datasets import DatasetError, read_image, refuse_held_out
from companion.geometry.camera import Intrinsics, Mount, Pose
from sim.flights.flight import (
    PHOTO_FREE_MARGIN_M,
    build_world,
    crossing_walkable,
    photo_ground,
    photo_scene_centre,
    touchdown_surfaces,
)
from sim.flights.results import row_key
from sim.flights.scenarios import FlightJob
from sim.flights.spec import FlightResult, FlightSpec
from sim.world.crowd import World, add_crossing_walkers
from sim.world.photo_ground import (
    PERSON,
    PHOTO_CLASSES,
    PHOTO_LANDABLE,
    PhotosError,
    check_photos,
    estimate_gsd,
)
from sim.world.photo_people import open_ground_walkers
from sim.world.render import render_world
from sim.world.walkers import Bounds, Circle


@pytest.fixture(scope="module")
def ground(photos: str):
    return photo_ground(photos)


def test_every_photo_gets_a_plausible_gsd_most_from_their_people_or_cars(ground) -> None:
    g = np.array([p.gsd for p in ground.patches])
    assert len(ground.patches) == 80
    # 5-30 m above ground with the data set's camera: about 0.004-0.04 m/px (finer ones kept at 0.01).
    assert g.min() >= 0.0099 and g.max() <= 0.04
    src = [p.gsd_from for p in ground.patches]
    assert src.count("car") >= 5 and src.count("person") >= 50 and src.count("median") <= 15


def test_a_car_sets_the_scale_when_there_is_one() -> None:
    classes = np.zeros((400, 600), np.uint8)
    classes[100:150, 100:325] = 17  # a car 225 px long
    classes[300:320, 400:420] = PERSON
    gsd, src = estimate_gsd(classes)
    assert src == "car" and gsd == pytest.approx(4.5 / 225, rel=0.02)
    classes[classes == 17] = 3
    gsd, src = estimate_gsd(classes)
    assert src == "person" and gsd == pytest.approx(0.85 / 20, rel=0.1)
    assert estimate_gsd(np.zeros((50, 50), np.uint8)) == (None, "none")


def test_each_ground_point_is_its_photos_pixel_and_class_north_up(ground) -> None:
    p = max(ground.patches, key=lambda p: p.gsd)  # a coarse patch: stored at its own pixels
    H, W = p.classes.shape
    rng = np.random.default_rng(5)
    on, oe = ground.origin
    for _ in range(20):
        x, y = int(rng.integers(2, W - 2)), int(rng.integers(2, H - 2))
        north = on + p.north + (H - y - 0.5) * p.gsd  # the photo's top edge faces north
        east = oe + p.east + (x + 0.5) * p.gsd
        assert ground.surface_at(north, east) == PHOTO_CLASSES[int(p.classes[y, x])]
    # The texture at the patch's own resolution is its photo.
    y, x = H // 2, W // 2
    north, east = on + p.north + (H - y - 0.5) * p.gsd, oe + p.east + (x + 0.5) * p.gsd
    mosaic, A = ground.view(north - 1, north + 1, east - 1, east + 1, 0.02)
    col, row, _ = A @ np.array([north, east, 1.0])
    got = mosaic[int(row), int(col)].astype(int)
    want = p.bgr[max(0, y - 2):y + 3, max(0, x - 2):x + 3].reshape(-1, 3).astype(int)
    assert np.abs(want - got).min(axis=0).max() <= 40


def test_the_ground_repeats_endlessly_and_photos_fill_their_shelves_mirrored(ground) -> None:
    """No flat grey band between photos (it looked like the cleanest ground in view, and a
    companion landed on it): each photo is mirrored into the room its shelf leaves, pixels,
    classes and people alike."""
    on, oe = ground.origin
    for n, e in ((3.3, 7.7), (40.0, 90.0)):
        assert ground.surface_at(on + n, oe + e) == ground.surface_at(on + n + ground.block_n, oe + e - 2 * ground.block_e)
    cls = ground.class_map(on, on + ground.block_n, oe, oe + ground.block_e, 0.2)
    assert (cls == 0).mean() < 0.01  # only the photos' own unlabelled pixels
    assert "unlabeled" not in PHOTO_LANDABLE
    # A patch with room above it: the ground just north of its top edge is its top row mirrored.
    p = next(p for p in ground.patches if p.cell_m[0] > p.size_m[0] + 1.0)
    H, W = p.classes.shape
    for x in (W // 4, W // 2, 3 * W // 4):
        east = oe + p.east + (x + 0.5) * p.gsd
        for y in (0, 3):
            inside = on + p.north + (H - y - 0.5) * p.gsd
            mirrored = on + p.north + (H + y + 0.5) * p.gsd
            assert ground.surface_at(mirrored, east) == ground.surface_at(inside, east) == PHOTO_CLASSES[int(p.classes[y, x])]


def test_the_photos_people_are_people_at_their_ground_positions(ground) -> None:
    on, oe = ground.origin
    centre, half = (on + ground.block_n / 2, oe + ground.block_e / 2), max(ground.block_n, ground.block_e) / 2 - 1e-6
    people = ground.people(centre, half)
    inside = ((people[:, 0] >= on) & (people[:, 0] < on + ground.block_n)
              & (people[:, 1] >= oe) & (people[:, 1] < oe + ground.block_e))
    # One block: each person once, and once more for each mirror image in its patch's cell.
    assert inside.sum() >= sum(len(p.people_px) for p in ground.patches)
    people = people[inside]
    for north, east in people[::max(1, len(people) // 60)]:
        assert "person" in ground.surfaces_within(float(north), float(east), 0.4)


@pytest.mark.parametrize("seed", range(1, 25))
def test_each_worlds_free_circle_is_landable_and_nobody_stands_in_it(photos: str, ground, seed: int) -> None:
    spec = FlightJob(seed, ground="photo", photos=photos).spec()
    world, free, start = build_world(spec)
    assert world.fixed_people is not None and len(world.fixed_people) > 100
    if spec.world == "dense":
        assert free is None
        return
    assert free is not None
    assert ground.surfaces_within(free.north, free.east, free.radius + 0.5) <= PHOTO_LANDABLE
    assert world.people_within(Circle(free.north, free.east, free.radius + 0.3)) == 0
    assert world.nearest_person_distance((free.north, free.east)) > free.radius


def test_scenes_are_drawn_among_every_photo_that_holds_their_disc(photos: str, ground) -> None:
    """Issue 59: a scene's photo is drawn first, each photo that holds a landable disc of the
    free radius plus 1 m (nobody of the photos within 1 m of it) as likely as any other, so a
    small landable photo hosts scenes too (until session 29 a point was drawn among the whole
    block's, and the two largest photos held every scene of seeds 1-75: 533 and 326 all but
    one). Every disc drawn is landable by the class maps, nobody of the photos within it."""
    radius = 5.2 + PHOTO_FREE_MARGIN_M  # the scenarios' radii are 5-8 m
    hosts = ground.places(radius)
    assert len(hosts) >= 3
    largest = ground.largest_discs()
    assert all(largest[name] >= radius for name in hosts)
    assert sum(r >= radius for r in largest.values()) == len(hosts)
    drawn = []
    for seed in range(1, 31):
        name, (north, east) = ground.place_centre(radius, np.random.default_rng([seed, 0x9407]))
        drawn.append(name)
        assert ground.surfaces_within(north, east, radius - 0.2) <= PHOTO_LANDABLE
        people = ground.people((north, east), radius + 5.0)
        assert len(people) == 0 or np.hypot(*(people - [north, east]).T).min() > radius + 1.0
    assert set(drawn) == set(hosts)  # every photo that can host one does
    assert max(drawn.count(n) for n in hosts) <= 2 * len(drawn) / len(hosts)  # none holds most
    # The flights' scenes (seeds 1-75) lie on every photo that holds the smallest of their discs.
    specs = [FlightJob(seed, ground="photo", photos=photos).spec() for seed in range(1, 76)]
    scenes = [s for s in specs if s.world not in ("dense", "uniform", "dronecrowd")]
    on = set()
    for spec in scenes:
        north, east = photo_scene_centre(spec)
        n, e = (north - ground.origin[0]) % ground.block_n, (east - ground.origin[1]) % ground.block_e
        on |= {p.name for p in ground.patches
               if p.north <= n < p.north + p.cell_m[0] and p.east <= e < p.east + p.cell_m[1]}
    assert on == set(ground.places(min(s.free_radius_m for s in scenes) + PHOTO_FREE_MARGIN_M))


@pytest.mark.parametrize("seed", [2, 8])  # crossing worlds whose crossers, drawn anywhere, leave it
def test_the_crossing_worlds_crossers_start_and_walk_on_ground_people_walk_on(photos: str, ground, seed: int) -> None:
    """Issue 59: the crossing world's crossers start, cross and stop on walkable ground by the
    class maps, every 0.1 s for a minute, as the flights draw them; drawn anywhere (as on the
    drawn ground, and on the photo ground until session 29) some of them stand on roofs, cars or
    vegetation."""
    spec = FlightJob(seed, ground="photo", photos=photos).spec()
    assert spec.world == "crossing"
    _world, free, _start = build_world(spec)
    assert free is not None
    walkable = crossing_walkable(spec, free)
    assert walkable is not None and walkable.mask.mean() < 1.0
    off = {}
    for on in (True, False):
        world = World(seed=seed)
        crossers = add_crossing_walkers(world, free, 0.0, seed, walkable=walkable if on else None)
        assert len(crossers) >= 2
        positions, entered = [], 0
        for _ in range(600):
            world.step(0.1)
            positions.append(world.positions())
            entered = max(entered, world.people_within(free))
        assert entered > 0  # they still cross the free circle
        off[on] = float((~walkable(np.vstack(positions))).mean())
    assert off[True] == 0.0
    assert off[False] > 0.05


def test_the_photos_people_count_for_the_judge_as_walkers_do() -> None:
    w = World(seed=1, fixed_people=np.array([[10.0, 0.0]]))
    assert w.nearest_person_distance((10.0, 1.5)) == pytest.approx(1.5)
    assert w.people_within(Circle(10.0, 0.0, 1.0)) == 1 and len(w.positions()) == 0
    assert World(seed=1).nearest_person_distance((0.0, 0.0)) == math.inf


def test_touchdowns_are_judged_on_the_class_maps(ground, photos: str) -> None:
    roof = PHOTO_CLASSES.index("roof")
    p = max(ground.patches, key=lambda p: int((p.classes == roof).sum()))
    H, W = p.classes.shape
    on, oe = ground.origin
    ys, xs = np.nonzero(p.classes == roof)
    k = len(ys) // 2
    point = (on + p.north + (H - ys[k] - 0.5) * p.gsd, oe + p.east + (xs[k] + 0.5) * p.gsd)
    surfaces = touchdown_surfaces(ground, point)
    assert surfaces is not None and "roof" in surfaces
    spec = FlightSpec(ground="photo", photos=photos)
    assert FlightResult(spec, "safe", touchdown_surfaces=surfaces).unlandable_touchdown
    assert not FlightResult(spec, "safe", touchdown_surfaces=["dirt", "grass"]).unlandable_touchdown


def test_photo_rows_say_so_and_are_keyed_apart_drawn_rows_do_not_change(photos: str) -> None:
    drawn = FlightResult(FlightSpec(), "safe").as_dict()
    photo = FlightResult(FlightSpec(ground="photo", photos=photos), "safe").as_dict()
    assert "ground" not in drawn and photo["ground"] == "photo"
    assert row_key(drawn) != row_key(photo)
    assert FlightJob(3, "px4").key() != FlightJob(3, "px4", ground="photo", photos=photos).key()
    assert FlightJob(3, "px4").key() == row_key({"seed": 3, "flavour": "px4"})
    with pytest.raises(ValueError, match="photos"):
        FlightSpec(ground="photo")


def test_walkers_are_drawn_as_real_silhouettes_the_same_every_time(photos: str, ground) -> None:
    spec = FlightJob(3, ground="photo", photos=photos).spec()
    world, free, start = build_world(spec)
    world.step(3.0)
    K = Intrinsics.from_fov(640, 480, 70.0)
    first = world.positions()[0]  # over a walker
    pose = Pose(0.0, float(first[0]) + 1.0, float(first[1]) + 1.0, -12.0, 0.0, 0.0, 0.0)
    a = render_world(world, pose, K, Mount(), ground)
    b = render_world(world, pose, K, Mount(), ground)
    assert np.array_equal(a, b)
    empty = World(seed=world.seed, free_areas=world.free_areas)
    bare = render_world(empty, pose, K, Mount(), ground)
    changed = np.abs(a.astype(int) - bare.astype(int)).max(axis=2) > 30
    # A walker in view from 12 m, and the silhouettes are person-sized, not blobs of paint.
    assert 50 < changed.sum() < 0.2 * changed.size


def test_open_ground_walkers_start_outside_the_circle_and_cross_it() -> None:
    free = Circle(0.0, 0.0, 6.0)
    crowd = open_ground_walkers(Bounds.around((0.0, 0.0), 20.0), free, seed=4, count=30)
    assert (free.distance(crowd.positions()) >= free.radius).all()
    world = World([crowd], [free], seed=4)
    entered = 0
    for _ in range(600):
        world.step(0.2)
        entered = max(entered, world.people_within(free))
    assert entered > 0  # they walk across the free circle, as people do
    assert world.nobody_walks_at((0.0, 0.0)) is True  # the circle is still the scene's free area


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_walkers_keep_to_ground_people_walk_on(photos: str, ground, seed: int) -> None:
    """Issue 59 item 2: walkers walk where people walk, not over roofs, water or trees: every
    lone walker, group member and standing person stays on walkable ground (by the class maps)
    for a minute (until session 28 a group's follower whose slot lay off it started there)."""
    spec = FlightJob(seed, ground="photo", photos=photos).spec()
    world, free, _start = build_world(spec)
    crowds = [s for s in world.sources if getattr(getattr(s, "params", None), "walkable", None) is not None]
    assert len(crowds) == 2  # the scene's crowd and the open-ground walkers
    walkable = crowds[0].params.walkable
    assert 0.2 < walkable.mask.mean() < 1.0  # the scene holds ground nobody walks on
    moved = 0.0
    for c in crowds:
        assert walkable(c.positions()).all()  # lone walkers, groups and standing people
    for _ in range(300):
        before = crowds[0].lead_pos.copy()
        world.step(0.2)
        for c in crowds:
            assert walkable(c.positions()).all()
        moved += float(np.hypot(*(crowds[0].lead_pos - before).T).mean())
    assert moved > 20.0  # they still walk (a metre or so a second, less their pauses and turns)


@pytest.mark.parametrize("seed", [16, 1])  # dense, dense_beyond
def test_the_dense_worlds_crowd_stands_on_ground_people_walk_on(photos: str, ground, seed: int) -> None:
    """Issue 59: the dense worlds' milling crowd stands on walkable ground by the class maps,
    not on roofs, water or trees, for a minute (until session 28 about 30 % of it did)."""
    spec = FlightJob(seed, ground="photo", photos=photos).spec()
    assert spec.world in ("dense", "dense_beyond")
    world, _free, start = build_world(spec)
    walkable = ground.walkable(start, 46.0)
    assert 0.2 < walkable.mask.mean() < 1.0  # the scene holds ground nobody walks on
    milling = world.sources[0]
    assert len(milling.positions()) > 1000  # still a dense crowd where people can stand
    for _ in range(300):
        assert walkable(world.positions()).all()
        world.step(0.2)
    assert walkable(world.positions()).all()


def test_a_missing_or_malformed_photos_folder_is_named(tmp_path: Path, photos: str) -> None:
    with pytest.raises(PhotosError, match=str(tmp_path / "nowhere")):
        check_photos(tmp_path / "nowhere")
    (tmp_path / "images").mkdir()
    with pytest.raises(PhotosError, match="labels"):
        check_photos(tmp_path)
    (tmp_path / "labels").mkdir()
    for name in sorted(os.listdir(Path(photos) / "images"))[:3]:
        (tmp_path / "images" / name).symlink_to(Path(photos) / "images" / name)
    with pytest.raises(PhotosError, match="fewer than"):
        check_photos(tmp_path)


def test_the_held_out_photos_are_refused_by_the_data_set_loaders(photos: str) -> None:
    first = sorted((Path(photos) / "images").glob("*.jpg"))[0]
    with pytest.raises(DatasetError, match="held-out"):
        read_image(first)
    refuse_held_out(Path(photos).parent / "images" / "000.jpg")  # the training folder is fine
