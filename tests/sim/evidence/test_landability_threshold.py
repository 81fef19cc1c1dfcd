"""``python -m sim.evidence.landability_threshold``: what the landability model's threshold trades
on the photo world, judged on the class maps."""

from __future__ import annotations

import json

from companion.config.schema import SHIPPED_LANDABILITY
from companion.pipeline.landability import LandabilityModel
from sim.evidence import landability_threshold as lt


def test_a_higher_threshold_frees_landable_ground_and_misses_more_of_the_rest(photos) -> None:
    """Seeds 1-3 from 20 m (where the frames show roofs and trees beside the free circle) and
    8 m: raising the threshold can only call less ground unlandable, so the landable ground
    marked falls and the unlandable ground left rises; the free circle is landable ground."""
    model = LandabilityModel(SHIPPED_LANDABILITY, threads=2)
    figs = lt.threshold_curve(model, [1, 2, 3], [20.0, 8.0], [0.5, 0.05, 0.2], photos)
    assert [(f.height_m, f.threshold) for f in figs] == [(h, t) for h in (20.0, 8.0) for t in (0.05, 0.2, 0.5)]
    for h in (20.0, 8.0):
        row = [f for f in figs if f.height_m == h]
        assert all(f.circles == 3 for f in row)
        marked = [f.landable_marked_pct for f in row]
        circle = [f.circle_marked_pct for f in row]
        assert marked == sorted(marked, reverse=True) and marked[0] > marked[-1]
        assert circle == sorted(circle, reverse=True)
        assert all(0.0 <= f.circle_marked_pct <= 100.0 for f in row)
    high = [f for f in figs if f.height_m == 20.0]
    left = [f.unlandable_left_pct for f in high if f.unlandable_left_pct is not None]
    assert len(left) == 3 and left == sorted(left) and left[0] < left[-1]


def test_cli_prints_the_models_own_threshold_and_refuses_bad_input(photos, tmp_path, capsys) -> None:
    assert lt.main(["--seeds", "3", "--heights", "8", "--thresholds", "0.5", "--photos", photos, "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    own = LandabilityModel(SHIPPED_LANDABILITY, threads=1).landability.threshold
    assert sorted(r["threshold"] for r in rows) == sorted({0.5, own})
    assert lt.main(["--seeds", "3", "--heights", "8", "--photos", photos]) == 0
    assert "(the model's own)" in capsys.readouterr().out
    assert lt.main(["--thresholds", "1.5", "--photos", photos]) == 2
    assert "--thresholds" in capsys.readouterr().err
    missing = tmp_path / "none"
    assert lt.main(["--photos", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err
    assert lt.main(["--photos", photos, "--model", str(tmp_path / "x.onnx")]) == 2
    assert "no model" in capsys.readouterr().err


def test_levels_sum_only_the_named_risk_levels(photos, capsys) -> None:
    """Vegetation alone can call no more ground unlandable than every level together, and an
    unknown level is refused naming the model's levels."""
    model = LandabilityModel(SHIPPED_LANDABILITY, threads=2)
    (every,) = lt.threshold_curve(model, [3], [20.0], [0.05], photos)
    (veg,) = lt.threshold_curve(model, [3], [20.0], [0.05], photos, levels=["vegetation"])
    assert veg.landable_marked_pct <= every.landable_marked_pct
    assert veg.unlandable_left_pct is not None and every.unlandable_left_pct is not None
    assert veg.unlandable_left_pct >= every.unlandable_left_pct
    assert lt.main(["--photos", photos, "--levels", "vegetation,lava"]) == 2
    err = capsys.readouterr().err
    assert "'lava'" in err and "obstacles" in err
