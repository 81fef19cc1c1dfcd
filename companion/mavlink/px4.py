"""PX4: OFFBOARD with a setpoint stream, then AUTO.LAND over the zone.

PX4's ``custom_mode`` packs the main mode in bits 16-23 and the sub mode in bits 24-31; DO_SET_MODE
takes them as param2 and param3. OFFBOARD is refused unless setpoints are already arriving, and
PX4 leaves OFFBOARD (its COM_OBL_RC_ACT action) if they stop for COM_OF_LOSS_T, so ``goto`` starts a
SET_POSITION_TARGET_GLOBAL_INT stream at ``setpoint_rate_hz`` (>= 5 Hz, well above PX4's 2 Hz
minimum) and only then switches, after ``warmup_s`` (PX4 >= 1.14 wants the offboard signal for
more than 1 s before it allows the switch); the stream runs until the vehicle is told to land, loiter or
return. Targets go in frame 5 (GLOBAL_INT, altitude above mean sea level), which PX4 converts
correctly; its frame-6 conversion is wrong (see ``TARGET_FRAME``).
"""

from __future__ import annotations

import asyncio
import logging

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.commands import PositionTarget
from companion.mavlink.autopilot import Autopilot, FlavourError
from companion.mavlink.link import MavLink

log = logging.getLogger(__name__)

# PX4 main modes (px4_custom_mode.h) and AUTO sub modes.
MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD, MAIN_STABILIZED = 1, 2, 3, 4, 5, 6, 7
AUTO_READY, AUTO_TAKEOFF, AUTO_LOITER, AUTO_MISSION, AUTO_RTL, AUTO_LAND = 1, 2, 3, 4, 5, 6

PX4_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (MAIN_MANUAL, 0),
    "ALTCTL": (MAIN_ALTCTL, 0),
    "POSCTL": (MAIN_POSCTL, 0),
    "OFFBOARD": (MAIN_OFFBOARD, 0),
    "STABILIZED": (MAIN_STABILIZED, 0),
    "ACRO": (MAIN_ACRO, 0),
    "TAKEOFF": (MAIN_AUTO, AUTO_TAKEOFF),
    "LOITER": (MAIN_AUTO, AUTO_LOITER),
    "MISSION": (MAIN_AUTO, AUTO_MISSION),
    "RTL": (MAIN_AUTO, AUTO_RTL),
    "LAND": (MAIN_AUTO, AUTO_LAND),
}
_NAMES = {v: k for k, v in PX4_MODES.items()}


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """The HEARTBEAT ``custom_mode`` of a PX4 main/sub mode."""
    return (main << 16) | (sub << 24)


class PX4(Autopilot):
    name = "px4"
    OFFBOARD = "OFFBOARD"
    # OFFBOARD position setpoints come down at most at MPC_Z_VEL_MAX_DN; AUTO.LAND's final
    # descent is MPC_LAND_SPEED. Both in m/s.
    DESCENT_PARAMS = {"MPC_Z_VEL_MAX_DN": ("descend_speed_mps", 1.0), "MPC_LAND_SPEED": ("land_speed_mps", 1.0)}

    def __init__(self, link: MavLink, *, setpoint_rate_hz: float = 10.0, warmup_s: float = 1.2) -> None:
        super().__init__(link)
        if setpoint_rate_hz < 5.0:
            raise FlavourError(f"PX4 setpoint_rate_hz must be >= 5 Hz, not {setpoint_rate_hz}")
        self.setpoint_rate_hz = setpoint_rate_hz
        self.warmup_s = warmup_s
        self.target: PositionTarget | None = None
        self._stream: asyncio.Task[None] | None = None
        self.setpoints_sent = 0

    def mode_name(self, base_mode: int, custom_mode: int) -> str:
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        if main != MAIN_AUTO:
            sub = 0
        return _NAMES.get((main, sub), f"MODE({main}.{sub})")

    def mode_params(self, name: str) -> tuple[float, ...]:
        if name not in PX4_MODES:
            raise FlavourError(f"PX4 has no mode {name!r}")
        main, sub = PX4_MODES[name]
        return (m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)

    @property
    def streaming(self) -> bool:
        return self._stream is not None and not self._stream.done()

    # Frame 5, altitude above mean sea level, never frame 6. PX4's MAVLink receiver (1.15 to 1.17)
    # converts frame 6 as z = (home_alt - alt) - ref_alt instead of ref_alt - home_alt - alt, so
    # every target is off by twice the altitude between home and the estimator's origin: 1.48 m
    # apart in SIH made each target about 3 m too high, and a vehicle told to descend climbed to
    # 220 m. Frame 5 is converted as z = ref_alt - alt, which is right. See docs/autopilot.md.
    TARGET_FRAME = m.MAV_FRAME_GLOBAL_INT

    def target_altitude(self, target: PositionTarget) -> float:
        if target.amsl_m is None:
            raise FlavourError("PX4 targets need home's altitude above mean sea level (HOME_POSITION)")
        return target.amsl_m

    async def goto(self, target: PositionTarget) -> None:
        self.target_altitude(target)  # refuse before streaming anything PX4 would misread
        self.target = target
        if not self.streaming:
            self._stream = asyncio.create_task(self._stream_loop(), name="px4 setpoints")
            await asyncio.sleep(self.warmup_s)
        if self.mode != self.OFFBOARD:
            try:
                await self.set_mode(self.OFFBOARD)
            except Exception:
                await self.stop()  # not in OFFBOARD: a stream nobody follows only confuses logs
                raise

    async def _stream_loop(self) -> None:
        period = 1.0 / self.setpoint_rate_hz
        while True:
            if self.target is not None:
                self.link.send(self.position_target_message(self.target))
                self.setpoints_sent += 1
            await asyncio.sleep(period)

    async def stop(self) -> None:
        if self._stream is not None:
            self._stream.cancel()
            try:
                await self._stream
            except asyncio.CancelledError:
                pass
            self._stream = None

    async def land(self, *, timeout_s: float | None = None, retries: int | None = None) -> None:
        # Switch first, then stop the stream: stopping first would make PX4 fire its
        # offboard-loss action before the LAND command arrives.
        await self.set_mode("LAND", timeout_s=timeout_s, retries=retries)
        await self.stop()

    async def rtl(self, *, timeout_s: float | None = None, retries: int | None = None) -> None:
        await self.set_mode("RTL", timeout_s=timeout_s, retries=retries)
        await self.stop()

    async def loiter(self) -> None:
        await self.set_mode("LOITER")
        await self.stop()
