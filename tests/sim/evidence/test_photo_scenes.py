"""``python -m sim.evidence.photo_scenes``: where the photo world's scenes lie and where its
crossers walk (docs/photo-world.md). Needs ``../shared``; skips without it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim.evidence.photo_scenes import main


def test_it_reports_each_scenes_photo_disc_and_crossers(photos: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--seeds", "2-3", "--photos", photos, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["seed"] for s in out["scenes"]] == [2, 3]
    for s in out["scenes"]:
        assert s["landable"] == 1.0  # every free circle is landable ground by the class maps
        assert s["nearest_person_m"] > s["radius_m"] + 1.0  # nobody of the photos in it
    allowed = {float(k): v for k, v in out["allowed"].items()}
    assert allowed[2.0] >= allowed[6.0] >= 2  # fewer photos hold a wider disc
    assert out["proposal"]["photos_used"] <= out["proposal"]["photos_allowing"]
    crossers = out["crossers"]
    assert crossers["seeds"] == [2] and crossers["crossers"] >= 2
    assert crossers["off_map_after"] == 0.0 < crossers["off_map_before"]


def test_bad_arguments_are_exit_2_naming_them(photos: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--seeds", "2", "--photos", photos, "--floor", "0"]) == 2
    assert "--floor" in capsys.readouterr().err
    assert main(["--seeds", "2", "--photos", str(tmp_path / "nowhere")]) == 2
    assert "nowhere" in capsys.readouterr().err
