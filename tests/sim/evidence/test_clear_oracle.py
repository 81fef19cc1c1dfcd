"""``python -m sim.evidence.clear_oracle``: the landing rules flown with perfect sight over a world's
truth. The rules on made-up distances, then real worlds (the photo world's skip without ``../shared``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim.evidence.clear_oracle import DT_S, Rules, candidate_points, judge, main, oracle
from sim.world.ground import LANDABLE_SURFACES, ProceduralGround

RULES = Rules(r0_m=2.0, radius_margin_m=2.0, calm_margin_m=1.0, min_calm_s=5.0, descend_s=4.0,
              last_metres_s=4.4, earliest_s=10.0, max_takeover_s=60.0)
T = int(round(RULES.max_takeover_s / DT_S)) + 1
#: Steps from the first judging to touchdown, and the first judging's step.
TO_TOUCHDOWN = int(round((RULES.descend_s + RULES.last_metres_s) / DT_S))
FIRST = int(round(RULES.earliest_s / DT_S))


def _far(points: int = 3) -> np.ndarray:
    return np.full((T, points), 50.0)


def test_empty_ground_lands_clear_at_the_first_chance() -> None:
    v = judge(_far(), RULES)
    assert v.foresight and v.earliest == "clear" and v.judgeable == 1.0
    assert v.earliest_touchdown_s == pytest.approx(RULES.earliest_s + RULES.descend_s + RULES.last_metres_s)


def test_a_person_standing_inside_the_calm_disc_leaves_no_landing() -> None:
    d = np.full((T, 1), 2.9)  # beyond r0 but inside r0 + the calm margin, all along
    v = judge(d, RULES)
    assert not v.foresight and v.earliest == "none" and v.earliest_touchdown_s is None and v.judgeable == 0.0


def test_a_walker_in_the_blind_last_metres_makes_the_first_chance_unsafe_not_the_world() -> None:
    d = _far(1)
    touchdown = FIRST + TO_TOUCHDOWN
    d[touchdown - 3: touchdown + 3, 0] = 1.0  # walks through the point as the vehicle touches down
    v = judge(d, RULES)
    assert v.earliest == "unsafe"
    assert v.foresight  # a later try (the calm watch over again after the walker) lands clear


def test_somebody_within_r0_during_the_descent_sends_it_back_and_it_tries_again() -> None:
    d = _far(1)
    d[FIRST + 5, 0] = 1.5  # within r0 two seconds into the descent of the first chance
    v = judge(d, RULES)
    assert v.earliest == "clear" and v.foresight
    # The calm watch must run again after the walker: 5 s after them at the soonest.
    assert v.earliest_touchdown_s >= (FIRST + 5) * DT_S + RULES.min_calm_s + RULES.descend_s + RULES.last_metres_s - 1e-9


def test_the_first_chance_takes_the_point_farthest_from_everybody() -> None:
    d = _far(2)
    d[:, 0] = 4.5                         # judgeable, but a walker will come
    d[:, 1] = 8.0
    d[FIRST + TO_TOUCHDOWN, 0] = 1.0      # ... to point 0 only, at touchdown
    assert judge(d, RULES).earliest == "clear"


def test_a_takeover_too_short_for_the_rules_has_no_chance() -> None:
    short = Rules(earliest_s=10.0, descend_s=4.0, last_metres_s=4.4, max_takeover_s=15.0)
    assert judge(np.full((int(15 / DT_S) + 1, 2), 50.0), short).earliest == "none"
    assert judge(np.empty((T, 0)), RULES).earliest == "none"


def test_candidate_points_lie_on_landable_drawn_ground_within_reach() -> None:
    ground = ProceduralGround(3)
    centre = ground.lawn_near(80.0, 80.0)
    pts = candidate_points("procedural", 3, centre, 6.0, None)
    assert len(pts) > 100
    assert np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1]).max() <= 6.0 + 1e-9
    for north, east in pts[:: max(1, len(pts) // 25)]:
        assert ground.surfaces_within(north, east, 0.45) <= LANDABLE_SURFACES


def test_a_drawn_world_is_judged_the_same_every_time() -> None:
    rules = Rules(max_takeover_s=26.0)
    a = oracle(3, "px4", "procedural", None, 4.0, rules)
    b = oracle(3, "px4", "procedural", None, 4.0, rules)
    assert a == b and a is not None
    assert a.world == "free_area" and a.foresight and a.earliest == "clear" and 0 < a.judgeable <= 1


def test_the_dense_world_has_no_free_circle_to_judge() -> None:
    from sim.flights.scenarios import scenario

    dense = next(s for s in range(1, 40) if scenario(s, "px4").world == "dense")
    assert oracle(dense, "px4", "procedural", None, 6.0, Rules(max_takeover_s=30.0)) is None


def test_photo_world_seed_7_could_land_clear(photos: str) -> None:
    # Issue 59's yardstick: the companion handed back over this world (photo-px4-landing-point-1000.jsonl);
    # with perfect sight the rules land clear at the first chance.
    v = oracle(7, "px4", "photo", photos, 4.0, Rules(max_takeover_s=26.0))
    assert v is not None and v.foresight and v.earliest == "clear"


def test_the_photo_crossing_worlds_crossers_are_the_flights(photos: str) -> None:
    """Photo seed 2's crossers, drawn anywhere, leave the ground people walk on
    (tests/sim/world/test_photo_world.py); its flight draws them on it. The oracle's crowd is the
    flight's: after 20 s it stands where a world with the flight's draw stands."""
    from dataclasses import replace

    from sim.evidence.clear_oracle import TRIGGER_T_S, distances
    from sim.flights.flight import build_world, crossing_walkable
    from sim.flights.scenarios import scenario
    from sim.world.crowd import TICK_S, add_crossing_walkers

    spec = replace(scenario(2, "px4"), ground="photo", photos=photos)
    assert spec.world == "crossing"
    world, free, _ = build_world(spec)
    distances(world, free, np.zeros((1, 2)), 20.0, spec)
    flown, free2, _ = build_world(spec)
    while flown.t < TRIGGER_T_S - 1e-9:
        flown.step(TICK_S)
    add_crossing_walkers(flown, free2, flown.t, 2, window=spec.crossing_window, walkable=crossing_walkable(spec, free2))
    for _ in range(100):
        flown.step(DT_S)
    np.testing.assert_array_equal(world.positions(), flown.positions())


def test_cli_prints_a_summary_and_refuses_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--seeds", "3", "--reach", "2", "--json"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert lines[0]["seed"] == 3 and lines[-1]["worlds"] == 1 and lines[-1]["foresight_clear"] == 1
    assert main(["--seeds", "3", "--reach", "0"]) == 2
    assert "--reach" in capsys.readouterr().err
    assert main(["--seeds", "3", "--ground", "photo", "--photos", str(tmp_path / "nowhere")]) == 2
    assert "nowhere" in capsys.readouterr().err
