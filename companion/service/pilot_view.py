"""What the status page tells a pilot beside the zones (``/status.json``'s ``vehicle`` and
``clearance_note``): the height, the autopilot's mode, armed or not, the time since the trigger,
the handback's reason, and whether the clearance at touchdown means anything yet.

The clearance at touchdown (``LandingController.touchdown_clearance``) is a zone's radius less the
distance a walker covers while the vehicle comes down from where it is now: from high up that time
is long and the figure is strongly negative (-24 m at 40 m), which says nothing about the zone. The
controller weighs it at the judging height (``descent.judging_height``), so the page shows it from
there down and says "n/a" above.
"""

from __future__ import annotations

from typing import Any

from companion.control.descent import judging_height
from companion.control.events import Event, HandedBack
from companion.control.landing import LandingController
from companion.mavlink.autopilot import Autopilot
from companion.mavlink.state import VehicleState


def _round(v: float | None, nd: int = 1) -> float | None:
    return None if v is None or v != v or abs(v) == float("inf") else round(float(v), nd)


def vehicle_fields(state: VehicleState, autopilot: Autopilot | None, controller: LandingController | None,
                   events: list[Event], now: float) -> dict[str, Any]:
    """The vehicle as the page shows it, at ``now`` (monotonic s): ``height_m`` above home and
    ``height_agl_m`` above the ground (a fresh downward rangefinder; None without one), ``mode``
    (the autopilot's name for it), ``armed``, ``trigger`` ({age_s, reason} once triggered) and
    ``handback`` (the reason of the last handback, None before one)."""
    mode = state.mode
    trigger = None if controller is None else controller.trigger
    handback = next((e for e in reversed(events) if isinstance(e, HandedBack)), None)
    return {
        "height_m": _round(state.altitude_above_home()),
        "height_agl_m": _round(state.altitude_above_ground(now)),
        "mode": None if mode is None or autopilot is None else autopilot.mode_name(*mode),
        "armed": state.armed,
        "trigger": None if trigger is None else {"age_s": round(now - trigger.t, 1), "reason": trigger.reason},
        "handback": None if handback is None else handback.reason or handback.text,
    }


def clearance_note(controller: LandingController | None) -> str | None:
    """None where the clearance at touchdown means something (at or below the judging height),
    else why the page shows none."""
    if controller is None or controller.status is None:
        return "n/a (no position)"
    judge = judging_height(controller.config)
    if controller.status.height > judge:
        return f"n/a above {judge:.0f} m (judged there)"
    return None
