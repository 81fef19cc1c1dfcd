"""The scenario runner's seeded draws, its summary and the baseline's (no flights here: `companion
sim-scenarios` flies them)."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest

from sim.flights import scenarios
from sim.flights.flight import FlightResult, FlightSpec, summarise
from sim.flights.results import (
    ResultsFile,
    baseline_text,
    phase_changes,
    read_rows,
    row_key,
    summarise_baseline,
    summarise_rows,
    summary_text,
)
from sim.flights.scenarios import FlightJob, parse_seeds, plan, run_jobs, scenario


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


# ---- the mix of worlds -----------------------------------------------------------------------

#: What seeds 1-12 drew before the ``crossing`` world was added (flavour, world, altitude, free
#: radius, failsafe, PX4 home-origin offset): the crossing draw came last, so they must stay.
BEFORE_CROSSING = {
    1: ("ardupilot", "dense", 24.5046, 6.2700, "rc_loss", 2.4831),
    2: ("px4", "free_area", 17.9849, 7.1857, "battery_critical", 0.5637),
    3: ("px4", "free_area", 17.3681, 6.2994, "battery_critical", 1.4372),
    4: ("px4", "free_area", 20.1133, 6.1295, "gcs_loss", 2.4057),
    5: ("px4", "free_area", 23.0794, 6.1501, "gcs_loss", 1.2254),
    6: ("ardupilot", "free_area", 18.4327, 6.8983, "rc_loss", 2.0230),
    7: ("px4", "free_area", 23.9721, 7.6207, "rc_loss", -0.0158),
    8: ("px4", "free_area", 24.8728, 6.1733, "battery_critical", 1.3136),
    9: ("ardupilot", "free_area", 17.8682, 7.7461, "gcs_loss", -2.5812),
    10: ("px4", "free_area", 17.0768, 5.4078, "gcs_loss", -2.0671),
    11: ("ardupilot", "free_area", 19.9928, 7.7846, "battery_critical", 0.2113),
    12: ("px4", "free_area", 24.4675, 5.6916, "battery_critical", 2.0113),
}


def test_every_seed_keeps_its_scene_and_some_free_areas_gain_crossing_walkers():
    for seed, (flavour, world, alt, radius, failsafe, offset) in BEFORE_CROSSING.items():
        s = scenario(seed)
        assert (s.flavour, s.failsafe) == (flavour, failsafe)
        assert s.altitude_m == pytest.approx(alt, abs=1e-4)
        assert s.home_origin_offset_m == pytest.approx(offset, abs=1e-4)
        # A free area may have become a crossing (the same scene, walkers added), and a dense crowd
        # may have gained one free circle out of view (its circle drawn anew); nothing else changes.
        assert s.world == world or (world, s.world) in (("free_area", "crossing"), ("dense", "dense_beyond")), \
            (seed, s.world)
        if s.world != "dense_beyond":
            assert s.free_radius_m == pytest.approx(radius, abs=1e-4)
        else:
            assert 22.0 <= math.hypot(*s.start_offset_m) <= 30.0 and 6.0 <= s.free_radius_m <= 8.0
    worlds = [scenario(seed).world for seed in range(1, 301)]
    assert set(worlds) == {"free_area", "dense", "dense_beyond", "crossing"}
    free_kinds = [w for w in worlds if not w.startswith("dense")]
    assert 0.25 < free_kinds.count("crossing") / len(free_kinds) < 0.42  # a third, drawn
    dense_kinds = [w for w in worlds if w.startswith("dense")]
    assert 0.35 < dense_kinds.count("dense_beyond") / len(dense_kinds) < 0.65  # a half, drawn
    assert any(scenario(seed).world == "crossing" for seed in range(1, 7))


def test_crossing_walkers_cross_the_zone_during_the_descent_at_walking_speed():
    from sim.world.crowd import CROSSING_WINDOW_S, World, add_crossing_walkers
    from sim.world.walkers import Circle, Crossing

    circle = Circle(10.0, -4.0, 6.0)
    for seed in range(1, 30):
        world = World(seed=seed)
        world.step(3.0)  # the failsafe comes at world time 3 s
        walkers = add_crossing_walkers(world, circle, world.t, seed)
        assert 2 <= len(walkers) <= 4
        assert all(1.0 <= w.speed <= 1.5 for w in walkers)
        inside_at: list[list[float]] = [[] for _ in walkers]
        last = world.positions()
        t_end = 3.0 + CROSSING_WINDOW_S[1] + 30.0
        while world.t < t_end:
            world.step(0.1)
            p = world.positions()
            assert (np.hypot(*(p - last).T) <= 1.5 * 0.1 + 1e-9).all()  # never faster than walking
            last = p
            for i, d in enumerate(circle.distance(p)):
                if d < circle.radius:
                    inside_at[i].append(world.t)
        for w, times in zip(walkers, inside_at):
            assert times, "every walker crosses the zone"
            assert times[0] == pytest.approx(w.t_enter, abs=0.11)
            assert 3.0 + CROSSING_WINDOW_S[0] - 0.11 <= times[0] <= 3.0 + CROSSING_WINDOW_S[1] + 0.11
            assert times[-1] - times[0] < 2 * circle.radius / w.speed + 0.2  # and leaves it
        assert (circle.distance(world.positions()) > circle.radius).all()
    assert add_crossing_walkers(World(), circle, 0.0, 5) == add_crossing_walkers(World(), circle, 0.0, 5)
    with pytest.raises(ValueError):
        Crossing(circle, 1.0, offset_m=6.0)


def test_a_crossing_flight_is_a_free_area_scene_and_a_baseline_has_no_companion():
    from sim.flights.flight import build_world

    spec = scenario(2)
    assert spec.world == "crossing" and spec.companion
    free_area = dataclasses.replace(spec, world="free_area")
    w1, free1, start1 = build_world(spec)
    w2, free2, start2 = build_world(free_area)
    assert free1 == free2 and start1 == start2 and (w1.positions() == w2.positions()).all()
    base = FlightJob(2, baseline=True)
    assert not base.spec().companion and dataclasses.replace(base.spec(), companion=True) == spec
    assert FlightResult(base.spec(), "handback").as_dict()["baseline"] is True
    assert FlightResult(spec, "safe").as_dict()["baseline"] is False


# ---- the summary's new figures, and the baseline kept apart ----------------------------------


def _row(seed: int, outcome: str, *, phases: int = 5, strike: bool = False, baseline: bool = False,
         clearance: float | None = 4.0, starved: bool = False) -> dict[str, Any]:
    return {"seed": seed, "flavour": "ardupilot", "world": "free_area", "outcome": outcome,
            "starved": starved, "strike": strike, "clearance_m": clearance, "time_to_touchdown_s": 20.0 + seed,
            "max_climb_m": 0.0, "altitude_m": 20.0, "phases": ["SELECT"] * phases, "messages": [],
            "baseline": baseline}


def test_the_summary_counts_phase_changes_and_strikes_from_rows():
    rows = [_row(1, "safe", phases=5), _row(2, "safe", phases=9), _row(3, "handback", phases=2, strike=True,
            clearance=0.5), _row(4, "unsafe", phases=35, strike=True, clearance=1.0),
            _row(5, "safe", phases=80, starved=True)]
    s = summarise_rows(rows)
    assert s["median_phase_changes"] == 7.0 and s["max_phase_changes"] == 35  # the clean flights'
    assert s["strikes"] == 2 and s["companion_landings"] == 3
    assert summarise_rows([])["median_phase_changes"] is None
    assert "phase changes per flight: median 7.0, most 35" in summary_text(s)
    # A flight's phase changes are its recorded phase-change events (FlightResult.phases).
    assert phase_changes({"phases": ["SELECT", "APPROACH", "DESCEND", "HOLD"]}) == 4
    assert phase_changes({}) == 0

    base = summarise_baseline([_row(1, "handback", phases=0, baseline=True, strike=True, clearance=0.3),
                               _row(2, "handback", phases=0, baseline=True, clearance=6.0),
                               _row(3, "handback", phases=0, baseline=True, strike=True, clearance=1.1),
                               _row(4, "timeout", phases=0, baseline=True, clearance=None)])
    assert (base["total"], base["clean_flights"], base["strikes"], base["timeouts"]) == (4, 4, 2, 1)
    assert base["strike_rate"] == 0.5 and base["min_clearance_m"] == 0.3
    assert base["strike_rate_ci95"][0] < 0.5 < base["strike_rate_upper95"]
    # The autopilot's own LAND over its last 3.5 m, the baseline's touchdowns (None: not recorded).
    assert base["median_last_metres_s"] is None
    timed = summarise_baseline([{**_row(s, "handback", phases=0, baseline=True), "last_metres_s": v}
                                for s, v in ((1, 3.6), (2, 3.8), (3, 7.1))])
    assert timed["median_last_metres_s"] == 3.8
    assert "last 3.5 m in a median 3.8 s" in baseline_text({**summarise_rows([_row(1, "safe")]), "baseline": timed})
    assert "last 3.5 m" not in baseline_text({**summarise_rows([_row(1, "safe")]), "baseline": base})


def test_baseline_rows_are_kept_apart_from_the_companions_on_resume(tmp_path, monkeypatch, capsys):
    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append(_row(1, "safe"))                                  # companion, seed 1
        f.append(_row(2, "handback", baseline=True, strike=True, clearance=0.8))  # baseline, seed 2
    assert row_key(_row(2, "handback", baseline=True)) == (2, "ardupilot", "baseline")
    assert row_key(_row(2, "handback")) == (2, "ardupilot")
    flown: list[tuple[int, bool]] = []

    def fake(job: FlightJob) -> dict[str, Any]:
        flown.append((job.seed, job.baseline))
        assert job.spec().companion is not job.baseline
        strike = job.baseline and job.seed == 1
        return _row(job.seed, "handback" if job.baseline else "safe", baseline=job.baseline, strike=strike,
                    phases=0 if job.baseline else 6, clearance=1.5 if strike else 5.0)

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    jobs = [FlightJob(s, "ardupilot", baseline=b) for s in (1, 2) for b in (False, True)]
    todo, kept = plan(jobs, read_rows(out)[0])
    assert [(j.seed, j.baseline) for j in todo] == [(1, True), (2, False)]
    assert set(kept) == {(1, "ardupilot"), (2, "ardupilot", "baseline")}

    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0
    assert flown == [(1, True), (2, False)]
    s = json.loads(capsys.readouterr().out)
    assert [(r["seed"], r["baseline"]) for r in s["flights"]] == [(1, False), (2, False)]
    assert (s["total"], s["safe"], s["strikes"]) == (2, 2, 0)  # baseline rows never counted here
    b = s["baseline"]
    assert [(r["seed"], r["baseline"]) for r in b["flights"]] == [(1, True), (2, True)]
    assert (b["total"], b["strikes"], b["strike_rate"]) == (2, 2, 1.0) and b["strike_rate_upper95"] == 1.0
    assert s["strikes_vs_baseline"] == 0.0
    assert len(read_rows(out)[0]) == 4

    # Again: nothing left to fly; without --baseline, the baseline rows stay out of the figures.
    flown.clear()
    assert run_jobs(jobs, workers=1, out=out) == 0 and flown == []
    text = capsys.readouterr().out
    assert "strikes, companion: 0/2 clean flights" in text
    assert "strikes, baseline (autopilot's failsafe alone, no companion): 2/2 clean flights" in text
    assert "companion strike rate / baseline strike rate: 0.00" in text
    line = scenarios.flight_line(_row(1, "handback", baseline=True, strike=True))
    assert line.startswith("baseline seed   1") and "STRIKE" in line
    companion_only = [FlightJob(s, "ardupilot") for s in (1, 2)]
    assert run_jobs(companion_only, workers=1, out=out, as_json=True) == 0 and flown == []
    s = json.loads(capsys.readouterr().out)
    assert "baseline" not in s and "strikes_vs_baseline" not in s and s["total"] == 2


def test_service_settings_fly_with_every_seed_and_keep_their_rows_apart(tmp_path, monkeypatch, capsys, model_path):
    # `--set model.path=...` flies a researcher's own model in closed loop; a results file never
    # resumes a seed from a row flown with other settings.
    own = tmp_path / "own.onnx"
    own.write_bytes(model_path.read_bytes())
    monkeypatch.chdir(tmp_path)
    ss = scenarios.service_settings(["model.path=own.onnx", "controller.min_calm_s=6"])
    assert ss == ("controller.min_calm_s=6", f"model.path={own}")  # sorted, the path absolute
    job = FlightJob(1, "ardupilot", service_set=ss, threads=1)
    assert set(ss) <= set(job.spec().service_set) and "model.threads=1" in job.spec().service_set
    assert job.key() != FlightJob(1, "ardupilot").key()
    assert job.key() == row_key({"seed": 1, "flavour": "ardupilot", "settings": list(ss)})

    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append(_row(1, "safe"))  # seed 1 flown with the defaults: not this experiment's
    flown: list[tuple[int, tuple[str, ...]]] = []

    def fake(j: FlightJob) -> dict[str, Any]:
        flown.append((j.seed, j.service_set))
        return {**_row(j.seed, "safe"), "settings": list(j.service_set)}

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    jobs = [FlightJob(s, "ardupilot", service_set=ss) for s in (1, 2)]
    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0
    assert flown == [(1, ss), (2, ss)]
    s = json.loads(capsys.readouterr().out)
    assert [(r["seed"], r["settings"]) for r in s["flights"]] == [(1, list(ss)), (2, list(ss))]
    flown.clear()
    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0 and flown == []  # resumed


@pytest.mark.parametrize("item, says", [
    ("controller.no_such_key=1", "no_such_key"),
    ("model.path=/nonexistent/model.onnx", "no such file"),
    ("pipeline.r0_m=-1", "r0_m"),
    ("justakey", "key=value"),
])
def test_a_bad_setting_is_exit_2_before_anything_flies(item, says, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--set", item]) == 2
    err = capsys.readouterr().err
    assert "--set" in err and says in err


def test_the_land_speed_flies_the_autopilots_land_and_keeps_its_rows_apart(tmp_path, monkeypatch, capsys):
    # `--land-speed 0.5` flies the simulated autopilot's LAND as a vehicle left at ArduPilot's
    # default; rows flown at the scenarios' own speed are not resumed from, nor mixed in.
    from sim.flights.flight import build_scene
    from sim.flights.results import SCENARIO_LAND_SPEED

    assert scenario(3).land_speed == SCENARIO_LAND_SPEED == 1.0
    job = FlightJob(3, "ardupilot", land_speed=0.5)
    assert job.spec().land_speed == 0.5 and FlightJob(3, "ardupilot", baseline=True, land_speed=0.5).spec().land_speed == 0.5
    _world, _free, sim, _camera = build_scene(job.spec(), 14550, 8080)  # built, not started
    assert sim.vehicle.params.land_speed == 0.5
    assert job.key() == (3, "ardupilot", "land:0.5")
    assert FlightJob(3, "ardupilot").key() == (3, "ardupilot") == row_key({**_row(3, "safe"), "land_speed": 1.0})
    assert FlightJob(3, "ardupilot", land_speed=1.0).key() == (3, "ardupilot")  # the scenarios' own speed

    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append({**_row(1, "safe"), "land_speed": 1.0})  # the scenarios' speed: not this experiment's
    flown: list[float | None] = []

    def fake(j: FlightJob) -> dict[str, Any]:
        flown.append(j.land_speed)
        return {**_row(j.seed, "safe"), "land_speed": j.spec().land_speed}

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    jobs = [FlightJob(s, "ardupilot", land_speed=0.5) for s in (1, 2)]
    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0 and flown == [0.5, 0.5]
    s = json.loads(capsys.readouterr().out)
    assert [(r["seed"], r["land_speed"]) for r in s["flights"]] == [(1, 0.5), (2, 0.5)]
    flown.clear()
    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0 and flown == []  # resumed


def test_a_longer_watch_is_flown_and_keeps_its_rows_apart(tmp_path, monkeypatch, capsys):
    # `--watch-s 30` lets the service watch the crowd 30 s before the failsafe (a service that ran
    # the whole flight has seen more than the scenarios' 4 s); rows of the scenarios' own watch,
    # and rows written before the field existed, are not resumed from, nor mixed in.
    from sim.flights.results import SCENARIO_WATCH_S

    assert scenario(3).watch_s == SCENARIO_WATCH_S == 4.0
    job = FlightJob(3, "ardupilot", watch_s=30.0)
    assert job.spec().watch_s == 30.0 and FlightJob(3, "ardupilot", baseline=True, watch_s=30.0).spec().watch_s == 30.0
    assert job.key() == (3, "ardupilot", "watch:30")
    assert FlightJob(3, "ardupilot").key() == (3, "ardupilot") == row_key({**_row(3, "safe"), "watch_s": 4.0})
    assert FlightJob(3, "ardupilot", watch_s=4.0).key() == (3, "ardupilot") == row_key(_row(3, "safe"))

    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append(_row(1, "safe"))  # the scenarios' own watch: not this experiment's
    flown: list[float | None] = []

    def fake(j: FlightJob) -> dict[str, Any]:
        flown.append(j.watch_s)
        return {**_row(j.seed, "safe"), "watch_s": j.spec().watch_s}

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    from companion.cli import main

    args = ["sim-scenarios", "--seeds", "1-2", "--flavour", "ardupilot", "--workers", "1", "--no-progress",
            "--no-machine-check", "--json", "--watch-s", "30", "--out", str(out)]
    assert main(args) == 0 and flown == [30.0, 30.0]
    s = json.loads(capsys.readouterr().out)
    assert [(r["seed"], r["watch_s"]) for r in s["flights"]] == [(1, 30.0), (2, 30.0)]
    flown.clear()
    assert main(args) == 0 and flown == []  # resumed


def test_link_latency_is_flown_recorded_and_keeps_its_rows_apart(tmp_path, monkeypatch, capsys):
    # `--link-latency 0.2` flies every seed with 200 ms added each way (on the simulated clock in
    # lockstep), records it in the row and keys it apart, so the same seed with and without it
    # pairs in sim-compare; without it (or at 0) the rows keep exactly the fields they had.
    job = FlightJob(3, "px4", lockstep=True, link_latency=0.2)
    assert job.spec().latency_ms == pytest.approx(200.0) and FlightJob(3, "px4").spec().latency_ms == 0.0
    assert job.key() == (3, "px4", "latency:0.2", "lockstep")
    assert FlightJob(3, "px4", lockstep=True).key() == (3, "px4", "lockstep")
    assert scenarios.link_latency_field(job.spec()) == {"link_latency_s": pytest.approx(0.2)}
    assert scenarios.link_latency_field(FlightJob(3, "px4").spec()) == {}

    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append(_row(1, "safe"))  # flown without latency: not this experiment's
    flown: list[float] = []

    def fake(j: FlightJob) -> dict[str, Any]:
        flown.append(j.spec().latency_ms)
        return {**_row(j.seed, "safe"), **scenarios.link_latency_field(j.spec())}

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    from companion.cli import main

    args = ["sim-scenarios", "--seeds", "1-2", "--flavour", "ardupilot", "--workers", "1", "--no-progress",
            "--no-machine-check", "--json", "--link-latency", "0.2", "--out", str(out)]
    assert main(args) == 0 and flown == [200.0, 200.0]
    s = json.loads(capsys.readouterr().out)
    assert [(r["seed"], r["link_latency_s"]) for r in s["flights"]] == [(1, 0.2), (2, 0.2)]
    flown.clear()
    assert main(args) == 0 and flown == []  # resumed
    assert main([*args[:-4], "--link-latency", "0", "--out", str(tmp_path / "none.jsonl")]) == 0
    assert flown == [0.0, 0.0]  # 0 is no latency: the rows of a flight without the option
    assert "link_latency_s" not in read_rows(tmp_path / "none.jsonl")[0][0]


@pytest.mark.parametrize("value", ["-0.1", "nan", "inf", "5.5"])
def test_a_bad_link_latency_is_exit_2_before_anything_flies(value, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--link-latency", value]) == 2
    assert "--link-latency must be 0-5 s" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "0.5", "-1", "nan", "inf", "601"])
def test_a_bad_watch_is_exit_2_before_anything_flies(value, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--watch-s", value]) == 2
    assert "--watch-s must be 1-600 s" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "3.5"])
def test_a_bad_land_speed_is_exit_2_before_anything_flies(value, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--land-speed", value]) == 2
    assert "--land-speed must be 0.1-3 m/s" in capsys.readouterr().err


def test_a_crossing_window_draws_crossings_over_it_at_the_same_rate_and_keeps_its_rows_apart(tmp_path, monkeypatch,
                                                                                              capsys):
    # `--crossing-window 4-84`: the crossing world's walkers cross over 80 s after the failsafe, as
    # many more of them as keep the rate of its own 4-24 s; rows are keyed apart.
    from sim.flights.flight import build_world
    from sim.flights.results import SCENARIO_CROSSING_WINDOW_S
    from sim.world.crowd import CROSSING_WINDOW_S, Circle, World, add_crossing_walkers

    assert SCENARIO_CROSSING_WINDOW_S == CROSSING_WINDOW_S == scenario(3).crossing_window
    circle = Circle(0.0, 0.0, 6.0)
    own = add_crossing_walkers(World(seed=1), circle, 10.0, seed=7)
    wide = add_crossing_walkers(World(seed=1), circle, 10.0, seed=7, window=(4.0, 84.0))
    assert 2 <= len(own) <= 4 and len(wide) == 4 * len(own)  # 80 s against 20 s: four times as many
    assert all(14.0 <= c.t_enter <= 34.0 for c in own) and all(14.0 <= c.t_enter <= 94.0 for c in wide)
    assert max(c.t_enter for c in wide) > 34.0
    # The default window draws what it always drew (the seeds' scenes stay).
    again = add_crossing_walkers(World(seed=1), circle, 10.0, seed=7, window=CROSSING_WINDOW_S)
    assert [c.t_enter for c in again] == [c.t_enter for c in own]
    with pytest.raises(ValueError, match="crossing window"):
        add_crossing_walkers(World(seed=1), circle, 10.0, seed=7, window=(5.0, 5.0))

    crossing = next(s for s in range(1, 60) if scenario(s).world == "crossing")
    job = FlightJob(crossing, "ardupilot", crossing_window=(4.0, 84.0))
    assert job.spec().crossing_window == (4.0, 84.0)
    assert build_world(job.spec())[1] is not None
    assert job.key() == (crossing, "ardupilot", "cross:4-84")
    assert FlightJob(crossing, "ardupilot", crossing_window=(4.0, 24.0)).key() == (crossing, "ardupilot")
    assert row_key({**_row(3, "safe"), "crossing_window": [4.0, 24.0]}) == (3, "ardupilot")

    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append({**_row(1, "safe"), "crossing_window": [4.0, 24.0]})  # the world's own window
    flown: list[tuple[float, float] | None] = []

    def fake(j: FlightJob) -> dict[str, Any]:
        flown.append(j.crossing_window)
        return {**_row(j.seed, "safe"), "crossing_window": list(j.spec().crossing_window)}

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    jobs = [FlightJob(s, "ardupilot", crossing_window=(4.0, 84.0)) for s in (1, 2)]
    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0 and flown == [(4.0, 84.0)] * 2
    capsys.readouterr()
    flown.clear()
    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0 and flown == []  # resumed


@pytest.mark.parametrize("value", ["24-4", "5-5", "-1-10", "4", "a-b", "4-400", "nan-10"])
def test_a_bad_crossing_window_is_exit_2_before_anything_flies(value, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress",
                 f"--crossing-window={value}"]) == 2
    assert "--crossing-window: want FROM-TO seconds after the failsafe" in capsys.readouterr().err


def test_lockstep_clock_starts_are_fixed_recorded_and_keyed_apart(tmp_path, monkeypatch, capsys):
    # A lockstep flight's clock starts at a fixed second, not at the machine's uptime (a flight's
    # verdict can turn on how its times round); `--clock-start` flies every seed from each start
    # given, recorded in its row and keyed apart, so two starts of one code are a yardstick.
    from sim.flights.results import LOCKSTEP_CLOCK_START_S

    assert scenario(3).clock_start_s == LOCKSTEP_CLOCK_START_S == 1000.0
    lock = FlightJob(3, "ardupilot", lockstep=True)
    assert lock.spec().clock_start_s == 1000.0 and lock.key() == (3, "ardupilot", "lockstep")
    moved = FlightJob(3, "ardupilot", lockstep=True, clock_start=2000.5)
    assert moved.spec().clock_start_s == 2000.5 and moved.key() == (3, "ardupilot", "clock:2000.5", "lockstep")
    assert FlightJob(3, "ardupilot", lockstep=True, clock_start=1000.0).key() == lock.key()
    assert FlightJob(3, "ardupilot", lockstep=True, clock_start=1000.001).key()[2] == "clock:1000.001"
    # A lockstep row without the field started on the machine's uptime: never resumed from. A
    # real-time row has no clock part, whatever it says.
    assert row_key({**_row(3, "safe"), "lockstep": True}) == (3, "ardupilot", "clock:unknown", "lockstep")
    assert row_key({**_row(3, "safe"), "clock_start_s": 5.0}) == (3, "ardupilot")

    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append({**_row(1, "safe"), "lockstep": True})  # flown before the start was fixed
    flown: list[tuple[int, float]] = []

    def fake(j: FlightJob) -> dict[str, Any]:
        spec = j.spec()
        flown.append((j.seed, spec.clock_start_s))
        return {**_row(j.seed, "safe"), "lockstep": True, "clock_start_s": spec.clock_start_s}

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    from companion.cli import main

    args = ["sim-scenarios", "--seeds", "1-2", "--flavour", "ardupilot", "--workers", "1", "--no-progress",
            "--no-machine-check", "--json", "--lockstep", "--clock-start", "1000,2000", "--out", str(out)]
    assert main(args) == 0
    assert sorted(flown) == [(1, 1000.0), (1, 2000.0), (2, 1000.0), (2, 2000.0)]
    s = json.loads(capsys.readouterr().out)
    assert s["total"] == 4  # the old row of seed 1 is in the file but stood for neither start
    flown.clear()
    assert main(args) == 0 and flown == []  # resumed from both starts


def test_row_keys_keep_the_spelling_results_files_hold() -> None:
    # Each way a row is flown apart is one part of its key, spelt as files written since each
    # option came hold it: a changed spelling would fly their seeds again on resume.
    row = {**_row(7, "safe"), "settings": ["a=1", "b=2"], "land_speed": 0.5, "crossing_window": [4.0, 84.0],
           "watch_s": 30.0, "lockstep": True, "clock_start_s": 1000.0}
    assert row_key(row) == (7, "ardupilot", "set:a=1;b=2", "land:0.5", "cross:4-84", "watch:30", "lockstep")
    assert row_key({**row, "baseline": True})[2] == "baseline"


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "1e8", "abc", "1000,1000", "1000,"])
def test_a_bad_clock_start_is_exit_2_before_anything_flies(value, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--lockstep",
                 "--clock-start", value]) == 2
    assert "--clock-start" in capsys.readouterr().err


def test_a_clock_start_without_lockstep_is_exit_2(monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--clock-start", "2000"]) == 2
    assert "--clock-start needs --lockstep" in capsys.readouterr().err
    with pytest.raises(ValueError, match="clock_start_s"):
        FlightSpec(clock_start_s=0.0)


def test_a_row_says_which_software_flew_it() -> None:
    # The libraries that compute a flight and the commit of this checkout: what a comparison needs
    # to tell another version's rounding from a change (sim-compare names a difference).
    from importlib import metadata

    from sim.flights.results import SOFTWARE, software

    sw = software()
    assert sw["numpy"] == np.__version__ == metadata.version("numpy")
    assert set(SOFTWARE) <= set(sw) and sw["python"].count(".") == 2
    assert "git" not in sw or len(sw["git"].split("+")[0]) == 12


def test_a_camera_flies_both_cameras_as_one_and_is_keyed_apart(monkeypatch, capsys):
    # Issue 60: `--camera MODEL:HFOV` is the simulator's camera and the service's; a row says it
    # only when it is not the scenarios' own (pinhole:70), so the committed rows stay as they are.
    from sim.flights.spec import camera_name, parse_camera, service_settings

    assert parse_camera("fisheye:160") == ("fisheye", 160.0) and parse_camera("pinhole:110") == ("pinhole", 110.0)
    for bad in ("fisheye", "omni:120", "pinhole:0", "pinhole:180", "fisheye:nan", "fisheye:wide"):
        with pytest.raises(ValueError):
            parse_camera(bad)
    plain = FlightJob(3, "px4", lockstep=True)
    fish = FlightJob(3, "px4", lockstep=True, camera=("fisheye", 160.0))
    assert camera_name(plain.spec()) == "pinhole:70" and plain.key() == (3, "px4", "lockstep")
    assert fish.spec().camera_model == "fisheye" and fish.spec().hfov_deg == 160.0
    assert fish.key() == (3, "px4", "camera:fisheye:160", "lockstep")
    assert FlightJob(3, "px4", lockstep=True, camera=("pinhole", 70.0)).key() == plain.key()
    assert "camera.model=fisheye" in service_settings(fish.spec())
    assert not any(s.startswith("camera.model") for s in service_settings(plain.spec()))
    assert "camera" not in FlightResult(plain.spec(), "safe").as_dict()
    assert FlightResult(fish.spec(), "safe").as_dict()["camera"] == "fisheye:160"

    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--camera", "fish:160"]) == 2
    assert "--camera" in capsys.readouterr().err


def test_runners_cross_at_their_speed_drawn_apart_and_are_keyed_apart(monkeypatch, capsys):
    # Issue 60 item 5: a share of the crossing world's walkers run or cycle (2.4-3 m/s). Who does is
    # drawn from a stream of its own: with no runners the world is what it always was, and with
    # them every walker keeps its bearing, chord and time.
    from sim.world.crowd import RUNNER_SPEEDS, World, add_crossing_walkers
    from sim.world.walkers import Circle

    circle = Circle(10.0, -4.0, 6.0)
    fast_seen = 0
    for seed in range(1, 20):
        plain = add_crossing_walkers(World(), circle, 0.0, seed)
        assert add_crossing_walkers(World(), circle, 0.0, seed, runners=0.0) == plain
        everyone = add_crossing_walkers(World(), circle, 0.0, seed, runners=1.0)
        assert all(RUNNER_SPEEDS[0] <= w.speed <= RUNNER_SPEEDS[1] for w in everyone)
        assert [(w.bearing, w.offset_m, w.t_enter) for w in everyone] == \
               [(w.bearing, w.offset_m, w.t_enter) for w in plain]
        half = add_crossing_walkers(World(), circle, 0.0, seed, runners=0.5)
        fast_seen += sum(w.speed >= RUNNER_SPEEDS[0] for w in half)
        assert all(w.speed in (a.speed, b.speed) for w, a, b in zip(half, plain, everyone))
    assert fast_seen > 0
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match="runners"):
            add_crossing_walkers(World(), circle, 0.0, 1, runners=bad)

    plain_job = FlightJob(2, "px4", lockstep=True)
    run = FlightJob(2, "px4", lockstep=True, runners=0.3)
    assert run.spec().runners == 0.3 and plain_job.spec().runners == 0.0
    assert run.key() == (2, "px4", "runners:0.3", "lockstep") and plain_job.key() == (2, "px4", "lockstep")
    assert "runners" not in FlightResult(plain_job.spec(), "safe").as_dict()
    row = FlightResult(run.spec(), "safe").as_dict()
    assert row["runners"] == 0.3 and row_key({**row, "seed": 2, "clock_start_s": 1000.0}) == run.key()

    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress", "--runners", "1.5"]) == 2
    assert "--runners" in capsys.readouterr().err
