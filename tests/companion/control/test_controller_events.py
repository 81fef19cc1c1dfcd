"""The controller's typed events: every phase change reported once, in order, with its time.

The service used to poll the phase every 0.25 s; a trigger over a ready zone goes MONITOR ->
SELECT -> APPROACH inside one call, and a poller sees only APPROACH. Events cannot miss it.
"""

from __future__ import annotations

import json

from companion.control.events import EVENT_TYPES, HandedBack, Holding, Phase, PhaseChanged, TargetChosen
from companion.control.landing import LandingController
from tests.companion.control.test_landing_controller import CFG, pose, status, trigger, zone


def _changes(events) -> list[tuple[str, str]]:
    return [(e.old.value, e.phase.value) for e in events if e.changed]


def test_a_trigger_over_a_ready_zone_reports_select_and_approach_from_one_call():
    ctl = LandingController(CFG)
    ctl.on_state(status(10.0))
    ctl.on_frame(10.0, [zone(3, 12.0, 5.0, 10.0)], pose(10.0))
    assert ctl.pop_events() == []  # nothing happens before a trigger
    ctl.on_trigger(trigger(10.05))
    events = ctl.pop_events()
    assert _changes(events) == [("MONITOR", "SELECT"), ("SELECT", "APPROACH")]
    first, chosen = events
    assert isinstance(first, PhaseChanged) and first.t == 10.05 and first.warning
    assert isinstance(chosen, TargetChosen)
    assert (chosen.zone_id, chosen.north, chosen.east, chosen.r) == (3, 12.0, 5.0, 4.1)
    assert chosen.text.startswith("SLZ: ") and "zone 3" in chosen.text


def test_a_lost_target_holds_and_a_timeout_hands_back_each_as_its_own_event():
    ctl = LandingController(CFG)
    ctl.on_state(status(0.0))
    ctl.on_frame(0.0, [zone(3, 12.0, 5.0, 0.0)], pose(0.0))
    ctl.on_trigger(trigger(0.0))
    ctl.pop_events()
    for t in (0.1, 0.2):  # shrank below r0 on two frames in a row: lost, nothing else
        ctl.on_state(status(t))
        ctl.on_frame(t, [zone(3, 12.0, 5.0, t, r=1.0)], pose(t))
    hold = ctl.pop_events()
    assert _changes(hold) == [("APPROACH", "HOLD")]
    assert isinstance(hold[0], Holding) and hold[0].lost_zone_id == 3 and "shrank" in hold[0].reason
    while ctl.phase == Phase.HOLD and t < 20.0:
        t += 0.1
        ctl.on_state(status(t))
        ctl.on_frame(t, [], pose(t))
        ctl.tick(t)
    back = ctl.pop_events()
    assert _changes(back) == [("HOLD", "HANDBACK")]
    assert isinstance(back[-1], HandedBack) and back[-1].action == "LAND" and back[-1].reason


def test_events_are_json_records_that_name_their_type():
    ctl = LandingController(CFG)
    ctl.on_state(status(1.0))
    ctl.on_frame(1.0, [zone(3, 12.0, 5.0, 1.0)], pose(1.0))
    ctl.on_trigger(trigger(1.0))
    for event in ctl.pop_events():
        record = json.loads(json.dumps(event.as_record()))
        assert EVENT_TYPES[record["event"]] is type(event)
        assert record["t"] == 1.0 and record["phase"] in {p.value for p in Phase}
