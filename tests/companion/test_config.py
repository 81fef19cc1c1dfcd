"""Configuration: defaults, the documented example, and errors that name the key."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from companion import config
from companion.config import ConfigError

REPO = Path(__file__).resolve().parents[2]
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
        ("[link]\nsystem_id = 300\n", r"link\.system_id must be 1\.\.255, got 300"),
        ("[link]\nsystem_id = 1.5\n", r"link\.system_id must be an integer"),
        ("[link]\nflavour = 'inav'\n", r"link\.flavour must be one of 'auto', 'ardupilot', 'px4'"),
        ("[recorder]\nenabled = 'yes'\n", r"recorder\.enabled must be true or false"),
        ("[camera]\nmount_offset_m = [0, 0]\n", r"camera\.mount_offset_m must hold exactly 3 numbers"),
        ("[link]\nsigning_key = 'abc'\n", r"link\.signing_key was removed: .*link\.signing_key_file"),
        ("[link]\nurl = 'http://x'\n", r"link\.url must start with udpin:"),
        ("camera = 3\n", r"camera must be a table"),
        ("[camera]\nfps = nan\n", r"camera\.fps must be a finite number"),
        ("[controller]\nmin_person_px = -3\n", r"controller\.min_person_px must be >= 0"),
        ("[controller]\nmin_calm_s = -1\n", r"controller\.min_calm_s must be >= 0"),
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
    ],
)
def test_bad_values_name_the_key(tmp_path: Path, text: str, pattern: str) -> None:
    f = tmp_path / "c.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=pattern):
        config.load(f)


#: Every numeric key that had a bound when the schema still repeated the parts' rules (before
#: companion.config.compose checked them by building the parts), each with values just outside and
#: on each bound, and whether it is refused: the bounds now live in the schema (the operator's
#: limits, the stand-ins) or in the part's object (its invariants), never both, and together they
#: refuse exactly what was refused before. ``descend_alt_m = 1`` and ``land_alt_m = 200`` are
#: refused by the rule between the two (land_alt_m 4 m, descend_alt_m 10 m by default).
BOUNDS = [
    ("link.system_id", [(0, True), (1, False), (255, False), (256, True)]),
    ("link.component_id", [(0, True), (1, False), (255, False), (256, True)]),
    ("link.target_system", [(-1, True), (0, False), (255, False), (256, True)]),
    ("camera.width", [(15, True), (16, False), (8192, False), (8193, True)]),
    ("camera.height", [(15, True), (16, False), (8192, False), (8193, True)]),
    ("camera.fps", [(0.099, True), (0.1, False), (240.0, False), (240.001, True)]),
    ("camera.hfov_deg", [(0.999, True), (1.0, False), (179.0, False), (179.001, True)]),
    ("camera.fx", [(-0.001, True), (0.0, False)]),
    ("camera.fy", [(-0.001, True), (0.0, False)]),
    ("camera.cx", [(-1.001, True), (-1.0, False)]),
    ("camera.cy", [(-1.001, True), (-1.0, False)]),
    ("camera.mount_roll_deg", [(-180.001, True), (-180.0, False), (180.0, False), (180.001, True)]),
    ("camera.mount_pitch_deg", [(-180.001, True), (-180.0, False), (180.0, False), (180.001, True)]),
    ("camera.mount_yaw_deg", [(-180.001, True), (-180.0, False), (180.0, False), (180.001, True)]),
    ("camera.stall_timeout_s", [(0.099, True), (0.1, False), (60.0, False), (60.001, True)]),
    ("camera.reopen_max_backoff_s", [(0.099, True), (0.1, False), (300.0, False), (300.001, True)]),
    ("controller.select_timeout_s", [(0.499, True), (0.5, False), (600.0, False), (600.001, True)]),
    ("controller.hold_timeout_s", [(0.499, True), (0.5, False), (600.0, False), (600.001, True)]),
    ("camera.sensor_width_mm", [(-0.001, True), (0.0, False), (100.0, False), (100.001, True)]),
    ("model.threads", [(0, True), (1, False), (64, False), (65, True)]),
    ("pipeline.occupancy_threshold", [(-1.001, True), (-1.0, False)]),
    ("pipeline.head_height_m", [(-0.001, True), (0.0, False), (3.0, False), (3.001, True)]),
    ("pipeline.r0_m", [(0.099, True), (0.1, False), (100.0, False), (100.001, True)]),
    ("pipeline.proposal_tie_m", [(-0.001, True), (0.0, False), (5.0, False), (5.001, True)]),
    ("pipeline.walk_speed_mps", [(0.099, True), (0.1, False), (15.0, False), (15.001, True)]),
    ("pipeline.calm_margin_m", [(-0.001, True), (0.0, False), (50.0, False), (50.001, True)]),
    ("pipeline.person_px", [(-0.001, True), (0.0, False), (1000.0, False), (1000.001, True)]),
    ("pipeline.unlandable_threshold", [(-1.001, True), (-1.0, False), (0.999, False), (1.0, True)]),
    ("controller.min_track_age_s", [(-0.001, True), (0.0, False)]),
    ("controller.min_calm_s", [(-0.001, True), (0.0, False), (120.0, False), (120.001, True)]),
    ("controller.radius_margin_m", [(-0.001, True), (0.0, False)]),
    ("controller.steady_s", [(-0.001, True), (0.0, False), (120.0, False), (120.001, True)]),
    ("controller.descend_alt_m", [(0.999, True), (1.0, True), (200.0, False), (200.001, True)]),
    ("controller.land_alt_m", [(-0.001, True), (0.0, False), (200.0, True), (200.001, True)]),
    ("controller.land_agl_m", [(-0.001, True), (0.0, False), (200.0, True), (200.001, True)]),
    ("controller.descend_speed_mps", [(0.099, True), (0.1, False), (10.0, False), (10.001, True)]),
    ("controller.land_speed_mps", [(0.099, True), (0.1, False), (5.0, False), (5.001, True)]),
    ("controller.land_abort_above_m", [(-0.001, True), (0.0, False), (100.0, False), (100.001, True)]),
    ("controller.min_person_px", [(-0.001, True), (0.0, False), (1000.0, False), (1000.001, True)]),
    ("controller.hold_height_m", [(1.999, True), (2.0, False), (120.0, False), (120.001, True)]),
    ("controller.max_takeover_s", [(9.999, True), (10.0, False), (600.0, False), (600.001, True)]),
    ("controller.search_s", [(-0.001, True), (0.0, False), (600.0, False), (600.001, True)]),
    ("controller.search_radius_m", [(-0.001, True), (0.0, False), (500.0, False), (500.001, True)]),
    ("controller.search_reserve_s", [(-0.001, True), (0.0, False), (600.0, False), (600.001, True)]),
    ("controller.search_climb_m", [(0.999, True), (1.0, False), (50.0, False), (50.001, True)]),
    ("controller.max_alt_m", [(4.999, True), (5.0, False), (500.0, False), (500.001, True)]),
    ("controller.obey_tolerance_z_m", [(0.299, True), (0.3, False), (20.0, False), (20.001, True)]),
    ("controller.obey_tolerance_xy_m", [(0.499, True), (0.5, False), (50.0, False), (50.001, True)]),
    ("recorder.max_mb", [(0.999, True), (1.0, False)]),
    ("gcs.values_hz", [(-0.001, True), (0.0, False), (10.0, False), (10.001, True)]),
    ("live.port", [(0, True), (1, False), (65535, False), (65536, True)]),
    ("log.health_interval_s", [(0.499, True), (0.5, False), (3600.0, False), (3600.001, True)]),
]


@pytest.mark.parametrize("key, value, refused",
                         [(key, value, refused) for key, cases in BOUNDS for value, refused in cases])
def test_every_bound_is_checked_once_and_names_the_key(key: str, value: float, refused: bool) -> None:
    if not refused:
        config.load(None, {key: value})
        return
    with pytest.raises(ConfigError) as e:
        config.load(None, {key: value})
    assert key in str(e.value), str(e.value)


@pytest.mark.parametrize(
    "key, value, pattern",
    [
        ("controller.handback_action", "HOVER", r"^controller\.handback_action must be 'LAND' or 'RTL', got 'HOVER'"),
        ("failsafe.battery_level", "flat", r"^failsafe\.battery_level must be one of 'low', 'critical', 'emergency'"),
        ("link.peers", ["radio"], r"^link\.peers must list IP addresses or networks .*'radio'"),
        ("controller.descend_alt_m", 3.0, r"^controller\.land_alt_m \(4 m\) must not be above "
                                          r"controller\.descend_alt_m \(3 m\)"),
        ("controller.search_climb_m", 0.5, r"^controller\.search_climb_m must be >= LandingConfig\.ceiling_margin_m"),
        ("camera.cx", 0.0, r"^camera\.cx / camera\.fx and camera\.cy / camera\.fy through camera\.model \(the camera.s footprint\) must be > 0"),
    ],
)
def test_a_part_rule_refuses_the_setting_naming_the_key(key: str, value: object, pattern: str) -> None:
    """The rules that live only in a part's object (choices, rules between keys) still refuse a
    file at start-up, with the settings key in the part's field's place."""
    with pytest.raises(ConfigError, match=pattern):
        config.load(None, {key: value})


def test_a_lens_that_sees_none_of_its_border_is_refused_at_start_up() -> None:
    """The footprint (issue 60, item 4) walks the image border through the lens: a fisheye whose
    image circle lies inside the frame's border everywhere has no footprint to land by."""
    with pytest.raises(ConfigError, match=r"^camera: the lens sees none of its image border"):
        config.load(None, {"camera.model": "fisheye", "camera.fx": 50.0})


def test_the_parts_keep_their_own_rules_when_built_directly() -> None:
    """Tests, replay, the evaluation and the simulator build the parts themselves: a part refuses
    a bad value with its own field's name (``FieldError``, a ValueError)."""
    from companion.control.landing import LandingConfig
    from companion.invariant import FieldError

    with pytest.raises(FieldError, match=r"^controller descend_alt_m must be > 0, got -1\.0$") as e:
        LandingConfig(descend_alt_m=-1.0)
    assert e.value.field == "descend_alt_m"
    assert e.value.named({"descend_alt_m": "controller.descend_alt_m"}) == "controller.descend_alt_m must be > 0, got -1.0"
    with pytest.raises(FieldError, match=r"^controller land_alt_m \(12 m\) must not be above descend_alt_m"):
        LandingConfig(land_alt_m=12.0)


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


def test_the_signing_key_lives_in_a_file_never_in_the_config(tmp_path: Path) -> None:
    key = "ab" * 32
    f = tmp_path / "c.toml"
    f.write_text(f'[link]\nsigning_key = "{key}"\n')
    # A secret inline in the file was removed (issue 61): the message says where it goes instead.
    with pytest.raises(ConfigError, match=r"link\.signing_key was removed: .*64-hex secret in a file.*"
                                          r"link\.signing_key_file"):
        config.load(f)
    (tmp_path / "signing.key").write_text(key + "\n")
    f.write_text('[link]\nsigning_key_file = "signing.key"\n')  # relative to the config file
    cfg = config.load(f)
    assert config.signing_key(cfg) == bytes.fromhex(key)  # the service still has it
    dumped = repr(cfg.to_dict())  # what the recorder writes into meta.json
    assert key not in dumped


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


def test_unwalked_ground_is_preferred_and_the_pipeline_measures_it() -> None:
    # A constant since issue 58 (compose.PREFER_UNWALKED; docs/design.md, "Unwalked ground").
    cfg = config.load(None)
    assert config.planner_config(cfg).prefer_unwalked and config.pipeline_config(cfg).unwalked
    off = config.load(None, {"controller.min_calm_s": 0.0})
    assert not config.pipeline_config(off).calm and config.pipeline_config(off).unwalked


def test_the_search_starts_early_over_an_empty_view() -> None:
    c = config.landing_config(config.load(None))
    assert c.select_empty_s == config.SELECT_EMPTY_S == 3.0


@pytest.mark.parametrize("key", ["controller.hold_looks", "pipeline.fusion", "pipeline.tracker.motion",
                                 "controller.predict_people"])
def test_a_removed_switch_says_so_and_where_it_was_measured(tmp_path: Path, key: str) -> None:
    section, name = key.rsplit(".", 1)
    value = config.REMOVED[key].value
    f = tmp_path / "c.toml"
    f.write_text(f"[{section}]\n{name} = {'true' if value is True else 'false' if value is False else repr(value)}\n")
    with pytest.raises(ConfigError) as e:
        config.load(f)
    msg = str(e.value)
    assert msg.startswith(f"{key} was removed") and "docs/measurements.md" in msg and "unknown key" not in msg
    with pytest.raises(ConfigError, match=rf"^{re.escape(key)} was removed"):
        config.load(None, {key: value})  # --set too


def test_a_key_that_became_a_constant_says_where_it_went() -> None:
    with pytest.raises(ConfigError, match=r"^pipeline\.tracker\.mu_1 was removed: internal tuning, now "
                                          r"companion\.pipeline\.tracker\.TrackerParams\.mu_1 = 3"):
        config.load(None, {"pipeline.tracker.mu_1": 3})
    with pytest.raises(ConfigError, match=r"^controller\.arrive_radius_m was removed"):
        config.from_dict({"controller": {"arrive_radius_m": 2.0}})
    with pytest.raises(ConfigError, match=r"\[pipeline\.tracker\] was removed"):
        config.from_dict({"pipeline": {"tracker": {}}})


def test_removed_keys_are_no_keys_and_the_count_stays_lean() -> None:
    keys = {key for key, _default, _doc in config.all_keys()}
    assert not keys & set(config.REMOVED)
    # Issue 58 aims at 80 (136 before). Issue 60 adds camera.model and camera.calibration (a fisheye
    # and its calibration file): 82.
    # Issue 59 adds pipeline.person_px (the frame shrunk low over real ground): 83, and
    # pipeline.unlandable_scope (unlandable ground keeps the landing point off, not the zone): 84.
    assert len(keys) <= 84


def test_a_recording_with_removed_keys_at_the_values_flown_now_replays() -> None:
    flown = config.load(None).to_dict()
    flown["controller"].update(hold_looks=False, recentre_m=0.0, place_lookback_s=30.0)
    flown["pipeline"].update(fusion="frame", tracker={"mu_1": 3, "motion": "position"})
    flown["live"]["max_fps"] = 2.0  # the live view does not change what a replay computes
    assert config.from_recording(flown) == config.load(None)
    flown["controller"]["hold_looks"] = True
    with pytest.raises(ConfigError, match=r"flown with controller\.hold_looks = True, which was removed"):
        config.from_recording(flown)


def test_a_recording_flown_before_land_agl_m_existed_is_read_with_it_off() -> None:
    # Recordings hold the whole resolved config; one without controller.land_agl_m was flown
    # before the setting existed, with the LAND at land_alt_m: replay must not figure its
    # touchdowns with whatever the default is today.
    assert config.from_recording({"controller": {"land_alt_m": 4.0}}).controller.land_agl_m == 0.0
    assert config.from_recording({}).controller.land_agl_m == 0.0
    flown = config.load(None, {"controller.land_agl_m": 1.0}).to_dict()
    assert config.from_recording(flown).controller.land_agl_m == 1.0
    assert config.from_recording({}, {"controller.land_agl_m": 1.0}).controller.land_agl_m == 1.0


def test_a_recording_flown_before_person_px_existed_replays_on_the_full_frame() -> None:
    # Before 2026-12-07 the density model always saw the full frame; the default now shrinks it.
    assert config.load(None).pipeline.person_px == 12.0
    assert config.from_recording({"pipeline": {"r0_m": 2.0}}).pipeline.person_px == 0.0
    flown = config.load(None).to_dict()
    assert config.from_recording(flown).pipeline.person_px == 12.0
    assert config.from_recording({}, {"pipeline.person_px": 8.0}).pipeline.person_px == 8.0


def test_a_recording_flown_before_unlandable_scope_existed_keeps_zones_off_unlandable_ground() -> None:
    # Before it, a landability model on kept whole zones off unlandable ground.
    assert config.from_recording({"model": {"landability": True}}).pipeline.unlandable_scope == "zone"
    flown = config.load(None, {"pipeline.unlandable_scope": "landing_point"}).to_dict()
    assert config.from_recording(flown).pipeline.unlandable_scope == "landing_point"


def test_an_unknown_unlandable_scope_is_refused_naming_the_key() -> None:
    with pytest.raises(ConfigError, match=r"pipeline\.unlandable_scope must be one of 'zone', 'landing_point'"):
        config.load(None, {"pipeline.unlandable_scope": "roof"})
