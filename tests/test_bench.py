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
