"""ArduPilot Copter: GUIDED with SET_POSITION_TARGET_GLOBAL_INT, then LAND over the zone.

Copter's custom modes are plain numbers (``custom_mode`` = mode). GUIDED holds the last position
target by itself, so no stream is needed; LAND descends vertically where the vehicle is.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.commands import PositionTarget
from companion.mavlink.autopilot import Autopilot, FlavourError

# ArduCopter flight modes (Copter's mode numbers, ardupilotmega COPTER_MODE_*).
COPTER_MODES: dict[str, int] = {
    "STABILIZE": m.COPTER_MODE_STABILIZE,  # 0
    "ALT_HOLD": m.COPTER_MODE_ALT_HOLD,  # 2
    "AUTO": m.COPTER_MODE_AUTO,  # 3
    "GUIDED": m.COPTER_MODE_GUIDED,  # 4
    "LOITER": m.COPTER_MODE_LOITER,  # 5
    "RTL": m.COPTER_MODE_RTL,  # 6
    "LAND": m.COPTER_MODE_LAND,  # 9
    "POSHOLD": m.COPTER_MODE_POSHOLD,  # 16
    "BRAKE": m.COPTER_MODE_BRAKE,  # 17
    "SMART_RTL": m.COPTER_MODE_SMART_RTL,  # 21
}
_NAMES = {v: k for k, v in COPTER_MODES.items()}


class ArduPilotCopter(Autopilot):
    name = "ardupilot"
    GUIDED = "GUIDED"
    FAILSAFE_MODES = frozenset({"LAND", "RTL", "SMART_RTL"})
    # GUIDED comes down at WPNAV_SPEED_DN; LAND below LAND_ALT_LOW (10 m by default, where the
    # companion commands it) at LAND_SPEED. Both in cm/s.
    DESCENT_PARAMS = {"WPNAV_SPEED_DN": ("descend_speed_mps", 0.01), "LAND_SPEED": ("land_speed_mps", 0.01)}

    def mode_name(self, base_mode: int, custom_mode: int) -> str:
        return _NAMES.get(custom_mode, f"MODE({custom_mode})")

    def mode_params(self, name: str) -> tuple[float, ...]:
        if name not in COPTER_MODES:
            raise FlavourError(f"ArduCopter has no mode {name!r}")
        return (m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES[name])

    async def goto(self, target: PositionTarget) -> None:
        if self.mode != self.GUIDED:
            await self.set_mode(self.GUIDED)
        self.link.send(self.position_target_message(target))
