"""The benchmark command's output shape (figures are printed, never asserted against targets)."""

import json

from companion.cli import main


def test_bench_json_has_every_stage_for_both_resolutions(capsys):
    assert main(["bench", "--json", "--frames", "3", "--no-model"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"640x480", "1280x720"}
    for stages in out.values():
        assert {"occupancy", "projection", "proposals", "tracking", "post_density"} <= set(stages)
        for s in stages.values():
            assert s["median_ms"] > 0 and s["p99_ms"] >= s["median_ms"]


def test_bench_with_the_shipped_model_times_density_and_total(capsys, model_path):
    assert main(["bench", "--json", "--frames", "2", "--model", str(model_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    for stages in out.values():
        assert {"density", "total"} <= set(stages)
        assert stages["total"]["median_ms"] >= stages["density"]["median_ms"]


def test_bench_with_a_missing_model_names_the_file(capsys, tmp_path):
    missing = tmp_path / "nope.onnx"
    assert main(["bench", "--frames", "1", "--model", str(missing)]) == 2
    assert "nope.onnx" in capsys.readouterr().err
