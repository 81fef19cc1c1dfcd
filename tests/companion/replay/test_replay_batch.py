"""``companion replay`` over several inputs (a fleet's recordings): one folder per input, one
summary table, a bad input reported in its row without stopping the others, and the same results
in this process, in worker processes and on Ray."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import pytest

from companion import config, synthetic
from companion.cli import main
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.replay.batch import COLUMNS, expand_inputs, output_names
from companion.replay.summary import SummaryBuilder
from tests.companion.replay.test_replay import GSD, _darkness_model, _read_jsonl, _scenes

N = 5  # frames per input: tracks are confirmed after 3, so the last ones hold a target
# Shifts of the scene per input, so that the three inputs differ.
SHIFTS = {"north": 0.0, "south": 6.0}
COMPARED = ("kind", "status", "frames", "frames_skipped", "frames_with_target", "target_switches",
            "time_on_target_s", "settings")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Three inputs of N frames each under ``fleet/``: two folders of frames and a recording
    flown with its own settings (r0 1 m, the planner's age check off)."""
    root = tmp_path_factory.mktemp("fleet")
    scenes = _scenes()[:N]
    for name, shift in SHIFTS.items():
        folder = root / "fleet" / name
        folder.mkdir(parents=True)
        for k, s in enumerate(scenes):
            cv2.imwrite(str(folder / f"f{k:03d}.png"),
                        synthetic.render(synthetic.move(s, (shift, 0.0)), seed=k))
    from companion.recording import FlightRecorder

    key_file = root / "signing.key"
    key_file.write_text("ab" * 32 + "\n")
    flown = config.load(None, {"pipeline.r0_m": 1.0, "controller.min_track_age_s": 0.0,
                               "link.signing_key_file": str(key_file)})
    rec = FlightRecorder(root / "rec", intrinsics=Intrinsics.from_fov(640, 480, 70.0), mount=Mount(),
                         fps=10.0, meta={"config": flown.to_dict()})
    run_dir = rec.start()
    for k, s in enumerate(scenes):
        assert rec.add_frame(k, 100.0 + 0.1 * k, synthetic.render(s, seed=k),
                             Pose(100.0 + 0.1 * k, 10.0, -5.0, -25.0, 0.0, 0.0, 0.0))
    rec.close()
    recording = root / "fleet" / "flight"
    run_dir.rename(recording)
    return {"root": root, "fleet": root / "fleet", "north": root / "fleet" / "north",
            "south": root / "fleet" / "south", "flight": recording,
            "model": _darkness_model(root / "darkness.onnx")}


def _options(fleet: dict[str, Path]) -> list[str]:
    # --nadir for every input: the folders have no poses; the recording keeps its own settings.
    return ["--nadir", "--gsd", str(GSD), "--model", str(fleet["model"]), "--threads", "1",
            "--set", "controller.min_track_age_s=0", "--no-progress"]


def _replay(inputs: list[Path | str], out: Path, *extra: str) -> tuple[int, dict]:
    code = main(["replay", *map(str, inputs), "--out-dir", str(out), *extra])
    table = json.loads((out / "summary.json").read_text()) if (out / "summary.json").is_file() else {}
    return code, table


def _by_name(table: dict) -> dict[str, dict]:
    return {r["name"]: r for r in table["rows"]}


def _three(fleet: dict[str, Path]) -> list[Path]:
    return [fleet["north"], fleet["south"], fleet["flight"]]


@pytest.fixture(scope="module")
def sequential(fleet: dict[str, Path]) -> tuple[int, dict, Path]:
    out = fleet["root"] / "out1"
    code, table = _replay(_three(fleet), out, *_options(fleet), "--videos")
    return code, table, out


def test_three_inputs_give_three_folders_and_one_summary(sequential: tuple[int, dict, Path],
                                                         fleet: dict[str, Path]) -> None:
    code, table, out = sequential
    assert code == 0
    assert (table["inputs"], table["ok"], table["failed"], table["exit_status"]) == (3, 3, 0, 0)
    rows = table["rows"]
    assert [r["input"] for r in rows] == [str(p) for p in _three(fleet)]  # the order given
    assert [r["name"] for r in rows] == ["north", "south", "flight"]
    for r in rows:
        assert set(r) == set(COLUMNS)
        assert r["status"] == "ok" and r["error"] is None
        assert (r["frames"], r["frames_skipped"]) == (N, 0)
        assert 1 <= r["frames_with_target"] < N  # not on the first frames: tracks need 3 hits
        assert r["target_switches"] == 0
        # Evenly spaced at 10 fps, none skipped: frames with a target / fps.
        assert r["time_on_target_s"] == pytest.approx(r["frames_with_target"] / 10.0)
        folder = out / r["name"]
        recs = _read_jsonl(folder / "frames.jsonl")
        assert len(recs) == N
        assert sum(rec["target"] is not None for rec in recs) == r["frames_with_target"]
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["frames"] == N and summary["input"]["path"] == r["input"]
        assert summary["settings"] == r["settings"]
        assert (folder / "video.mp4").stat().st_size > 0
    kinds = {r["name"]: r["kind"] for r in rows}
    assert kinds == {"north": "frames", "south": "frames", "flight": "recording"}
    by = _by_name(table)
    # Per input, the settings rule of a single replay: the recording's own, the others the defaults.
    assert by["flight"]["settings"].startswith("the recording")
    assert by["north"]["settings"].startswith("the built-in defaults")
    assert all("controller.min_track_age_s=0" in r["settings"] for r in rows)
    with open(out / "summary.csv", newline="") as f:
        lines = list(csv.DictReader(f))
    assert [line["name"] for line in lines] == ["north", "south", "flight"]
    assert list(lines[0]) == list(COLUMNS)
    assert all(line["status"] == "ok" and line["error"] == "" for line in lines)
    assert [int(line["frames_with_target"]) for line in lines] == [r["frames_with_target"] for r in rows]


def test_the_table_is_printed(fleet: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code = main(["replay", str(fleet["north"]), str(fleet["south"]), "--out-dir", str(tmp_path),
                 *_options(fleet), "--max-frames", "2"])
    assert code == 0
    text = capsys.readouterr().out
    assert "input" in text and "on target s" in text and "2 input(s): 2 replayed, 0 failed" in text
    assert str(fleet["north"]) in text and "settings:" in text


def test_a_bad_input_is_an_error_row_and_the_others_complete(fleet: dict[str, Path], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    missing = tmp_path / "missing"
    code, table = _replay([fleet["north"], missing, empty, fleet["south"]], tmp_path / "out",
                          *_options(fleet))
    assert code == 1
    assert (table["ok"], table["failed"], table["exit_status"]) == (2, 2, 1)
    by = _by_name(table)
    assert by["north"]["status"] == by["south"]["status"] == "ok"
    assert by["north"]["frames"] == by["south"]["frames"] == N
    assert by["missing"]["status"] == "error" and "does not exist" in by["missing"]["error"]
    assert str(missing) in by["missing"]["error"] and by["missing"]["frames"] is None
    assert by["empty"]["status"] == "error" and "empty" in by["empty"]["error"]
    assert (tmp_path / "out" / "south" / "frames.jsonl").is_file()
    assert not (tmp_path / "out" / "missing" / "summary.json").exists()
    assert "does not exist" in capsys.readouterr().out  # the errors under the printed table


def test_no_input_replayed_exits_2(fleet: dict[str, Path], tmp_path: Path) -> None:
    code, table = _replay([tmp_path / "a", tmp_path / "b"], tmp_path / "out", *_options(fleet))
    assert code == 2 and (table["ok"], table["failed"], table["exit_status"]) == (0, 2, 2)


def test_an_input_with_no_processable_frame_is_an_error(fleet: dict[str, Path], tmp_path: Path) -> None:
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "a.png").write_bytes(b"garbage")
    code, table = _replay([fleet["north"], bad], tmp_path / "out", *_options(fleet), "--max-frames", "1")
    assert code == 1
    row = _by_name(table)["bad"]
    assert row["status"] == "error" and (row["frames"], row["frames_skipped"]) == (0, 1)
    assert "no frame" in row["error"]


def test_two_workers_give_the_same_results(sequential: tuple[int, dict, Path], fleet: dict[str, Path]) -> None:
    _, table1, out1 = sequential
    code, table2 = _replay(_three(fleet), fleet["root"] / "out2", *_options(fleet), "--workers", "2")
    assert code == 0
    rows1, rows2 = _by_name(table1), _by_name(table2)
    assert list(rows1) == list(rows2)
    for name in rows1:
        assert {k: rows1[name][k] for k in COMPARED} == {k: rows2[name][k] for k in COMPARED}
        targets = [[r["target"] for r in _read_jsonl(out / name / "frames.jsonl")]
                   for out in (out1, fleet["root"] / "out2")]
        assert targets[0] == targets[1]
    assert not (fleet["root"] / "out2" / "north" / "video.mp4").exists()  # no --videos


def test_a_pattern_is_expanded(fleet: dict[str, Path], tmp_path: Path) -> None:
    # Quoted, as the shell leaves it: expanded here, sorted.
    code, table = _replay([str(fleet["fleet"]) + "/*/", str(tmp_path / "none-*")], tmp_path / "out",
                          *_options(fleet), "--max-frames", "3")
    assert code == 1
    rows = table["rows"]
    assert [Path(r["input"]).name for r in rows[:3]] == ["flight", "north", "south"]
    assert all(r["status"] == "ok" and r["frames"] == 3 for r in rows[:3])
    assert rows[3]["status"] == "error" and "no input matches the pattern" in rows[3]["error"]


def test_expand_inputs_and_unique_folder_names(tmp_path: Path) -> None:
    for name in ("b", "a", "c.mp4"):
        (tmp_path / name).mkdir()
    got = expand_inputs([str(tmp_path / "[ab]"), str(tmp_path / "a"), str(tmp_path / "zz*")])
    assert [i.path for i in got] == [str(tmp_path / "a"), str(tmp_path / "b"), str(tmp_path / "zz*")]
    assert [i.problem is None for i in got] == [True, True, False]  # "a" twice: replayed once
    assert output_names(["x/rec", "y/rec", "z/clip.mp4", "r/q/w e"]) == ["x_rec", "y_rec", "clip_mp4", "w_e"]
    assert output_names(["/", "a/b", "a/b/"]) == ["input", "b", "b-2"]  # the same path: numbered


def test_time_on_target_is_the_held_frame_intervals() -> None:
    s = SummaryBuilder()
    for t, target in ((0.0, None), (0.1, 1), (0.2, 1), (0.5, None), (0.6, 2)):
        s.add_frame(t, {}, target)
    # Held 0.1 -> 0.2 -> 0.5 (a gap counts as held), then the last frame's median interval 0.1.
    assert s.build(1.0, 0, 0)["time_on_target_s"] == pytest.approx(0.1 + 0.3 + 0.1)
    one = SummaryBuilder()
    one.add_frame(0.0, {}, 1)
    assert one.build(1.0, 0, 0)["time_on_target_s"] == 0.0


@pytest.mark.parametrize("extra, message", [
    ([], "--out-dir"),
    (["--out-dir", "OUT", "--jsonl", "x.jsonl"], "--jsonl names one file"),
])
def test_several_inputs_need_an_out_dir_and_no_single_file_outputs(
        extra: list[str], message: str, fleet: dict[str, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture) -> None:
    extra = [str(tmp_path / "out") if a == "OUT" else a for a in extra]
    code = main(["replay", str(fleet["north"]), str(fleet["south"]), *_options(fleet), *extra])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("companion replay: error:") and message in err


def test_one_input_with_an_out_dir_gets_the_folder_layout(fleet: dict[str, Path], tmp_path: Path) -> None:
    code, table = _replay([fleet["north"]], tmp_path, *_options(fleet), "--max-frames", "2")
    assert code == 0 and table["rows"][0]["frames"] == 2
    assert len(_read_jsonl(tmp_path / "north" / "frames.jsonl")) == 2


def test_ray_gives_the_same_rows(sequential: tuple[int, dict, Path], fleet: dict[str, Path]) -> None:
    try:
        import ray  # noqa: F401
    except ImportError:
        pytest.skip("Ray is not installed (the optional extra: pip install '.[scale]')")
    _, table1, _ = sequential
    inputs = [fleet["north"], fleet["flight"]]
    code, table2 = _replay(inputs, fleet["root"] / "out-ray", *_options(fleet), "--ray", "auto")
    assert code == 0
    rows1, rows2 = _by_name(table1), _by_name(table2)
    assert list(rows2) == ["north", "flight"]
    for name in rows2:
        assert {k: rows1[name][k] for k in COMPARED} == {k: rows2[name][k] for k in COMPARED}
