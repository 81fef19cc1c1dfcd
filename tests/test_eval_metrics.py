"""Evaluation: the curve's level map agrees with the pipeline's occupancy step; figures on real data."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from companion.evaluation import datasets as D
from companion.evaluation.metrics import CURVE_THRESHOLDS, best_threshold, evaluate_set, level_map, tally_occupancy
from companion.pipeline.density import DensityModel
from companion.pipeline.occupancy import FREE, OccupancyParams, occupancy_map

CARD = Path(__file__).resolve().parents[1] / "companion" / "models" / "MODEL_CARD.md"


@pytest.mark.parametrize("shape,image_hw", [((30, 40), (120, 160)), ((125, 188), (500, 750)), ((9, 9), (9, 9))])
def test_level_map_matches_occupancy_map_at_every_threshold(shape, image_hw) -> None:
    rng = np.random.default_rng(1)
    d = (rng.random(shape) ** 6).astype(np.float32)
    d[0, 0] = np.nan  # a broken value must stay occupied at every threshold
    lv = level_map(d, image_hw)
    for t in (0.0, 1e-3, 0.05, 0.3, 0.9):
        occ = occupancy_map(d, image_hw, OccupancyParams(t)) != FREE
        np.testing.assert_array_equal(occ, lv > t)


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


def _card_row(name: str) -> tuple[float, float]:
    """(recall, free) of a row of the model card's 'ours at the shipped threshold' table."""
    text = CARD.read_text()
    m = re.search(rf"^\| {re.escape(name)} \|[^|]*\| ([\d.]+) % \| ([\d.]+) % \|", text, re.M)
    assert m, f"no '{name}' row in {CARD}"
    return float(m.group(1)) / 100, float(m.group(2)) / 100


def test_dronecrowd_recall_matches_the_model_card(model_path: Path, shared_dir: Path) -> None:
    model = DensityModel(model_path)
    r = evaluate_set("dronecrowd6", D.dronecrowd_frames(shared_dir), model, model.spec.occupancy_threshold)
    recall, free = _card_row("DroneCrowd, six frames")
    assert r.recall == pytest.approx(recall, abs=0.003)
    assert r.free == pytest.approx(free, abs=0.003)


def test_eval_cli_json_with_peer(model_path: Path, shared_dir: Path, capsys) -> None:
    from companion.cli import main

    rc = main(["eval", "--shared", str(shared_dir), "--sets", "semantic,mall", "--limit", "2", "--mall-step", "300",
               "--latency-runs", "1", "--peer", str(shared_dir / "peers" / "mcnn-shb.onnx"), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    ours, peer = doc["model"], doc["peer"]
    assert set(ours["sets"]) == {"semantic_drone_val", "mall"}
    assert ours["sets"]["mall"]["images"] == 2 and ours["sets"]["mall"]["mae"] is not None
    assert peer["spec"]["color"] == "gray" and peer["threshold"] == 0.0
    assert doc["latency_ratio_ours_over_peer"]["640x480"] > 0
    sd = ours["sets"]["semantic_drone_val"]
    assert 0 <= sd["ours_recall_at_peer_free"] <= 1 and sd["peer_free"] == peer["sets"]["semantic_drone_val"]["free"]
    assert 0 <= sd["peer_best_recall"] <= 1


def test_eval_cli_rejects_bad_input(tmp_path: Path, capsys) -> None:
    from companion.cli import main

    assert main(["eval", "--model", str(tmp_path / "missing.onnx"), "--shared", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["eval", "--sets", "shb,moon", "--shared", str(tmp_path)]) == 2
    assert "unknown set" in capsys.readouterr().err


def test_eval_cli_reports_missing_data(model_path: Path, tmp_path: Path, capsys) -> None:
    from companion.cli import main

    assert main(["eval", "--model", str(model_path), "--shared", str(tmp_path), "--sets", "mall"]) == 2
    assert "missing" in capsys.readouterr().err
