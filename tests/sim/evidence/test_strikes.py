"""``python -m sim.evidence.strikes``: each strike of a results file traced on the world's truth."""

from __future__ import annotations

import json
import math

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
