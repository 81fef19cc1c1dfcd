"""Which autopilot flavour talks to the vehicle: ArduPilot Copter or PX4.

Kept apart from the flavours' common base (``autopilot.py``) so that base and flavours never
import each other: this module sits above both.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.ardupilot import ArduPilotCopter
from companion.mavlink.autopilot import Autopilot, FlavourError
from companion.mavlink.link import MavLink
from companion.mavlink.px4 import PX4


def select_flavour(link: MavLink, override: str = "auto") -> Autopilot:
    """The flavour named by ``override`` ("ardupilot", "px4"), or from the heartbeat with "auto".

    With "auto" the link must have heard the autopilot (``link.vehicle_autopilot``).
    """
    if override == "ardupilot":
        return ArduPilotCopter(link)
    if override == "px4":
        return PX4(link)
    if override != "auto":
        raise FlavourError(f"autopilot flavour must be auto, ardupilot or px4, not {override!r}")
    if link.vehicle_autopilot == m.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return ArduPilotCopter(link)
    if link.vehicle_autopilot == m.MAV_AUTOPILOT_PX4:
        return PX4(link)
    raise FlavourError(
        f"cannot choose the autopilot flavour from heartbeat autopilot={link.vehicle_autopilot!r}; "
        "set link.flavour to ardupilot or px4"
    )
