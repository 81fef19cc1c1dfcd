"""The landing controller's phases, and which phase may follow which.

Phases::

    MONITOR --trigger--> SELECT --eligible zone--> APPROACH --over it--> DESCEND --low enough--> LAND
       LAND --on ground / disarmed--> LANDED
    APPROACH/DESCEND/LAND --zone lost--> APPROACH (another eligible zone) or HOLD
    HOLD/SEARCH --eligible zone--> APPROACH
    SELECT/HOLD timeout --> SEARCH (with ``search_s`` 0: HANDBACK)
    SEARCH out of time, radius or battery, stale pose, repeated refusals --> HANDBACK (the
        autopilot's LAND or RTL)
    APPROACH/DESCEND/HOLD/LAND/SEARCH --pilot changes mode--> HANDBACK (without a command)

``TRANSITIONS`` is that diagram as data. ``PhaseMachine`` is how the landing controller
(``companion.control.landing``) changes phase and reports: only through ``TRANSITIONS`` (a change it
does not list is a bug, not a flight), and every change and every note as one typed event
(``companion.control.events``), in order, on the controller's clock.
"""

from __future__ import annotations

import logging
import math

from companion.control.events import Event, Note, Phase, PhaseChanged

log = logging.getLogger("companion.control.landing")

#: The phases in which the companion has taken over (after a trigger, before the end).
ACTIVE = frozenset({Phase.SELECT, Phase.APPROACH, Phase.DESCEND, Phase.LAND, Phase.HOLD, Phase.SEARCH})
#: The phases in which the companion flies the vehicle (or the autopilot's LAND it commanded does).
FLYING = frozenset({Phase.APPROACH, Phase.DESCEND, Phase.LAND, Phase.HOLD, Phase.SEARCH})

#: Which phases may follow each phase. A phase listed after itself is entered again with an
#: event (APPROACH: a lost zone re-targeted to another). LANDED and HANDBACK are the ends.
TRANSITIONS: dict[Phase, frozenset[Phase]] = {
    Phase.MONITOR: frozenset({Phase.SELECT}),
    Phase.SELECT: frozenset({Phase.APPROACH, Phase.SEARCH, Phase.HANDBACK}),
    Phase.APPROACH: frozenset({Phase.APPROACH, Phase.DESCEND, Phase.HOLD, Phase.LANDED, Phase.HANDBACK}),
    Phase.DESCEND: frozenset({Phase.APPROACH, Phase.LAND, Phase.HOLD, Phase.LANDED, Phase.HANDBACK}),
    Phase.LAND: frozenset({Phase.APPROACH, Phase.HOLD, Phase.LANDED, Phase.HANDBACK}),
    Phase.HOLD: frozenset({Phase.APPROACH, Phase.SEARCH, Phase.LANDED, Phase.HANDBACK}),
    Phase.SEARCH: frozenset({Phase.APPROACH, Phase.LANDED, Phase.HANDBACK}),
    Phase.LANDED: frozenset(),
    Phase.HANDBACK: frozenset(),
}


def allowed(old: Phase, new: Phase) -> bool:
    """Whether the phase machine may go from ``old`` to ``new`` (``TRANSITIONS``)."""
    return new in TRANSITIONS[old]


class PhaseMachine:
    """The phase, the controller's clock (monotonic s, from its inputs) and the events not yet
    popped. Subclasses act through ``_set_phase`` and ``_event`` alone."""

    def __init__(self) -> None:
        self.phase = Phase.MONITOR
        self.now = -math.inf
        self._phase_t = 0.0  # when the phase was entered
        self._events: list[Event] = []

    def pop_events(self) -> list[Event]:
        """The events since the last call, oldest first."""
        events, self._events = self._events, []
        return events

    def _advance(self, t: float) -> None:
        if math.isfinite(t):
            self.now = max(self.now, t)

    def _entering(self, phase: Phase) -> None:
        """Called before every ``_set_phase``, the phase still the old one: what a subclass
        forgets on entering ``phase``."""

    def _set_phase(self, phase: Phase, text: str, warning: bool = False, event: type[Event] = PhaseChanged,
                   **fields: object) -> None:
        """Enter ``phase`` (or stay in it), reporting it as one ``event`` of the given type: the
        only way the phase changes, so no change goes unreported, and only as ``TRANSITIONS``
        allows."""
        old = self.phase
        if not allowed(old, phase):
            raise RuntimeError(f"landing: no transition from {old.value} to {phase.value}")
        self._entering(phase)
        if phase != old:
            log.info("landing: %s -> %s", old.value, phase.value)
            self.phase = phase
            self._phase_t = self.now
        self._emit(event(self.now, old, phase, f"SLZ: {text}", warning, **fields))

    def _event(self, text: str, warning: bool = False) -> None:
        """A note for the pilot that changes no phase."""
        self._emit(Note(self.now, self.phase, self.phase, f"SLZ: {text}", warning))

    def _emit(self, event: Event) -> None:
        (log.warning if event.warning else log.info)("%s", event.text)
        self._events.append(event)
