"""``python -m sim.evidence.commits``: how each LAND of a results file was committed, read from the
kept yardstick rows (docs/yardstick/), whose figures docs/measurements.md (session 30) quotes."""

from __future__ import annotations

import json
from pathlib import Path

from sim.evidence.commits import commit_of, main, summarise
from sim.flights.results import read_rows

YARDSTICK = Path(__file__).resolve().parents[3] / "docs" / "yardstick"


def _summary(name: str) -> dict:
    rows, bad = read_rows(YARDSTICK / name)
    assert bad == 0
    return summarise(rows)


def test_the_fisheye_commits_at_its_commit_height_once_and_lands_after_the_hold_otherwise():
    s = _summary("px4-fisheye160-1000.jsonl")
    assert s["flights"] == 75 and s["no_land"] == 1
    assert s["paths"] == {"commit safe": 1, "held_out handback": 3, "held_out safe": 69, "held_out unsafe": 1}
    # The free ground round the vehicle was far short of r0 plus a walker's reach when the holds began.
    assert s["held"] == 74 and s["held_free_m"]["median"] == 4.7 and s["held_needed_m"] == 11.8
    assert s["held_free_m"]["max"] < s["held_needed_m"]


def test_a_narrow_camera_lands_where_it_planned_without_a_hold():
    s = _summary("px4-defaults-1000.jsonl")
    assert s["paths"] == {"commit safe": 57, "commit unsafe": 3} and s["held"] == 0 and s["held_free_m"] is None


def test_one_row_read_from_its_texts():
    row = {"seed": 35, "world": "free_area", "outcome": "unsafe", "messages": [
        "SLZ: zone 24 judged at 10.1 m (calm 6.0 s): descending over it to 8.9 m before the LAND",
        "SLZ: zone 24: free around the vehicle 5.3 m, not r0 plus the 9.8 m a walker covers before touchdown "
        "(11.8 m): holding the LAND",
        "SLZ: LAND over zone 24 at 4.5 m, radius 3.3 m",
        "SLZ: landed in zone 24"]}
    c = commit_of(row)
    assert c is not None and (c.path, c.zone, c.land_m, c.planned_m, c.free_m, c.needed_m) == (
        "held_out", 24, 4.5, 8.9, 5.3, 11.8)
    # Another zone's hold is not this LAND's; no LAND at all is none.
    other = dict(row, messages=[m.replace("zone 24:", "zone 7:") if "holding" in m else m for m in row["messages"]])
    assert commit_of(other).path == "below"  # type: ignore[union-attr]
    assert commit_of({"seed": 1, "messages": ["SLZ: handing back"]}) is None


def test_the_command_prints_each_file_and_refuses_a_missing_one(tmp_path: Path, capsys) -> None:
    assert main([str(YARDSTICK / "ardupilot-fisheye160-1000.jsonl"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["paths"]["held_out unsafe"] == 2 and len(out["landings"]) == 75 - out["no_land"]
    assert main([str(tmp_path / "none.jsonl")]) == 2
    assert "no such results file" in capsys.readouterr().err
