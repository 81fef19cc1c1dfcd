"""What the landing controller needs from an autopilot, whatever its dialect.

An ``Autopilot`` flavour knows its flight modes and how to: fly to a point and hold there
(``goto``), land where it is (``land``), loiter (``hold_position``) and hand control back to its own
failsafe (``handback``: LAND or RTL). Every mode change is a ``MAV_CMD_DO_SET_MODE`` with
``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` that waits for its COMMAND_ACK (``MavLink.command_long``:
retries, timeout); a refusal raises ``CommandRefused`` and a silence ``CommandTimeout``, both
``CommandError``, which the controller's runner counts.

``companion.mavlink.flavours.select_flavour`` picks ArduPilot or PX4.
"""

from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.commands import PositionTarget
from companion.mavlink.link import MavLink
from companion.mavlink.params import read_params

log = logging.getLogger(__name__)

#: Speeds read from an autopilot outside this range (m/s) are not believed (a unit mix-up, a
#: garbled value): the configured speed stays.
PLAUSIBLE_SPEED_MPS = (0.05, 20.0)

# SET_POSITION_TARGET_* type_mask: use x/y/z only; ignore velocity, acceleration, yaw, yaw rate.
TYPE_MASK_POSITION_ONLY = (
    m.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | m.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | m.POSITION_TARGET_TYPEMASK_VZ_IGNORE
    | m.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | m.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | m.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | m.POSITION_TARGET_TYPEMASK_YAW_IGNORE
    | m.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)  # = 0x0DF8 = 3576


class FlavourError(ValueError):
    """An unknown flavour name or a mode the flavour does not have."""


class Autopilot(ABC):
    """One flavour of autopilot behind a ``MavLink``. ``mode`` follows the autopilot's heartbeat."""

    name = "autopilot"
    #: mode names that mean the autopilot's own failsafe is landing or returning
    FAILSAFE_MODES = frozenset({"LAND", "RTL"})

    #: The parameters that set how fast the vehicle comes down: name -> (``DescentProfile`` field,
    #: factor to m/s). Empty: the configured speeds are used.
    DESCENT_PARAMS: dict[str, tuple[str, float]] = {}

    def __init__(self, link: MavLink) -> None:
        self.link = link
        self.mode: str | None = None  # current mode name from the last autopilot heartbeat
        self.commanded_mode: str | None = None  # last mode we asked for (acked or not)
        self.commanded_t: float | None = None
        link.subscribe("HEARTBEAT", self._on_heartbeat)
        if link.last_heartbeat is not None:
            self._on_heartbeat(link.last_heartbeat, 0.0)

    def _on_heartbeat(self, msg: Any, _t: float) -> None:
        if self.link.is_autopilot_heartbeat(msg):
            self.mode = self.mode_name(msg.base_mode, msg.custom_mode)

    async def descent_speeds(self, *, timeout_s: float = 1.0, retries: int = 2) -> dict[str, float]:
        """The autopilot's own descent speeds (m/s) by ``DescentProfile`` field, read from its
        parameters (``DESCENT_PARAMS``): those it answered in time with a plausible value."""
        if not self.DESCENT_PARAMS:
            return {}
        values = await read_params(self.link, self.DESCENT_PARAMS, timeout_s=timeout_s, retries=retries)
        speeds: dict[str, float] = {}
        lo, hi = PLAUSIBLE_SPEED_MPS
        for name, raw in values.items():
            field, factor = self.DESCENT_PARAMS[name]
            mps = raw * factor
            if lo <= mps <= hi:
                speeds[field] = mps
            else:
                log.warning("autopilot parameter %s = %g gives %g m/s, outside %g-%g m/s: not used",
                            name, raw, mps, lo, hi)
        return speeds

    # -- modes -------------------------------------------------------------------------------

    @abstractmethod
    def mode_name(self, base_mode: int, custom_mode: int) -> str:
        """The name of a heartbeat's mode (``"GUIDED"``, ``"LAND"``, ...) or ``"MODE(n)"``."""

    @abstractmethod
    def mode_params(self, name: str) -> tuple[float, ...]:
        """DO_SET_MODE params (base mode, custom main mode, custom sub mode) for a mode name."""

    async def set_mode(self, name: str, *, timeout_s: float | None = None, retries: int | None = None) -> None:
        """Switch mode and wait for the ack; raises ``CommandError`` (``FlavourError`` for a bad name).

        ``timeout_s``/``retries``: per-attempt wait and resends (default: the link's)."""
        params = self.mode_params(name)
        # Recorded before sending: the heartbeat showing the new mode may overtake the ack, and
        # the failsafe monitor must know this switch was ours, not the autopilot's own failsafe.
        self.commanded_mode = name
        self.commanded_t = time.monotonic()
        await self.link.command_long(m.MAV_CMD_DO_SET_MODE, params, timeout_s=timeout_s, retries=retries)
        self.mode = name  # the next heartbeat confirms; meanwhile do not command it twice
        log.info("%s: mode %s", self.name, name)

    # -- actions -----------------------------------------------------------------------------

    @abstractmethod
    async def goto(self, target: PositionTarget) -> None:
        """Enter the external-control mode if needed and fly to ``target``, holding there."""

    async def land(self, *, timeout_s: float | None = None, retries: int | None = None) -> None:
        """Land where the vehicle is (the autopilot descends vertically)."""
        await self.stop()
        await self.set_mode("LAND", timeout_s=timeout_s, retries=retries)

    async def rtl(self, *, timeout_s: float | None = None, retries: int | None = None) -> None:
        await self.stop()
        await self.set_mode("RTL", timeout_s=timeout_s, retries=retries)

    async def loiter(self) -> None:
        await self.stop()
        await self.set_mode("LOITER")

    async def handback(self, action: str, *, timeout_s: float | None = None, retries: int | None = None) -> None:
        """Give control back to the autopilot's own failsafe: ``action`` is "LAND" or "RTL".

        ``timeout_s``/``retries`` as for ``set_mode`` (shutdown resends quickly within its 2 s)."""
        if action not in self.FAILSAFE_MODES:
            raise FlavourError(f"handback action must be LAND or RTL, not {action!r}")
        switch = self.land if action == "LAND" else self.rtl
        await switch(timeout_s=timeout_s, retries=retries)

    async def stop(self) -> None:  # noqa: B027 - a no-op by default, not abstract: ArduPilot streams nothing
        """Stop any background stream (PX4's setpoints). Idempotent."""

    #: SET_POSITION_TARGET_GLOBAL_INT frame: altitude above home. ArduPilot Copter turns it into a
    #: Location with ALT_FRAME_ABOVE_HOME and converts through home's altitude, which is right.
    TARGET_FRAME = m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT

    def target_altitude(self, target: PositionTarget) -> float:
        """The ``alt`` field of the target in ``TARGET_FRAME`` (metres)."""
        return target.rel_alt_m

    def position_target_message(self, target: PositionTarget) -> Any:
        """SET_POSITION_TARGET_GLOBAL_INT, position only, in the flavour's ``TARGET_FRAME``."""
        return self.link.mav.set_position_target_global_int_encode(
            int(time.monotonic() * 1000) & 0xFFFFFFFF,
            self.link.target_system,
            self.link.config.target_component,
            self.TARGET_FRAME,
            TYPE_MASK_POSITION_ONLY,
            round(target.lat_deg * 1e7),
            round(target.lon_deg * 1e7),
            self.target_altitude(target),
            0, 0, 0, 0, 0, 0, 0, 0,
        )


FLAVOURS = ("ardupilot", "px4")
