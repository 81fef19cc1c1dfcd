"""`python -m sim.evidence.person_halo`: how far around one standing person the pipeline marks occupied."""

from __future__ import annotations

import contextlib
import io
import json
import math
import sys
from pathlib import Path

import pytest

from sim.evidence.person_halo import (
    BEARINGS_DEG,
    PHOTO_DISC_MARGIN_M,
    HaloRow,
    main,
    measure,
    parse_floats,
    photo_point,
)
from sim.flights.flight import photo_ground
from sim.world.photo_ground import PHOTO_WALKABLE
from tests import early


def lawn_rows() -> tuple[list[HaloRow], list[HaloRow]]:
    """The rows of a person 3.5 m away seen from 10 m, and 4 m away seen from 4.4 m, on seed 18's
    lawn with the shipped model."""
    return measure([10.0], [3.5]), measure([4.4], [4.0])


@early.batch("person-halo-lawn")
def _person_halo_lawn(folder: Path) -> list[early.Run]:
    """:func:`lawn_rows` (seconds of rendering and inference): a process of its own, started once
    the session knows it runs the test (tests/early.py)."""
    return [early.call(folder / "rows.pickle", lawn_rows)]


@pytest.mark.started_early("person-halo-lawn")
def test_a_person_is_marked_nearer_than_they_stand_by_about_a_metre(model_path) -> None:
    # The halo the zone losses' truth showed (a "1.9 m free" loss is a person about 3.2 m away):
    # never nearer than the person (the pipeline errs toward occupied), and by at most 2 m.
    (row,), (low,) = early.returned("person-halo-lawn")
    assert row.view_m > 3.5 and len(row.free_m) == 4
    assert all(h is not None and 0.5 <= h <= 2.0 for h in row.halo_m), row
    # Out of reach of a low camera's view: no halo to speak of, and said so.
    assert low.view_m < 2.0 and low.halo_m == [None] * 4


def test_bad_arguments_and_a_missing_model_are_exit_2(tmp_path, capsys) -> None:
    with pytest.raises(ValueError):
        parse_floats("3,-1")
    assert main(["--heights", "ten"]) == 2
    assert main(["--heights", "1.5", "--distances", "3"]) == 2  # under the head plane: no frame to place
    assert "head plane" in capsys.readouterr().err
    assert main(["--model", str(tmp_path / "none.onnx"), "--heights", "10", "--distances", "3"]) == 2
    assert "none.onnx" in capsys.readouterr().err


@early.batch("person-halo-json")
def _person_halo_json(folder: Path) -> list[early.Run]:
    """The command's JSON rows for one height and distance: a process of its own, started once the
    session knows it runs the test (tests/early.py)."""
    return [early.Run([sys.executable, "-m", "sim.evidence.person_halo", "--heights", "7", "--distances", "3",
                       "--json"])]


@pytest.mark.started_early("person-halo-json")
def test_json_rows(model_path) -> None:
    (r,) = early.result("person-halo-json")[1]
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    assert rows[0]["height_m"] == 7 and rows[0]["distance_m"] == 3 and len(rows[0]["halo_m"]) == 4


def photo_rows(photos: str) -> tuple[list[HaloRow], int, str]:
    """The row of a person 3 m from the point below, seen from 10 m, over the photo ground of
    ``photos`` (seed 18, the shipped model); then the command's exit status and standard output
    for the same (``main``, in the same process: the photo ground is loaded once)."""
    rows = measure([10.0], [3.0], seed=18, photos=photos)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["--heights", "10", "--distances", "3", "--ground", "photo", "--photos", photos, "--json"])
    return rows, code, out.getvalue()


@early.batch("person-halo-photo")
def _person_halo_photo(folder: Path) -> list[early.Run]:
    """:func:`photo_rows` (the photo ground's load and seconds of rendering and inference): a
    process of its own, started once the session knows it runs the test (tests/early.py)."""
    from tests.conftest import held_out_photos
    photos = held_out_photos()
    if photos is None:
        return []  # the test skips (photos)
    return [early.call(folder / "rows.pickle", photo_rows, photos)]


@pytest.mark.started_early("person-halo-photo")
def test_over_the_photo_ground_the_person_stands_on_walkable_ground(photos: str, model_path, capsys) -> None:
    """``--ground photo``: the point below is drawn where the disc out to the person is walkable
    ground with none of the photos' people in it, so at every bearing the person stands on paved
    area, dirt, grass or gravel by the class maps; the row says the ground, the free radius with
    nobody there and how far the photos' nearest person stands."""
    ground = photo_ground(photos)
    (cn, ce), near = photo_point(ground, 18, 3.0)
    for bearing in BEARINGS_DEG:
        b = math.radians(bearing)
        assert ground.surface_at(cn + 3.0 * math.cos(b), ce + 3.0 * math.sin(b)) in PHOTO_WALKABLE
    assert near > 3.0 + PHOTO_DISC_MARGIN_M
    (call,) = early.result("person-halo-photo")[1]  # measure() and the command over these photos
    assert json.loads(call.args[-1]) == [photos]
    (row,), code, out_json = early.returned("person-halo-photo")
    assert row.ground == "photo" and row.nearest_other_m == round(near, 2)
    assert row.empty_m is not None and 0.0 <= row.empty_m <= row.view_m and len(row.free_m) == 4
    # A halo only where the person, not the view's end nor the ground's own marks, sets the radius.
    for r, h in zip(row.free_m, row.halo_m, strict=True):
        assert h is None or (r < row.view_m and row.empty_m > 3.0 and h == round(3.0 - r, 2))
    assert code == 0
    (out,) = json.loads(out_json)
    assert out["ground"] == "photo" and out["free_m"] == row.free_m
    # No walkable disc is 80 m wide: said, exit 2, before any frame.
    assert main(["--heights", "10", "--distances", "80", "--ground", "photo", "--photos", photos]) == 2
    assert "no landable disc" in capsys.readouterr().err


def test_a_missing_or_malformed_photos_folder_is_exit_2_naming_it(tmp_path: Path, capsys) -> None:
    missing = tmp_path / "nowhere"
    assert main(["--ground", "photo", "--photos", str(missing), "--heights", "10", "--distances", "3"]) == 2
    assert str(missing) in capsys.readouterr().err
    (tmp_path / "bad" / "images").mkdir(parents=True)
    (tmp_path / "bad" / "labels").mkdir()
    assert main(["--ground", "photo", "--photos", str(tmp_path / "bad")]) == 2
    assert str(tmp_path / "bad") in capsys.readouterr().err
    assert main(["--photos", str(tmp_path / "bad")]) == 2  # --photos without --ground photo
    assert "--ground photo" in capsys.readouterr().err
