"""Failsafes: raising (latched), the firmware's reaction, clearing, and the GCS heartbeat feed."""

from __future__ import annotations

from sim.vehicle.autopilot.base import AutopilotConfig, Behaviour, MAVMessage, MixinBase, R
from sim.vehicle.faults import Failsafe
from sim.vehicle.kinematics import Vehicle


class FailsafesMixin(MixinBase):
    """Failsafe detection results and what the autopilot does about them (part of ``Autopilot``)."""

    # Set by ``Autopilot.__init__``.
    vehicle: Vehicle
    config: AutopilotConfig
    now: float
    failsafes: set[Failsafe]
    _last_gcs_heartbeat: float | None

    def trigger_failsafe(self, kind: Failsafe) -> None:
        """Raise a failsafe as the firmware would: flag it (latched), then ``react_to_failsafe``."""
        if kind in self.failsafes:
            return
        self.failsafes.add(kind)
        if kind is Failsafe.BATTERY_LOW:
            self.vehicle.set_battery_remaining(min(self.vehicle.battery_remaining,
                                                   self.config.battery_low))
        elif kind is Failsafe.BATTERY_CRITICAL:
            self.vehicle.set_battery_remaining(min(self.vehicle.battery_remaining,
                                                   self.config.battery_critical))
        self.react_to_failsafe(kind)

    def react_to_failsafe(self, kind: Failsafe) -> None:
        """What the firmware does about a new failsafe: tell the GCS, switch mode at once."""
        action = self.config.failsafe_action.get(kind, "land")
        self._say(R.MAV_SEVERITY_CRITICAL, f"Failsafe {kind.value}: {action.upper()}")
        target = self.failsafe_target(kind)
        if target is not None:
            self.set_mode(self.mode_for(target))

    def failsafe_target(self, kind: Failsafe) -> Behaviour | None:
        """The behaviour ``kind``'s action switches to now; None when it changes nothing."""
        if not self.flying:
            return None
        action = self.config.failsafe_action.get(kind, "land")
        target = Behaviour.RTL if action == "rtl" else Behaviour.LAND
        # A failsafe never de-escalates: already landing stays landing.
        if self.behaviour is Behaviour.LAND or self.behaviour is target:
            return None
        return target

    def clear_failsafe(self, kind: Failsafe) -> None:
        """The condition went away (RC back, GCS back); the mode stays as it is, like the firmwares."""
        self.failsafes.discard(kind)
        if kind is Failsafe.GCS_LOSS and self._last_gcs_heartbeat is not None:
            self._last_gcs_heartbeat = self.now

    def on_peer_heartbeat(self, msg: MAVMessage) -> None:
        """A heartbeat from a peer: the GCS's ones feed the GCS failsafe, others are ignored."""
        if msg.get_srcSystem() == self.config.gcs_system_id:
            self._last_gcs_heartbeat = self.now
