"""The scenario runner's seeded draws (no flights here: `companion sim-scenarios` flies them)."""

from __future__ import annotations

import dataclasses

import pytest

from sim.flight import FlightResult, FlightSpec, summarise
from sim.scenarios import parse_seeds, scenario


def test_a_seed_is_the_same_scene_whatever_the_flavour():
    for seed in range(1, 40):
        drawn = scenario(seed)
        for flavour in ("ardupilot", "px4"):
            forced = scenario(seed, flavour)
            assert forced.flavour == flavour
            assert dataclasses.replace(forced, flavour=drawn.flavour) == drawn


def test_px4_home_origin_offsets_are_drawn_within_3_m_both_ways():
    offsets = [scenario(seed).home_origin_offset_m for seed in range(1, 200)]
    assert all(abs(o) <= 3.0 for o in offsets)
    assert min(offsets) < -1.0 and max(offsets) > 1.0
    assert scenario(7) == scenario(7)  # deterministic


def test_summary_reports_the_highest_climb_over_the_flights():
    spec = FlightSpec()
    results = [FlightResult(spec, "safe", touchdown=(0.0, 0.0), clearance_m=5.0, time_to_touchdown_s=20.0,
                            max_climb_m=0.4),
               FlightResult(spec, "handback", touchdown=(1.0, 0.0), clearance_m=3.0, time_to_touchdown_s=60.0,
                            max_climb_m=2.5)]
    s = summarise(results)
    assert s["max_climb_m"] == 2.5 and s["safe"] == 1 and s["handbacks"] == 1
    assert results[1].as_dict()["max_climb_m"] == 2.5


def test_seed_lists_parse_and_bad_ones_are_refused():
    assert parse_seeds("1-3,7") == [1, 2, 3, 7]
    with pytest.raises(ValueError):
        parse_seeds("5-2")
