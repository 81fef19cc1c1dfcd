"""A lockstep flight over the photo world (issue 59) flies the same flight every time."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim.flights.scenarios import FlightJob, run_jobs


@pytest.mark.sitl
@pytest.mark.timeout(900)
def test_a_photo_world_seed_flies_the_same_row_twice_in_lockstep(tmp_path: Path, shared_dir: Path, model_path,
                                                                 capsys) -> None:
    photos = shared_dir / "data" / "semantic_drone" / "full"
    if not (photos / "images").is_dir():
        pytest.skip(f"needs the held-out full-size photos at {photos}")
    job = FlightJob(3, "px4", lockstep=True, ground="photo", photos=str(photos.resolve()))
    rows = []
    for name in ("one", "two"):
        out = tmp_path / f"{name}.jsonl"
        run_jobs([job], workers=1, out=out, as_json=True)
        capsys.readouterr()
        (row,) = [json.loads(line) for line in out.read_text().splitlines()]
        rows.append(row)
    host = ("wall_s", "cpu_s", "host", "software", "frame_ms_p95", "processed_fps")
    a, b = ({k: v for k, v in r.items() if k not in host} for r in rows)
    assert a == b
    assert a["ground"] == "photo" and a["lockstep"] and a["touchdown"] is not None
    assert a["touchdown_surfaces"] and isinstance(a["unlandable_touchdown"], bool)
