"""``Autopilot``: the mixins combined, with its state, the flavour hooks and the periodic step."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

from sim.vehicle.autopilot.base import AutopilotConfig, Behaviour, GeoFrame, R, Setpoint
from sim.vehicle.autopilot.commands import CommandsMixin
from sim.vehicle.autopilot.failsafes import FailsafesMixin
from sim.vehicle.autopilot.modes import ModesMixin
from sim.vehicle.autopilot.params import ParamsMixin
from sim.vehicle.autopilot.telemetry import TelemetryMixin
from sim.vehicle.faults import Failsafe
from sim.vehicle.kinematics import Demand, Vehicle


class Autopilot(ModesMixin, CommandsMixin, ParamsMixin, TelemetryMixin, FailsafesMixin, ABC):
    """The flavour-independent part of a simulated autopilot. ``tick(now)`` every physics step."""

    MAV_AUTOPILOT: int = R.MAV_AUTOPILOT_GENERIC
    FLAVOUR: str = "generic"
    LAND_DISARM_S: float = 0.0  # after the land detector fires (see ``disarms_when_landed``)
    LANDED_DISARM_TEXT: str = "Disarming: landed"
    IDLE_DISARM_TEXT: str = "Disarming: auto disarm while landed"

    def __init__(self, vehicle: Vehicle, config: AutopilotConfig | None = None,
                 start_time: float = 0.0) -> None:
        self.vehicle = vehicle
        self.config = config or AutopilotConfig()
        self.geo = GeoFrame(self.config.home_lat, self.config.home_lon, self.config.home_alt)
        self.start_time = start_time
        self.now = start_time
        self.custom_mode = self.initial_mode()
        self.failsafes: set[Failsafe] = set()
        self.counters: dict[str, int] = {
            "commands": 0, "commands_unsupported": 0, "setpoints": 0,
            "setpoints_ignored": 0, "setpoints_invalid": 0, "messages_ignored": 0, "timesync": 0,
        }
        self._rtl_phase = ""
        self._armed_on_ground_since: float | None = None
        # Airborne since the last arming: the land detector's disarm applies only after a flight.
        self._has_flown = vehicle.state.armed and not vehicle.state.land_complete
        self.on_mode_change: list[Callable[[int, int], None]] = []
        self.on_touchdown: list[Callable[[], None]] = []
        self._was_landed = vehicle.state.land_complete
        self._last_gcs_heartbeat: float | None = None  # the GCS failsafe arms on the first one
        self.status_text: list[tuple[int, str]] = []  # pending STATUSTEXT (severity, text)

    # ----- flavour hooks -----

    @abstractmethod
    def initial_mode(self) -> int: ...

    @abstractmethod
    def behaviour_of(self, custom_mode: int) -> Behaviour | None:
        """The behaviour of a flavour mode number, None when the firmware has no such mode."""

    @abstractmethod
    def mode_for(self, behaviour: Behaviour) -> int:
        """The flavour mode number the autopilot itself switches to for a behaviour."""

    def mode_name(self, custom_mode: int | None = None) -> str:
        """Human name of a mode number (the current one by default)."""
        return str(self.custom_mode if custom_mode is None else custom_mode)

    @abstractmethod
    def base_mode_flags(self) -> int:
        """HEARTBEAT base_mode without SAFETY_ARMED."""

    @abstractmethod
    def default_rates(self) -> dict[int, float]:
        """Default telemetry rates in Hz per message id on a new link."""

    @abstractmethod
    def handle_setpoint(self, sp: Setpoint) -> None:
        """A parsed SET_POSITION_TARGET_*: apply or ignore as the flavour does."""

    @abstractmethod
    def request_mode(self, custom_mode: int) -> int:
        """A mode change asked over MAVLink; returns the MAV_RESULT to ack with."""

    def mode_from_command(self, main: float, sub: float) -> int:
        """The custom_mode that MAV_CMD_DO_SET_MODE param2/param3 name (flavour encoding)."""
        return int(main)

    def origin_down_m(self) -> float:
        """World down (m) of the local frame's origin (the estimator's origin); 0 = at home."""
        return 0.0

    def global_target_down(self, frame: int, alt: float) -> float | None:
        """World down (m) of a SET_POSITION_TARGET_GLOBAL_INT altitude in ``frame``.

        ``alt`` is metres AMSL (GLOBAL), above home (RELATIVE_ALT) or above terrain (TERRAIN_ALT;
        the terrain is flat at home's height here). None: the firmware discards that frame.
        """
        if frame in (R.MAV_FRAME_GLOBAL_INT, R.MAV_FRAME_GLOBAL):
            return self.config.home_alt - alt
        if frame in (R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, R.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                     R.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT, R.MAV_FRAME_GLOBAL_TERRAIN_ALT):
            return -alt
        return None

    def disarms_when_landed(self, behaviour: Behaviour) -> bool:
        """Whether the land detector disarms (after LAND_DISARM_S) in this behaviour.

        Otherwise an armed vehicle on the ground disarms after ``idle_disarm_s``.
        """
        return behaviour in (Behaviour.LAND, Behaviour.RTL)

    # ----- the periodic step -----

    def tick(self, now: float) -> None:
        """Run mode logic, failsafe detection and auto-disarm at simulator time ``now`` (s)."""
        self.now = now
        v, s = self.vehicle, self.vehicle.state
        b = self.behaviour
        if b is Behaviour.RTL and self.flying:
            self._run_rtl()
        if b is Behaviour.TAKEOFF and self.flying and v.demand is Demand.POSITION:
            if abs(s.position[2] - v.target_position[2]) < 0.3:
                self.set_mode(self.mode_for(Behaviour.HOLD))
        remaining = v.battery_remaining
        if remaining <= self.config.battery_critical and Failsafe.BATTERY_CRITICAL not in self.failsafes:
            self.trigger_failsafe(Failsafe.BATTERY_CRITICAL)
        elif remaining <= self.config.battery_low and Failsafe.BATTERY_LOW not in self.failsafes:
            self.trigger_failsafe(Failsafe.BATTERY_LOW)
        landed = s.land_complete
        if landed and not self._was_landed and s.armed:
            for cb in list(self.on_touchdown):
                cb()
        self._was_landed = landed
        if s.armed and not landed:
            self._has_flown = True
        if s.armed and landed:
            by_landing = self.disarms_when_landed(b)
            if by_landing and v.landed_for_s >= self.LAND_DISARM_S:
                self.disarm()
                self._say(R.MAV_SEVERITY_INFO, self.LANDED_DISARM_TEXT)
            elif self._armed_on_ground_since is not None and not by_landing:
                if now - self._armed_on_ground_since >= self.config.idle_disarm_s:
                    self.disarm()
                    self._say(R.MAV_SEVERITY_INFO, self.IDLE_DISARM_TEXT)
        if not landed:
            self._armed_on_ground_since = now if s.armed else None
        timeout = self.config.gcs_timeout_s
        if (timeout is not None and self._last_gcs_heartbeat is not None and self.flying
                and now - self._last_gcs_heartbeat > timeout):
            self.trigger_failsafe(Failsafe.GCS_LOSS)
        self.on_tick(now)

    def on_tick(self, now: float) -> None:
        """Flavour-specific periodic logic (offboard loss on PX4)."""
