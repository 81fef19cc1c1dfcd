"""The composition: the one place where validated settings (``companion.config.schema.Config``)
become each part's own configuration objects. The service, replay and the simulator call these,
so a setting has one name and one meaning everywhere.

It is also where the parts' own rules check a configuration: each part's object refuses what it
cannot fly with in its ``__post_init__`` (``companion.invariant.FieldError``), and the tables
below say which settings key each field came from, so that ``load`` (``checked``) refuses a bad
value at start-up naming the key (``controller.descend_alt_m must be > 0, got -1.0``). The
schema does not repeat those rules.

A part's tuning that is no setting keeps its value here or in the part's own dataclass default:
the core's dataclasses default to the paper's rules (tests and the evaluation use them), and the
service's choices where they differ are the named constants below.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar, cast

from companion.config import schema
from companion.config.schema import Config, ConfigError
from companion.control.landing import LandingConfig, person_trust_height
from companion.control.obedience import ObedienceConfig
from companion.control.planner import PlannerConfig
from companion.control.touchdown import DescentProfile
from companion.geometry import calibration
from companion.geometry.camera import GeometryError, Intrinsics, Mount
from companion.invariant import FieldError
from companion.mavlink.clock import MAX_TELEMETRY_LAG_S, AutopilotClock
from companion.mavlink.failsafe import FailsafeConfig
from companion.mavlink.gcs_commands import CameraInfo
from companion.mavlink.link import POSE_RATE_HZ, LinkConfig, message_rates
from companion.mavlink.state import MAX_POSE_AGE_S
from companion.pipeline.density import DensitySpec, resolve_threshold
from companion.pipeline.occupancy import OccupancyParams
from companion.pipeline.riskmap import RiskMapConfig
from companion.pipeline.slz import PipelineConfig
from companion.pipeline.tracker import GROUND_MOTION, GROUND_SIGMA_V, TrackerParams

#: Among calm zones the planner chooses first the one whose ground has gone longest without
#: anybody seen on it since the camera first saw it, then the oldest (docs/design.md, "Unwalked
#: ground"; the core's ``PlannerConfig`` keeps the paper's age order by default).
PREFER_UNWALKED = True
#: With nothing in view since the trigger that could become a zone (none of r0 or more), the
#: search starts this long after the trigger (s) instead of at ``select_timeout_s``: each second
#: of waiting over a crowd costs about a metre of height and of view.
SELECT_EMPTY_S = 3.0
#: The landing point goes where the risk map saw people farthest away within this many seconds,
#: and moves there again before the zone is judged when that is ``PLACE_GAIN_M`` farther from
#: them (docs/design.md, "Where people walked").
PLACE_LOOKBACK_S = 30.0


def _keys(section: str, *names: str, **renamed: str) -> dict[str, str]:
    """Field -> settings key: ``names`` are called so in ``section``, ``renamed`` maps field=key."""
    return {**{n: f"{section}.{n}" for n in names}, **renamed}


#: Which settings key each part's field is made from (a field missing is no setting, or derived).
LANDING_KEYS = _keys("controller", "select_timeout_s", "hold_timeout_s", "descend_alt_m", "land_abort_above_m", "hold_height_m", "max_takeover_s",
                     "land_alt_m", "land_agl_m", "handback_action", "search_climb_m", "max_alt_m", "search_s",
                     "search_radius_m", "search_reserve_s",
                     view_ratio="camera.cx / camera.fx and camera.cy / camera.fy through camera.model (the camera's footprint)",
                     trust_height_m="the height people are trusted below (controller.min_person_px)",
                     ceiling_margin_m="LandingConfig.ceiling_margin_m")
PLANNER_KEYS = _keys("controller", "radius_margin_m", "min_track_age_s", "min_calm_s", "steady_s",
                     r0_m="pipeline.r0_m")
OBEDIENCE_KEYS = _keys("controller", tolerance_z_m="controller.obey_tolerance_z_m",
                       tolerance_xy_m="controller.obey_tolerance_xy_m")
#: ``land_alt_m`` is ``controller.land_alt_m``, or ``descend_alt_m`` where that is 0.
DESCENT_KEYS = _keys("controller", "descend_speed_mps", "land_alt_m", "land_speed_mps",
                     walk_speed_mps="pipeline.walk_speed_mps")
PIPELINE_KEYS = _keys("pipeline", "head_height_m", "r0_m", "proposal_tie_m", "calm_margin_m", "person_px",
                      surface_threshold="pipeline.unlandable_threshold",
                      surface_scope="pipeline.unlandable_scope")
RISK_KEYS = _keys("pipeline", "walk_speed_mps")
OCCUPANCY_KEYS = _keys("pipeline", threshold="pipeline.occupancy_threshold")
LINK_KEYS = _keys("link", "system_id", "component_id", "target_system", "peers")
FAILSAFE_KEYS = _keys("failsafe", "battery_level", "gcs_system_ids")

_Part = TypeVar("_Part")


def _made(keys: Mapping[str, str], make: Callable[..., _Part], *args: Any, **kwargs: Any) -> _Part:
    """``make(*args, **kwargs)``, a part's object; a field it refuses is a ConfigError naming the
    settings key ``keys`` gives for it (the part's own name for it where none)."""
    try:
        return make(*args, **kwargs)
    except FieldError as exc:
        raise ConfigError(exc.named(keys) if exc.field in keys else str(exc)) from None


def threshold_setting(cfg: Config) -> float | None:
    """``pipeline.occupancy_threshold`` with TOML's stand-in for "not set" (-1) turned into None,
    for ``companion.pipeline.density.resolve_threshold``."""
    value = cfg.pipeline.occupancy_threshold
    return None if value < 0 else value


def intrinsics(cfg: Config) -> Intrinsics:
    """The camera (``geometry.camera.Intrinsics``: matrix, lens model and distortion) for
    ``camera.width x camera.height``: from ``camera.calibration`` when set (the file is read and
    checked here: ConfigError naming the key), else from the fx..distortion keys or hfov_deg."""
    c = cfg.camera
    if c.calibration:
        return _calibrated(cfg)
    base = Intrinsics.from_fov(c.width, c.height, c.hfov_deg, c.model)
    fx = c.fx or base.fx
    fy = c.fy or fx
    cx = base.cx if c.cx < 0 else c.cx
    cy = base.cy if c.cy < 0 else c.cy
    try:
        return Intrinsics(fx, fy, cx, cy, c.width, c.height, tuple(c.distortion), c.model)
    except GeometryError as exc:
        raise ConfigError(f"camera.distortion: {exc}") from None


def _calibrated(cfg: Config) -> Intrinsics:
    c = cfg.camera
    key = f"camera.calibration {c.calibration}"
    if c.fx or c.fy or c.cx >= 0 or c.cy >= 0 or c.distortion:
        raise ConfigError(f"{key}: camera.fx, fy, cx, cy and distortion must stay unset with a calibration "
                          "file (it holds them)")
    try:
        cal = calibration.load(c.calibration)
    except calibration.CalibrationError as exc:
        raise ConfigError(f"{key}: {exc}") from None
    if (cal.width, cal.height) != (c.width, c.height):
        raise ConfigError(f"{key}: the calibration is for {cal.width}x{cal.height} but camera.width x "
                          f"camera.height is {c.width}x{c.height}")
    if cal.fisheye is not None and cal.fisheye != (c.model == "fisheye"):
        raise ConfigError(f"{key}: the file is a {'fisheye' if cal.fisheye else 'pinhole'} calibration "
                          f"but camera.model is {c.model}")
    if c.model == "fisheye" and len(cal.dist) != 4:
        raise ConfigError(f"{key}: a fisheye (camera.model) takes 4 distortion coefficients (k1..k4), "
                          f"the file holds {len(cal.dist)}")
    K = cal.camera_matrix
    try:
        return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), c.width, c.height,
                          cal.dist, c.model)
    except GeometryError as exc:
        raise ConfigError(f"{key}: {exc}") from None


def mount(cfg: Config) -> Mount:
    """The camera mount (``geometry.camera.Mount``) from ``camera.mount_*``."""
    c = cfg.camera
    offset = cast("tuple[float, float, float]", tuple(c.mount_offset_m))  # length 3: validated
    return Mount.from_degrees(c.mount_roll_deg, c.mount_pitch_deg, c.mount_yaw_deg, offset)


def pipeline_config(cfg: Config, model_spec: DensitySpec | None = None) -> PipelineConfig:
    """The pipeline's ``PipelineConfig``; the occupancy threshold resolved against the model's
    ``DensitySpec`` (``resolve_threshold``: the setting, else the model's, else 0). Posed frames
    in the world frame: zones are ground (the tracker's ``GROUND_MOTION``)."""
    p = cfg.pipeline
    planner = planner_config(cfg)
    return _made(
        PIPELINE_KEYS, PipelineConfig,
        occupancy=_made(OCCUPANCY_KEYS, OccupancyParams,
                        threshold=resolve_threshold(threshold_setting(cfg), model_spec)),
        tracker=TrackerParams(motion=GROUND_MOTION, sigma_v=GROUND_SIGMA_V),
        head_height_m=p.head_height_m,
        r0_m=p.r0_m,
        proposal_tie_m=p.proposal_tie_m,
        person_px=p.person_px,
        calm=cfg.controller.min_calm_s > 0,
        calm_margin_m=p.calm_margin_m,
        unwalked=planner.prefer_unwalked,
        surface_threshold=None if p.unlandable_threshold < 0 else p.unlandable_threshold,
        surface_scope=p.unlandable_scope,
        steady_margin_m=planner.steady_margin_m if planner.steady_s > 0 else None,
        risk=_made(RISK_KEYS, RiskMapConfig, walk_speed_mps=p.walk_speed_mps),
    )


def descent_profile(cfg: Config) -> DescentProfile:
    """How long a descent from a height takes, and how far a walker gets meanwhile."""
    c = cfg.controller
    return _made(DESCENT_KEYS, DescentProfile, descend_speed_mps=c.descend_speed_mps,
                 land_alt_m=c.land_alt_m or c.descend_alt_m, land_speed_mps=c.land_speed_mps,
                 walk_speed_mps=cfg.pipeline.walk_speed_mps)


def planner_config(cfg: Config) -> PlannerConfig:
    """The ``PlannerConfig``: the one rule for which zone is the target (flight and replay)."""
    c = cfg.controller
    return _made(PLANNER_KEYS, PlannerConfig, r0_m=cfg.pipeline.r0_m, radius_margin_m=c.radius_margin_m,
                 min_track_age_s=c.min_track_age_s, min_calm_s=c.min_calm_s,
                 prefer_unwalked=PREFER_UNWALKED, steady_s=c.steady_s)


def landing_config(cfg: Config, model_spec: DensitySpec | None = None) -> LandingConfig:
    """The landing controller's ``LandingConfig``; ``model_spec`` gives the model's smallest
    reliably seen person (``min_person_px``) when ``controller.min_person_px`` is 0."""
    c = cfg.controller
    min_px = c.min_person_px or (model_spec.min_person_px if model_spec is not None else None)
    k = intrinsics(cfg)
    try:
        ratio = k.seen_ratio()
    except GeometryError as exc:
        raise ConfigError(f"camera: {exc}") from None
    return _made(
        LANDING_KEYS, LandingConfig,
        planner=planner_config(cfg),
        select_timeout_s=c.select_timeout_s, select_empty_s=SELECT_EMPTY_S, hold_timeout_s=c.hold_timeout_s,
        descend_alt_m=c.descend_alt_m,
        land_abort_above_m=c.land_abort_above_m, hold_height_m=c.hold_height_m, max_takeover_s=c.max_takeover_s,
        land_alt_m=c.land_alt_m, land_agl_m=c.land_agl_m, max_pose_age_s=MAX_POSE_AGE_S,
        handback_action=c.handback_action, search_climb_m=c.search_climb_m, max_alt_m=c.max_alt_m,
        obedience=_made(OBEDIENCE_KEYS, ObedienceConfig, tolerance_z_m=c.obey_tolerance_z_m,
                        tolerance_xy_m=c.obey_tolerance_xy_m),
        descent=descent_profile(cfg),
        search_s=c.search_s, search_radius_m=c.search_radius_m, search_reserve_s=c.search_reserve_s,
        place_lookback_s=PLACE_LOOKBACK_S,
        view_ratio=ratio,
        trust_height_m=person_trust_height(min(k.fx, k.fy), min_px or None, head_m=cfg.pipeline.head_height_m),
    )


def signing_key(cfg: Config) -> bytes | None:
    """The 32-byte MAVLink signing secret from ``link.signing_key_file`` (None when it is empty);
    ConfigError naming the file when it cannot be read or holds no key."""
    text = ""
    if cfg.link.signing_key_file:
        try:
            text = Path(cfg.link.signing_key_file).read_text().strip()
        except OSError as exc:
            raise ConfigError(f"link.signing_key_file {cfg.link.signing_key_file}: {exc.strerror}") from None
        if len(text) != 64 or any(ch not in "0123456789abcdefABCDEF" for ch in text):
            raise ConfigError(f"link.signing_key_file {cfg.link.signing_key_file} must hold 64 "
                              "hexadecimal characters")
    return bytes.fromhex(text) if text else None


def camera_info(cfg: Config) -> CameraInfo:
    """What CAMERA_INFORMATION tells a ground station of the camera: the calibrated resolution,
    and, when ``camera.sensor_width_mm`` is set, the focal length and sensor size in millimetres
    from the intrinsics (pixel pitch = sensor width / width; fy sets the vertical pitch)."""
    c = cfg.camera
    k = intrinsics(cfg)
    focal = sensor_w = sensor_h = math.nan
    if c.sensor_width_mm > 0:
        pitch_x = c.sensor_width_mm / k.width
        focal = k.fx * pitch_x
        sensor_w = c.sensor_width_mm
        sensor_h = k.height * focal / k.fy
    return CameraInfo(width=k.width, height=k.height, focal_length_mm=focal, sensor_width_mm=sensor_w,
                      sensor_height_mm=sensor_h)


def link_config(cfg: Config) -> LinkConfig:
    """The MAVLink link's ``LinkConfig`` (reads the signing key file)."""
    return _link_config(cfg, signing_key(cfg))


def _link_config(cfg: Config, key: bytes | None) -> LinkConfig:
    c = cfg.link
    return _made(
        LINK_KEYS, LinkConfig,
        url=c.url, system_id=c.system_id, component_id=c.component_id,
        target_system=c.target_system or None, signing_key=key,
        message_rates_hz=message_rates(POSE_RATE_HZ), peers=tuple(c.peers),
    )


def autopilot_clock(cfg: Config) -> AutopilotClock:
    """The clock that places telemetry in time, with the lag limit ``MAX_TELEMETRY_LAG_S``."""
    # A TIMESYNC round trip is two one-way trips: one slower than twice the lag allowed would
    # only say that every sample is late.
    return AutopilotClock(max_lag_s=MAX_TELEMETRY_LAG_S, max_rtt_s=2.0 * MAX_TELEMETRY_LAG_S)


def frame_budget_ms(cfg: Config) -> float:
    """A median pipeline time per frame above this reports 'model slow': the camera's frame
    period (ms), the time one frame has before the next arrives."""
    return 1000.0 / cfg.camera.fps


def failsafe_config(cfg: Config) -> FailsafeConfig:
    """The failsafe monitor's ``FailsafeConfig``."""
    f = cfg.failsafe
    return _made(FAILSAFE_KEYS, FailsafeConfig, battery=f.battery, battery_level=f.battery_level,
                 system_status=f.system_status, autopilot_land=f.autopilot_land, gcs_command=f.gcs_command,
                 local_trigger=f.local_trigger, gcs_system_ids=tuple(f.gcs_system_ids),
                 local_socket=f.local_socket or None)


def checked(cfg: Config) -> Config:
    """``cfg`` once every part's object made from it accepts its values (their rules are not
    repeated in the schema); else a ConfigError naming the key. Reads one file, the camera's
    calibration (``camera.calibration``); the signing key file is read when the link is made
    (``link_config``; ``companion check-config`` does)."""
    try:
        landing_config(cfg)
        pipeline_config(cfg)
        mount(cfg)
        _link_config(cfg, None)
        failsafe_config(cfg)
    except ConfigError:
        raise
    except ValueError as exc:  # a rule of a part no field names: still exit 2, not a traceback
        raise ConfigError(f"the settings make no valid part: {exc}") from None
    return cfg


def load(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """``schema.load`` (the file's rules) and ``checked`` (the parts'): the settings
    ``companion run`` starts with, or a ConfigError naming the key."""
    return checked(schema.load(path, overrides))


def from_dict(raw: Mapping[str, Any], source: Path | None = None) -> Config:
    """``schema.from_dict`` and ``checked``: a validated :class:`Config` from nested TOML-like data."""
    return checked(schema.from_dict(raw, source))


def from_recording(meta_config: Mapping[str, Any], overrides: Mapping[str, Any] | None = None) -> Config:
    """``schema.from_recording`` and ``checked``: the settings a recording was flown with."""
    return checked(schema.from_recording(meta_config, overrides))


__all__ = [
    "PREFER_UNWALKED", "SELECT_EMPTY_S", "PLACE_LOOKBACK_S", "threshold_setting", "intrinsics", "mount",
    "pipeline_config", "descent_profile", "planner_config", "landing_config", "signing_key", "camera_info",
    "link_config", "autopilot_clock", "frame_budget_ms", "failsafe_config", "checked", "load", "from_dict",
    "from_recording", "LANDING_KEYS", "PLANNER_KEYS", "OBEDIENCE_KEYS", "DESCENT_KEYS", "PIPELINE_KEYS",
    "RISK_KEYS", "OCCUPANCY_KEYS", "LINK_KEYS", "FAILSAFE_KEYS",
]
