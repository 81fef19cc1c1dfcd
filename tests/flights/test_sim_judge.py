"""The simulator's verdicts rest on its truth and the controller's recorded events, not on logs.

The flight of ``test_sitl.py::test_uniform_free_ground_lands_under_the_companion_within_the_budget``
(ArduPilot), whose verdict there is "safe", is flown with every log message of the service
reworded (a ``sitecustomize`` module rewrites ``LogRecord.getMessage`` in the service process).
The verdict must still be "safe", with every phase of the landing; the reworded log must really
hold none of the original wording, so a judge matching log lines (as this one once did) would have
seen no phase at all and called the flight a handback.

A baseline flight (no companion, the autopilot's own failsafe alone) is judged on the same truth.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
from pathlib import Path

import pytest

from companion.pipeline.slz import SLZPipeline
from companion.recording import RecordingReader
from sim.flights.flight import FlightSpec, fly
from tests.patched_service import patched_env

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(300)]

REWORD = '''\
import logging

_original = logging.LogRecord.getMessage


def _reworded(self):
    # Every word reversed and upper-cased: the meaning is gone for any pattern matcher.
    return "REWORDED " + " ".join(w[::-1].upper() for w in _original(self).split())


logging.LogRecord.getMessage = _reworded
'''


def test_verdicts_do_not_depend_on_the_wording_of_the_log(tmp_path: Path, model_path) -> None:
    spec = FlightSpec(flavour="ardupilot", world="uniform", seed=6, altitude_m=18.0,
                      record_dir=tmp_path / "rec", service_log=tmp_path / "service.log",
                      service_env=patched_env(tmp_path / "site", REWORD))
    r = asyncio.run(fly(spec))

    log = spec.service_log.read_text()  # type: ignore[union-attr]
    assert "REWORDED" in log and "landing controller:" not in log and "SLZ:" not in log
    assert r.service_exit == 0, r.log_tail
    assert r.outcome == "safe" and not r.handed_back, (r.phases, r.log_tail)
    assert r.phases[:2] == ["SELECT", "APPROACH"] and r.phases[-2:] == ["LAND", "LANDED"], r.phases
    # The phases are the recorded events'; their STATUSTEXT wording is the controller's own.
    runs = sorted(p.parent for p in (tmp_path / "rec").glob("*/meta.json"))
    recorded = list(RecordingReader(runs[-1]).events("controller"))
    assert [e["phase"] for e in recorded if e["old"] != e["phase"]] == r.phases
    assert {e["event"] for e in recorded} >= {"phase", "target"}
    assert all(m.startswith("SLZ: ") for m in r.messages) and r.messages

    # The same recorded flight, replayed with the settings it flew with: each frame's target in
    # the replay's JSONL is the planner's choice among that frame's tracks (one rule, one decider).
    _replay_target_is_the_planners_choice(runs[-1], tmp_path / "replay.jsonl")


def _replay_target_is_the_planners_choice(run: Path, jsonl_path: Path) -> None:
    from companion import config
    from companion.control.planner import ZonePlanner
    from companion.pipeline.density import DensityModel
    from companion.replay.runner import ReplayOutputs, replay
    from companion.replay.sources import open_input

    source = open_input(run)
    flown = config.from_recording(source.meta["config"])
    model = DensityModel(flown.model.path, threads=2)
    pipe = SLZPipeline(model, config.pipeline_config(flown, model.spec), intrinsics=source.intrinsics,
                       mount=source.mount)
    planner = ZonePlanner(config.planner_config(flown))
    chosen: dict[int, int | None] = {}

    def check(frame, result) -> None:
        target = planner.choose(result.tracks, result.t)
        chosen[frame.index] = None if target is None else target.id

    with open(jsonl_path, "w") as fh:
        summary = replay(source, pipe, ReplayOutputs(jsonl=fh), use_pose=True, on_result=check,
                         planner=ZonePlanner(config.planner_config(flown)))
    records = [json.loads(line) for line in jsonl_path.read_text().splitlines()]
    assert len(records) == summary["frames"] == len(chosen) > 50
    assert {rec["frame"]: rec["target"] for rec in records} == chosen
    assert summary["frames_with_target"] > 0  # over free ground the planner picks zones


@pytest.mark.timeout(90)
def test_the_baseline_lands_where_the_autopilot_is_and_is_judged_the_same_way(tmp_path: Path) -> None:
    # `companion sim-scenarios --baseline`: a free-area seed (ArduPilot) flown with the
    # autopilot's own failsafe alone. No service starts; the same failsafe comes watch_s after the
    # start and ArduPilot's LAND brings the vehicle down where it hovered; the touchdown is judged
    # on the simulator's truth exactly as a companion flight's.
    from sim.flights.flight import build_world
    from sim.flights.scenarios import FlightJob

    job = FlightJob(6, "ardupilot", baseline=True)
    spec = job.spec()
    assert spec.world == "free_area" and not spec.companion
    spec = dataclasses.replace(spec, record_dir=tmp_path / "rec", service_log=tmp_path / "service.log")
    r = asyncio.run(fly(spec))

    assert r.service_exit is None and not (tmp_path / "rec").exists()  # no companion started
    assert r.events == [] and r.phases == [] and r.processed_fps is None and not r.starved
    assert r.touchdown is not None and r.time_to_touchdown_s is not None and r.time_to_touchdown_s < 40
    assert r.outcome == "handback"  # the companion never took control: the autopilot landed
    start = build_world(spec)[2]
    assert math.dist(r.touchdown, start) < 3.0, (r.touchdown, start)  # where it was at the failsafe
    assert r.clearance_m is not None and 0.0 <= r.clearance_m < 60.0
    assert r.struck == (r.clearance_m < spec.r0_m)
    row = r.as_dict()
    assert row["baseline"] is True and row["strike"] == r.struck and row["clearance_m"] is not None
    assert r.max_climb_m is not None and r.max_climb_m < 0.5
