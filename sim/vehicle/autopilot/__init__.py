"""What an autopilot does on top of the vehicle: modes, commands, telemetry, failsafes.

``Autopilot`` holds the behaviour common to ArduPilot Copter (``sim.vehicle.ardupilot``) and PX4
(``sim.vehicle.px4``): telemetry message construction, message-interval scheduling per link, the command
dispatcher with its COMMAND_ACK results, position-target parsing, return-to-launch and landing
sequences, and failsafes. Each flavour maps its own ``custom_mode`` numbers onto a small set of
``Behaviour``s and decides which commands it accepts in which state, as its firmware does.

Units: world = local NED metres from home, ground ``z = 0``; MAVLink fields in their own units
(degE7, mm, cm/s, cdeg) are converted at the message boundary only. Times are seconds of the
simulator clock, ``time_boot_ms`` counts from the simulator start.

The autopilot's own local frame (LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED in
MAV_FRAME_LOCAL_NED, HOME_POSITION x/y/z) has its origin at the estimator's origin, which a flavour
may put ``origin_down_m()`` metres below home (world down); horizontally it is home. In that frame
``z_local = world_down - origin_down_m()``. ArduPilot's is home here (0); PX4's is
``AutopilotConfig.origin_alt_offset_m``.

Package layout, one concern per module (``Autopilot`` combines the mixins):

- ``base``: shared types and helpers (``Behaviour``, ``Channel``, ``StreamSchedule``,
  ``AutopilotConfig``, ``GeoFrame``, ``Setpoint``, ``quaternion_from_euler``) and
  ``AutopilotHost``, what the mixins call on one another and on the flavour;
- ``modes``: mode/behaviour switching, arming, takeoff, landing and RTL sequences;
- ``commands``: incoming-message dispatch, COMMAND_LONG/COMMAND_INT with their COMMAND_ACK,
  SET_MODE, position-target parsing;
- ``params``: the handful of parameters (PARAM_REQUEST_* / PARAM_SET);
- ``telemetry``: message construction, stream scheduling, STATUSTEXT, reported states;
- ``failsafes``: raising, reacting to and clearing failsafes;
- ``core``: ``Autopilot`` itself: state, flavour hooks and the periodic ``tick``.
"""

from __future__ import annotations

from sim.vehicle.autopilot.base import (
    AutopilotConfig,
    Behaviour,
    Channel,
    GeoFrame,
    MAVMessage,
    R,
    Setpoint,
    StreamSchedule,
    quaternion_from_euler,
)
from sim.vehicle.autopilot.commands import CommandsMixin
from sim.vehicle.autopilot.core import Autopilot
from sim.vehicle.autopilot.failsafes import FailsafesMixin
from sim.vehicle.autopilot.modes import ModesMixin
from sim.vehicle.autopilot.params import ParamsMixin
from sim.vehicle.autopilot.telemetry import TelemetryMixin

__all__ = [
    "Autopilot", "AutopilotConfig", "Behaviour", "Channel", "CommandsMixin", "FailsafesMixin",
    "GeoFrame", "MAVMessage", "ModesMixin", "ParamsMixin", "R", "Setpoint", "StreamSchedule",
    "TelemetryMixin", "quaternion_from_euler",
]
