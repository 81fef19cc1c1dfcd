"""``companion sim``: run the simulated vehicle (and, with ``--camera``, its world and camera).

    companion sim --flavour px4 --out udpout:127.0.0.1:14540 --start-alt 30
    companion sim --out udp:127.0.0.1:14550 --out udpout:127.0.0.1:14540 --camera
    companion sim --camera-only --pose-from udpin:127.0.0.1:14551    # a real SITL flies (docs/sitl.md)

Like SITL's ``--out``, each ``--out`` is a UDP address the vehicle streams telemetry to and whose
replies it obeys; ``udpin:HOST:PORT`` binds a port instead and answers whoever sends to it.

The vehicle forwards MAVLink between its links as the real autopilot does (``sim.vehicle.routing``), so a
ground station on one ``--out`` sees the companion on another: ArduPilot on every link, PX4 only
between links marked ``?forward=1`` (its ``MAV_X_FORWARD``):

    companion sim --flavour px4 --out "udpout:127.0.0.1:14540?forward=1" \
        --out "udpin:127.0.0.1:14560?forward=1"
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math

from sim.vehicle.autopilot import AutopilotConfig
from sim.vehicle.endpoint import parse_url
from sim.vehicle.faults import Failsafe
from sim.vehicle.kinematics import VehicleParams
from sim.vehicle.simulator import FLAVOURS, SimConfig, Simulator

log = logging.getLogger("sim")


def _home(text: str) -> tuple[float, float, float]:
    try:
        lat, lon, alt = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--home wants LAT,LON,ALT_M, got {text!r}") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180 and math.isfinite(alt)):
        raise argparse.ArgumentTypeError(f"--home {text!r} is not a place on Earth")
    return lat, lon, alt


def _out(text: str) -> str:
    try:
        parse_url(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _pose_url(text: str) -> str:
    from companion.mavlink.transports import TransportError
    from companion.mavlink.transports import parse_url as parse_link_url

    try:
        parse_link_url(text)
    except TransportError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--flavour", choices=FLAVOURS, default="ardupilot",
                        help="which autopilot to behave like (default ardupilot)")
    parser.add_argument("--out", action="append", type=_out, metavar="URL",
                        help="MAVLink output, udpout:HOST:PORT (alias udp:) or udpin:HOST:PORT, "
                             "optionally ?forward=1 (PX4's MAV_X_FORWARD on that link: PX4 forwards "
                             "only between such links; ArduPilot routes on all); repeatable; "
                             "default udpout:127.0.0.1:14550")
    parser.add_argument("--start-alt", type=float, default=0.0,
                        help="start airborne this many metres above home (0 = on the ground)")
    parser.add_argument("--start-north", type=float, default=0.0, help="start position, m north of home")
    parser.add_argument("--start-east", type=float, default=0.0, help="start position, m east of home")
    parser.add_argument("--start-yaw-deg", type=float, default=0.0, help="start heading, degrees")
    parser.add_argument("--takeoff-alt", type=float, default=None,
                        help="start on the ground, then arm and climb to this altitude (m)")
    parser.add_argument("--home", type=_home, default=None, metavar="LAT,LON,ALT",
                        help="home in degrees and metres AMSL (default PX4's Zurich SITL home)")
    parser.add_argument("--sysid", type=int, default=1, help="MAVLink system id (default 1)")
    parser.add_argument("--origin-alt-offset", type=float, default=0.0, metavar="M",
                        help="PX4: home altitude minus the EKF origin's, m (SIH showed -1.48); "
                             "non-zero reproduces PX4's GLOBAL_RELATIVE_ALT_INT altitude error")
    parser.add_argument("--failsafe-action", choices=("land", "rtl"), default=None,
                        help="what every failsafe does (default: battery low RTL, others LAND; "
                             "PX4 only warns on battery low)")
    parser.add_argument("--failsafe", choices=[f.value for f in Failsafe], default=None,
                        help="raise this failsafe after --failsafe-after seconds")
    parser.add_argument("--failsafe-after", type=float, default=30.0, help="seconds (default 30)")
    parser.add_argument("--speed", type=float, default=5.0, help="horizontal speed limit m/s (WPNAV_SPEED)")
    parser.add_argument("--land-speed", type=float, default=0.5, help="final descent m/s (LAND_SPEED)")
    parser.add_argument("--loss", type=float, default=0.0, help="packet loss probability per direction")
    parser.add_argument("--latency-ms", type=float, default=0.0, help="added one-way latency, ms")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--seed", type=int, default=0, help="random seed (link faults, world)")
    cam = parser.add_argument_group("camera and world (needs sim.world.crowd / sim.world.camera_server)")
    cam.add_argument("--camera", action="store_true",
                     help="also simulate a crowd and serve the downward camera as MJPEG")
    cam.add_argument("--camera-port", type=int, default=8080, help="TCP port on 127.0.0.1 (default 8080)")
    cam.add_argument("--fps", type=float, default=12.0, help="camera frames per second")
    cam.add_argument("--hfov-deg", type=float, default=70.0, help="camera horizontal field of view")
    cam.add_argument("--width", type=int, default=640)
    cam.add_argument("--height", type=int, default=480)
    ext = parser.add_argument_group("camera on an external vehicle (a real ArduPilot or PX4 SITL; docs/sitl.md)")
    ext.add_argument("--camera-only", action="store_true",
                     help="no simulated vehicle: only the crowd and the camera, which follows the pose "
                          "read with --pose-from")
    ext.add_argument("--pose-from", metavar="URL", type=_pose_url, default=None,
                     help="MAVLink URL of the external vehicle (udpin:HOST:PORT, tcp:HOST:PORT, ...): its "
                          "HOME_POSITION, GLOBAL_POSITION_INT and ATTITUDE place the camera")


def build_config(args: argparse.Namespace) -> SimConfig:
    """The simulator configuration the command-line arguments describe."""
    ap = AutopilotConfig(system_id=args.sysid, origin_alt_offset_m=args.origin_alt_offset)
    if args.home is not None:
        ap.home_lat, ap.home_lon, ap.home_alt = args.home
    if args.failsafe_action is not None:
        ap.failsafe_action = {kind: args.failsafe_action for kind in Failsafe}
    if args.start_alt < 0:
        raise ValueError("--start-alt must be >= 0 (metres above home)")
    return SimConfig(
        flavour=args.flavour,
        outputs=list(args.out or ["udpout:127.0.0.1:14550"]),
        start_position=(args.start_north, args.start_east, -args.start_alt),
        start_yaw=math.radians(args.start_yaw_deg),
        vehicle=VehicleParams(max_speed_xy=args.speed, land_speed=args.land_speed),
        autopilot=ap, seed=args.seed)


async def _camera_only(args: argparse.Namespace) -> int:
    """The crowd and the camera, the camera riding on the external vehicle at ``--pose-from``."""
    from companion.geometry.camera import Intrinsics, Mount
    from sim.world.camera_server import CameraServer
    from sim.world.crowd import default_world
    from sim.world.pose_follow import ExternalPose, NoPose

    vehicle = ExternalPose(args.pose_from, system_id=args.sysid)
    world = default_world(seed=args.seed)
    intr = Intrinsics.from_fov(args.width, args.height, args.hfov_deg)
    camera = CameraServer(vehicle.pose, world, intr, Mount(), fps=args.fps, port=args.camera_port,
                          advance_world=True)
    await vehicle.start()
    try:
        async with camera:
            log.info("camera at %s, following the vehicle on %s", camera.url, args.pose_from)
            loop = asyncio.get_running_loop()
            start = loop.time()
            while args.duration is None or loop.time() - start < args.duration:
                await asyncio.sleep(1.0)
                try:
                    p = vehicle.pose()
                    log.info("pose N %.1f E %.1f alt %.1f m yaw %.0f deg; frames %d",
                             p.north, p.east, -p.down, math.degrees(p.yaw), camera.frames_rendered)
                except NoPose as exc:
                    log.info("waiting: %s (HOME_POSITION, GLOBAL_POSITION_INT, ATTITUDE on %s)", exc,
                             args.pose_from)
    finally:
        await vehicle.close()
    return 0


async def _main(args: argparse.Namespace) -> int:
    if args.camera_only:
        return await _camera_only(args)
    config = build_config(args)
    world = camera = None
    if args.camera:
        try:
            from companion.geometry.camera import Intrinsics, Mount
            from sim.world.camera_server import CameraServer
            from sim.world.crowd import default_world
        except ImportError as exc:
            log.error("--camera needs the world and camera modules: %s", exc)
            return 2
        world = default_world(seed=args.seed)
    sim = Simulator(config, world=world)
    if world is not None:
        intr = Intrinsics.from_fov(args.width, args.height, args.hfov_deg)
        camera = CameraServer(sim.pose, world, intr, Mount(), fps=args.fps, port=args.camera_port)
    async with sim:
        if camera is not None:
            await camera.start()
            log.info("camera at %s", camera.url)
        if args.takeoff_alt:
            sim.take_off(args.takeoff_alt)
        for link in sim.links:
            log.info("%s MAVLink on %s (local %s)", config.flavour, link.url, link.local_address)
        if args.loss or args.latency_ms:
            sim.set_link_faults(loss=args.loss, latency_s=args.latency_ms / 1000.0)
        loop = asyncio.get_running_loop()
        start = loop.time()
        raised = False
        try:
            while args.duration is None or loop.time() - start < args.duration:
                await asyncio.sleep(1.0)
                if args.failsafe and not raised and loop.time() - start >= args.failsafe_after:
                    sim.inject_failsafe(args.failsafe)
                    raised = True
                t = sim.truth
                log.info("mode %s %s alt %.1f m pos N %.1f E %.1f battery %.0f%% bad packets %d "
                         "forwarded %d", t.mode, "armed" if t.armed else "disarmed", t.altitude,
                         t.position[0], t.position[1], 100 * t.battery_remaining, sim.bad_packets,
                         sim.routing.stats.forwarded)
        finally:
            if camera is not None:
                await camera.stop()
    return 0


def run(args: argparse.Namespace) -> int:
    try:
        config_error = None
        build_config(args)
    except ValueError as exc:
        config_error = str(exc)
    if not config_error and args.camera_only != (args.pose_from is not None):
        config_error = "--camera-only and --pose-from go together: the camera follows the vehicle at --pose-from"
    if config_error:
        print(f"companion sim: {config_error}")
        return 2
    with contextlib.suppress(KeyboardInterrupt):
        return asyncio.run(_main(args))
    return 0
