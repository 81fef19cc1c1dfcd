"""The benchmark command's output shape (figures are printed, never asserted against targets)."""

import json
import sys
from pathlib import Path

import pytest

from companion.cli import main
from tests import early


def test_bench_json_has_every_stage_for_both_resolutions(capsys):
    assert main(["bench", "--json", "--frames", "3", "--no-model"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"640x480", "1280x720"}
    for stages in out.values():
        assert {"occupancy", "projection", "proposals", "tracking", "post_density", "live_view",
                "landing_spot"} <= set(stages)
        for s in stages.values():
            assert s["median_ms"] > 0 and s["p99_ms"] >= s["median_ms"]


@early.batch("bench-shipped-model")
def _bench_shipped_model(folder: Path) -> list[early.Run]:
    """``companion bench`` with the shipped model (seconds of inference at two resolutions): a
    process of its own, started once the session knows it runs the test (tests/early.py)."""
    from tests.conftest import MODEL
    return [early.Run([sys.executable, "-m", "companion", "bench", "--json", "--frames", "2", "--model", str(MODEL)])]


@pytest.mark.started_early("bench-shipped-model")
def test_bench_with_the_shipped_model_times_density_and_total(model_path):
    (r,) = early.result("bench-shipped-model")[1]
    assert r.args[r.args.index("--model") + 1] == str(model_path)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for stages in out.values():
        assert {"density", "total"} <= set(stages)
        assert stages["total"]["median_ms"] >= stages["density"]["median_ms"]


def test_bench_with_a_missing_model_names_the_file(capsys, tmp_path):
    missing = tmp_path / "nope.onnx"
    assert main(["bench", "--frames", "1", "--model", str(missing)]) == 2
    assert "nope.onnx" in capsys.readouterr().err


def test_bench_pauses_before_each_frame_when_asked(capsys):
    import time

    t0 = time.monotonic()
    assert main(["bench", "--json", "--frames", "2", "--no-model", "--no-landability", "--pause-ms", "40"]) == 0
    # 5 warm-up frames + 2 per resolution, each after a 40 ms sleep: at least 0.56 s in all.
    assert time.monotonic() - t0 >= 14 * 0.04
    assert set(json.loads(capsys.readouterr().out)) == {"640x480", "1280x720"}


def test_bench_refuses_a_bad_pause(capsys):
    assert main(["bench", "--frames", "1", "--no-model", "--pause-ms", "nan"]) == 2
    assert "--pause-ms" in capsys.readouterr().err


def test_bench_times_the_pipeline_as_configured_at_the_cameras_resolution(capsys, tmp_path):
    """--configured builds the pipeline from the service's settings: one resolution, the camera's;
    the people stage, which no setting asks for any more, does not run."""
    assert main(["bench", "--json", "--frames", "3", "--no-model", "--set", "camera.width=320",
                 "--set", "camera.height=240"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"320x240"}
    assert out["320x240"]["people"]["median_ms"] < 0.05  # not run
    cfg = tmp_path / "c.toml"
    cfg.write_text("[camera]\nwidth = 320\nheight = 240\n")
    assert main(["bench", "--json", "--frames", "3", "--no-model", "--config", str(cfg)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"320x240"} and out["320x240"]["people"]["median_ms"] < 0.05


def test_bench_refuses_a_bad_configuration_with_exit_2(capsys, tmp_path):
    assert main(["bench", "--frames", "1", "--no-model", "--set", "pipeline.r0_m=bogus"]) == 2
    assert "pipeline.r0_m" in capsys.readouterr().err
    assert main(["bench", "--frames", "1", "--no-model", "--set", "pipeline.fusion=map"]) == 2
    assert "pipeline.fusion was removed" in capsys.readouterr().err
    assert main(["bench", "--frames", "1", "--no-model", "--config", str(tmp_path / "none.toml")]) == 2
    assert "none.toml" in capsys.readouterr().err
    assert main(["bench", "--frames", "1", "--set", f"model.path={tmp_path / 'gone.onnx'}"]) == 2
    assert "gone.onnx" in capsys.readouterr().err
    assert main(["bench", "--frames", "1", "--no-model", "--threads", "0"]) == 2
    assert "--threads" in capsys.readouterr().err


def test_bench_times_a_peer_on_the_same_frame_and_gives_the_ratio(capsys, shared_dir, tmp_path):
    """--peer times another density model (the MCNN peer, its preset from its name) on the same
    frames in the same run: its density time and the whole frame's ratio to it."""
    peer = shared_dir / "peers" / "mcnn-shb.onnx"
    assert main(["bench", "--json", "--frames", "2", "--no-landability", "--set", "camera.width=320",
                 "--set", "camera.height=240", "--peer", str(peer)]) == 0
    stages = json.loads(capsys.readouterr().out)["320x240"]
    assert stages["peer_density"]["median_ms"] > 0
    ratio = stages["total"]["median_ms"] / stages["peer_density"]["median_ms"]
    assert stages["total_over_peer"]["ratio"] == round(ratio, 4)
    assert main(["bench", "--frames", "1", "--peer", str(tmp_path / "gone.onnx")]) == 2
    assert "gone.onnx" in capsys.readouterr().err
