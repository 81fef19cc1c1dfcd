"""The service configuration: a TOML file, validated at start-up, with command-line overrides.

Every key has a built-in default, so ``companion run`` with no file flies against the simulator's
defaults. A file only needs the keys it changes. Validation happens once, before anything opens a
socket or a camera, and every problem is reported as a :class:`ConfigError` whose message names
the key (``camera.fps``) and what is allowed, so an integrator reading ``journalctl`` knows what
to fix. ``companion.example.toml`` at the repository root documents every key.

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
from typing import Any, cast

from companion.control.landing import LAND_AGL_MIN_M, LandingConfig, person_trust_height
from companion.control.obedience import ObedienceConfig
from companion.control.planner import PlannerConfig
from companion.control.touchdown import DescentProfile
from companion.geometry.camera import Intrinsics, Mount
from companion.mavlink.clock import AutopilotClock
from companion.mavlink.failsafe import FailsafeConfig
from companion.mavlink.gcs_commands import CameraInfo
from companion.mavlink.link import LinkConfig, message_rates
from companion.mavlink.transports import TransportError, parse_peers, parse_url
from companion.pipeline.density import DensitySpec, resolve_threshold
from companion.pipeline.headplane import GridParams
from companion.pipeline.occupancy import OccupancyParams
from companion.pipeline.people import PeopleParams
from companion.pipeline.riskmap import MAX_HALF_CELLS, RiskMapConfig
from companion.pipeline.slz import FUSIONS, PipelineConfig
from companion.pipeline.tracker import MOTIONS, TrackerParams

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
#: Whether the landability model runs unless the configuration says otherwise: off, because on
#: the simulator's drawn ground the shipped model errs both ways (companion/models/LANDABILITY_CARD.md,
#: "On the simulator's ground"; docs/design.md, step 1b).
LANDABILITY_DEFAULT = False

FLAVOURS = ("auto", "ardupilot", "px4")
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


class ConfigError(ValueError):
    """A configuration problem; the message names the key and what is allowed."""


def _f(default: Any, doc: str = "", *, min: float | None = None, max: float | None = None,
       choices: tuple[Any, ...] | None = None, min_exclusive: bool = False, length: int | None = None,
       path: bool = False) -> Any:
    """A config field: default plus the checks the validator runs (kept next to the key)."""
    meta = {"doc": doc, "min": min, "max": max, "choices": choices, "min_exclusive": min_exclusive,
            "length": length, "path": path}
    if isinstance(default, (list, dict)):
        return field(default_factory=functools.partial(type(default), default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class LinkSettings:
    """MAVLink connection to the flight controller."""

    url: str = _f("udpin:127.0.0.1:14550", "udpin:HOST:PORT, udpout:, tcp:, tcpin:, serial:/dev/ttyX:BAUD")
    system_id: int = _f(1, "our MAVLink system id (normally the vehicle's)", min=1, max=255)
    component_id: int = _f(191, "our component id (191 = onboard computer)", min=1, max=255)
    target_system: int = _f(1, "autopilot system id (SYSID_THISMAV / MAV_SYS_ID); 0 = the first autopilot "
                               "heard, which anyone on the link could be", min=0, max=255)
    target_component: int = _f(1, "autopilot component id", min=0, max=255)
    flavour: str = _f("auto", "autopilot dialect", choices=FLAVOURS)
    signing_key: str = _f("", "MAVLink 2 signing secret as 64 hex characters; empty = unsigned")
    signing_key_file: str = _f("", "file holding the 64-hex signing secret (wins over signing_key)", path=True)
    require_signing: bool = _f(False, "refuse to start without a signing key (docs/signing.md); unsigned, "
                                      "the service warns at start and at every link-up")
    peers: list[str] = _f([], "UDP links: IP addresses or CIDR networks allowed to talk to the companion "
                              "(a ground station sharing the port); empty = any until the autopilot is "
                              "heard, then its address alone")
    heartbeat_timeout_s: float = _f(3.0, "link declared lost after this long without a heartbeat",
                                    min=0.5, max=60.0)
    telemetry_rate_hz: float = _f(20.0, "rate asked for ATTITUDE / GLOBAL_POSITION_INT", min=1.0, max=100.0)
    max_telemetry_lag_s: float = _f(0.5, "pose telemetry arriving later than this after the autopilot sampled "
                                         "it (its time_boot_ms) is dropped; frames wait this long for it (s)",
                                    min=0.05, max=5.0)
    timesync_period_s: float = _f(1.0, "TIMESYNC request period to measure the link latency and the "
                                       "autopilot's clock (s); 0 = off (arrival times bound the clock)",
                                  min=0.0, max=60.0)


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
    vendor_name: str = _f("companion-slz", "camera vendor a ground station is told (32 bytes at most)")
    model_name: str = _f("SLZ downward camera", "camera model a ground station is told (32 bytes at most)")


@dataclass(frozen=True)
class ModelSettings:
    """The ONNX density model."""

    path: str = _f(str(SHIPPED_MODEL), "ONNX density model file; empty = the model shipped in the package",
                   path=True)
    threads: int = _f(2, "onnxruntime intra-op threads", min=1, max=64)
    allow_spinning: bool = _f(False, "let onnxruntime's threads busy-wait between runs (off: they would take "
                                     "the CPU from the stages after the model on a small board)")
    overrides: dict[str, Any] = _f({}, "settings that win over the model's metadata (color, scale, ...)")
    landability: bool = _f(LANDABILITY_DEFAULT, "also keep zones off unlandable ground (water, vehicles, trees, "
                                                "roofs, ...) with the landability model")
    landability_path: str = _f(str(SHIPPED_LANDABILITY), "ONNX landability model file; empty = the model shipped "
                                                         "in the package", path=True)


@dataclass(frozen=True)
class TrackerSettings:
    """Kalman tracker of landing zones (pipeline step 5)."""

    sigma_a: float = _f(0.5, "process noise: acceleration std of zone centre/radius (m/s^2)", min=0.0,
                        min_exclusive=True)
    r_std: list[float] = _f([0.3, 0.3, 0.3], "measurement std of x, y, r (m)", length=3)
    min_iou: float = _f(0.3, "least circle IoU for a proposal to match a track", min=0.0, max=0.99)
    mu_1: int = _f(3, "a track missed more than this many frames is deleted", min=0, max=1000)
    mu_2: int = _f(3, "an unmatched proposal seen this many frames starts a track", min=1, max=1000)
    motion: str = _f("position", "zone motion model: position (a zone is ground: no velocity, a random walk of "
                                 "sigma_v; docs/design.md, 'Zones are ground') or velocity (the paper's constant "
                                 "velocity, for frames without a pose)", choices=MOTIONS)
    sigma_v: float = _f(0.1, "with motion = position, how far a zone's centre and radius wander (m per "
                             "square-root second)", min=0.0, min_exclusive=True)


@dataclass(frozen=True)
class PipelineSettings:
    """Safe-landing-zone pipeline (occupancy, head plane, proposals)."""

    occupancy_threshold: float = _f(-1.0, "density above min(D) marking a pixel occupied; "
                                          "-1 = not set: the model's validated value, else 0", min=-1.0)
    dilate_kernel: int = _f(5, "side of the square dilation kernel (px, odd)", min=1, max=99)
    dilate_iterations: int = _f(2, "dilations applied to the occupied map", min=0, max=20)
    head_height_m: float = _f(1.7, "height of the head plane above the ground (m)", min=0.0, max=3.0)
    cell_size_m: float = _f(0.1, "metric grid cell on the head plane (m)", min=0.01, max=2.0)
    max_extent_m: float = _f(40.0, "half-width of the metric grid around the camera (m)", min=1.0, max=1000.0)
    n_proposals: int = _f(5, "landing-zone proposals per frame (N_p)", min=1, max=50)
    r0_m: float = _f(2.0, "smallest useful landing-zone radius (m)", min=0.1, max=100.0)
    proposal_tie_m: float = _f(0.3, "a proposal may give up this much radius to sit nearer the ground under "
                                    "the camera (m; 0 = the paper's first largest circle)", min=0.0, max=5.0)
    max_pose_age_s: float = _f(0.25, "a frame whose pose is further than this from its capture time "
                                     "is not used for decisions (s)", min=0.0, max=5.0, min_exclusive=True)
    fusion: str = _f("frame", "proposals from each frame alone, as in the paper (frame), or from the ground "
                              "risk map fused over frames (map: a person missed in a few frames stays occupied; in the "
                              "simulator it hands back far more often, docs/design.md, 'Step 3b')", choices=FUSIONS)
    walk_speed_mps: float = _f(1.5, "how fast a person may walk (m/s): risk grows this fast from where "
                                    "someone was seen (1.34 m/s is the mean, Weidmann 1993)",
                               min=0.1, max=15.0)
    occupied_hold_s: float = _f(1.0, "ground seen occupied stays occupied this long although now seen free "
                                     "(s; a person the network misses in a few frames)", min=0.0, max=30.0)
    occupied_trail_s: float = _f(0.0, "zones are proposed only on ground nobody was seen on within this (s; "
                                      "under either fusion): a path people walk is not a lawn; whether a zone "
                                      "still holds is measured without it; 0 = off", min=0.0, max=600.0)
    map_memory_s: float = _f(10.0, "ground not seen for longer than this is unknown again (s)", min=0.1, max=600.0)
    map_half_extent_m: float = _f(60.0, "the risk map covers this far around the vehicle (m)", min=5.0, max=400.0)
    calm_margin_m: float = _f(1.0, "a zone is calm when nobody has been seen within r0 plus this of it while "
                                   "watched (m; controller.min_calm_s)", min=0.0, max=50.0)
    quiet_margin_m: float = _f(2.0, "the quiet disc around a landing point is r0 plus this (m; "
                                    "controller.min_quiet_s)", min=0.0, max=50.0)
    unlandable_levels: list[str] = _f([], "risk levels of the landability model that keep zones off the ground; "
                                          "empty = every level but the model's landable one")
    unlandable_threshold: float = _f(-1.0, "probability of the unlandable levels above which a cell is "
                                           "unlandable; -1 = the model's validated value", min=-1.0, max=0.999)
    tracker: TrackerSettings = field(default_factory=TrackerSettings)


@dataclass(frozen=True)
class FailsafeSettings:
    """Which telemetry events trigger a safe landing."""

    battery: bool = _f(True, "battery charge state LOW/CRITICAL/EMERGENCY")
    battery_level: str = _f("critical", "lowest battery state that triggers", choices=("low", "critical", "emergency"))
    system_status: bool = _f(True, "heartbeat system_status CRITICAL/EMERGENCY")
    autopilot_land: bool = _f(True, "the autopilot switches itself to LAND or RTL")
    gcs_command: bool = _f(True, "an explicit command from the ground station")
    local_trigger: bool = _f(True, "SIGUSR1 to the service triggers (bench tests)")
    gcs_system_ids: list[int] = _f([255], "system ids whose MAV_CMD_USER_1 trigger is accepted (1..255)")
    local_socket: str = _f("", "Unix socket taking 'trigger [reason]' lines; empty = none", path=True)


@dataclass(frozen=True)
class ControllerSettings:
    """Landing controller timeouts and margins."""

    min_track_age_s: float = _f(1.0, "a zone must have been tracked this long to be a target (s)", min=0.0)
    min_track_hits: int = _f(3, "a zone must have been matched this many times", min=1)
    zone_max_age_s: float = _f(1.0, "a zone not confirmed for this long is stale (s)", min=0.05, max=30.0)
    min_calm_s: float = _f(5.0, "the ground around a landing point (r0 plus pipeline.calm_margin_m) must have "
                                "been watched and seen free this long before the LAND; calm zones are chosen "
                                "first (s; 0 = not required, the paper's rule; docs/design.md)", min=0.0, max=120.0)
    min_quiet_s: float = _f(0.0, "with min_calm_s, nobody may have been seen within r0 plus pipeline.quiet_margin_m "
                                 "of the landing point this long before the LAND, on the 80 % or more of that disc "
                                 "seen within pipeline.map_memory_s (s; 0 = not required; docs/design.md, 'Quiet ground')",
                            min=0.0, max=120.0)
    min_unwalked_s: float = _f(0.0, "with min_calm_s, nobody may have been seen within r0 plus "
                                    "pipeline.calm_margin_m of the landing point since the camera first saw all of "
                                    "that ground, for this long, before the LAND: ground people walk over (a gap "
                                    "in a crowd) waits, ground nobody walks on does not (s; 0 = not required; "
                                    "docs/design.md, 'Ground nobody walks on')", min=0.0, max=300.0)
    prefer_unwalked: bool = _f(True, "among calm zones, choose first the one whose ground (r0 plus "
                                      "pipeline.calm_margin_m) has gone longest without anybody seen on it since "
                                      "the camera first saw it, then the oldest (docs/design.md, 'Unwalked ground')")
    recentre_m: float = _f(0.0, "over a zone bounded by people (not by the view), the landing point moves to the "
                                "zone's centre once it is more than this far from it (m; 0 = only when the zone "
                                "no longer holds r0 plus the margin around it)", min=0.0, max=50.0)
    avoid_lost_s: float = _f(0.0, "a landing point lost because people came within r0 of it is avoided this "
                                  "long (s): no zone whose centre lies within r0 plus radius_margin_m of it is "
                                  "chosen or searched meanwhile (0 = not avoided; docs/design.md, 'Avoiding "
                                  "where people walked')", min=0.0, max=600.0)
    calm_wait_s: float = _f(15.0, "with min_calm_s, wait at most this long over a zone for it to be calm, then "
                                  "give it up for the takeover (s)", min=0.5, max=300.0)
    radius_margin_m: float = _f(2.0, "zone radius must exceed r0 plus this margin to be chosen (m); once chosen it is kept, and the LAND commanded, while r0 stays free around the landing point, and its landing point stays put while the zone holds r0 plus this around it", min=0.0)
    steady_s: float = _f(8.0, "a zone smaller than r0 plus radius_margin_m may still be chosen once every frame for "
                              "this long has seen r0 plus steady_margin_m free round the same point (a gap that "
                              "travels with its crowd starts again): its edge is something that "
                              "does not walk into it (a tree or a bench on a lawn, a crowd that keeps off it); in such "
                              "a zone, too small for the calm disc, that steady watch stands for the calm ground "
                              "under the vehicle (s; 0 = never; docs/design.md, 'Steady zones')", min=0.0, max=120.0)
    steady_margin_m: float = _f(0.5, "with steady_s, the free radius beyond r0 a steady zone must keep on every frame (m)",
                                min=0.0, max=20.0)
    select_timeout_s: float = _f(10.0, "no safe zone this long after the trigger: search (search_s), or hand back when "
                                       "searching is off or out of time (s)", min=0.5)
    select_empty_s: float = _f(3.0, "with nothing in view since the trigger that could become a zone (no zone of "
                                    "r0 or more), start the search this long after the trigger instead of at "
                                    "select_timeout_s (s; 0 = not earlier)", min=0.0, max=120.0)
    hold_timeout_s: float = _f(15.0, "holding without a safe zone this long: search (search_s), or hand back when "
                                     "searching is off or out of time (s)", min=0.5)
    arrive_radius_m: float = _f(1.0, "horizontal distance to the zone centre counted as arrived (m)",
                                min=0.1, max=20.0)
    descend_alt_m: float = _f(10.0, "altitude above home at which the zone is judged (calm ground) before the "
                                     "LAND (m): where the camera still sees r0 plus radius_margin_m all round; "
                                     "the LAND itself is commanded at land_alt_m", min=1.0, max=200.0)
    land_alt_m: float = _f(4.0, "height at which the autopilot's LAND takes over (m): once the zone is judged "
                                "at descend_alt_m (calm ground), the companion's own stepped descent goes on "
                                "over it to this height, the ground under the vehicle re-checked every frame "
                                "(somebody within r0: HOLD); a shorter slow LAND leaves walkers less time to "
                                "reach the landing point; 0 = LAND at descend_alt_m (docs/design.md)",
                          min=0.0, max=200.0)
    land_agl_m: float = _f(0.0, "with a fresh downward rangefinder, the LAND commanded at land_alt_m is first "
                                "the companion's own committed descent, straight down at descend_speed_mps, to "
                                "this height above the ground the rangefinder measures, and the autopilot's "
                                "slower LAND only there (m); without a fresh rangefinder, or when it goes stale "
                                "or out of range on the way, the LAND at once; 0 = off, the default (docs/design.md, "
                                "\"The last metres by the rangefinder\": measured, and why it stays off); "
                                "1 m is the value measured", min=0.0, max=200.0)
    descend_speed_mps: float = _f(1.5, "how fast the stepped descent comes down (m/s; ArduPilot WPNAV_SPEED_DN, "
                                       "PX4 MPC_Z_VEL_MAX_DN): the time to touchdown", min=0.1, max=10.0)
    land_speed_mps: float = _f(0.5, "the autopilot's LAND descent speed (m/s; ArduPilot LAND_SPEED 50 cm/s, "
                                    "PX4 MPC_LAND_SPEED 0.7): the time to touchdown", min=0.1, max=5.0)
    descend_step_m: float = _f(3.0, "the descent plan goes down in steps of this, one step once the "
                               "vehicle has reached the last (m)",
                               min=0.5, max=50.0)
    land_abort_above_m: float = _f(3.5, "during LAND, a lost zone above this height sends the vehicle "
                                        "back to HOLD; below it the landing is committed (m)", min=0.0, max=100.0)
    min_person_px: float = _f(0.0, "people must look at least this many pixels across (the longer side of "
                              "their box from above) for the model's free to be trusted: above the height "
                              "where a 0.4 m person looks smaller, the vehicle approaches no higher and "
                              "judges the zone only below it; 0 = the model's own (metadata "
                              "companion.min_person_px), or no limit when it has none", min=0.0, max=1000.0)
    lose_after_frames: int = _f(2, "a zone seen with less than r0 free is dropped only after this many "
                                "frames in a row (one frame's false detection must not throw a landing "
                                "back to HOLD; a person walking in is seen on every frame)", min=1, max=10)
    predict_people: bool = _f(False, "follow the people seen on the ground and command the LAND (and let it go "
                                    "on above land_abort_above_m) only while nobody seen walking is predicted "
                                    "within r0 of the landing point before touchdown; otherwise the descent "
                                    "pauses until they are past (off: in the simulator it kept landing "
                                    "points from ever being judged clear; docs/design.md)")
    pose_uncertainty_m: float = _f(0.5, "the vehicle's horizontal position error, taken off every predicted "
                                        "clearance (m)", min=0.0, max=20.0)
    predict_rejudge: bool = _f(True, "with predict_people, a walker predicted in the way once the zone is judged "
                                     "sends the vehicle back up to descend_alt_m to judge the zone again (calm, "
                                     "the walkers), instead of waiting low beside them (docs/design.md)")
    predict_lead_s: float = _f(2.0, "with predict_people, judge the prediction only this long before the "
                                    "landing is committed (s): until then the camera watches the zone", min=0.1,
                               max=120.0)
    predict_min_height_m: float = _f(0.0, "with predict_people, no new prediction below this height (m) "
                                          "unless a pause is on: low down the view is barely r0 wide and the "
                                          "people at its edge seem to move with it", min=0.0, max=120.0)
    hold_height_m: float = _f(15.0, "on a lost zone the vehicle holds at least this high above the "
                              "ground, where the camera sees enough to confirm a zone again", min=2.0, max=120.0)
    max_takeover_s: float = _f(90.0, "not landed this long after the trigger: hand back to the "
                               "autopilot's own failsafe", min=10.0, max=600.0)
    handback_action: str = _f("LAND", "what the autopilot is asked to do on handback", choices=("LAND", "RTL"))
    search_s: float = _f(45.0, "with no zone in view at the SELECT or HOLD timeout, search this long (s) "
                         "before handing back: climb to the ceiling, then fly an expanding square; 0 = "
                         "hand back at once, as before (with steady_s, a look at a glimpse whose steady "
                         "watch runs is finished, at most steady_s more)", min=0.0, max=600.0)
    search_radius_m: float = _f(40.0, "the search goes no further than this from where it starts (m)",
                                min=0.0, max=500.0)
    search_reserve_s: float = _f(30.0, "stop searching (hand back) when the battery's time left, as the "
                                 "autopilot reports it, is less than the landing needs plus this (s)",
                                 min=0.0, max=600.0)
    hold_looks: bool = _f(False, "while holding, fly over free ground glimpsed at the edge of the view (as the "
                                 "search does) so the camera sees it whole, instead of hovering until "
                                 "hold_timeout_s")
    place_lookback_s: float = _f(30.0, "place the landing point inside the zone where the ground is farthest "
                                       "from anybody seen within this many seconds, and move it there again "
                                       "before the zone is judged when that is 0.5 m farther from them (s; 0 = "
                                       "the zone's centre when chosen; docs/design.md, 'Where people walked')",
                                 min=0.0, max=600.0)
    place_min_clear_m: float = _f(0.0, "the landing point moves (place_lookback_s) only to a point at least this "
                                       "far from anybody seen within the lookback (m; 0 = to any point 0.5 m "
                                       "farther from them than the present one)", min=0.0, max=50.0)
    place_descending: bool = _f(True, "the landing point moves (place_lookback_s) also while the vehicle "
                                      "descends over the zone to judge it (false: only while it approaches)")
    search_memory_s: float = _f(0.0, "the search flies over ground the risk map remembers free (seen free "
                                     "within this many seconds), nearest first, when none is in view (s; 0 = "
                                     "not at all); the zone is still chosen on what the camera sees there",
                                min=0.0, max=600.0)
    search_climb_m: float = _f(5.0, "the ceiling: the vehicle is never sent more than this above its "
                               "altitude at the trigger (m); above it, control goes back to LAND",
                               min=1.0, max=50.0)
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
    segment_s: float = _f(60.0, "length of one video segment (s)", min=1.0, max=3600.0)
    max_mb: float = _f(2048.0, "disk budget for everything recorded in dir (video, frame index, events); "
                       "oldest files deleted first (MiB)", min=1.0)
    codec: str = _f("MJPG", "video codec: MJPG (.avi) or mp4v (.mp4)", choices=("MJPG", "mp4v"))


@dataclass(frozen=True)
class GcsSettings:
    """What the ground station sees: health in the heartbeat, STATUSTEXT, named values."""

    values_hz: float = _f(1.0, "rate of the NAMED_VALUE_FLOAT/INT numbers a ground station plots "
                               "(docs/ground-station-values.md); 0 = none", min=0.0, max=10.0)
    frame_budget_ms: float = _f(0.0, "a median pipeline time per frame (last 20 frames) above this "
                                     "reports 'model slow'; 0 = the camera's frame period (1000 / camera.fps)",
                                min=0.0, max=60000.0)


@dataclass(frozen=True)
class LiveSettings:
    """The annotated live view (HTTP MJPEG) and the status page, served by the service."""

    enabled: bool = _f(False, "serve the status page (/), its JSON (/status.json) and the live view "
                              "(/stream.mjpg)")
    address: str = _f("127.0.0.1", "address to listen on: loopback by default; 0.0.0.0 exposes the "
                                   "camera view to the whole network")
    port: int = _f(8090, "TCP port (the simulator's camera uses 8080)", min=1, max=65535)
    max_fps: float = _f(5.0, "most frames per second drawn for the live view (drawn only while a "
                             "client watches)", min=0.1, max=30.0)
    jpeg_quality: int = _f(80, "JPEG quality of the live view (1..100)", min=1, max=100)


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
        """Plain nested dict (for the recorder's meta.json and debugging), secrets redacted: a
        recording must never carry the link's signing key."""
        d = {k: v for k, v in _to_dict(self).items() if k != "source"}
        if d["link"].get("signing_key"):
            d["link"]["signing_key"] = "<redacted>"
        return d


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
    """Rules that involve more than one key."""
    if cfg.pipeline.dilate_kernel % 2 == 0:
        raise ConfigError(f"pipeline.dilate_kernel must be odd, got {cfg.pipeline.dilate_kernel}")
    key = cfg.link.signing_key
    if key and (len(key) != 64 or any(c not in "0123456789abcdefABCDEF" for c in key)):
        raise ConfigError("link.signing_key must be 64 hexadecimal characters (a 32-byte secret)")
    for name in ("r_std",):
        if any(v <= 0 for v in getattr(cfg.pipeline.tracker, name)):
            raise ConfigError(f"pipeline.tracker.{name} values must be > 0")
    for name in ("vendor_name", "model_name"):
        if len(getattr(cfg.camera, name).encode()) > 32:
            raise ConfigError(f"camera.{name} must be at most 32 bytes (MAVLink's CAMERA_INFORMATION), "
                              f"got {getattr(cfg.camera, name)!r}")
    if cfg.controller.land_alt_m > cfg.controller.descend_alt_m:
        raise ConfigError(f"controller.land_alt_m ({cfg.controller.land_alt_m:g} m) must not be above "
                          f"controller.descend_alt_m ({cfg.controller.descend_alt_m:g} m), where the zone is "
                          "judged before it; set controller.land_alt_m at or below it (0: the LAND at "
                          "controller.descend_alt_m)")
    c = cfg.controller
    lands_at = c.land_alt_m or c.descend_alt_m
    if c.land_agl_m and not LAND_AGL_MIN_M <= c.land_agl_m < lands_at:
        raise ConfigError(f"controller.land_agl_m ({c.land_agl_m:g} m) must be 0 (off) or from "
                          f"{LAND_AGL_MIN_M:g} m up to below the height where the LAND is commanded "
                          f"(controller.land_alt_m, {lands_at:g} m): the companion's descent goes on "
                          "below that, by the rangefinder, to it")
    if len(cfg.camera.distortion) not in (0, 4, 5, 8, 12, 14):
        raise ConfigError("camera.distortion must hold 0, 4, 5, 8, 12 or 14 coefficients "
                          f"(OpenCV), got {len(cfg.camera.distortion)}")
    if not cfg.failsafe.gcs_system_ids or any(not 1 <= i <= 255 for i in cfg.failsafe.gcs_system_ids):
        raise ConfigError(f"failsafe.gcs_system_ids must list system ids 1..255, got "
                          f"{cfg.failsafe.gcs_system_ids!r}")
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
    for key in ("occupied_hold_s", "occupied_trail_s"):
        if getattr(p, key) > p.map_memory_s:
            raise ConfigError(f"pipeline.{key} ({getattr(p, key)} s) must not exceed "
                              f"pipeline.map_memory_s ({p.map_memory_s} s)")
    if p.map_half_extent_m / p.cell_size_m > MAX_HALF_CELLS:
        raise ConfigError(f"pipeline.map_half_extent_m / pipeline.cell_size_m must be at most {MAX_HALF_CELLS} "
                          f"cells (memory), got {p.map_half_extent_m / p.cell_size_m:.0f}")
    try:
        parse_peers(cfg.link.peers)
    except TransportError as exc:
        raise ConfigError(f"link.peers: {exc}") from None
    if not cfg.live.address.strip() or any(ch.isspace() for ch in cfg.live.address):
        raise ConfigError(f"live.address must be an IP address or host name, got {cfg.live.address!r}")
    if cfg.link.require_signing and not (cfg.link.signing_key or cfg.link.signing_key_file):
        raise ConfigError("link.require_signing is on but neither link.signing_key nor "
                          "link.signing_key_file is set (docs/signing.md)")


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



# ---- the objects each part takes ------------------------------------------------------------
# The one place where settings become the parts' own configuration objects: the service, replay
# and the simulator call these, so a setting has one name and one meaning everywhere.

def threshold_setting(cfg: Config) -> float | None:
    """``pipeline.occupancy_threshold`` with TOML's stand-in for "not set" (-1) turned into None,
    for ``companion.pipeline.density.resolve_threshold``."""
    value = cfg.pipeline.occupancy_threshold
    return None if value < 0 else value


def intrinsics(cfg: Config) -> Intrinsics:
    """Pinhole intrinsics (``geometry.camera.Intrinsics``) for ``camera.width x camera.height``."""
    c = cfg.camera
    base = Intrinsics.from_fov(c.width, c.height, c.hfov_deg)
    fx = c.fx or base.fx
    fy = c.fy or fx
    cx = base.cx if c.cx < 0 else c.cx
    cy = base.cy if c.cy < 0 else c.cy
    return Intrinsics(fx, fy, cx, cy, c.width, c.height, tuple(c.distortion))


def mount(cfg: Config) -> Mount:
    """The camera mount (``geometry.camera.Mount``) from ``camera.mount_*``."""
    c = cfg.camera
    offset = cast("tuple[float, float, float]", tuple(c.mount_offset_m))  # length 3: validated
    return Mount.from_degrees(c.mount_roll_deg, c.mount_pitch_deg, c.mount_yaw_deg, offset)


def pipeline_config(cfg: Config, model_spec: DensitySpec | None = None) -> PipelineConfig:
    """The pipeline's ``PipelineConfig``; the occupancy threshold resolved against the model's
    ``DensitySpec`` (``resolve_threshold``: the setting, else the model's, else 0)."""
    p, t = cfg.pipeline, cfg.pipeline.tracker
    return PipelineConfig(
        occupancy=OccupancyParams(threshold=resolve_threshold(threshold_setting(cfg), model_spec),
                                  kernel=p.dilate_kernel, iterations=p.dilate_iterations),
        grid=GridParams(cell=p.cell_size_m, max_extent=p.max_extent_m),
        tracker=TrackerParams(sigma_a=t.sigma_a, r_std=(t.r_std[0], t.r_std[1], t.r_std[2]),
                              min_iou=t.min_iou, mu_1=t.mu_1, mu_2=t.mu_2, max_tracks=p.n_proposals,
                              motion=t.motion, sigma_v=t.sigma_v),
        head_height_m=p.head_height_m,
        r0_m=p.r0_m,
        proposal_tie_m=p.proposal_tie_m,
        fusion=p.fusion,
        calm=cfg.controller.min_calm_s > 0 or cfg.controller.min_quiet_s > 0 or cfg.controller.min_unwalked_s > 0,
        calm_margin_m=p.calm_margin_m,
        quiet=cfg.controller.min_quiet_s > 0, quiet_margin_m=p.quiet_margin_m,
        unwalked=cfg.controller.prefer_unwalked, unwalked_below=cfg.controller.min_unwalked_s > 0,
        surface_threshold=None if p.unlandable_threshold < 0 else p.unlandable_threshold,
        steady_margin_m=cfg.controller.steady_margin_m if cfg.controller.steady_s > 0 else None,
        risk=RiskMapConfig(cell_m=p.cell_size_m, half_extent_m=p.map_half_extent_m,
                           walk_speed_mps=p.walk_speed_mps, hold_s=p.occupied_hold_s,
                           memory_s=p.map_memory_s, trail_s=p.occupied_trail_s),
        # Followed only for the controller's prediction (it costs about 0.7 ms a frame).
        people=PeopleParams(walk_speed_mps=p.walk_speed_mps) if cfg.controller.predict_people else None,
    )


def descent_profile(cfg: Config) -> DescentProfile:
    """How long a descent from a height takes, and how far a walker gets meanwhile."""
    c = cfg.controller
    return DescentProfile(descend_speed_mps=c.descend_speed_mps, land_alt_m=c.land_alt_m or c.descend_alt_m,
                          land_speed_mps=c.land_speed_mps, walk_speed_mps=cfg.pipeline.walk_speed_mps)


def planner_config(cfg: Config) -> PlannerConfig:
    """The ``PlannerConfig``: the one rule for which zone is the target (flight and replay)."""
    c = cfg.controller
    return PlannerConfig(r0_m=cfg.pipeline.r0_m, radius_margin_m=c.radius_margin_m,
                         min_track_age_s=c.min_track_age_s, min_track_hits=c.min_track_hits,
                         zone_max_age_s=c.zone_max_age_s, min_calm_s=c.min_calm_s,
                         prefer_unwalked=c.prefer_unwalked, steady_s=c.steady_s,
                         steady_margin_m=c.steady_margin_m)


def landing_config(cfg: Config, model_spec: DensitySpec | None = None) -> LandingConfig:
    """The landing controller's ``LandingConfig``; ``model_spec`` gives the model's smallest
    reliably seen person (``min_person_px``) when ``controller.min_person_px`` is 0."""
    c = cfg.controller
    min_px = c.min_person_px or (model_spec.min_person_px if model_spec is not None else None)
    k = intrinsics(cfg)
    return LandingConfig(
        planner=planner_config(cfg),
        select_timeout_s=c.select_timeout_s, select_empty_s=c.select_empty_s, hold_timeout_s=c.hold_timeout_s,
        arrive_radius_m=c.arrive_radius_m, descend_alt_m=c.descend_alt_m,
        descend_step_m=c.descend_step_m, land_abort_above_m=c.land_abort_above_m,
        lose_after_frames=c.lose_after_frames, hold_height_m=c.hold_height_m, max_takeover_s=c.max_takeover_s,
        calm_wait_s=c.calm_wait_s, land_alt_m=c.land_alt_m, land_agl_m=c.land_agl_m, max_pose_age_s=cfg.pipeline.max_pose_age_s, handback_action=c.handback_action,
        search_climb_m=c.search_climb_m, max_alt_m=c.max_alt_m,
        obedience=ObedienceConfig(tolerance_z_m=c.obey_tolerance_z_m, tolerance_xy_m=c.obey_tolerance_xy_m),
        descent=descent_profile(cfg),
        search_s=c.search_s, search_radius_m=c.search_radius_m, search_reserve_s=c.search_reserve_s,
        place_lookback_s=c.place_lookback_s,
        view_ratio=min(k.cx / k.fx, k.cy / k.fy),
        trust_height_m=person_trust_height(min(k.fx, k.fy), min_px or None, head_m=cfg.pipeline.head_height_m),
    )


def signing_key(cfg: Config) -> bytes | None:
    """The 32-byte MAVLink signing secret from ``link.signing_key_file`` or ``link.signing_key``;
    ConfigError naming the file when it cannot be read or holds no key."""
    text = cfg.link.signing_key
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
                      sensor_height_mm=sensor_h, vendor=c.vendor_name, model=c.model_name)


def link_config(cfg: Config) -> LinkConfig:
    """The MAVLink link's ``LinkConfig`` (reads the signing key file)."""
    c = cfg.link
    return LinkConfig(
        url=c.url, system_id=c.system_id, component_id=c.component_id,
        target_system=c.target_system or None, target_component=c.target_component,
        heartbeat_timeout_s=c.heartbeat_timeout_s, signing_key=signing_key(cfg),
        message_rates_hz=message_rates(c.telemetry_rate_hz), peers=tuple(c.peers),
    )


def autopilot_clock(cfg: Config) -> AutopilotClock:
    """The clock that places telemetry in time, with the configured lag limit."""
    lag = cfg.link.max_telemetry_lag_s
    # A TIMESYNC round trip is two one-way trips: one slower than twice the lag allowed would
    # only say that every sample is late.
    return AutopilotClock(max_lag_s=lag, max_rtt_s=2.0 * lag)


def failsafe_config(cfg: Config) -> FailsafeConfig:
    """The failsafe monitor's ``FailsafeConfig``."""
    f = cfg.failsafe
    return FailsafeConfig(battery=f.battery, battery_level=f.battery_level, system_status=f.system_status,
                          autopilot_land=f.autopilot_land, gcs_command=f.gcs_command,
                          local_trigger=f.local_trigger, gcs_system_ids=tuple(f.gcs_system_ids),
                          local_socket=f.local_socket or None)


#: Settings added after recordings were first made, with the value that flew before each existed
#: (a recording's ``meta.json`` without the key was flown so): ``controller.land_agl_m``, the
#: LAND at ``land_alt_m`` whatever the rangefinder said. Add a row when a new setting changes
#: what flies, so that old recordings replay as they were flown.
BEFORE_RECORDED: dict[str, Any] = {"controller.land_agl_m": 0.0}


def from_recording(meta_config: Mapping[str, Any], overrides: Mapping[str, Any] | None = None) -> Config:
    """The settings a recording was flown with (its ``meta.json`` ``config``), with ``overrides``
    (dotted keys) on top, validated as a file would be. The signing key is never recorded (it
    reads ``<redacted>``) and is dropped. A setting the recording lacks was added after it was
    flown: it takes the value that flew then (:data:`BEFORE_RECORDED`), not today's default."""
    raw = json.loads(json.dumps(dict(meta_config)))  # a deep copy of plain JSON data
    link = raw.get("link")
    if isinstance(link, dict):
        link.pop("signing_key", None)
        link.pop("signing_key_file", None)
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
    "TrackerSettings", "FailsafeSettings", "ControllerSettings", "RecorderSettings", "GcsSettings",
    "LiveSettings", "LogSettings",
    "load", "from_dict", "parse_assignment", "all_keys", "SHIPPED_MODEL", "SHIPPED_LANDABILITY",
    "PLAIN_MODEL", "X86_MODEL", "BLOCKED_MACHINES", "shipped_model",
    "LANDABILITY_DEFAULT", "threshold_setting",
    "intrinsics", "mount", "pipeline_config", "planner_config", "landing_config", "signing_key",
    "link_config", "failsafe_config", "from_recording", "BEFORE_RECORDED",
]
