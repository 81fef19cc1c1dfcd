"""What a flight flies and how it ended: ``FlightSpec``, ``FlightResult`` (a row of a results
file, ``FlightResult.as_dict()``), and the command line its service runs with.

The bottom of ``sim.flights``: the flight (``sim.flights.flight``), the service in the flight's own
process (``sim.flights.inprocess``) and the lockstep runner (``sim.flights.lockstep``) all take a
spec and give a result, so these live below all three.

Frames: world NED metres from home, ground z = 0; times in seconds.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

from sim.flights.results import DEFAULT_CAMERA, LOCKSTEP_CLOCK_START_S, SCENARIO_LAND_SPEED, SCENARIO_WATCH_S
from sim.world.crowd import CROSSING_WINDOW_S
from sim.world.ground import LANDABLE_SURFACES
from sim.world.photo_ground import PHOTO_LANDABLE, PhotosError, check_photos

WORLDS = ("free_area", "dense", "dense_beyond", "intrusion", "crossing", "dronecrowd", "uniform")
#: What the ground is made of: ``procedural`` (drawn, ``sim.world.ground``; the default and the
#: regression world) or ``photo`` (real nadir photos, ``sim.world.photo_ground``).
GROUNDS = ("procedural", "photo")


@dataclass(frozen=True)
class FlightSpec:
    """What to fly.

    world: ``free_area`` (a crowd with one free circle in view), ``dense`` (people everywhere:
    no safe zone), ``intrusion`` (the free circle is entered by walkers during the descent, who
    stay), ``crossing`` (the free area's crowd, and walkers who cross the free circle during the
    descent and leave it: ``sim.world.crowd.add_crossing_walkers``) or
    ``dronecrowd`` (real DroneCrowd motion, needs ../shared) or ``uniform`` (nobody, and a ground
    of one colour: every frame the same, the largest free circle bounded by the edge of the view).
    start_offset_m: where the vehicle hovers relative to the free circle's centre (north, east);
        the scene is laid out around a park lawn of the procedural ground (``scene_centre``).
    watch_s: seconds the service watches before the failsafe is raised (the vehicle hovering
        where it started): what its risk map has seen of the crowd when the failsafe comes.
    failsafe: the simulator failsafe raised (battery_critical, rc_loss, gcs_loss, battery_low).
    packet_loss: share of MAVLink datagrams dropped each way.
    latency_ms: one-way MAVLink latency added each way (ms), from the moment the service is ready.
    intrusion_after_s: for ``intrusion``, seconds after the failsafe when walkers reach the circle.
    land_speed: final-descent speed of the autopilot's LAND (m/s; ArduPilot LAND_SPEED, PX4
        MPC_LAND_SPEED). 1 m/s by default, faster than either autopilot's own default (0.5 and
        0.7 m/s): the blind end of a landing is shorter here than on a vehicle left at defaults.
    crossing_window: for ``crossing``, when its walkers cross the free circle's edge (seconds after
        the failsafe, drawn uniformly; ``sim.world.crowd.CROSSING_WINDOW_S`` by default, timed for
        landings at 1 m/s). A wider window keeps the same rate of crossings with more walkers, so
        that crossings come at any time of a landing, whatever its speed.
    home_origin_offset_m: the simulated PX4's home altitude minus its estimator origin's altitude
        (m). The real PX4 converts frame-6 position targets wrongly unless this is 0.
    alt_bias_m: the simulated autopilot's altitude error (m; ``AutopilotConfig.alt_bias_m``): it
        believes, reports and flies altitudes this much higher than true, as PX4 SIH's estimate
        does (-1.3 to +1.8 m on the ground). Not in the rows: the yardstick flies 0.
    rangefinder_max_m: the simulated rangefinder's range (m); a small one (0.5) leaves the
        companion the autopilot's altitude alone, as on a vehicle without one. Not in the rows.
    record_dir: where the service records the flight (a temporary folder when None: the judge
        reads the controller's events from the recording either way).
    service_env: extra environment variables for the service process (tests use it to prove the
        verdict does not depend on the log's wording); in lockstep, for the flight's own process,
        which is the service's.
    companion: False flies the **baseline**: no service, the autopilot's own failsafe alone.
    gcs_port: when set, the simulator also binds ``udpin:127.0.0.1:<gcs_port>`` for a ground
        station to watch the flight, and forwards between it and the companion's link as the
        autopilot does (PX4: both links with forwarding on, ``MAV_X_FORWARD``).
    ground: ``procedural`` (the drawn ground) or ``photo``: the held-out semantic-drone photos of
        ``photos`` laid as a mosaic (``sim.world.photo_ground``), the scene placed where its free
        circle is landable ground by their class maps and none of their people stands in it,
        their people counted by the judge, the walkers drawn as real silhouettes and a few of
        them crossing open ground (``sim.world.photo_people``).
    photos: the photos folder of a ``photo`` ground (``images/``, ``labels/``).
    lockstep: fly on the simulated clock (``sim.flights.lockstep``): the service runs in the flight's own
        process, every piece of work takes a fixed simulated time, and the same spec flies the
        same flight every time, however loaded the machine. Only ``sim.flights.lockstep.fly_lockstep``
        (which gives the flight its own event loop and clock) flies it.
    """

    flavour: str = "ardupilot"
    world: str = "free_area"
    seed: int = 0
    altitude_m: float = 20.0
    start_offset_m: tuple[float, float] = (-5.0, -7.0)
    free_radius_m: float = 7.0
    watch_s: float = SCENARIO_WATCH_S
    failsafe: str = "battery_critical"
    packet_loss: float = 0.0
    latency_ms: float = 0.0
    intrusion_after_s: float = 7.0
    timeout_s: float = 150.0
    r0_m: float = 2.0
    hfov_deg: float = 70.0
    #: The lens of the simulator's camera and the service's (``companion.geometry.lens``), as one.
    camera_model: str = "pinhole"
    fps: float = 10.0
    land_speed: float = SCENARIO_LAND_SPEED
    crossing_window: tuple[float, float] = CROSSING_WINDOW_S
    #: The share of the crossing world's walkers who run or cycle (``sim.world.crowd.RUNNER_SPEEDS``).
    runners: float = 0.0
    record_dir: Path | None = None
    service_log: Path | None = None
    service_set: tuple[str, ...] = ()
    home_origin_offset_m: float = 0.0
    alt_bias_m: float = 0.0
    rangefinder_max_m: float = 40.0
    service_env: tuple[tuple[str, str], ...] = ()
    companion: bool = True
    gcs_port: int | None = None
    lockstep: bool = False
    clock_start_s: float = LOCKSTEP_CLOCK_START_S
    ground: str = "procedural"
    photos: str | None = None

    def __post_init__(self) -> None:
        if self.ground not in GROUNDS:
            raise ValueError(f"ground must be one of {GROUNDS}, got {self.ground!r}")
        if self.ground == "photo" and not self.photos:
            raise ValueError("a photo ground needs its photos folder (photos)")
        if self.world not in WORLDS:
            raise ValueError(f"world must be one of {WORLDS}, got {self.world!r}")
        if self.flavour not in ("ardupilot", "px4"):
            raise ValueError(f"flavour must be ardupilot or px4, got {self.flavour!r}")
        if not (math.isfinite(self.clock_start_s) and self.clock_start_s > 0):
            raise ValueError(f"clock_start_s must be a finite number of seconds > 0, got {self.clock_start_s!r}")


@dataclass
class FlightResult:
    """How a flight ended, judged on the simulator's truth."""

    spec: FlightSpec
    outcome: str
    touchdown: tuple[float, float] | None = None
    clearance_m: float | None = None
    time_to_touchdown_s: float | None = None
    # From the vehicle's last moment above LAST_METRES_M (truth) to touchdown (s); None without one.
    last_metres_s: float | None = None
    phases: list[str] = field(default_factory=list)  # every phase the controller entered, in order
    messages: list[str] = field(default_factory=list)  # the events' STATUSTEXT lines, each once
    events: list[dict] = field(default_factory=list)  # the controller's events as recorded
    free_circle: tuple[float, float, float] | None = None
    trigger_alt_m: float | None = None
    max_climb_m: float | None = None  # highest altitude after the trigger less the altitude at it
    service_exit: int | None = None
    log_tail: str = ""
    processed_fps: float | None = None  # frames the service processed per second, READY to the end
    starved: bool = False  # the flight's CPU could not keep up (see :func:`starved`)
    frame_ms_p95: float | None = None  # the pipeline's time per frame (its "total"), 95th percentile
    world_t_trigger: float | None = None  # the world's clock at the failsafe (s; about watch_s)
    # Touched down on ground nobody walks into (the scene's free area, or beyond every crowd:
    # World.nobody_walks_at), rather than in a gap of the crowd that walkers may cross at any
    # time; None without a touchdown, or where the world cannot tell.
    in_free_area: bool | None = None
    # Each zone the controller gave up while over it (DESCEND or LAND), with the truth then
    # (:func:`zone_losses`); in time order.
    zone_losses: list[ZoneLoss] = field(default_factory=list)
    # The surfaces under the vehicle's footprint at touchdown (sim.world.ground.SURFACES, sorted); None
    # without a touchdown, or on a ground that does not say (the uniform world's).
    touchdown_surfaces: list[str] | None = None

    @property
    def unlandable_touchdown(self) -> bool | None:
        """Touched down with part of its footprint on ground that is not landable (a tree, a
        bench, a car, a roof; on the photo ground, any class but paved area, dirt, grass and
        gravel), whoever landed; None where the ground does not say."""
        if self.touchdown_surfaces is None:
            return None
        landable = PHOTO_LANDABLE if self.spec.ground == "photo" else LANDABLE_SURFACES
        return not set(self.touchdown_surfaces) <= landable

    @property
    def took_control(self) -> bool:
        return any(p in ("APPROACH", "DESCEND") for p in self.phases)

    @property
    def handed_back(self) -> bool:
        return "HANDBACK" in self.phases

    @property
    def struck(self) -> bool:
        """Touched down with somebody within ``r_0``, whoever landed (companion or autopilot)."""
        return self.touchdown is not None and (self.clearance_m or 0.0) < self.spec.r0_m

    def as_dict(self) -> dict:
        return {
            "flavour": self.spec.flavour, "world": self.spec.world, "seed": self.spec.seed,
            "outcome": self.outcome,
            "touchdown": None if self.touchdown is None else [round(v, 3) for v in self.touchdown],
            "clearance_m": None if self.clearance_m is None or not math.isfinite(self.clearance_m)
            else round(self.clearance_m, 3),
            "time_to_touchdown_s": None if self.time_to_touchdown_s is None
            else round(self.time_to_touchdown_s, 2),
            "last_metres_s": None if self.last_metres_s is None else round(self.last_metres_s, 2),
            "trigger_alt_m": None if self.trigger_alt_m is None else round(self.trigger_alt_m, 2),
            "max_climb_m": None if self.max_climb_m is None else round(self.max_climb_m, 2),
            "home_origin_offset_m": round(self.spec.home_origin_offset_m, 3),
            "r0_m": self.spec.r0_m, "strike": self.struck,
            "processed_fps": None if self.processed_fps is None else round(self.processed_fps, 2),
            "starved": self.starved,
            "frame_ms_p95": None if self.frame_ms_p95 is None else round(self.frame_ms_p95, 1),
            "phases": self.phases, "messages": self.messages,
            "baseline": not self.spec.companion, "lockstep": self.spec.lockstep,
            "world_t_trigger": None if self.world_t_trigger is None else round(self.world_t_trigger, 2),
            "in_free_area": self.in_free_area,
            "touchdown_surfaces": self.touchdown_surfaces,
            "unlandable_touchdown": self.unlandable_touchdown,
            "zone_losses": len(self.zone_losses),
            "zone_losses_r0_free": sum(z.nearest_m >= self.spec.r0_m for z in self.zone_losses),
            "zone_loss_nearest_m": [None if not math.isfinite(z.nearest_m) else round(z.nearest_m, 2)
                                    for z in self.zone_losses],
            # Only a camera other than the scenarios' own: rows flown with it stay as they were.
            **({} if camera_name(self.spec) == DEFAULT_CAMERA else {"camera": camera_name(self.spec)}),
            # Only with runners in the crossing world: rows without stay as the yardstick has them.
            **({"runners": self.spec.runners} if self.spec.runners else {}),
            # Only when not the drawn ground: the procedural rows stay as the yardstick has them.
            **({} if self.spec.ground == "procedural" else {"ground": self.spec.ground}),
        }


#: Widest horizontal field of view a ``--camera`` may ask (degrees; ``camera.hfov_deg``'s bound).
MAX_CAMERA_HFOV = 179.0


def camera_name(spec: FlightSpec) -> str:
    """``MODEL:HFOV`` of a flight's camera, e.g. ``fisheye:160``."""
    return f"{spec.camera_model}:{spec.hfov_deg:g}"


def parse_camera(text: str) -> tuple[str, float]:
    """``MODEL:HFOV`` (``pinhole:70``, ``pinhole:110``, ``fisheye:160``) -> (model, degrees);
    ValueError saying what is wrong."""
    from companion.geometry.lens import MODELS

    model, sep, hfov = text.partition(":")
    if not sep or model not in MODELS:
        raise ValueError(f"want MODEL:HFOV with MODEL one of {', '.join(MODELS)}, e.g. fisheye:160, not {text!r}")
    try:
        deg = float(hfov)
    except ValueError:
        raise ValueError(f"the field of view must be degrees, not {hfov!r}") from None
    if not (math.isfinite(deg) and 1.0 <= deg <= MAX_CAMERA_HFOV):
        raise ValueError(f"the field of view must be 1-{MAX_CAMERA_HFOV:g} degrees, not {hfov!r}")
    return model, deg


@dataclass(frozen=True)
class ZoneLoss:
    """A zone the landing controller gave up while over it, and the truth at that moment.

    t: the controller event's time (``time.monotonic()`` of the service, the clock of the
    flight's truth samples: one host). zone_id, reason: the event's (its ``reason``, or the
    words between "lost (" and ")" of a re-targeting). nearest_m: the horizontal distance (m) from
    the vehicle to the nearest person of the world at the last truth sample at or before ``t``
    (inf: nobody in the world, or no sample yet)."""

    t: float
    zone_id: int
    reason: str
    nearest_m: float


def service_settings(spec: FlightSpec) -> tuple[str, ...]:
    """The ``KEY=VALUE`` settings the flight's service runs with (``--set``, in this order: the
    scenario's camera and r0, then ``spec.service_set``, which wins): one list for the service
    and for ``sim.flights.scenarios.machine_check``, which times the same pipeline."""
    lens = () if spec.camera_model == "pinhole" else (f"camera.model={spec.camera_model}",)
    return (f"camera.hfov_deg={spec.hfov_deg}", *lens, f"camera.fps={spec.fps}", f"pipeline.r0_m={spec.r0_m}",
            "log.health_interval_s=5", *spec.service_set)


def service_command(spec: FlightSpec, link_port: int, camera_url: str, record_dir: Path) -> list[str]:
    """``companion run`` as the flight starts it (a subprocess, like systemd would)."""
    cmd = [sys.executable, "-m", "companion", "--log-level", "INFO", "run",
           "--link", f"udpin:127.0.0.1:{link_port}", "--camera", camera_url,
           "--flavour", spec.flavour, "--record", str(record_dir)]
    for item in service_settings(spec):
        cmd += ["--set", item]
    return cmd


def default_photos() -> Path:
    """``../shared/data/semantic_drone/full`` beside the checkout the package runs from."""
    return Path(__file__).resolve().parents[2].parent / "shared" / "data" / "semantic_drone" / "full"


def photos_folder(ground: str, photos: Path | None) -> str | None:
    """The checked photos folder (absolute) of a photo ground, None for the drawn one; raises
    ValueError naming the folder when it is missing or malformed (``sim.world.photo_ground.check_photos``),
    before anything flies."""
    if ground != "photo":
        if photos is not None:
            raise ValueError("--photos needs --ground photo")
        return None
    folder = (photos if photos is not None else default_photos()).resolve()
    try:
        check_photos(folder)
    except PhotosError as exc:
        raise ValueError(str(exc)) from None
    return str(folder)


@dataclass(frozen=True)
class CameraAndPhotos:
    """``--camera`` and ``--photos`` checked: camera (model, horizontal field of view in degrees),
    None where no ``--camera`` was given; photos the absolute photos folder of a photo ground, None
    for the drawn one."""

    camera: tuple[str, float] | None
    photos: str | None


def parse_camera_and_photos(prog: str, camera: str | None, ground: str,
                            photos: Path | None) -> CameraAndPhotos | str:
    """The flight commands' ``--camera`` (``parse_camera``) and ``--photos`` (``photos_folder``)
    checked before anything flies, or the message to print before exit 2: ``"{prog}: --camera:
    ..."`` or ``"{prog}: --photos: ..."``."""
    try:
        lens = None if camera is None else parse_camera(camera)
    except ValueError as exc:
        return f"{prog}: --camera: {exc}"
    try:
        folder = photos_folder(ground, photos)
    except ValueError as exc:
        return f"{prog}: --photos: {exc}"
    return CameraAndPhotos(lens, folder)
