"""``python -m sim.evidence.walker_alarms --ground photo``: the people stage's walkers scored over the
photo world. Needs ``../shared`` (the held-out full-size photos); skips without it."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest

from companion.pipeline.density import DensityModel
from sim.evidence.walker_alarms import Descent, fly_over_circle, main
from tests import early


def photo_descent(model: str, photos: str) -> tuple[Descent, int, str, str]:
    """Seed 2's descent over its photo scene for 4 s with the model ``model`` (one thread); then
    the command's exit status, standard output and standard error for the same (``main``, in the
    same process: the photo ground is loaded once)."""
    descent = fly_over_circle(DensityModel(Path(model), threads=1), 2, seconds=4.0, horizon_s=3.0, photos=photos)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["--seeds", "2", "--seconds", "4", "--horizon", "3", "--blind-from", "1", "--ground", "photo",
                     "--photos", photos, "--model", model, "--json"])
    return descent, code, out.getvalue(), err.getvalue()


@early.batch("walker-alarms-photo")
def _walker_alarms_photo(folder: Path) -> list[early.Run]:
    """:func:`photo_descent` (the photo ground's load and seconds of rendering and inference): a
    process of its own, started once the session knows it runs the test (tests/early.py)."""
    from tests.conftest import MODEL, held_out_photos
    photos = held_out_photos()
    if photos is None:
        return []  # the test skips (photos)
    return [early.call(folder / "descent.pickle", photo_descent, str(MODEL), photos)]


@pytest.mark.started_early("walker-alarms-photo")
def test_a_descent_over_the_photo_world_keeps_its_people_on_walkable_ground(photos: str, model_path: Path) -> None:
    """Seed 2's photo scene (a crossing world): its walkers stand on walkable ground by the class
    maps in every frame, the photos' own people are in the truth, and the command scores it."""
    (call,) = early.result("walker-alarms-photo")[1]  # the descent and the command, with these arguments
    assert json.loads(call.args[-1]) == [str(model_path), photos]
    descent, code, out, err = early.returned("walker-alarms-photo")
    assert descent.ground == "photo" and descent.frames
    assert descent.people_frames > 0 and descent.off_walkable == 0
    fixed = [fr for fr in descent.frames if (fr.ids < 0).any()]  # the photos' people, negative ids
    assert len(fixed) == len(descent.frames) and len(descent.truth[0][1]) == len(descent.frames[0].people)
    assert code == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    assert [(r["seed"], r["ground"]) for r in rows] == [(2, "photo"), (None, "photo")]
    assert rows[0]["safe_frames"] + rows[0]["danger_frames"] > 0
    assert "seed 2: 0 of" in err and "off walkable ground" in err


def test_a_missing_or_malformed_photos_folder_is_exit_2_naming_it(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nowhere"
    assert main(["--seeds", "2", "--ground", "photo", "--photos", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err
    (tmp_path / "bad" / "images").mkdir(parents=True)
    (tmp_path / "bad" / "labels").mkdir()
    assert main(["--seeds", "2", "--ground", "photo", "--photos", str(tmp_path / "bad")]) == 2
    assert str(tmp_path / "bad") in capsys.readouterr().err
    assert main(["--seeds", "2", "--photos", str(tmp_path / "bad")]) == 2  # --photos without --ground photo
    assert "--ground photo" in capsys.readouterr().err
