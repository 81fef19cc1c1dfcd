"""``python -m sim.evidence.strikes``: each strike of a results file traced on the world's truth."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from sim.evidence import strikes
from sim.flights.flight import build_world
from sim.flights.scenarios import scenario
from sim.world.crowd import TICK_S, add_crossing_walkers

T_TRIGGER = 4.0
TO_TOUCHDOWN = 8.0


def _world_at(seed: int, t: float, crossing: bool = False):
    spec = scenario(seed, None)
    world, free, _ = build_world(spec)
    added = False
    while world.t < t - 1e-9:
        if crossing and not added and world.t >= T_TRIGGER - 1e-9:
            add_crossing_walkers(world, free, world.t, seed, window=spec.crossing_window)
            added = True
        world.step(TICK_S)
    return spec, world, free


def _row(spec, point, clearance, **extra) -> dict:
    row = {"seed": spec.seed, "flavour": spec.flavour, "world": spec.world, "outcome": "unsafe",
           "strike": True, "baseline": False, "touchdown": [float(point[0]), float(point[1])],
           "clearance_m": clearance, "world_t_trigger": T_TRIGGER, "time_to_touchdown_s": TO_TOUCHDOWN,
           "r0_m": 2.0}
    row.update(extra)
    return row


def test_a_crowd_walker_beside_the_touchdown_is_found_at_their_true_distance():
    seed = 3  # a free-area world
    spec, world, free = _world_at(seed, T_TRIGGER + TO_TOUCHDOWN)
    assert spec.world == "free_area"
    p = world.positions()
    point = p[0] + np.array([1.0, 0.0])
    clearance = float(np.min(np.hypot(*(p - point).T)))
    [s], skipped = strikes.strikes([_row(spec, point, clearance)], [2.0, 4.0])
    assert skipped == 0
    assert s.striker == "crowd" and not s.mismatch
    assert s.recomputed_m == pytest.approx(clearance, abs=1e-3)
    assert set(s.distance_before_m) == {"2", "4"}
    # Nobody walks faster than the crowd's walkers do: the distance 2 s before is within reach.
    assert s.distance_before_m["2"] <= s.recomputed_m + 2.0 * 2.0
    assert s.walking_mps >= 0 and math.isfinite(s.distance_at_trigger_m)
    assert s.lawn_radius_m == pytest.approx(free.radius, abs=0.01)
    expected = float(np.hypot(*(point - np.asarray(free.centre))))
    assert s.lawn_centre_m == pytest.approx(expected, abs=0.01)


def test_a_crossing_walker_is_named_and_traced_from_the_trigger():
    seed = 2  # a crossing world
    spec, world, _ = _world_at(seed, T_TRIGGER + TO_TOUCHDOWN, crossing=True)
    assert spec.world == "crossing"
    moving = world.moving()
    scripted = world.ids() >= 1_000_000 * (len(world.sources) - 1)
    candidates = np.flatnonzero(moving & scripted)
    if len(candidates) == 0:
        pytest.skip("no crossing walker is on the lawn at this seed's chosen time")
    point = world.positions()[candidates[0]]
    [s], _ = strikes.strikes([_row(spec, point, 0.0)], [2.0])
    assert s.striker == "crossing"
    assert s.recomputed_m == pytest.approx(0.0, abs=1e-6)
    assert s.within_r0_for_s > 0
    assert math.isfinite(s.distance_at_trigger_m)  # not before they existed


def test_a_row_from_another_world_is_flagged_and_rows_without_strikes_are_left_alone():
    spec, world, _ = _world_at(3, T_TRIGGER + TO_TOUCHDOWN)
    point = world.positions()[0]
    rows = [_row(spec, point, 5.0),  # the truth says ~0 m
            _row(spec, point, 0.0, strike=False, outcome="safe"),
            _row(spec, point, 0.0, world="dronecrowd")]
    found, skipped = strikes.strikes(rows, [2.0])
    assert len(found) == 1 and found[0].mismatch and skipped == 1


def test_a_seed_drawing_another_world_than_the_row_says_is_refused():
    spec, world, _ = _world_at(3, T_TRIGGER + TO_TOUCHDOWN)
    row = _row(spec, world.positions()[0], 0.0, world="crossing")
    with pytest.raises(ValueError, match="draws a free_area world"):
        strikes.strikes([row], [2.0])


def test_cli_prints_each_strike_and_exits_2_on_a_missing_file(tmp_path, capsys):
    spec, world, _ = _world_at(3, T_TRIGGER + TO_TOUCHDOWN)
    point = world.positions()[0] + np.array([0.5, 0.0])
    clearance = float(np.min(np.hypot(*(world.positions() - point).T)))
    path = tmp_path / "rows.jsonl"
    path.write_text(json.dumps(_row(spec, point, clearance)) + "\n" + "not json\n")
    assert strikes.main([str(path), "--json"]) == 0
    out = capsys.readouterr()
    [line] = out.out.strip().splitlines()
    assert json.loads(line)["seed"] == 3
    assert "could not be read" in out.err
    assert strikes.main([str(path)]) == 0
    assert "1 strike(s) traced of 1" in capsys.readouterr().out
    assert strikes.main([str(tmp_path / "none.jsonl")]) == 2
    assert "no such results file" in capsys.readouterr().err
    assert strikes.main([str(path), "--before", "-1"]) == 2


def _photo_world_at(seed: int, photos: str, t: float):
    spec = replace(scenario(seed, None), ground="photo", photos=photos)
    world, free, _ = build_world(spec)
    while world.t < t - 1e-9:
        world.step(TICK_S)
    return spec, world, free


def test_a_photo_row_is_traced_on_the_photo_world_not_the_drawn_one(photos):
    """Seed 3 over the photos: its walkers are the photo world's (they keep to walkable ground
    by the class maps), so the drawn world's would put the striker elsewhere."""
    spec, world, _ = _photo_world_at(3, photos, T_TRIGGER + TO_TOUCHDOWN)
    p = world.positions()
    point = p[0] + np.array([0.7, 0.0])
    everyone = np.vstack([p, np.asarray(world.fixed_people, float).reshape(-1, 2)])
    clearance = float(np.min(np.hypot(*(everyone - point).T)))
    row = _row(spec, point, clearance, ground="photo")
    [s], skipped = strikes.strikes([row], [2.0], photos)
    assert skipped == 0 and not s.mismatch and s.striker == "crowd"
    assert s.recomputed_m == pytest.approx(clearance, abs=1e-3)
    [drawn], _ = strikes.strikes([dict(row, ground="procedural")], [2.0])
    assert drawn.mismatch  # the drawn world's crowd is elsewhere
    with pytest.raises(ValueError, match="photo world"):
        strikes.strikes([row], [2.0])  # a photo row needs its photos


def test_a_person_standing_in_a_photo_is_named_and_never_moves(photos):
    """A touchdown 0.5 m from one of the people the photos show (``World.fixed_people``): the
    striker is ``photo``, at the same distance at every instant, within r0 since the trigger."""
    for seed in range(1, 40):
        spec, world, _ = _photo_world_at(seed, photos, 0.0)
        if world.fixed_people is not None and len(world.fixed_people):
            break
    else:
        pytest.fail("no seed of 1-39 shows a person in its photos")
    fixed = np.asarray(world.fixed_people, float).reshape(-1, 2)
    spec, world, _ = _photo_world_at(seed, photos, T_TRIGGER + TO_TOUCHDOWN)
    point = fixed[0] + np.array([0.0, 0.5])
    everyone = np.vstack([world.positions(), fixed])
    nearest = float(np.min(np.hypot(*(everyone - point).T)))
    if nearest < 0.5 - 1e-9:
        pytest.skip(f"seed {seed}: somebody else stands nearer the point than the photo's person")
    [s], _ = strikes.strikes([_row(spec, point, 0.5, ground="photo")], [2.0, 4.0], photos)
    assert s.striker == "photo" and s.recomputed_m == pytest.approx(0.5, abs=1e-3) and not s.mismatch
    assert s.distance_before_m == {"2": 0.5, "4": 0.5} and s.walking_mps == 0.0
    assert s.within_r0_for_s == pytest.approx(TO_TOUCHDOWN)
    assert "0.50 m from a person standing in a photo" in s.text()


def test_cli_exits_2_naming_a_missing_photos_folder(tmp_path, capsys, photos):
    spec, world, _ = _photo_world_at(3, photos, T_TRIGGER + TO_TOUCHDOWN)
    path = tmp_path / "rows.jsonl"
    path.write_text(json.dumps(_row(spec, world.positions()[0], 0.0, ground="photo")) + "\n")
    missing = tmp_path / "no-photos"
    assert strikes.main([str(path), "--photos", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err
    assert strikes.main([str(path), "--photos", photos]) == 0
    assert "1 strike(s) traced of 1" in capsys.readouterr().out
