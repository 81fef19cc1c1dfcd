"""``--ground photo`` on the commands (issue 59): a missing or malformed photos folder is exit 2
naming it, before anything flies; the drawn ground stays the default."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim.flights import demo, scenarios
from sim.flights.scenarios import FlightJob
from sim.flights.spec import default_photos, photos_folder


@pytest.mark.parametrize("command", ["sim-scenarios", "demo"])
def test_a_missing_photos_folder_is_exit_2_naming_it_before_anything_flies(command, tmp_path, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    monkeypatch.setattr(demo, "fly", lambda spec: pytest.fail("nothing may fly"))
    missing = tmp_path / "no-photos-here"
    args = ["--seeds", "1", "--workers", "1", "--no-progress"] if command == "sim-scenarios" else \
        ["--no-video", "--out", str(tmp_path / "demo")]
    assert main([command, *args, "--ground", "photo", "--photos", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err


def test_a_malformed_photos_folder_is_exit_2_naming_it(tmp_path, monkeypatch, capsys):
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    (tmp_path / "images").mkdir()
    (tmp_path / "labels").mkdir()
    for k in range(10):  # photos that are no photos
        (tmp_path / "images" / f"{k:03d}.jpg").write_bytes(b"not a jpeg")
        (tmp_path / "labels" / f"{k:03d}.png").write_bytes(b"not a png")
    assert main(["sim-scenarios", "--seeds", "1", "--workers", "1", "--no-progress",
                 "--ground", "photo", "--photos", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path) in err and "1500x1000" in err


def test_photos_need_the_photo_ground_and_procedural_is_the_default(tmp_path) -> None:
    with pytest.raises(ValueError, match="--ground photo"):
        photos_folder("procedural", tmp_path)
    assert photos_folder("procedural", None) is None
    assert FlightJob(1).spec().ground == "procedural" and FlightJob(1).spec().photos is None
    assert default_photos().parts[-4:] == ("shared", "data", "semantic_drone", "full")
    assert default_photos().parent.parent.parent.parent == Path(scenarios.__file__).resolve().parents[3]


@pytest.mark.parametrize("command", ["sim-scenarios", "demo"])
def test_both_commands_name_themselves_and_the_option_in_the_exit_2_message(command, tmp_path, monkeypatch, capsys):
    # One check of --camera and --photos serves both commands (spec.parse_camera_and_photos); the
    # message still says which command and which option.
    from companion.cli import main

    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    monkeypatch.setattr(demo, "fly", lambda spec: pytest.fail("nothing may fly"))
    args = ["--seeds", "1", "--workers", "1", "--no-progress"] if command == "sim-scenarios" else \
        ["--no-video", "--out", str(tmp_path / "demo")]
    prog = "companion sim-scenarios" if command == "sim-scenarios" else "companion: demo"
    assert main([command, *args, "--camera", "fish:160"]) == 2
    assert capsys.readouterr().err.startswith(f"{prog}: --camera: want MODEL:HFOV")
    assert main([command, *args, "--photos", str(tmp_path)]) == 2
    assert capsys.readouterr().err == f"{prog}: --photos: --photos needs --ground photo\n"
