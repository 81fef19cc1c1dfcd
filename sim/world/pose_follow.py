"""The simulated camera riding on an external vehicle: a real ArduPilot or PX4 SITL.

``companion sim --camera-only --pose-from URL`` starts no simulated vehicle. It reads the SITL's
pose over MAVLink (HOME_POSITION, GLOBAL_POSITION_INT, ATTITUDE, asked for with
``MAV_CMD_SET_MESSAGE_INTERVAL`` as the service asks) through the service's own link and vehicle
state (``companion.mavlink``), so the camera sees the simulated crowd from where the service
believes the vehicle is: world = local NED metres from the SITL's home, as the service's. It serves
that view as the MJPEG camera the service reads (docs/sitl.md).

It speaks as component 100 (``MAV_COMP_ID_CAMERA``) of the vehicle's system, beside the service
(191) on the same vehicle; it sends no command but the message-interval requests.
"""

from __future__ import annotations

import time

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.geometry.camera import Pose
from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.state import VehicleState

#: What the camera needs: the pose fast enough for the frame rate, home for the world's origin.
POSE_RATES_HZ = {"ATTITUDE": 25.0, "GLOBAL_POSITION_INT": 10.0, "HOME_POSITION": 0.5}


class NoPose(LookupError):
    """No trustworthy pose yet (no home, no telemetry, or stale telemetry)."""


class ExternalPose:
    """The pose of the vehicle at ``url`` now, for :class:`sim.world.camera_server.CameraServer`.

    ``pose()`` raises :class:`NoPose` until home and telemetry have arrived, and whenever the
    newest sample is older than ``max_hold_s`` (the camera counts the failed render and shows no
    frame rather than a wrong one).
    """

    def __init__(self, url: str, system_id: int = 1, target_system: int | None = None,
                 max_hold_s: float = 0.5) -> None:
        self.link = MavLink(LinkConfig(url=url, system_id=system_id, component_id=m.MAV_COMP_ID_CAMERA,
                                       target_system=target_system, message_rates_hz=dict(POSE_RATES_HZ)))
        self.state = VehicleState(max_extrapolation_s=max_hold_s)
        self.state.attach(self.link)

    async def start(self) -> None:
        await self.link.start()

    async def close(self) -> None:
        await self.link.close()

    def pose(self) -> Pose:
        pose = self.state.pose_at(time.monotonic())
        if pose is None:
            raise NoPose("no pose from the vehicle yet" if self.state.home is None else "vehicle pose is stale")
        return pose
