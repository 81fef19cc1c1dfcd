"""What the landing controller reports: typed events, each with its time and the phase it left.

Every phase change is an event (none can be missed: the controller changes phase only by emitting
one), and so is every choice of target, every hold, every handback and every other notable fact.
Each event carries the one-line ``text`` (beginning "SLZ: ") that the service sends to the ground
station as STATUSTEXT; the fields beside it are what programs read (the flight recording, the
simulator's judge, the ground station view). Programs never parse ``text``.

Times are monotonic seconds (the controller's clock, from its inputs); positions are world NED
metres from home; radii metres.
"""

from __future__ import annotations

import enum
from dataclasses import asdict, dataclass
from typing import Any, ClassVar


class Phase(str, enum.Enum):
    MONITOR = "MONITOR"
    SELECT = "SELECT"
    APPROACH = "APPROACH"
    DESCEND = "DESCEND"
    LAND = "LAND"
    HOLD = "HOLD"
    SEARCH = "SEARCH"
    LANDED = "LANDED"
    HANDBACK = "HANDBACK"


@dataclass(frozen=True)
class Event:
    """Something the controller did at ``t``: it was in ``old`` and is now in ``phase``."""

    kind: ClassVar[str] = "note"

    t: float
    old: Phase
    phase: Phase
    text: str
    warning: bool = False

    @property
    def changed(self) -> bool:
        """True when this event is a phase change."""
        return self.old != self.phase

    def as_record(self) -> dict[str, Any]:
        """The event as a JSON-ready dict (``event`` names its type; phases as their names)."""
        d = asdict(self)
        d["old"], d["phase"] = self.old.value, self.phase.value
        return {"event": self.kind, **d}


@dataclass(frozen=True)
class Note(Event):
    """A fact worth telling the pilot that changes no phase (a refused command, a committed landing)."""


@dataclass(frozen=True)
class PhaseChanged(Event):
    """A phase change with nothing more to say (SELECT on a trigger, DESCEND, LAND, LANDED)."""

    kind: ClassVar[str] = "phase"
    zone_id: int | None = None
    touchdown_clearance_m: float | None = None  # see TargetChosen
    #: On LAND: how long the ground under the vehicle had been watched and seen free (s).
    calm_s: float | None = None


@dataclass(frozen=True)
class TargetChosen(Event):
    """A zone became the target (the first, or another after the last was lost)."""

    kind: ClassVar[str] = "target"
    zone_id: int = -1
    north: float = 0.0
    east: float = 0.0
    r: float = 0.0
    lost_zone_id: int | None = None
    #: The least clearance (m) the zone can have at touchdown if the vehicle came down now, with
    #: every walker heading for it (``companion.control.touchdown``): the zone's radius less the
    #: walking speed times the time to touchdown. Negative: a walker could be there by then.
    touchdown_clearance_m: float | None = None
    #: What bounds the zone on the frame that chose it: "people", "surface" (unlandable ground,
    #: the landability model) or "view" (``companion.pipeline.edges``); None when not judged.
    edge: str | None = None


@dataclass(frozen=True)
class Holding(Event):
    """The target was lost and no other zone qualifies: hold (and climb to see) until one does."""

    kind: ClassVar[str] = "hold"
    lost_zone_id: int = -1
    reason: str = ""


@dataclass(frozen=True)
class HandedBack(Event):
    """Control went back to the autopilot's own failsafe (``action`` LAND or RTL, or "" when it
    was taken from the companion and nothing was commanded)."""

    kind: ClassVar[str] = "handback"
    action: str = ""
    reason: str = ""


#: Every event type by its ``kind`` (readers of recordings use it).
EVENT_TYPES: dict[str, type[Event]] = {
    cls.kind: cls for cls in (Note, PhaseChanged, TargetChosen, Holding, HandedBack)
}
