"""What a ground station sees of the companion, received by a pymavlink peer over loopback UDP:
the heartbeat's status following health, each state change as one STATUSTEXT with its severity,
the named values; and the severities of the controller's events."""

from __future__ import annotations

import asyncio
import contextlib
import math

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.events import HandedBack, Holding, Note, Phase, PhaseChanged, TargetChosen
from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.statustext import STATUSTEXT_LEN, TextPacer, event_severity, shadow_text
from companion.service.gcs import CONDITIONS, VALUE_NAMES, GroundStation, companion_state
from companion.service.health import Fault, Health
from tests.mavpeer import MavPeer

FAST = dict(heartbeat_period_s=0.05, heartbeat_timeout_s=0.5, command_timeout_s=0.1, command_retries=1)
OK = Health()
CAMERA_DOWN = Health((Fault("camera", "camera not delivering", internal=False),))
LINK_DOWN = Health((Fault("link", "no autopilot heartbeat", internal=False),))
STUCK = Health((Fault("pipeline", "pipeline stuck for 6.1 s", internal=True),))


@contextlib.asynccontextmanager
async def ground_station():
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    # The gap and the pacing are tested on their own (tests/companion/mavlink/test_statustext_pacing.py).
    gcs = GroundStation(link, frame_budget_ms=100.0, min_gap_s=0.0,
                        pacer=TextPacer(max_per_window=100, min_gap_s=0.0, repeat_s=0.0))
    await link.start()
    peer = MavPeer()
    await peer.connect_udp(link.local_address)
    peer.start_heartbeats(0.05)
    await link.wait_connected(2.0)
    try:
        yield gcs, peer
    finally:
        await peer.close()
        await link.close()


async def companion_status(peer: MavPeer) -> int:
    """The system_status of the companion's next HEARTBEAT."""
    start = len(peer.received)
    hb = await peer.wait_for("HEARTBEAT", lambda h: True, start=start)
    assert hb.type == m.MAV_TYPE_ONBOARD_CONTROLLER and hb.autopilot == m.MAV_AUTOPILOT_INVALID
    assert (hb.base_mode, hb.custom_mode) == (0, 0)
    return int(hb.system_status)


async def test_the_heartbeat_says_standby_then_active_then_critical_while_the_camera_is_down():
    async with ground_station() as (gcs, peer):
        assert await companion_status(peer) == m.MAV_STATE_STANDBY
        gcs.update(OK, 0.0)
        assert await companion_status(peer) == m.MAV_STATE_STANDBY  # healthy, not ready yet
        gcs.set_ready(["SLZ: ready, model slz-density, camera 640x480"])
        gcs.update(OK, 1.0)
        assert await companion_status(peer) == m.MAV_STATE_ACTIVE
        gcs.update(CAMERA_DOWN, 2.0)
        assert await companion_status(peer) == m.MAV_STATE_CRITICAL
        gcs.update(OK, 3.0)
        assert await companion_status(peer) == m.MAV_STATE_ACTIVE
        assert companion_state(True, STUCK) == m.MAV_STATE_CRITICAL
        assert companion_state(True, LINK_DOWN) == m.MAV_STATE_CRITICAL


async def test_each_state_change_arrives_once_with_its_severity():
    async with ground_station() as (gcs, peer):
        gcs.set_ready(["SLZ: ready, model slz-density, camera 640x480"])
        await asyncio.sleep(0.05)  # the outbox sends from the event loop: let it, between changes
        for k in range(5):  # a fault lasting five health ticks is told once
            gcs.update(CAMERA_DOWN, 1.0 + k)
        for health, t in ((OK, 7.0), (LINK_DOWN, 8.0), (OK, 9.0), (STUCK, 10.0), (OK, 11.0)):
            await asyncio.sleep(0.05)
            gcs.update(health, t)
        for k in range(80):  # frames twice over the 100 ms budget for 6 s after a full window: slow
            gcs.frame(200.0, 230.0, 12.0 + 0.1 * k)
        await asyncio.sleep(0.05)
        gcs.update(OK, 20.0)
        for k in range(80):
            gcs.frame(40.0, 60.0, 20.0 + 0.1 * k)
        await asyncio.sleep(0.05)
        gcs.update(OK, 28.0)
        await peer.wait_for_text("model speed ok")
        await asyncio.sleep(0.1)
        got = peer.statustexts()
        assert got == [
            (m.MAV_SEVERITY_NOTICE, "SLZ: ready, model slz-density, camera 640x480"),
            (m.MAV_SEVERITY_ERROR, "SLZ: camera lost: no landing zones"),
            (m.MAV_SEVERITY_NOTICE, "SLZ: camera back"),
            (m.MAV_SEVERITY_WARNING, "SLZ: autopilot link lost"),
            (m.MAV_SEVERITY_NOTICE, "SLZ: autopilot link back"),
            (m.MAV_SEVERITY_ERROR, "SLZ: pipeline stuck for 6.1 s"),
            (m.MAV_SEVERITY_NOTICE, "SLZ: pipeline running again"),
            (m.MAV_SEVERITY_WARNING, "SLZ: model slow: 200 ms/frame > 100 ms"),
            (m.MAV_SEVERITY_NOTICE, "SLZ: model speed ok: 40 ms/frame"),
        ], got
        # Each in one packet: no text over the 50 characters of a STATUSTEXT.
        assert all(not t.id for t in peer.of_type("STATUSTEXT"))


def test_a_flapping_camera_is_told_at_most_once_per_gap_and_its_last_state_always():
    from companion.service.gcs import ConditionReporter

    rep = ConditionReporter(min_gap_s=5.0)
    told = []
    for k in range(40):  # down and up every 0.25 s for 10 s
        told += rep.update({"camera": (k % 2 == 0, "")}, k * 0.25)
    assert len(told) <= 3, told
    told += rep.update({"camera": (False, "")}, 30.0)
    assert told[-1][1] == "SLZ: camera back"
    assert rep.update({"camera": (False, "")}, 31.0) == []  # nothing new to tell
    # Healthy from the start: nobody is told the camera is "back".
    assert ConditionReporter().update({"camera": (False, "")}, 0.0) == []


def test_a_new_reason_while_bad_is_told_where_the_condition_says_so():
    """Lost then frozen, no pose then stale pose: each is told (no sooner than the gap); the model's
    speed, whose detail is a number that changes every frame, is not told again for it."""
    from companion.service.gcs import ConditionReporter

    rep = ConditionReporter(min_gap_s=5.0)
    assert rep.update({"camera": (True, "lost")}, 0.0) == [(m.MAV_SEVERITY_ERROR, "SLZ: camera lost: no landing zones")]
    assert rep.update({"camera": (True, "frozen")}, 1.0) == []  # within the gap
    assert rep.update({"camera": (True, "frozen")}, 6.0) == [(m.MAV_SEVERITY_ERROR, "SLZ: camera frozen: no landing zones")]
    assert rep.update({"camera": (True, "frozen")}, 20.0) == []
    told = rep.update({"frames": (True, "no pose")}, 0.0) + rep.update({"frames": (True, "stale pose")}, 5.0)
    assert [t for _, t in told] == ["SLZ: frames not used: no pose", "SLZ: frames not used: stale pose"]
    assert rep.update({"ground": (True, "on the ground")}, 0.0) == [(m.MAV_SEVERITY_NOTICE, "SLZ: standby, on the ground")]
    assert rep.update({"ground": (False, "")}, 9.0) == [(m.MAV_SEVERITY_NOTICE, "SLZ: airborne, frames used")]
    assert rep.update({"slow": (True, "200 ms/frame > 100 ms")}, 0.0) != []
    assert rep.update({"slow": (True, "210 ms/frame > 100 ms")}, 10.0) == []


def test_every_condition_text_fits_one_statustext():
    for cond in CONDITIONS.values():
        for text in (cond.bad_text, cond.good_text):
            assert len(text.format("for 12345.6 s > 99999 ms")) <= 60  # details are cut at 50 when sent
            assert len(text.format("")) <= STATUSTEXT_LEN


async def test_the_named_values_arrive_with_their_names_and_values():
    async with ground_station() as (gcs, peer):
        for k in range(20):
            gcs.frame(45.0, 80.0, 1.0 + k * 0.1)
        v = gcs.values(2.95, phase=Phase.APPROACH, zones=3, health=CAMERA_DOWN, target_r_m=4.5, clearance_m=-1.25)
        await peer.wait_for("NAMED_VALUE_FLOAT", lambda msg: msg.name == "SLZ_LAT_MS")
        gcs.values(3.0, phase=Phase.MONITOR, zones=0, health=OK, target_r_m=None, clearance_m=None)
        await peer.wait_for("NAMED_VALUE_FLOAT", lambda msg: msg.name == "SLZ_CLEAR" and math.isnan(msg.value))
        ints = {msg.name: msg.value for msg in peer.of_type("NAMED_VALUE_INT")[:3]}
        floats = {msg.name: msg.value for msg in peer.of_type("NAMED_VALUE_FLOAT")[:5]}
        assert ints == {"SLZ_PHASE": 2, "SLZ_ZONES": 3, "SLZ_HEALTH": 1}
        assert floats["SLZ_TGT_R"] == 4.5 and floats["SLZ_CLEAR"] == -1.25
        assert math.isclose(floats["SLZ_FPS"], 10.0, rel_tol=1e-3) and math.isclose(v.fps, floats["SLZ_FPS"], rel_tol=1e-6)
        assert floats["SLZ_FRM_MS"] == 45.0 and floats["SLZ_LAT_MS"] == 80.0
        later = {msg.name: msg.value for msg in peer.of_type("NAMED_VALUE_INT")[3:6]}
        assert later == {"SLZ_PHASE": 0, "SLZ_ZONES": 0, "SLZ_HEALTH": 0}
        names = {msg.name for msg in peer.of_type("NAMED_VALUE_INT") + peer.of_type("NAMED_VALUE_FLOAT")}
        assert names == {name for name, *_ in VALUE_NAMES}
        assert all(len(name) <= 10 for name in names)


def test_the_controllers_events_have_the_severities_ground_stations_rank_them_by():
    S, A, H = Phase.SELECT, Phase.APPROACH, Phase.HANDBACK
    trigger = PhaseChanged(0.0, Phase.MONITOR, S, "SLZ: trigger: battery; looking for a landing zone", True)
    assert event_severity(trigger) == m.MAV_SEVERITY_WARNING
    assert event_severity(TargetChosen(1.0, S, A, "SLZ: landing at zone 3", zone_id=3)) == m.MAV_SEVERITY_NOTICE
    assert event_severity(PhaseChanged(2.0, A, Phase.DESCEND, "SLZ: over zone 3")) == m.MAV_SEVERITY_NOTICE
    assert event_severity(Holding(3.0, A, Phase.HOLD, "SLZ: zone 3 lost; holding", True)) == m.MAV_SEVERITY_WARNING
    assert event_severity(HandedBack(4.0, A, H, "SLZ: ...", True, action="LAND")) == m.MAV_SEVERITY_CRITICAL
    assert event_severity(HandedBack(4.0, A, H, "SLZ: mode changed", True, action="")) == m.MAV_SEVERITY_WARNING
    assert event_severity(Note(5.0, A, A, "SLZ: landing committed")) == m.MAV_SEVERITY_INFO
    assert event_severity(Note(5.0, A, A, "SLZ: command Goto failed", True)) == m.MAV_SEVERITY_WARNING
    assert shadow_text("SLZ: landing at zone 3") == "SHADOW: landing at zone 3"


def test_the_docs_table_lists_every_named_value_as_sent():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[3] / "docs" / "ground-station-values.md").read_text()
    rows = [line.split("|")[1:4] for line in doc.splitlines() if line.startswith("| `SLZ_")]
    assert [(n.strip().strip("`"), k.strip()) for n, k, _ in rows] == \
        [(name, f"NAMED_VALUE_{kind}") for name, kind, _, _ in VALUE_NAMES]


def test_the_model_speed_is_told_with_a_band_and_a_hold_time():
    """A median wandering around the 100 ms budget says nothing; over it for 5 s it is slow, and
    it is fast again only once under 80 ms for 5 s."""
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    gcs = GroundStation(link, frame_budget_ms=100.0)
    t, flips, was = 0.0, 0, False
    for k in range(600):  # 60 s: 2 s at 110 ms, 2 s at 90 ms, ...
        gcs.frame(110.0 if (k // 20) % 2 == 0 else 90.0, 120.0, t)
        flips += gcs.slow != was
        was = gcs.slow
        t += 0.1
    assert flips == 0
    for _ in range(49):  # over budget for 4.9 s: not yet
        gcs.frame(150.0, 160.0, t)
        t += 0.1
    assert not gcs.slow
    for _ in range(12):
        gcs.frame(150.0, 160.0, t)
        t += 0.1
    assert gcs.slow
    for _ in range(100):  # 95 ms: under the budget, not under the band: still slow
        gcs.frame(95.0, 100.0, t)
        t += 0.1
    assert gcs.slow
    for _ in range(75):
        gcs.frame(60.0, 70.0, t)
        t += 0.1
    assert not gcs.slow
