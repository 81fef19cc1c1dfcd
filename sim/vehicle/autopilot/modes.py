"""Modes and flight sequences: behaviour switching, arming, takeoff, landing and RTL."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from sim.vehicle.autopilot.base import AutopilotConfig, Behaviour, MixinBase
from sim.vehicle.faults import Failsafe
from sim.vehicle.kinematics import Vehicle

log = logging.getLogger(__name__)


class ModesMixin(MixinBase):
    """What a mode does to the vehicle and the arm/disarm state (part of ``Autopilot``)."""

    # Set by ``Autopilot.__init__``.
    vehicle: Vehicle
    config: AutopilotConfig
    now: float
    custom_mode: int
    failsafes: set[Failsafe]
    on_mode_change: list[Callable[[int, int], None]]
    _rtl_phase: str
    _armed_on_ground_since: float | None
    _has_flown: bool

    @property
    def behaviour(self) -> Behaviour:
        b = self.behaviour_of(self.custom_mode)
        assert b is not None
        return b

    @property
    def flying(self) -> bool:
        s = self.vehicle.state
        return s.armed and not s.land_complete

    def set_mode(self, custom_mode: int) -> None:
        """Switch mode and start its behaviour (no checks: callers have done them)."""
        old = self.custom_mode
        self.custom_mode = custom_mode
        self._enter(self.behaviour)
        if old != custom_mode:
            log.info("%s mode %s -> %s", self.FLAVOUR, self.mode_name(old), self.mode_name(custom_mode))
            for cb in list(self.on_mode_change):
                cb(old, custom_mode)

    def _enter(self, b: Behaviour) -> None:
        v = self.vehicle
        if b is Behaviour.LAND:
            if self.flying:
                v.land()
        elif b is Behaviour.RTL:
            self._rtl_phase = "climb"
            if self.flying:
                north, east = v.state.position[:2]
                v.fly_to(north, east, min(v.state.position[2], -self.config.rtl_alt))
        elif b in (Behaviour.HOLD, Behaviour.MANUAL, Behaviour.GUIDED):
            if self.flying:
                v.hold()
        elif b is Behaviour.TAKEOFF:
            self._start_takeoff(self.config.takeoff_alt)

    def _start_takeoff(self, altitude: float) -> bool:
        v = self.vehicle
        if not v.state.armed:
            return False
        if v.state.land_complete:
            v.take_off(altitude)
        else:
            north, east = v.state.position[:2]
            v.fly_to(north, east, -abs(altitude))
        return True

    def arm(self) -> None:
        self.vehicle.arm()
        self._armed_on_ground_since = self.now
        self._has_flown = False

    def disarm(self) -> None:
        self.vehicle.disarm()
        self._armed_on_ground_since = None

    def can_arm(self) -> bool:
        return self.vehicle.state.land_complete and Failsafe.BATTERY_CRITICAL not in self.failsafes

    def _run_rtl(self) -> None:
        v, s = self.vehicle, self.vehicle.state
        if self._rtl_phase == "climb":
            if s.position[2] <= v.target_position[2] + 0.3:
                self._rtl_phase = "return"
                v.fly_to(0.0, 0.0, float(v.target_position[2]))
        elif self._rtl_phase == "return":
            if math.hypot(*s.position[:2]) < 0.5 and float(np.linalg.norm(s.velocity)) < 0.3:
                self._rtl_phase = "land"
                v.land()
