"""Evaluation: the curve's level map agrees with the pipeline's occupancy step; figures on real data."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.evaluation import datasets as D
from companion.evaluation.metrics import CURVE_THRESHOLDS, best_threshold, evaluate_set, level_map, tally_occupancy
from companion.pipeline.density import DensityModel
from companion.pipeline.occupancy import FREE, OccupancyParams, occupancy_map
from tests import early

CARD = Path(__file__).resolve().parents[3] / "companion" / "models" / "MODEL_CARD.md"


@pytest.mark.parametrize("shape,image_hw", [((30, 40), (120, 160)), ((125, 188), (500, 750)), ((9, 9), (9, 9))])
def test_level_map_matches_occupancy_map_at_every_threshold(shape, image_hw) -> None:
    rng = np.random.default_rng(1)
    d = (rng.random(shape) ** 6).astype(np.float32)
    d[0, 0] = np.nan  # a broken value must stay occupied at every threshold
    lv = level_map(d, image_hw)
    for t in (0.0, 1e-3, 0.05, 0.3, 0.9):
        occ = occupancy_map(d, image_hw, OccupancyParams(t)) != FREE
        np.testing.assert_array_equal(occ, lv > t)


def test_the_speck_rule_is_measured_where_the_pipeline_applies_it() -> None:
    """``evaluate_set(params=OccupancyParams(min_mass=...))`` (``companion eval --min-people``):
    a head covered only by a speck of the map is lost, and the speck's ground becomes free."""
    d = np.zeros((30, 40), np.float32)
    d[5:8, 5:8] = 0.5                      # a person's patch: sum 4.5
    d[20, 30] = 0.02                       # a faint response over a second head
    sample = D.Sample("s", Path("x"), np.array([[26.0, 26.0], [122.0, 82.0]], np.float32),
                      pixels=np.zeros((120, 160, 3), np.uint8))
    paper = evaluate_set("s", [sample], lambda img: d, 0.01)
    specks = evaluate_set("s", [sample], lambda img: d, 0.01, params=OccupancyParams(min_mass=0.1))
    assert (paper.recall, specks.recall) == (1.0, 0.5)
    assert specks.free > paper.free


def test_tally_counts_heads_on_occupied_pixels() -> None:
    occ = np.full((10, 10), FREE, np.uint8)
    occ[2:4, 2:4] = 0
    t = tally_occupancy(occ, np.array([[2.5, 3.9], [8.0, 8.0], [-5.0, 2.0]]))  # one in, one out, one clipped
    assert (t.heads, t.covered, t.pixels, t.free) == (3, 1, 100, 96)


def test_best_threshold_is_the_largest_meeting_recall_on_every_set() -> None:
    from companion.evaluation.metrics import SetResult

    def res(recalls):
        return SetResult("x", 1, 0, 0, 0, 1, [{"threshold": t, "recall": r, "free": 0.0} for t, r in zip([0, 1, 2], recalls)])

    assert best_threshold([res([1, 0.995, 0.98]), res([1, 0.999, 0.999])], 0.99) == 1
    assert best_threshold([res([0.5, 0.4, 0.3])], 0.99) is None


def test_best_threshold_takes_one_minimum_per_set() -> None:
    """The drone calibration rule: each set held to its own recall (Mall, street-level, to less)."""
    from companion.evaluation.metrics import SetResult

    def res(name, recalls):
        return SetResult(name, 1, 0, 0, 0, 1,
                         [{"threshold": t, "recall": r, "free": 0.0} for t, r in zip([0, 1, 2], recalls)])

    sets = [res("drone", [1, 0.996, 0.99]), res("mall", [1, 0.991, 0.985])]
    assert best_threshold(sets, {"drone": 0.995, "mall": 0.99}) == 1
    assert best_threshold(sets, {"drone": 0.995, "mall": 0.995}) == 0  # Mall held to 99.5 % would limit it
    with pytest.raises(KeyError):
        best_threshold(sets, {"drone": 0.995})  # every set must be named


def test_calibration_rules_and_their_bad_values(capsys) -> None:
    from companion.training.calibrate import RULES, main, rule_minimums

    assert rule_minimums("drone") == {"dronecrowd6": 0.995, "semantic_drone_val": 0.995, "synthetic_val": 0.995,
                                      "mall": 0.99}
    assert rule_minimums("v1") == {"dronecrowd6": 0.992, "semantic_drone_val": 0.992, "mall": 0.992}
    assert set(rule_minimums("v1", 0.99).values()) == {0.99}
    assert sorted(RULES) == ["drone", "v1"]
    for argv, says in ((["--rule", "drone", "--min-recall", "0.99"], "v1 rule only"),
                       (["--rule", "v1", "--min-recall", "1.5"], "(0, 1]")):
        assert main(["--model", "nowhere.onnx", *argv]) == 2
        assert says in capsys.readouterr().err


def test_loaders_read_the_documented_formats(shared_dir: Path) -> None:
    assert len(D.shanghaitech_b(shared_dir, "test")) == 100
    assert len(D.mall(shared_dir, 100)) == 12
    dc = {s.name: s for s in D.dronecrowd_frames(shared_dir)}
    assert len(dc) == 6 and len(dc["img017012"].points) == 153
    val, train = D.semantic_drone(shared_dir, "val"), D.semantic_drone(shared_dir, "train")
    assert (len(val), len(train)) == (80, 320)
    assert not {s.name for s in val} & {s.name for s in train}
    s = next(x for x in val if x.boxes is not None and len(x.boxes))
    assert s.boxes[0, 0] <= s.points[0, 0] <= s.boxes[0, 2]


def test_evaluate_on_a_small_real_slice(model_path: Path, shared_dir: Path) -> None:
    model = DensityModel(model_path)
    samples = D.semantic_drone(shared_dir, "val")[:4] + D.mall(shared_dir, 400)
    r = evaluate_set("slice", samples, model, model.spec.occupancy_threshold, model.count)
    assert r.images == 7 and r.heads == sum(len(s.points) for s in samples)
    assert 0.8 <= r.recall <= 1.0 and 0.05 < r.free < 0.95
    rec = [c["recall"] for c in r.curve]
    free = [c["free"] for c in r.curve]
    assert all(a >= b for a, b in zip(rec, rec[1:])) and all(a <= b for a, b in zip(free, free[1:]))
    assert len(r.curve) == len(CURVE_THRESHOLDS)
    assert r.mae is not None and 0 <= r.mae < 40


def test_eval_cli_rejects_bad_input(tmp_path: Path, capsys) -> None:
    from companion.cli import main

    assert main(["eval", "--model", str(tmp_path / "missing.onnx"), "--shared", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["eval", "--sets", "shb,moon", "--shared", str(tmp_path)]) == 2
    assert "unknown set" in capsys.readouterr().err
    assert main(["eval", "--min-people", "-0.1", "--shared", str(tmp_path)]) == 2
    assert "--min-people" in capsys.readouterr().err


def test_eval_cli_reports_missing_data(model_path: Path, tmp_path: Path, capsys) -> None:
    from companion.cli import main

    assert main(["eval", "--model", str(model_path), "--shared", str(tmp_path), "--sets", "mall"]) == 2
    assert "missing" in capsys.readouterr().err


# --- recall by person size (issue 13) --------------------------------------------------------


def test_size_recall_bins_and_the_smallest_trusted_size() -> None:
    from companion.evaluation.metrics import min_person_px, size_recall

    rng = np.random.default_rng(0)
    sizes = rng.uniform(5, 60, 2000)
    covered = sizes >= 12  # a model that sees everyone from 12 px and nobody below
    bins = {(b["lo"], b["hi"]): b for b in size_recall(sizes, covered)}
    assert bins[(5.0, 8.0)]["recall"] == 0.0 and bins[(12.0, 16.0)]["recall"] == 1.0
    assert bins[(0.0, 5.0)]["people"] == 0 and np.isnan(bins[(0.0, 5.0)]["recall"])
    assert sum(b["people"] for b in bins.values()) == 2000
    assert min_person_px(sizes, covered) == 12.0
    # One miss in a large bin (of ~300) keeps 99.5 %; a cluster of misses there moves the size up.
    big = np.flatnonzero((sizes >= 24) & (sizes < 40))
    c1 = covered.copy()
    c1[big[:1]] = False
    assert min_person_px(sizes, c1) == 12.0
    c2 = covered.copy()
    c2[big[:5]] = False
    assert min_person_px(sizes, c2) == 40.0
    # Too few people at or above a size: no claim (one miss in fewer than 200 already fails it).
    assert min_person_px(sizes[:150], covered[:150]) is None
    # Everyone seen, but nobody smaller than 20 px measured: the claim starts where the data does.
    s3 = rng.uniform(20, 60, 500)
    assert min_person_px(s3, np.ones(500, bool)) == 16.0


def test_evaluate_set_reports_recall_by_size_only_where_sizes_are_known() -> None:
    from companion.evaluation.metrics import overall_min_person_px

    img = np.zeros((64, 64, 3), np.uint8)
    pts = np.array([[10.5, 10.5], [50.5, 50.5]], np.float32)

    class Mem(D.Sample):
        def image(self) -> np.ndarray:
            return img

    def left_half(frame: np.ndarray) -> np.ndarray:  # "sees" people only in the left half
        d = np.zeros((16, 16), np.float32)
        d[:, :4] = 1.0
        return d

    sized = Mem("a", Path("a"), pts, sizes=np.array([30.0, 6.0], np.float32))
    r = evaluate_set("sized", [sized] * 250, left_half, 0.5)  # 250 people of 30 px: enough for a claim
    bins = {b["lo"]: b for b in r.size_recall or []}
    assert bins[24.0]["recall"] == 1.0 and bins[5.0]["recall"] == 0.0 and r.min_person_px == 24.0
    r2 = evaluate_set("plain", [Mem("b", Path("b"), pts)], left_half, 0.5)
    assert r2.size_recall is None and r2.min_person_px is None
    assert overall_min_person_px([r, r2]) == 24.0
    assert overall_min_person_px([r2]) is None
    r.min_person_px = None  # a sized set that never reaches 99.5 %: no figure for the model
    assert overall_min_person_px([r, r2]) is None


def test_scaled_samples_keep_annotations_on_the_same_pixels(shared_dir: Path) -> None:
    s = next(x for x in D.semantic_drone(shared_dir, "val") if len(x.points) >= 2)
    (half,) = D.scaled([s], 0.5, "_x0.5")
    img = half.image()
    assert img.shape[:2] == (250, 375) and half.name.endswith("_x0.5")
    np.testing.assert_allclose(half.points, s.points / 2, atol=1e-4)
    np.testing.assert_allclose(half.sizes, s.sizes / 2, atol=1e-4)  # type: ignore[operator]
    with pytest.raises(ValueError, match="scale factor"):
        D.scaled([s], 1.5)


# -- started early (tests/early.py); last in the module, so that the tests above run meanwhile --

def _card_row(name: str) -> tuple[float, float]:
    """(recall, free) of a row of the model card's 'ours at the shipped threshold' table."""
    text = CARD.read_text()
    m = re.search(rf"^\| {re.escape(name)} \|[^|]*\| ([\d.]+) % \| ([\d.]+) % \|", text, re.M)
    assert m, f"no '{name}' row in {CARD}"
    return float(m.group(1)) / 100, float(m.group(2)) / 100


def dronecrowd_recall(model: str, shared: str) -> tuple[float, float]:
    """(recall, free) of the model ``model`` on the six DroneCrowd frames of ``shared`` at the
    model's own threshold."""
    density = DensityModel(Path(model))
    r = evaluate_set("dronecrowd6", D.dronecrowd_frames(Path(shared)), density, density.spec.occupancy_threshold)
    return r.recall, r.free


@early.batch("dronecrowd-recall")
def _dronecrowd_recall(folder: Path) -> list[early.Run]:
    """:func:`dronecrowd_recall` with version 1 (seconds of inference): a process of its own,
    started once the session knows it runs the test (tests/early.py)."""
    from tests.conftest import MODEL, SHARED
    if not (SHARED / "data").is_dir():
        return []  # the test skips (shared_dir)
    return [early.call(folder / "recall.pickle", dronecrowd_recall, str(MODEL.with_name("slz-density.onnx")),
                       str(SHARED))]


@pytest.mark.started_early("dronecrowd-recall")
def test_dronecrowd_recall_matches_the_model_card(model_path: Path, shared_dir: Path) -> None:
    # The card's "ours at the shipped threshold" table is version 1's (the default until
    # 2026-11-27); version 4's figures are in its own section, from the same command.
    (run,) = early.result("dronecrowd-recall")[1]
    assert json.loads(run.args[-1]) == [str(model_path.with_name("slz-density.onnx")), str(shared_dir)]
    r_recall, r_free = early.returned("dronecrowd-recall")
    recall, free = _card_row("DroneCrowd, six frames")
    assert r_recall == pytest.approx(recall, abs=0.003)
    assert r_free == pytest.approx(free, abs=0.003)


@early.batch("eval-json-with-peer")
def _eval_json_with_peer(folder: Path) -> list[early.Run]:
    """``companion eval --json`` with the MCNN peer (its latency runs alone take seconds): a
    process of its own, started once the session knows it runs the test (tests/early.py)."""
    from tests.conftest import SHARED
    if not (SHARED / "data").is_dir():
        return []  # the test skips (shared_dir)
    return [early.Run([sys.executable, "-m", "companion", "eval", "--shared", str(SHARED), "--sets", "semantic,mall",
                       "--limit", "2", "--mall-step", "300", "--latency-runs", "1",
                       "--peer", str(SHARED / "peers" / "mcnn-shb.onnx"), "--json"])]


@pytest.mark.started_early("eval-json-with-peer")
def test_eval_cli_json_with_peer(model_path: Path, shared_dir: Path) -> None:
    (r,) = early.result("eval-json-with-peer")[1]
    assert r.args[r.args.index("--shared") + 1] == str(shared_dir)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    ours, peer = doc["model"], doc["peer"]
    assert set(ours["sets"]) == {"semantic_drone_val", "mall"}
    assert ours["sets"]["mall"]["images"] == 2 and ours["sets"]["mall"]["mae"] is not None
    assert peer["spec"]["color"] == "gray" and peer["threshold"] == 0.0
    assert doc["latency_ratio_ours_over_peer"]["640x480"] > 0
    sd = ours["sets"]["semantic_drone_val"]
    assert 0 <= sd["ours_recall_at_peer_free"] <= 1 and sd["peer_free"] == peer["sets"]["semantic_drone_val"]["free"]
    assert 0 <= sd["peer_best_recall"] <= 1


@early.batch("eval-size-recall")
def _eval_size_recall(folder: Path) -> list[early.Run]:
    """``companion eval --json`` on the semantic, DroneCrowd and synthetic sets: a process of its
    own, started once the session knows it runs the test (tests/early.py). The synthetic set's
    compositor loads every held-out photo's people and ground (seconds on the full set): here the
    first five's (``few_photos_tree``; the semantic set's first three are the full set's)."""
    from tests.conftest import SHARED, few_photos_tree
    if not (SHARED / "data").is_dir():
        return []  # the test skips (shared_dir)
    shared = few_photos_tree(SHARED, folder / "shared")
    return [early.Run([sys.executable, "-m", "companion", "eval", "--shared", str(shared), "--sets",
                       "semantic,dronecrowd,synthetic", "--limit", "3", "--synthetic-n", "3", "--latency-runs", "0",
                       "--json"])]


@pytest.mark.started_early("eval-size-recall")
def test_eval_cli_reports_size_recall_and_the_model_figure(model_path: Path, few_photos_shared: Path,
                                                          capsys) -> None:
    from companion.cli import main

    (r,) = early.result("eval-size-recall")[1]
    shared = Path(r.args[r.args.index("--shared") + 1])  # laid out as few_photos_shared is
    assert sorted(p.name for p in (shared / "data" / "semantic_drone" / "images").iterdir()) == \
        sorted(p.name for p in (few_photos_shared / "data" / "semantic_drone" / "images").iterdir())
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)["model"]
    assert doc["min_person_px_sets"] == ["semantic_drone_val", "synthetic_val"]
    assert doc["sets"]["dronecrowd6"]["size_recall"] is None  # 20 px head boxes: no person size
    syn = doc["sets"]["synthetic_val"]
    assert syn["images"] == 3 and syn["heads"] == sum(b["people"] for b in syn["size_recall"])
    assert "min_person_px" in doc and doc["min_person_px_metadata"] == DensityModel(model_path).min_person_px
    assert main(["eval", "--shared", str(few_photos_shared), "--sets", "synthetic", "--synthetic-n", "0"]) == 2
