"""`python -m sim.evidence.lens_recall`: the shipped model's recall by the ray's angle, drawn and composited."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from sim.evidence.lens_recall import main
from tests import early


@early.batch("lens-recall-photo")
def _lens_recall_photo(folder: Path) -> list[early.Run]:
    """The command over the photo ground (seconds of rendering and inference): a process of its
    own, started once the session knows it runs the test (tests/early.py)."""
    from tests.conftest import held_out_photos
    photos = held_out_photos()
    if photos is None:
        return []  # the test skips (photos)
    return [early.Run([sys.executable, "-m", "sim.evidence.lens_recall", "--camera", "fisheye:160", "--heights", "20",
                       "--seeds", "1", "--frames", "1", "--ground", "photo", "--photos", photos])]


@pytest.mark.started_early("lens-recall-photo")
def test_over_the_photo_ground_walkers_and_the_photos_people_are_counted(photos: str, model_path) -> None:
    """``--ground photo``: one frame of the seed's photo scene through the fisheye; each bin
    counts the composited walkers and the photos' own people apart, and their sum is the bin's."""
    (r,) = early.result("lens-recall-photo")[1]
    assert r.args[-1] == photos
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["ground"] == "photo" and res["heights_m"] == [20.0]
    bins = res["bins"]
    for b in bins:
        w, p = b["walkers"], b["photo_people"]
        assert b["people"] == w["people"] + p["people"] and b["found"] == w["found"] + p["found"]
        assert 0 <= b["found"] <= b["people"]
        assert b["recall"] == (None if b["people"] == 0 else round(b["found"] / b["people"], 4))
    # Both kinds are in view, and the photos' people are found near the axis (real people, seen
    # from above, where the model was trained to find them).
    assert sum(b["walkers"]["people"] for b in bins) > 0
    assert sum(b["photo_people"]["people"] for b in bins) > 0
    near = [b for b in bins if b["to_deg"] <= 60 and b["people"]]
    assert near and sum(b["found"] for b in near) >= 0.9 * sum(b["people"] for b in near)


def test_a_missing_or_malformed_photos_folder_is_exit_2_naming_it(tmp_path: Path, capsys) -> None:
    missing = tmp_path / "nowhere"
    assert main(["--ground", "photo", "--photos", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err
    (tmp_path / "bad" / "images").mkdir(parents=True)
    (tmp_path / "bad" / "labels").mkdir()
    assert main(["--ground", "photo", "--photos", str(tmp_path / "bad")]) == 2
    assert str(tmp_path / "bad") in capsys.readouterr().err
    assert main(["--photos", str(tmp_path / "bad")]) == 2  # --photos without --ground photo
    assert "--ground photo" in capsys.readouterr().err
