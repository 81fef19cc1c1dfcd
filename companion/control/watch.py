"""What the vehicle and the clock say, whatever zone is being flown to.

The vehicle: on the ground or disarmed (landed, or its motors stopped in the air: PX4's land
detector disarms in OFFBOARD too, its heartbeat still saying OFFBOARD), above the ceiling, or
taken over by someone else (pilot, GCS, the autopilot's own failsafe: a mode the companion did not
command, once its own was confirmed). The clock: the SELECT and HOLD timeouts that start the
search, the search's end, the takeover's budget (``max_takeover_s``: zones that keep being lost
and re-targeted must not keep a vehicle with a failing battery in the air; in LAND the autopilot
is already landing over a confirmed zone, so the budget does not apply there), and stale
positions or frames.

These functions answer; the phase machine (``companion.control.landing``) acts on the answers.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from companion.control.events import Phase
from companion.control.phases import FLYING
from companion.control.settings import LandingConfig
from companion.control.vehicle import VehicleStatus


class Seen(enum.Enum):
    """What the vehicle's status says happened."""

    GROUND_EARLY = "ground early"  # on the ground, armed, in the companion's low descent
    LANDED = "landed"  # on the ground or disarmed in LAND
    LANDED_DISARMED = "landed disarmed"  # on the ground and disarmed outside LAND
    DISARMED_IN_AIR = "disarmed in the air"
    ABOVE_CEILING = "above the ceiling"


@dataclass(frozen=True)
class News:
    """``seen`` happened; ``text`` says so for the pilot where the event needs the words."""

    seen: Seen
    text: str = ""


@dataclass(frozen=True)
class Due:
    """A timeout: start the search (``search``) or hand back, ``why`` (for the pilot)."""

    search: bool
    why: str


def vehicle_news(s: VehicleStatus, phase: Phase, low_descent: bool, ceiling_m: float | None,
                 zone: str) -> News | None:
    """What ``s`` says happened, in ``phase`` (``low_descent``: the companion's own descent to
    ``land_agl_m`` is under way; ``zone``: the target's id, for the words), or None."""
    flying = phase in FLYING
    landing = phase == Phase.LAND
    if landing and low_descent and s.on_ground and s.armed is not False:
        # The ground came before land_agl_m (a slope, a rangefinder reading long): in
        # GUIDED/OFFBOARD the autopilot would sit on it armed; its LAND finishes and disarms.
        return News(Seen.GROUND_EARLY, f"on the ground at {s.height:.1f} m by the rangefinder")
    if landing and (s.on_ground or s.armed is False):
        return News(Seen.LANDED, f"landed in zone {zone}")
    if flying and s.armed is False and s.on_ground:
        return News(Seen.LANDED_DISARMED, f"vehicle on the ground and disarmed (zone {zone})")
    if flying and s.armed is False:
        return News(Seen.DISARMED_IN_AIR, "vehicle disarmed in the air")
    if flying and ceiling_m is not None and s.alt > ceiling_m:
        return News(Seen.ABOVE_CEILING, f"vehicle at {s.alt:.1f} m, above the {ceiling_m:.1f} m ceiling")
    return None


def obeying_watched(phase: Phase, low_descent: bool, mode: str | None, c: LandingConfig, sent: bool) -> bool:
    """Whether the obedience monitor watches now: the vehicle in the companion's mode (``mode``),
    flying a target it was sent (``sent``) in a phase the companion flies (in LAND, only its own
    low descent, ``low_descent``)."""
    flying = phase in (Phase.APPROACH, Phase.DESCEND, Phase.HOLD, Phase.SEARCH) or (phase == Phase.LAND and low_descent)
    return flying and mode in c.external_modes and sent


def ours(mode: str, c: LandingConfig) -> bool:
    """Whether ``mode`` is one the companion commands (GUIDED/OFFBOARD, or the LAND it asks for)."""
    return mode in (*c.external_modes, "LAND")


def timeout(phase: Phase, now: float, phase_t: float, c: LandingConfig, candidate_seen: bool,
            search_over: str | None, trigger_t: float | None, status_t: float | None,
            frame_t: float | None) -> Due | None:
    """Which timeout is due at ``now`` in ``phase`` (entered at ``phase_t``), or None.
    ``candidate_seen``: a zone of at least r0 seen since the trigger (``select_empty_s``);
    ``search_over``: why the search must stop, if it must; ``status_t``/``frame_t``: the latest
    vehicle position's and usable frame's times (None: none yet)."""
    if phase == Phase.SELECT and c.select_empty_s > 0 and not candidate_seen and now - phase_t > c.select_empty_s:
        return Due(True, f"nothing in view within {c.select_empty_s:g} s could be a safe zone")
    if phase == Phase.SELECT and now - phase_t > c.select_timeout_s:
        return Due(True, f"no safe zone confirmed within {c.select_timeout_s:g} s")
    if phase == Phase.HOLD and now - phase_t > c.hold_timeout_s:
        return Due(True, f"held {c.hold_timeout_s:g} s without a safe zone")
    if phase == Phase.SEARCH and search_over is not None:
        return Due(False, search_over)
    if trigger_t is not None and phase != Phase.LAND and now - trigger_t > c.max_takeover_s:
        return Due(False, f"not landed within {c.max_takeover_s:g} s of the trigger")
    if phase in FLYING:
        if status_t is None or now - status_t > c.pose_timeout_s:
            return Due(False, "vehicle position stale")
        if phase != Phase.LAND and (frame_t is None or now - frame_t > c.pose_timeout_s):
            return Due(False, "no frame with a fresh pose")
    return None
