"""The settings' schema: every key a user sets, its type, default and help, read from a TOML file
and ``--set`` overrides, and the rules only the file knows.

Every key has a built-in default, so ``companion run`` with no file flies against the simulator's
defaults. A file only needs the keys it changes. Validation happens once, before anything opens a
socket or a camera, and every problem is reported as a :class:`ConfigError` whose message names
the key (``camera.fps``) and what is allowed, so an integrator reading ``journalctl`` knows what
to fix; a key that was removed (:data:`REMOVED`) says so and where it went.
``companion.example.toml`` at the repository root documents every key.

Each rule lives in one place. Here: that a key exists, its TOML type, finite numbers, list
lengths, the names a file spells (``link.flavour``), the stand-ins for "not set" (``-1``, ``0``),
the operator's limits no part has (``camera.fps`` up to 240), and the rules of keys no part's
object checks (``link.url``, ``live.address``, the signing key). A part's own invariants (a
speed > 0, ``land_alt_m`` not above ``descend_alt_m``) live in its configuration object's
``__post_init__``; ``companion.config.compose`` builds those objects from a :class:`Config` and
names the key of a field they refuse. ``companion.config.load`` (and ``from_dict``,
``from_recording``) run both; this module's functions of those names only the file's rules.

Units are in the key names where they matter (``_s`` seconds, ``_m`` metres, ``_deg`` degrees,
``_mb`` mebibytes); angles are converted to radians only when handed to the pipeline.
"""

from __future__ import annotations

import functools
import importlib.resources
import json
import math
import platform
import re
import sys
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from companion.config.removed import REMOVED, REMOVED_TABLES
from companion.mavlink.transports import TransportError, parse_url

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (NVIDIA JetPack 6): tomli is the package tomllib was taken from
    import tomli as tomllib


def _packaged(name: str) -> Path:
    """A model file shipped as package data in ``companion/models/``."""
    return Path(str(importlib.resources.files("companion") / "models" / name))


#: Version 4 (MODEL_CARD.md) is shipped in two layouts with the same map: as trained, and with
#: its concatenated channels in whole blocks of 16 (``companion.training.layout``), which keeps
#: onnxruntime's blocked convolutions (NCHWc) through the concatenation on x86-64: about 10 % less
#: density time on the development machine, and 7 % more on a CPU that does not block
#: (onnxruntime's ARM builds without their NEON NCHWc kernels), where the plain file is taken.
PLAIN_MODEL = _packaged("slz-density-v4.onnx")
X86_MODEL = _packaged("slz-density-v4-x86.onnx")
#: ``platform.machine()`` names (lower case) of the CPUs whose onnxruntime blocks convolutions:
#: mlas sets its NCHWc block size on 64-bit x86 only.
BLOCKED_MACHINES = frozenset({"x86_64", "amd64"})


def shipped_model(machine: str | None = None) -> Path:
    """The shipped density model for ``machine`` (``platform.machine()``; default: this one): the
    blocked layout on 64-bit x86 where the package has it, else the plain file."""
    name = (platform.machine() if machine is None else machine).lower()
    return X86_MODEL if name in BLOCKED_MACHINES and X86_MODEL.is_file() else PLAIN_MODEL


#: The shipped density model: package data in ``companion/models/``, so it is found the same way
#: in a source checkout, an editable install and an installed wheel (``pip install .`` from any
#: directory). The one definition the service, replay, evaluation and the benchmark use. A wheel is
#: always unpacked on disk, so the resource is a real file onnxruntime can open by path.
SHIPPED_MODEL = shipped_model()
#: The shipped landability model (water, vehicles, trees, roofs, ...: ground that is no place to
#: land), beside the density model; ``model.landability`` switches it on.
SHIPPED_LANDABILITY = _packaged("slz-landability.onnx")
#: Whether the landability model runs unless the configuration says otherwise: on since
#: 2026-12-07, in the landing-point scope with the water, vehicle and obstacle levels
#: (``pipeline.unlandable_scope``, ``pipeline.unlandable_levels``): on the photo world that keeps
#: the vehicle off roofs at no cost in clear landings; keeping whole zones off unlandable ground,
#: or counting trees, cost them far beyond chance (companion/models/LANDABILITY_CARD.md, "On the
#: photo world"; docs/photo-world.md; docs/design.md, step 1b).
LANDABILITY_DEFAULT = True

FLAVOURS = ("auto", "ardupilot", "px4")
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


class ConfigError(ValueError):
    """A configuration problem; the message names the key and what is allowed."""


def _f(default: Any, doc: str = "", *, min: float | None = None, max: float | None = None,
       choices: tuple[Any, ...] | None = None, min_exclusive: bool = False, length: int | None = None,
       path: bool = False) -> Any:
    """A config field: default plus the file's checks of it (kept next to the key): ``min``/``max``
    are the operator's limits and the stand-ins' floor, where no part's object already refuses the
    value (companion.config.compose)."""
    meta = {"doc": doc, "min": min, "max": max, "choices": choices, "min_exclusive": min_exclusive,
            "length": length, "path": path}
    if isinstance(default, (list, dict)):
        return field(default_factory=functools.partial(type(default), default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class LinkSettings:
    """MAVLink connection to the flight controller."""

    url: str = _f("udpin:127.0.0.1:14550", "udpin:HOST:PORT, udpout:, tcp:, tcpin:, serial:/dev/ttyX:BAUD")
    system_id: int = _f(1, "our MAVLink system id (normally the vehicle's)")
    component_id: int = _f(191, "our component id (191 = onboard computer)")
    target_system: int = _f(1, "autopilot system id (SYSID_THISMAV / MAV_SYS_ID); 0 = the first autopilot "
                               "heard, which anyone on the link could be")
    flavour: str = _f("auto", "autopilot dialect", choices=FLAVOURS)
    signing_key_file: str = _f("", "file (mode 0600) holding the 64-hex MAVLink 2 signing secret; empty = "
                                    "unsigned", path=True)
    require_signing: bool = _f(False, "refuse to start without a signing key (docs/signing.md); unsigned, "
                                      "the service warns at start and at every link-up")
    peers: list[str] = _f([], "UDP links: IP addresses or CIDR networks allowed to talk to the companion "
                              "(a ground station sharing the port); empty = any until the autopilot is "
                              "heard, then its address alone")


@dataclass(frozen=True)
class CameraSettings:
    """Camera source, calibration and mount."""

    source: str = _f("http://127.0.0.1:8080/stream.mjpg",
                     "/dev/video0, a device index, a video file, a folder of frames, rtsp:// or "
                     "http:// (MJPEG) URL, or a GStreamer pipeline (gst: ... ! appsink)")
    width: int = _f(640, "frame width the calibration is for (px); frames of another size are rescaled",
                    min=16, max=8192)
    height: int = _f(480, "frame height the calibration is for (px)", min=16, max=8192)
    fps: float = _f(10.0, "frame rate asked of the device; pace of files and folders", min=0.1, max=240.0)
    model: str = _f("pinhole", "lens model: pinhole (OpenCV's distortion) or fisheye (OpenCV's equidistant "
                                "cv2.fisheye, distortion k1..k4)", choices=("pinhole", "fisheye"))
    calibration: str = _f("", "calibration file written by OpenCV (FileStorage YAML/XML/JSON: camera_matrix, "
                              "distortion_coefficients, image_width/height); wins over hfov_deg, and fx..distortion "
                              "must then stay unset", path=True)
    hfov_deg: float = _f(70.0, "horizontal field of view used when fx/fy are 0 (the simulator's is 70)", min=1.0, max=179.0)
    fx: float = _f(0.0, "focal length x (px); 0 = from hfov_deg", min=0.0)
    fy: float = _f(0.0, "focal length y (px); 0 = same as fx", min=0.0)
    cx: float = _f(-1.0, "principal point x (px); -1 = image centre", min=-1.0)
    cy: float = _f(-1.0, "principal point y (px); -1 = image centre", min=-1.0)
    distortion: list[float] = _f([], "OpenCV distortion k1, k2, p1, p2[, k3...]; empty = none")
    mount_roll_deg: float = _f(0.0, "camera mount roll relative to the body (deg)", min=-180.0, max=180.0)
    mount_pitch_deg: float = _f(-90.0, "camera mount pitch (deg); -90 = straight down", min=-180.0, max=180.0)
    mount_yaw_deg: float = _f(0.0, "camera mount yaw (deg)", min=-180.0, max=180.0)
    mount_offset_m: list[float] = _f([0.0, 0.0, 0.0], "camera position in body FRD (m)", length=3)
    stall_timeout_s: float = _f(2.0, "no frame for this long = camera stalled, reopen", min=0.1, max=60.0)
    reopen_max_backoff_s: float = _f(10.0, "longest wait between reopen attempts", min=0.1, max=300.0)
    loop: bool = _f(False, "restart a video file or folder at its end (bench tests)")
    sensor_width_mm: float = _f(0.0, "image sensor width (mm), for the focal length in mm a ground station "
                                     "is told (CAMERA_INFORMATION); 0 = unknown", min=0.0, max=100.0)


@dataclass(frozen=True)
class ModelSettings:
    """The ONNX density model."""

    path: str = _f(str(SHIPPED_MODEL), "ONNX density model file; empty = the model shipped in the package",
                   path=True)
    threads: int = _f(2, "onnxruntime intra-op threads", min=1, max=64)
    overrides: dict[str, Any] = _f({}, "settings that win over the model's metadata (color, scale, ...)")
    landability: bool = _f(LANDABILITY_DEFAULT, "also keep landing points (or zones) off unlandable ground "
                                                "(water, vehicles, roofs, walls, ...) with the landability model")
    landability_path: str = _f(str(SHIPPED_LANDABILITY), "ONNX landability model file; empty = the model shipped "
                                                         "in the package", path=True)


@dataclass(frozen=True)
class PipelineSettings:
    """Safe-landing-zone pipeline: what is occupied, how far people walk, what is unlandable."""

    occupancy_threshold: float = _f(-1.0, "density above min(D) marking a pixel occupied; "
                                          "-1 = not set: the model's validated value, else 0", min=-1.0)
    head_height_m: float = _f(1.7, "height of the head plane above the ground (m)", max=3.0)
    r0_m: float = _f(2.0, "smallest useful landing-zone radius (m)", min=0.1, max=100.0)
    proposal_tie_m: float = _f(0.3, "a proposal may give up this much radius to sit nearer the ground under "
                                    "the camera (m; 0 = the paper's first largest circle)", max=5.0)
    person_px: float = _f(12.0, "through a pinhole, shrink each frame before the density model (and the landability "
                                "model) so that the smallest person (0.4 m) still spans this many pixels: low over "
                                "real ground the full frame shows the models the ground's grain, which they take for "
                                "people, roofs and walls (px; 0 = always the full frame, as before 2026-12-07)", max=1000.0)
    walk_speed_mps: float = _f(1.5, "how fast a person may walk (m/s): risk grows this fast from where "
                                    "someone was seen (1.34 m/s is the mean, Weidmann 1993)",
                               min=0.1, max=15.0)
    calm_margin_m: float = _f(1.0, "a zone is calm when nobody has been seen within r0 plus this of it while "
                                   "watched (m; controller.min_calm_s)", max=50.0)
    unlandable_levels: list[str] = _f(["water", "vehicles", "obstacles"],
                                      "risk levels of the landability model that keep landing points off the ground; "
                                      "empty = every level but the model's landable one")
    unlandable_threshold: float = _f(-1.0, "probability of the unlandable levels above which a cell is "
                                           "unlandable; -1 = the model's validated value", min=-1.0, max=0.999)
    unlandable_scope: str = _f("landing_point", "what unlandable ground keeps off: zone = the whole zone (its radius is the "
                                       "free ground of people and ground together), landing_point = only the landing "
                                       "point and 0.5 m around it (the zone's radius is people's alone)",
                                 choices=("zone", "landing_point"))


@dataclass(frozen=True)
class FailsafeSettings:
    """Which telemetry events trigger a safe landing."""

    battery: bool = _f(True, "battery charge state LOW/CRITICAL/EMERGENCY")
    battery_level: str = _f("critical", "lowest battery state that triggers")
    system_status: bool = _f(True, "heartbeat system_status CRITICAL/EMERGENCY")
    autopilot_land: bool = _f(True, "the autopilot switches itself to LAND or RTL")
    gcs_command: bool = _f(True, "an explicit command from the ground station")
    local_trigger: bool = _f(True, "SIGUSR1 to the service triggers (bench tests)")
    gcs_system_ids: list[int] = _f([255], "system ids whose MAV_CMD_USER_1 trigger is accepted (1..255)")
    local_socket: str = _f("", "Unix socket taking 'trigger [reason]' lines; empty = none", path=True)


@dataclass(frozen=True)
class ControllerSettings:
    """The landing decision's heights, speeds, margins and limits."""

    min_track_age_s: float = _f(1.0, "a zone must have been tracked this long to be a target (s; 0 for a "
                                     "replay of a clip shorter than that)")
    min_calm_s: float = _f(5.0, "the ground around a landing point (r0 plus pipeline.calm_margin_m) must have "
                                "been watched and seen free this long before the LAND; calm zones are chosen "
                                "first (s; 0 = not required, the paper's rule; docs/design.md)", max=120.0)
    radius_margin_m: float = _f(2.0, "zone radius must exceed r0 plus this margin to be chosen (m); once chosen it "
                                     "is kept, and the LAND commanded, while r0 stays free around the landing "
                                     "point, and its landing point stays put while the zone holds r0 plus this "
                                     "around it")
    steady_s: float = _f(8.0, "a zone smaller than r0 plus radius_margin_m may still be chosen once every frame for "
                              "this long has seen r0 plus 0.5 m free round the same point: its edge is something "
                              "that does not walk into it (a tree or a bench on a lawn, a crowd that keeps off "
                              "it); that steady watch stands for the calm ground under the vehicle (s; 0 = never; "
                              "docs/design.md, 'Steady zones')", max=120.0)
    descend_alt_m: float = _f(10.0, "altitude above home at which the zone is judged (calm ground) before the "
                                     "LAND (m): where the camera still sees r0 plus radius_margin_m all round; "
                                     "the LAND itself is commanded at land_alt_m", min=1.0, max=200.0)
    land_alt_m: float = _f(4.0, "height at which the autopilot's LAND takes over (m): once the zone is judged "
                                "at descend_alt_m (calm ground), the companion's own stepped descent goes on "
                                "over it to this height, the ground under the vehicle re-checked every frame "
                                "(somebody within r0: HOLD); a shorter slow LAND leaves walkers less time to "
                                "reach the landing point; 0 = LAND at descend_alt_m (docs/design.md)",
                          max=200.0)
    land_agl_m: float = _f(0.0, "with a fresh downward rangefinder, the LAND commanded at land_alt_m is first "
                                "the companion's own committed descent, straight down at descend_speed_mps, to "
                                "this height above the ground the rangefinder measures, and the autopilot's "
                                "slower LAND only there (m); without a fresh rangefinder, or when it goes stale "
                                "or out of range on the way, the LAND at once; 0 = off, the default (docs/design.md, "
                                "\"The last metres by the rangefinder\": measured, and why it stays off); "
                                "1 m is the value measured")
    descend_speed_mps: float = _f(1.5, "how fast the stepped descent comes down (m/s; ArduPilot WPNAV_SPEED_DN, "
                                       "PX4 MPC_Z_VEL_MAX_DN): the time to touchdown", min=0.1, max=10.0)
    land_speed_mps: float = _f(0.5, "the autopilot's LAND descent speed (m/s; ArduPilot LAND_SPEED 50 cm/s, "
                                    "PX4 MPC_LAND_SPEED 0.7): the time to touchdown", min=0.1, max=5.0)
    land_abort_above_m: float = _f(3.5, "during LAND, a lost zone above this height sends the vehicle "
                                        "back to HOLD; below it the landing is committed (m)", min=0.0, max=100.0)
    min_person_px: float = _f(0.0, "people must look at least this many pixels across (the longer side of "
                              "their box from above) for the model's free to be trusted: above the height "
                              "where a 0.4 m person looks smaller, the vehicle approaches no higher and "
                              "judges the zone only below it; 0 = the model's own (metadata "
                              "companion.min_person_px), or no limit when it has none", min=0.0, max=1000.0)
    hold_height_m: float = _f(15.0, "on a lost zone the vehicle holds at least this high above the "
                              "ground, where the camera sees enough to confirm a zone again", min=2.0, max=120.0)
    max_takeover_s: float = _f(90.0, "not landed this long after the trigger: hand back to the "
                               "autopilot's own failsafe", min=10.0, max=600.0)
    handback_action: str = _f("LAND", "what the autopilot is asked to do on handback")
    select_timeout_s: float = _f(10.0, "no safe zone this long after the trigger: search (search_s), or hand back when "
                                       "searching is off or out of time (s)", min=0.5, max=600.0)
    hold_timeout_s: float = _f(15.0, "holding without a safe zone this long: search (search_s), or hand back when "
                                     "searching is off or out of time (s)", min=0.5, max=600.0)
    search_s: float = _f(45.0, "with no zone in view at the SELECT or HOLD timeout, search this long (s) "
                         "before handing back: climb to the ceiling, then fly an expanding square; 0 = "
                         "hand back at once, as before (with steady_s, a look at a glimpse whose steady "
                         "watch runs is finished, at most steady_s more)", max=600.0)
    search_radius_m: float = _f(40.0, "the search goes no further than this from where it starts (m)",
                                max=500.0)
    search_reserve_s: float = _f(30.0, "stop searching (hand back) when the battery's time left, as the "
                                 "autopilot reports it, is less than the landing needs plus this (s)",
                                 max=600.0)
    search_climb_m: float = _f(5.0, "the ceiling: the vehicle is never sent more than this above its "
                               "altitude at the trigger (m); above it, control goes back to LAND",
                               max=50.0)
    max_alt_m: float = _f(120.0, "the ceiling is never above this altitude above home (m)", min=5.0, max=500.0)
    obey_tolerance_z_m: float = _f(1.0, "a vehicle further than this above or below its target than it "
                                   "has shown it can be is handed back to LAND (m)", min=0.3, max=20.0)
    obey_tolerance_xy_m: float = _f(2.0, "a vehicle further than this from its target than it has shown "
                                    "it can be is handed back to LAND (m)", min=0.5, max=50.0)
    shadow: bool = _f(False, "shadow mode: watch, decide and report (STATUSTEXT 'SHADOW: ...', the "
                             "recording) but never send a mode or position command (companion run --shadow)")


@dataclass(frozen=True)
class RecorderSettings:
    """Flight recorder."""

    enabled: bool = _f(False, "record frames, poses, telemetry and decisions")
    dir: str = _f("/var/lib/companion/recordings", "where recordings go (one folder per run)", path=True)
    max_mb: float = _f(2048.0, "disk budget for everything recorded in dir (video, frame index, events); "
                       "oldest files deleted first (MiB)", min=1.0)


@dataclass(frozen=True)
class GcsSettings:
    """What the ground station sees: health in the heartbeat, STATUSTEXT, named values."""

    values_hz: float = _f(1.0, "rate of the NAMED_VALUE_FLOAT/INT numbers a ground station plots "
                               "(docs/ground-station-values.md); 0 = none", min=0.0, max=10.0)


@dataclass(frozen=True)
class LiveSettings:
    """The annotated live view (HTTP MJPEG) and the status page, served by the service."""

    enabled: bool = _f(False, "serve the status page (/), its JSON (/status.json) and the live view "
                              "(/stream.mjpg)")
    address: str = _f("127.0.0.1", "address to listen on: loopback by default; 0.0.0.0 exposes the "
                                   "camera view to the whole network")
    port: int = _f(8090, "TCP port (the simulator's camera uses 8080)", min=1, max=65535)


@dataclass(frozen=True)
class LogSettings:
    """Logging (stderr; journald under systemd)."""

    level: str = _f("INFO", "log level", choices=LOG_LEVELS)
    health_interval_s: float = _f(10.0, "how often timings and health are logged (s)", min=0.5, max=3600.0)


@dataclass(frozen=True)
class Config:
    """The whole service configuration (one section per TOML table)."""

    link: LinkSettings = field(default_factory=LinkSettings)
    camera: CameraSettings = field(default_factory=CameraSettings)
    model: ModelSettings = field(default_factory=ModelSettings)
    pipeline: PipelineSettings = field(default_factory=PipelineSettings)
    failsafe: FailsafeSettings = field(default_factory=FailsafeSettings)
    controller: ControllerSettings = field(default_factory=ControllerSettings)
    recorder: RecorderSettings = field(default_factory=RecorderSettings)
    gcs: GcsSettings = field(default_factory=GcsSettings)
    live: LiveSettings = field(default_factory=LiveSettings)
    log: LogSettings = field(default_factory=LogSettings)
    #: The file it came from (None for built-in defaults); relative paths resolve beside it.
    source: Path | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (for the recorder's meta.json and debugging). It holds no secret: the
        signing key lives only in the file ``link.signing_key_file`` names."""
        return {k: v for k, v in _to_dict(self).items() if k != "source"}


# ---- keys that are gone ---------------------------------------------------------------------
# Naming one is an error that says so and where it went; the table is ``companion.config.removed``.


def removed_error(key: str) -> ConfigError:
    """The error for a file or ``--set`` that names the removed ``key``."""
    gone = REMOVED[key]
    return ConfigError(f"{key} was removed: {gone.why}; delete it from the configuration")


def _to_dict(obj: Any) -> Any:
    if hasattr(obj, "__dataclass_fields__"):
        return {f.name: _to_dict(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, list):
        return [_to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: _to_dict(v) for k, v in obj.items()}
    return obj


def _is_section(tp: Any) -> bool:
    return isinstance(tp, type) and hasattr(tp, "__dataclass_fields__")


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is list:
        return "a list of numbers"
    if origin is dict:
        return "a table"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(tp, str(tp))


def _check_value(key: str, tp: Any, meta: Mapping[str, Any], value: Any) -> Any:
    """The value converted to the field's type, or a ConfigError naming ``key``."""
    origin = typing.get_origin(tp)
    bad = ConfigError(f"{key} must be {_type_name(tp)}, got {value!r}")
    if tp is bool:
        if not isinstance(value, bool):
            raise bad
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{key} must be a finite number, got {value!r}")
    elif tp is str:
        if not isinstance(value, str):
            raise bad
    elif origin is list and typing.get_args(tp) == (str,):
        if not isinstance(value, list) or any(not isinstance(v, str) for v in value):
            raise ConfigError(f"{key} must be a list of strings, got {value!r}")
        value = list(value)
    elif origin is list and typing.get_args(tp) == (int,):
        if not isinstance(value, list) or any(isinstance(v, bool) or not isinstance(v, int) for v in value):
            raise ConfigError(f"{key} must be a list of integers, got {value!r}")
        value = [int(v) for v in value]
    elif origin is list:
        if not isinstance(value, list) or any(isinstance(v, bool) or not isinstance(v, (int, float))
                                               for v in value):
            raise bad
        value = [float(v) for v in value]
        if not all(math.isfinite(v) for v in value):
            raise ConfigError(f"{key} must hold finite numbers, got {value!r}")
        if meta.get("length") is not None and len(value) != meta["length"]:
            raise ConfigError(f"{key} must hold exactly {meta['length']} numbers, got {len(value)}")
    elif origin is dict:
        if not isinstance(value, dict):
            raise bad
        value = dict(value)
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(f"{key} must be one of {', '.join(map(repr, choices))}, got {value!r}")
    lo, hi = meta.get("min"), meta.get("max")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if lo is not None and (value < lo or (meta.get("min_exclusive") and value <= lo)):
            op = ">" if meta.get("min_exclusive") else ">="
            rng = f"{op} {lo}" + (f" and <= {hi}" if hi is not None else "")
            raise ConfigError(f"{key} must be {rng}, got {value!r}")
        if hi is not None and value > hi:
            rng = f">= {lo} and <= {hi}" if lo is not None else f"<= {hi}"
            raise ConfigError(f"{key} must be {rng}, got {value!r}")
    return value


def _build(cls: type, raw: Mapping[str, Any], prefix: str, base_dir: Path | None) -> Any:
    hints = typing.get_type_hints(cls)
    by_name = {f.name: f for f in fields(cls) if not (cls is Config and f.name == "source")}
    for name in raw:
        if name not in by_name:
            dotted = f"{prefix}{name}"
            if dotted in REMOVED:
                raise removed_error(dotted)
            if dotted in REMOVED_TABLES:
                inner = raw[name]
                first = sorted(inner)[0] if isinstance(inner, dict) and inner else None
                if first is not None and f"{dotted}.{first}" in REMOVED:
                    raise removed_error(f"{dotted}.{first}")
                raise ConfigError(f"[{dotted}] was removed with all its keys (internal tuning, now constants; "
                                  "docs/measurements.md); delete it from the configuration")
    unknown = sorted(set(raw) - set(by_name))
    if unknown:
        allowed = ", ".join(f"{prefix}{n}" for n in by_name)
        raise ConfigError(f"unknown key '{prefix}{unknown[0]}' (allowed: {allowed})")
    kwargs: dict[str, Any] = {}
    for name, value in raw.items():
        f, tp = by_name[name], hints[name]
        key = f"{prefix}{name}"
        if _is_section(tp):
            if not isinstance(value, dict):
                raise ConfigError(f"{key} must be a table ([{key}]), got {value!r}")
            kwargs[name] = _build(tp, value, key + ".", base_dir)
            continue
        if isinstance(value, dict) and typing.get_origin(tp) is not dict:
            raise ConfigError(f"{key} must be {_type_name(tp)}, got a table")
        value = _check_value(key, tp, f.metadata, value)
        if f.metadata.get("path") and value and base_dir is not None and not Path(value).is_absolute():
            value = str((base_dir / value).resolve())
        kwargs[name] = value
    return cls(**kwargs)


def _cross_checks(cfg: Config) -> None:
    """The file's rules that involve more than one key, or a key that no part's object checks (the
    parts' own rules, ranges and rules between keys, are checked by building the parts:
    ``companion.config.compose.checked``)."""
    if cfg.camera.model == "fisheye" and len(cfg.camera.distortion) not in (0, 4):
        raise ConfigError("camera.distortion of a fisheye (camera.model) must hold 0 or 4 coefficients "
                          f"(k1..k4), got {len(cfg.camera.distortion)}")
    if len(cfg.camera.distortion) not in (0, 4, 5, 8, 12, 14):
        raise ConfigError("camera.distortion must hold 0, 4, 5, 8, 12 or 14 coefficients "
                          f"(OpenCV), got {len(cfg.camera.distortion)}")
    if not cfg.failsafe.gcs_system_ids:  # their range is FailsafeConfig's
        raise ConfigError("failsafe.gcs_system_ids must list system ids 1..255, got []")
    if cfg.link.url.split(":", 1)[0] not in ("udpin", "udpout", "tcp", "tcpin", "serial"):
        raise ConfigError(f"link.url must start with udpin:, udpout:, tcp:, tcpin: or serial:, got "
                          f"{cfg.link.url!r}")
    try:
        parse_url(cfg.link.url)
    except TransportError as exc:
        # A port above 65535 (or no host) used to pass here and crash the start (exit 1, a
        # traceback, systemd restarting it): say what is wrong, exit 2.
        raise ConfigError(f"link.url: {exc}") from None
    p = cfg.pipeline
    names = p.unlandable_levels
    if len(set(names)) != len(names) or any(not re.fullmatch(r"[a-z0-9][a-z0-9_-]{0,31}", n) for n in names):
        raise ConfigError(f"pipeline.unlandable_levels must list distinct level names (lower case, "
                          f"[a-z0-9_-]), got {names!r}")
    if -1.0 < p.unlandable_threshold < 0.0:
        raise ConfigError(f"pipeline.unlandable_threshold must be -1 (the model's) or in [0, 1), "
                          f"got {p.unlandable_threshold!r}")
    if not cfg.live.address.strip() or any(ch.isspace() for ch in cfg.live.address):
        raise ConfigError(f"live.address must be an IP address or host name, got {cfg.live.address!r}")
    if cfg.link.require_signing and not cfg.link.signing_key_file:
        raise ConfigError("link.require_signing is on but link.signing_key_file is not set (docs/signing.md)")


def from_dict(raw: Mapping[str, Any], source: Path | None = None) -> Config:
    """A validated :class:`Config` from nested TOML-like data (missing keys take defaults)."""
    base_dir = source.parent if source is not None else None
    cfg = _build(Config, raw, "", base_dir)
    cfg = replace(cfg, source=source)
    if not cfg.model.path:
        # "" names the shipped model wherever the package is installed, so the example file works
        # copied to /etc/companion unchanged.
        cfg = replace(cfg, model=replace(cfg.model, path=str(SHIPPED_MODEL)))
    if not cfg.model.landability_path:
        cfg = replace(cfg, model=replace(cfg.model, landability_path=str(SHIPPED_LANDABILITY)))
    _cross_checks(cfg)
    return cfg


def load(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """Read and validate a TOML file (or the defaults when ``path`` is None), then apply
    ``overrides`` (dotted keys such as ``camera.fps``) and validate again.

    Raises ConfigError for a missing or unparsable file and for any bad key or value.
    """
    raw: dict[str, Any] = {}
    source = None
    if path is not None:
        source = Path(path).resolve()
        try:
            with open(source, "rb") as fh:
                raw = tomllib.load(fh)
        except FileNotFoundError:
            raise ConfigError(f"config file {path} does not exist") from None
        except OSError as exc:
            raise ConfigError(f"config file {path} cannot be read: {exc.strerror}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    for dotted, value in (overrides or {}).items():
        _set_dotted(raw, dotted, value)
    return from_dict(raw, source)


def _set_dotted(raw: dict[str, Any], dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = raw
    for i, part in enumerate(parts[:-1]):
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"{'.'.join(parts[: i + 1])} is not a table, cannot set {dotted}")
        node = nxt
    node[parts[-1]] = value


def parse_assignment(text: str) -> tuple[str, Any]:
    """``key=value`` from ``--set``: the value is read as a TOML value (``10``, ``true``,
    ``[0, 0, 0]``, ``"x"``) and, failing that, taken as a bare string (``camera.source=/dev/video1``).
    """
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"--set expects key=value, got {text!r}")
    value = value.strip()
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    return key, parsed


def all_keys(cls: type = Config, prefix: str = "") -> list[tuple[str, Any, str]]:
    """Every leaf key as (dotted name, default, doc), in declaration order (docs and tests)."""
    out: list[tuple[str, Any, str]] = []
    hints = typing.get_type_hints(cls)
    inst = cls()
    for f in fields(cls):
        if cls is Config and f.name == "source":
            continue
        if _is_section(hints[f.name]):
            out += all_keys(hints[f.name], f"{prefix}{f.name}.")
        else:
            out.append((f"{prefix}{f.name}", getattr(inst, f.name), f.metadata.get("doc", "")))
    return out



#: Settings added after recordings were first made, with the value that flew before each existed
#: (a recording's ``meta.json`` without the key was flown so): ``controller.land_agl_m``, the
#: LAND at ``land_alt_m`` whatever the rangefinder said; ``pipeline.person_px``, the density
#: model on the full frame; ``pipeline.unlandable_scope``, unlandable ground keeping whole zones
#: off. Add a row when a new setting changes what flies, so that old recordings replay as they
#: were flown.
BEFORE_RECORDED: dict[str, Any] = {"controller.land_agl_m": 0.0, "pipeline.person_px": 0.0,
                                   "pipeline.unlandable_scope": "zone"}


#: Removed keys whose recorded value does not change what a replay computes (the link, the
#: recorder, the live view, the ground station's values, onnxruntime's threads waiting).
_NOT_REPLAYED = ("link.", "recorder.", "live.", "gcs.", "model.allow_spinning")


def _drop_removed(raw: dict[str, Any], prefix: str = "") -> None:
    """Take the removed keys out of a recording's settings. One recorded at another value than
    flights now use (a switch that was on) is an error naming it: the replay would not be the
    flight (a setting only the live service reads is dropped whatever its value)."""
    for name in list(raw):
        dotted = f"{prefix}{name}"
        value = raw[name]
        if dotted in REMOVED:
            del raw[name]
            if value != REMOVED[dotted].value and not dotted.startswith(_NOT_REPLAYED):
                raise ConfigError(f"the recording was flown with {dotted} = {value!r}, which was removed "
                                  f"({REMOVED[dotted].why}): it cannot be replayed as flown")
        elif isinstance(value, dict):
            _drop_removed(value, dotted + ".")
            if dotted in REMOVED_TABLES and not value:
                del raw[name]


def from_recording(meta_config: Mapping[str, Any], overrides: Mapping[str, Any] | None = None) -> Config:
    """The settings a recording was flown with (its ``meta.json`` ``config``), with ``overrides``
    (dotted keys) on top, validated as a file would be. The signing key (``<redacted>`` in
    recordings older than issue 61) and the key file's name are dropped. A setting the recording
    lacks was added after it was flown: it takes the value that flew then (:data:`BEFORE_RECORDED`), not today's default."""
    raw = json.loads(json.dumps(dict(meta_config)))  # a deep copy of plain JSON data
    link = raw.get("link")
    if isinstance(link, dict):
        link.pop("signing_key", None)
        link.pop("signing_key_file", None)
    _drop_removed(raw)
    for dotted, then in BEFORE_RECORDED.items():
        section, key = dotted.split(".", 1)
        table = raw.setdefault(section, {})
        if isinstance(table, dict):
            table.setdefault(key, then)
    for dotted, value in (overrides or {}).items():
        _set_dotted(raw, dotted, value)
    return from_dict(raw)


__all__ = [
    "Config", "ConfigError", "LinkSettings", "CameraSettings", "ModelSettings", "PipelineSettings",
    "FailsafeSettings", "ControllerSettings", "RecorderSettings", "GcsSettings",
    "LiveSettings", "LogSettings", "removed_error",
    "load", "from_dict", "parse_assignment", "all_keys", "SHIPPED_MODEL", "SHIPPED_LANDABILITY",
    "PLAIN_MODEL", "X86_MODEL", "BLOCKED_MACHINES", "shipped_model",
    "LANDABILITY_DEFAULT", "from_recording", "BEFORE_RECORDED", "FLAVOURS", "LOG_LEVELS",
]
