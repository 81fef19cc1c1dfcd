"""Configuration: defaults, the documented example, and errors that name the key."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from companion import config
from companion.config import ConfigError

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "companion.example.toml"

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib


def test_defaults_point_at_the_simulator() -> None:
    cfg = config.load()
    assert cfg.link.url == "udpin:127.0.0.1:14550"
    assert cfg.camera.source.startswith("http://127.0.0.1:")
    assert cfg.camera.mount_pitch_deg == -90.0
    assert cfg.source is None


def test_example_documents_every_key_with_its_default() -> None:
    text = EXAMPLE.read_text()
    raw = tomllib.loads(text)
    cfg = config.load(EXAMPLE)  # validates
    defaults = config.Config()
    for key, default, _doc in config.all_keys():
        node = raw
        for part in key.split("."):
            assert part in node, f"{key} missing from companion.example.toml"
            node = node[part]
        if key not in ("model.path", "model.landability_path"):  # the example leaves them empty (= the shipped
            # models); the defaults are absolute
            assert node == default, f"{key}: example says {node!r}, default is {default!r}"
    assert Path(cfg.model.path) == config.shipped_model()
    assert Path(cfg.model.path).parent == REPO / "companion" / "models"
    assert Path(cfg.model.landability_path) == (REPO / "companion" / "models" / "slz-landability.onnx")
    assert cfg.camera == defaults.camera
    # Every key line is preceded by a comment (the example is the reference documentation).
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if re.match(r"^[a-z_0-9]+ = ", line):
            j = i - 1
            while j >= 0 and re.match(r"^[a-z_0-9]+ = ", lines[j]):
                j -= 1  # keys grouped under one comment
            assert lines[j].startswith("#"), f"key line {i + 1} ({line}) has no comment above it"


def test_unknown_key_names_key_and_allowed(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text("[camera]\nfsp = 10\n")
    with pytest.raises(ConfigError) as e:
        config.load(f)
    msg = str(e.value)
    assert "unknown key 'camera.fsp'" in msg
    assert "camera.fps" in msg and "allowed" in msg


def test_unknown_section(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text("[camra]\nfps = 10\n")
    with pytest.raises(ConfigError, match=r"unknown key 'camra' \(allowed: link, camera"):
        config.load(f)


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("[camera]\nfps = 'fast'\n", r"camera\.fps must be a number, got 'fast'"),
        ("[camera]\nfps = 0.0\n", r"camera\.fps must be >= 0\.1 and <= 240\.0, got 0\.0"),
        ("[link]\nsystem_id = 300\n", r"link\.system_id must be >= 1 and <= 255, got 300"),
        ("[link]\nsystem_id = 1.5\n", r"link\.system_id must be an integer"),
        ("[link]\nflavour = 'inav'\n", r"link\.flavour must be one of 'auto', 'ardupilot', 'px4'"),
        ("[recorder]\nenabled = 'yes'\n", r"recorder\.enabled must be true or false"),
        ("[camera]\nmount_offset_m = [0, 0]\n", r"camera\.mount_offset_m must hold exactly 3 numbers"),
        ("[pipeline.tracker]\nsigma_a = 0\n", r"pipeline\.tracker\.sigma_a must be > 0"),
        ("[pipeline.tracker]\nmotion = 'constant'\n", r"pipeline\.tracker\.motion must be one of 'velocity', 'position'"),
        ("[pipeline.tracker]\nsigma_v = 0\n", r"pipeline\.tracker\.sigma_v must be > 0"),
        ("[controller]\nmin_quiet_s = -1\n", r"controller\.min_quiet_s must be >= 0"),
        ("[controller]\nmin_unwalked_s = -1\n", r"controller\.min_unwalked_s must be >= 0"),
        ("[controller]\navoid_lost_s = -1\n", r"controller\.avoid_lost_s must be >= 0"),
        ("[controller]\nprefer_unwalked = 1\n", r"controller\.prefer_unwalked must be true or false"),
        ("[controller]\nselect_empty_s = -1\n", r"controller\.select_empty_s must be >= 0"),
        ("[controller]\nsearch_memory_s = 601\n", r"controller\.search_memory_s must be >= 0\.0 and <= 600\.0"),
        ("[controller]\nhold_looks = 'yes'\n", r"controller\.hold_looks must be true or false"),
        ("[controller]\npredict_rejudge = 'yes'\n", r"controller\.predict_rejudge must be true or false"),
        ("[pipeline]\nquiet_margin_m = -1\n", r"pipeline\.quiet_margin_m must be >= 0"),
        ("[pipeline]\ndilate_kernel = 4\n", r"pipeline\.dilate_kernel must be odd"),
        ("[link]\nsigning_key = 'abc'\n", r"link\.signing_key must be 64 hexadecimal"),
        ("[link]\nurl = 'http://x'\n", r"link\.url must start with udpin:"),
        ("camera = 3\n", r"camera must be a table"),
        ("[camera]\nfps = nan\n", r"camera\.fps must be a finite number"),
        ("[controller]\nmin_person_px = -3\n", r"controller\.min_person_px must be >= 0"),
        ("[controller]\nlose_after_frames = 0\n", r"controller\.lose_after_frames must be >= 1"),
        ("[pipeline]\nproposal_tie_m = -0.1\n", r"pipeline\.proposal_tie_m must be >= 0"),
        ("[controller]\npredict_lead_s = 0\n", r"controller\.predict_lead_s must be >= 0\.1"),
        ("[controller]\npredict_min_height_m = -1\n", r"controller\.predict_min_height_m must be >= 0"),
        ("[controller]\nmin_calm_s = -1\n", r"controller\.min_calm_s must be >= 0"),
        ("[controller]\ncalm_wait_s = 0\n", r"controller\.calm_wait_s must be >= 0\.5"),
        ("[controller]\nrecentre_m = -1\n", r"controller\.recentre_m must be >= 0"),
        ("[controller]\nland_alt_m = -1\n", r"controller\.land_alt_m must be >= 0"),
        ("[controller]\nland_alt_m = 12\n", r"controller\.land_alt_m \(12 m\) must not be above "
                                             r"controller\.descend_alt_m \(10 m\)"),
        ("[controller]\nland_agl_m = -1\n", r"controller\.land_agl_m must be >= 0"),
        ("[controller]\nland_agl_m = 0.3\n", r"controller\.land_agl_m \(0\.3 m\) must be 0 \(off\) or from 0\.5 m"),
        ("[controller]\nland_agl_m = 4\n", r"controller\.land_agl_m \(4 m\) must be 0 \(off\) or from 0\.5 m up "
                                              r"to below the height where the LAND is commanded "
                                              r"\(controller\.land_alt_m, 4 m\)"),
        ("[controller]\nland_alt_m = 0\nland_agl_m = 10\n", r"controller\.land_alt_m, 10 m"),
        ("[pipeline]\ncalm_margin_m = -1\n", r"pipeline\.calm_margin_m must be >= 0"),
        ("[pipeline]\noccupied_trail_s = 20\n", r"pipeline\.occupied_trail_s \(20\.0 s\) must not exceed "
                                                r"pipeline\.map_memory_s"),
        ("[pipeline]\noccupied_hold_s = 20\n", r"pipeline\.occupied_hold_s \(20\.0 s\) must not exceed"),
    ],
)
def test_bad_values_name_the_key(tmp_path: Path, text: str, pattern: str) -> None:
    f = tmp_path / "c.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=pattern):
        config.load(f)


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        config.load(tmp_path / "nope.toml")
    f = tmp_path / "bad.toml"
    f.write_text("[camera\nfps = 3\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        config.load(f)


def test_overrides_and_relative_paths(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text('[model]\npath = "m/x.onnx"\n[camera]\nfps = 5\n')
    cfg = config.load(f, {"camera.fps": 12, "recorder.dir": "rec"})
    assert cfg.camera.fps == 12.0
    assert cfg.model.path == str(tmp_path / "m" / "x.onnx")
    assert cfg.recorder.dir == str(tmp_path / "rec")
    with pytest.raises(ConfigError, match="unknown key 'camera.fsp'"):
        config.load(f, {"camera.fsp": 12})


def test_parse_assignment() -> None:
    assert config.parse_assignment("camera.fps=15") == ("camera.fps", 15)
    assert config.parse_assignment("camera.source=/dev/video1") == ("camera.source", "/dev/video1")
    assert config.parse_assignment("camera.mount_offset_m=[0.1, 0, 0]") == ("camera.mount_offset_m", [0.1, 0, 0])
    assert config.parse_assignment("recorder.enabled=true") == ("recorder.enabled", True)
    with pytest.raises(ConfigError, match="key=value"):
        config.parse_assignment("camera.fps")


def test_ground_station_ids_and_the_trigger_socket_are_settings(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text('[failsafe]\ngcs_system_ids = [42, 255]\nlocal_socket = "run/trigger.sock"\n')
    cfg = config.load(f)
    assert cfg.failsafe.gcs_system_ids == [42, 255]
    assert cfg.failsafe.local_socket == str(tmp_path / "run" / "trigger.sock")  # beside the file
    for text, pattern in (("gcs_system_ids = [0]", "1..255"), ("gcs_system_ids = []", "1..255"),
                          ("gcs_system_ids = [2.5]", "list of integers")):
        f.write_text(f"[failsafe]\n{text}\n")
        with pytest.raises(ConfigError, match=rf"failsafe\.gcs_system_ids .*{pattern}"):
            config.load(f)


def test_the_signing_key_never_leaves_in_the_config_dict(tmp_path: Path) -> None:
    key = "ab" * 32
    f = tmp_path / "c.toml"
    f.write_text(f'[link]\nsigning_key = "{key}"\n')
    cfg = config.load(f)
    assert cfg.link.signing_key == key  # the service still has it
    dumped = repr(cfg.to_dict())  # what the recorder writes into meta.json
    assert key not in dumped and "<redacted>" in dumped


def test_the_trust_height_comes_from_the_setting_or_else_the_model() -> None:
    import dataclasses
    import math

    from companion.pipeline.density import DensitySpec

    spec = DensitySpec("bgr", 1 / 255, (0.0,) * 3, (1.0,) * 3, 4, 4, 0.01, 1.0, min_person_px=10.0)
    fx = 320.0 / math.tan(math.radians(35.0))  # the default camera: 640 px, 70 degrees
    assert config.landing_config(config.load()).trust_height_m == math.inf  # nobody says
    assert config.landing_config(config.load(), spec).trust_height_m == pytest.approx(1.7 + fx * 0.4 / 10.0)
    mine = config.load(overrides={"controller.min_person_px": 8})
    assert config.landing_config(mine, spec).trust_height_m == pytest.approx(1.7 + fx * 0.4 / 8.0)
    assert config.landing_config(mine, dataclasses.replace(spec, min_person_px=None)).trust_height_m == \
        pytest.approx(1.7 + fx * 0.4 / 8.0)


def test_prefer_unwalked_reaches_the_planner_and_has_the_pipeline_measure_it() -> None:
    on = config.load(None)  # the default since 2026-11-26 (docs/design.md, "Unwalked ground")
    assert config.planner_config(on).prefer_unwalked
    assert config.pipeline_config(on).unwalked
    off = config.load(None, {"controller.prefer_unwalked": False})
    assert not config.planner_config(off).prefer_unwalked
    assert not config.pipeline_config(off).unwalked


def test_the_search_settings_reach_the_controller() -> None:
    """select_empty_s (3 s by default) arrives in the controller's LandingConfig as set."""
    c = config.landing_config(config.load(None))
    assert c.select_empty_s == 3.0
    c = config.landing_config(config.load(None, {"controller.select_empty_s": 0.0}))
    assert c.select_empty_s == 0.0


def test_a_recording_flown_before_land_agl_m_existed_is_read_with_it_off() -> None:
    # Recordings hold the whole resolved config; one without controller.land_agl_m was flown
    # before the setting existed, with the LAND at land_alt_m: replay must not figure its
    # touchdowns with whatever the default is today.
    assert config.from_recording({"controller": {"land_alt_m": 4.0}}).controller.land_agl_m == 0.0
    assert config.from_recording({}).controller.land_agl_m == 0.0
    flown = config.load(None, {"controller.land_agl_m": 1.0}).to_dict()
    assert config.from_recording(flown).controller.land_agl_m == 1.0
    assert config.from_recording({}, {"controller.land_agl_m": 1.0}).controller.land_agl_m == 1.0
