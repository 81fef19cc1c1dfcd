"""The defaults' rows kept in docs/yardstick/ (docs/scale.md, "The defaults' rows, kept"): each
file the README's tables name is there, is what the table says it is (the defaults in lockstep
from the table's clock start, seeds 1-75 on one autopilot; or the baseline's flights, the
autopilot's own failsafe alone), and its unsafe landings, strikes and handbacks (the baseline's
strikes) are the table's figures, counted from the rows by the summary the command prints; and
``sim-compare`` pairs each companion file with itself with no verdict changed (it pairs the
companion's flights; a baseline's are its own)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sim.evidence.compare import compare
from sim.flights.results import read_rows, summarise_baseline, summarise_rows

YARDSTICK = Path(__file__).resolve().parents[3] / "docs" / "yardstick"


COMPANION = ("file", "autopilot", "clock start", "flown", "software", "unsafe", "strikes", "handbacks")
BASELINE = ("file", "autopilot", "clock start", "flown", "software", "strikes")


#: The README's autopilot column, as rows spell the flavour.
FLAVOURS = {"PX4": "px4", "ArduPilot": "ardupilot"}


def _camera(entry: dict[str, str]) -> str | None:
    """The ``camera`` a row of the entry's file says: None for the scenarios' own ("default", or a
    baseline's), else the ``--camera`` the table names."""
    cell = entry["camera"]
    return None if cell in ("baseline", "default") else cell.strip("`").removeprefix("--camera ")


def _table(columns: tuple[str, ...]) -> list[dict[str, str]]:
    """The rows of the README's tables headed by these columns (the companion's, the baseline's,
    ...): a file's row belongs to the table whose header line came last above it."""
    rows, mine = [], False
    for line in (YARDSTICK / "README.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] == "file":
            # A header cell may say more than the column's name ("software (each row's ...)").
            mine = len(cells) == len(columns) and all(c.startswith(name) for c, name in zip(cells, columns))
        elif mine and len(cells) == len(columns) and cells[0].startswith("`") and cells[0].endswith(".jsonl`"):
            rows.append(dict(zip(columns, cells)))
    return rows


def _rows(entry: dict[str, str], baseline: bool) -> list[dict]:
    """The file's rows, checked to be what the table says: seeds 1-75, one autopilot, the
    defaults in lockstep from the table's clock start; the baseline's flights or the companion's."""
    rows, bad = read_rows(YARDSTICK / entry["file"].strip("`"))
    assert bad == 0 and sorted(r["seed"] for r in rows) == list(range(1, 76))
    flavour = FLAVOURS[entry["autopilot"]]
    start = float(entry["clock start"].removesuffix(" s"))
    for r in rows:
        assert r["flavour"] == flavour and r["lockstep"] and r["clock_start_s"] == start
        assert r["settings"] == [] and r["baseline"] is baseline and r["land_speed"] == 1.0
        assert r["watch_s"] == 4.0 and r["crossing_window"] == [4.0, 24.0]
        assert re.match(r"^[0-9a-f]{12}", r["software"]["git"])
    if not baseline:  # sim-compare pairs the companion's flights; a baseline's are its own
        same = compare(rows, rows)
        assert same.pairs == 75 and same.changed == [] and same.lockstep
    return rows


def test_the_readme_names_both_autopilots_files_from_both_clock_starts_and_their_baselines():
    assert {(r["autopilot"], r["clock start"]) for r in _table(COMPANION)} == {
        (a, s) for a in ("PX4", "ArduPilot") for s in ("1000 s", "2000 s")}
    assert {r["autopilot"] for r in _table(BASELINE)} == {"PX4", "ArduPilot"}


@pytest.mark.parametrize("entry", _table(COMPANION), ids=lambda e: e["file"])
def test_each_file_is_the_defaults_and_its_figures_are_the_tables(entry):
    summary = summarise_rows(_rows(entry, baseline=False))
    assert (summary["unsafe"], summary["strikes"], summary["handbacks"]) == (
        int(entry["unsafe"]), int(entry["strikes"]), int(entry["handbacks"]))


@pytest.mark.parametrize("entry", _table(BASELINE), ids=lambda e: e["file"])
def test_each_baseline_file_is_the_autopilots_failsafe_alone_and_its_strikes_are_the_tables(entry):
    assert summarise_baseline(_rows(entry, baseline=True))["strikes"] == int(entry["strikes"])


CAMERA = ("file", "autopilot", "camera", "flown", "software", "unsafe", "strikes (outside dense worlds)",
          "handbacks", "clear landings of 66 with free ground")


@pytest.mark.parametrize("entry", _table(CAMERA), ids=lambda e: e["file"])
def test_each_other_camera_file_is_that_camera_and_its_figures_are_the_tables(entry):
    # The wide lenses' rows (issue 60): the defaults but the camera, seeds 1-75 from 1000 s.
    rows, bad = read_rows(YARDSTICK / entry["file"].strip("`"))
    assert bad == 0 and sorted(r["seed"] for r in rows) == list(range(1, 76))
    camera = _camera(entry)
    flavour = FLAVOURS[entry["autopilot"]]
    for r in rows:
        assert r["camera"] == camera and r["flavour"] == flavour and r["lockstep"]
        assert r["clock_start_s"] == 1000.0 and r["settings"] == [] and not r["baseline"]
        assert r["land_speed"] == 1.0 and r["watch_s"] == 4.0 and r["crossing_window"] == [4.0, 24.0]
    summary = summarise_rows(rows)
    m = re.fullmatch(r"(\d+) \((\d+)\)", entry["strikes (outside dense worlds)"])
    assert m is not None
    strikes, outside = m.groups()
    assert (summary["unsafe"], summary["strikes"], summary["handbacks"]) == (
        int(entry["unsafe"]), int(strikes), int(entry["handbacks"]))
    assert sum(bool(r["strike"]) and r["world"] != "dense" for r in rows) == int(outside)
    free = [r for r in rows if r["world"] != "dense"]
    assert len(free) == 66
    assert sum(r["outcome"] == "safe" for r in free) == int(entry["clear landings of 66 with free ground"])


def test_the_readme_names_the_wide_lenses_files():
    assert [(r["autopilot"], r["camera"]) for r in _table(CAMERA)] == [
        ("PX4", "`--camera fisheye:160`"), ("PX4", "`--camera pinhole:110`"), ("ArduPilot", "`--camera fisheye:160`"),
        ("ArduPilot", "`--camera pinhole:110`")]


SECOND_HALF = ("file", "autopilot", "camera", "seeds", "flown", "software", "unsafe",
               "strikes (outside dense worlds)", "handbacks", "clear landings (worlds with free ground)")


@pytest.mark.parametrize("entry", _table(SECOND_HALF), ids=lambda e: e["file"])
def test_each_second_half_file_is_its_seeds_and_camera_and_its_figures_are_the_tables(entry):
    # Issue 60 asks for seeds 1-150: seeds 76-150 from 1000 s in lockstep, kept apart from the
    # 1-75 yardstick files (which the tables above hold to seeds 1-75); a baseline row is the
    # autopilot's own failsafe alone on the same seeds ("-" where a figure is the companion's).
    rows, bad = read_rows(YARDSTICK / entry["file"].strip("`"))
    first, last = (int(s) for s in entry["seeds"].split("-"))
    assert bad == 0 and sorted(r["seed"] for r in rows) == list(range(first, last + 1))
    flavour = FLAVOURS[entry["autopilot"]]
    baseline = entry["camera"] == "baseline"
    camera = _camera(entry)
    for r in rows:
        assert r["flavour"] == flavour and r["lockstep"] and r["clock_start_s"] == 1000.0
        assert r["settings"] == [] and r["baseline"] is baseline and r.get("camera") == camera
        assert r["land_speed"] == 1.0 and r["watch_s"] == 4.0 and r["crossing_window"] == [4.0, 24.0]
        assert r["software"]["git"].startswith(entry["software"])
    m = re.fullmatch(r"(\d+) \((\d+)\)", entry["strikes (outside dense worlds)"])
    assert m is not None
    strikes, outside = (int(g) for g in m.groups())
    assert sum(bool(r["strike"]) for r in rows) == strikes
    assert sum(bool(r["strike"]) and r["world"] != "dense" for r in rows) == outside
    if baseline:
        assert summarise_baseline(rows)["strikes"] == strikes
        assert (entry["unsafe"], entry["handbacks"], entry["clear landings (worlds with free ground)"]) == ("-", "-", "-")
        return
    summary = summarise_rows(rows)
    assert (summary["unsafe"], summary["strikes"], summary["handbacks"]) == (
        int(entry["unsafe"]), strikes, int(entry["handbacks"]))
    free = [r for r in rows if r["world"] != "dense"]
    clear, of = (int(s) for s in entry["clear landings (worlds with free ground)"].split(" of "))
    assert (sum(r["outcome"] == "safe" for r in free), len(free)) == (clear, of)


def test_the_readme_names_the_second_halfs_files():
    assert [(r["autopilot"], r["camera"], r["seeds"]) for r in _table(SECOND_HALF)][:4] == [
        ("PX4", "default", "76-150"), ("PX4", "baseline", "76-150"), ("PX4", "`--camera fisheye:160`", "76-150"),
        ("PX4", "`--camera pinhole:110`", "76-150")]
    assert [(r["autopilot"], r["camera"]) for r in _table(SECOND_HALF)][4:] == [
        ("ArduPilot", "default"), ("ArduPilot", "baseline"), ("ArduPilot", "`--camera fisheye:160`"),
        ("ArduPilot", "`--camera pinhole:110`")]


#: 12 columns: ``_table`` tells the tables apart by their number of columns.
RUNNERS = ("file", "autopilot", "camera", "runners", "seeds", "flown", "software", "unsafe", "strikes", "handbacks",
           "clear landings", "baseline strikes")


def _crossing_seeds(flavour: str) -> list[int]:
    """The crossing worlds among seeds 1-150: the kept defaults' rows say which seeds they are."""
    rows = read_rows(YARDSTICK / f"{flavour}-defaults-1000.jsonl")[0] + \
        read_rows(YARDSTICK / f"{flavour}-defaults-1000-76-150.jsonl")[0]
    return sorted(r["seed"] for r in rows if r["world"] == "crossing")


@pytest.mark.parametrize("entry", _table(RUNNERS), ids=lambda e: e["file"])
def test_each_runners_file_is_the_crossing_worlds_with_runners_and_its_figures_are_the_tables(entry):
    # Issue 60 item 5: the crossing worlds of seeds 1-150 flown again with a share of runners and
    # cyclists (`--runners`), the companion and (in the defaults' file) the autopilot alone.
    rows, bad = read_rows(YARDSTICK / entry["file"].strip("`"))
    flavour = FLAVOURS[entry["autopilot"]]
    camera = _camera(entry)
    crossing = _crossing_seeds(flavour)
    assert bad == 0 and len(crossing) == 43 and entry["seeds"] == "the 43 crossing worlds of 1-150"
    for r in rows:
        assert r["flavour"] == flavour and r["lockstep"] and r["clock_start_s"] == 1000.0
        assert r["world"] == "crossing" and r["runners"] == float(entry["runners"])
        assert r["settings"] == [] and r.get("camera") == camera
        assert r["software"]["git"].startswith(entry["software"])
    companion = [r for r in rows if not r["baseline"]]
    baseline = [r for r in rows if r["baseline"]]
    assert sorted(r["seed"] for r in companion) == crossing
    assert sum(r["outcome"] == "unsafe" for r in companion) == int(entry["unsafe"])
    assert sum(bool(r["strike"]) for r in companion) == int(entry["strikes"])
    assert sum(r["outcome"] == "safe" for r in companion) == int(entry["clear landings"])
    assert sum(r["outcome"] == "handback" for r in companion) == int(entry["handbacks"])
    if entry["baseline strikes"] == "-":
        assert baseline == []
    else:
        assert sorted(r["seed"] for r in baseline) == crossing
        assert summarise_baseline(baseline)["strikes"] == int(entry["baseline strikes"])


def test_the_readme_names_the_runners_files():
    assert [(r["autopilot"], r["camera"]) for r in _table(RUNNERS)] == [
        ("PX4", "default"), ("PX4", "`--camera fisheye:160`"), ("ArduPilot", "default"),
        ("ArduPilot", "`--camera fisheye:160`")]


SHRUNK = ("file", "autopilot", "ground", "settings", "seeds", "flown", "software", "unsafe",
          "strikes (outside dense worlds)", "handbacks", "clear landings (worlds with free ground)",
          "the autopilot alone's strikes")


def _check_photo_entry(entry: dict[str, str], unlandable: int | None) -> None:
    """A file of the photo-world tables is what its row says: seeds, autopilot, ground and
    settings (each in backticks, or ``-`` for none), lockstep from 1000 s, the summary's figures,
    clear landings of the worlds with free ground, the autopilot alone's strikes when the file
    holds its rows, and ``unlandable`` companion touchdowns on unlandable ground by the class maps
    (None: the table has no such column, and its photo rows hold none)."""
    rows, bad = read_rows(YARDSTICK / entry["file"].strip("`"))
    first, last = (int(s) for s in entry["seeds"].split("-"))
    flavour = FLAVOURS[entry["autopilot"]]
    ground = None if entry["ground"] == "drawn" else "photo"
    settings = re.findall(r"`([^`]*)`", entry["settings"])
    assert settings or entry["settings"] == "-"
    companion = [r for r in rows if not r["baseline"]]
    baseline = [r for r in rows if r["baseline"]]
    assert bad == 0 and sorted(r["seed"] for r in companion) == list(range(first, last + 1))
    assert sorted(r["seed"] for r in baseline) in ([], list(range(first, last + 1)))
    for r in rows:
        assert r["flavour"] == flavour and r["lockstep"] and r["clock_start_s"] == 1000.0
        assert r.get("ground") == ground and r.get("camera") is None
        assert r["settings"] == ([] if r["baseline"] else settings)
        assert r["software"]["git"].startswith(entry["software"])
    m = re.fullmatch(r"(\d+) \((\d+)\)", entry["strikes (outside dense worlds)"])
    assert m is not None
    strikes, outside = (int(g) for g in m.groups())
    summary = summarise_rows(companion)
    assert (summary["unsafe"], summary["strikes"], summary["handbacks"]) == (
        int(entry["unsafe"]), strikes, int(entry["handbacks"]))
    assert sum(bool(r["strike"]) and r["world"] != "dense" for r in companion) == outside
    free = [r for r in companion if r["world"] != "dense"]
    clear = re.fullmatch(r"(\d+) of (\d+)", entry["clear landings (worlds with free ground)"])
    assert clear is not None and len(free) == int(clear.group(2))
    assert sum(r["outcome"] == "safe" for r in free) == int(clear.group(1))
    alone = entry["the autopilot alone's strikes"]
    assert (alone == "-") == (not baseline)
    if baseline:
        assert summarise_baseline(baseline)["strikes"] == int(alone)
    # Companion touchdowns on unlandable ground by the class maps (issue 59's first target: none).
    landed_unlandable = sum(bool(r["unlandable_touchdown"]) for r in companion if r["outcome"] in ("safe", "unsafe"))
    if ground == "photo":
        assert landed_unlandable == (0 if unlandable is None else unlandable)


@pytest.mark.parametrize("entry", _table(SHRUNK), ids=lambda e: e["file"])
def test_each_photo_world_and_shrunk_frame_file_is_what_the_table_says(entry):
    # Issue 59: the photo world's rows, and the frame shrunk before the density model
    # (pipeline.person_px) on both grounds, in lockstep from 1000 s; a file flown with
    # --baseline holds the autopilot alone's rows of the same seeds too.
    _check_photo_entry(entry, None)


#: Session 33's photo files: 13 columns, the last the companion's touchdowns on unlandable ground.
PHOTO = (*SHRUNK, "companion touchdowns on unlandable ground")


@pytest.mark.parametrize("entry", _table(PHOTO), ids=lambda e: e["file"])
def test_each_photo_yardstick_file_is_what_the_table_says(entry):
    # Issue 59's photo yardstick beyond seeds 1-12, and the landability settings flown on it.
    _check_photo_entry(entry, int(entry["companion touchdowns on unlandable ground"]))


def test_the_readme_names_the_photo_world_and_shrunk_frame_files():
    entries = _table(SHRUNK)
    assert {(e["autopilot"], e["ground"]) for e in entries} == {
        (a, g) for a in ("PX4", "ArduPilot") for g in ("drawn", "photo")}
