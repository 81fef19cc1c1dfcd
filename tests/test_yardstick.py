"""The defaults' rows kept in docs/yardstick/ (docs/scale.md, "The defaults' rows, kept"): each
file the README's table names is there, is what the table says it is (the defaults, in
lockstep from 1000 s, seeds 1-75 on one autopilot), and its unsafe landings, strikes and
handbacks are the table's figures, counted from the rows by the summary the command prints;
and ``sim-compare`` pairs it with itself with no verdict changed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sim.compare import compare
from sim.evidence import read_rows, summarise_rows

YARDSTICK = Path(__file__).resolve().parent.parent / "docs" / "yardstick"


def _table() -> list[dict[str, str]]:
    """The README table's rows: file, autopilot, unsafe, strikes, handbacks."""
    rows = []
    for line in (YARDSTICK / "README.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 7 and cells[0].startswith("`") and cells[0].endswith(".jsonl`"):
            rows.append(dict(zip(("file", "autopilot", "flown", "software", "unsafe", "strikes", "handbacks"), cells)))
    return rows


def test_the_readme_names_both_autopilots_files():
    assert {r["autopilot"] for r in _table()} == {"PX4", "ArduPilot"}


@pytest.mark.parametrize("entry", _table(), ids=lambda e: e["file"])
def test_each_file_is_the_defaults_from_1000_s_and_its_figures_are_the_tables(entry):
    rows, bad = read_rows(YARDSTICK / entry["file"].strip("`"))
    assert bad == 0 and sorted(r["seed"] for r in rows) == list(range(1, 76))
    flavour = {"PX4": "px4", "ArduPilot": "ardupilot"}[entry["autopilot"]]
    for r in rows:
        assert r["flavour"] == flavour and r["lockstep"] and r["clock_start_s"] == 1000.0
        assert r["settings"] == [] and not r["baseline"] and r["land_speed"] == 1.0
        assert r["watch_s"] == 4.0 and r["crossing_window"] == [4.0, 24.0]
        assert re.match(r"^[0-9a-f]{12}", r["software"]["git"])
    summary = summarise_rows(rows)
    assert (summary["unsafe"], summary["strikes"], summary["handbacks"]) == (
        int(entry["unsafe"]), int(entry["strikes"]), int(entry["handbacks"]))
    same = compare(rows, rows)
    assert same.pairs == 75 and same.changed == [] and same.lockstep
