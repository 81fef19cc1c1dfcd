"""SITL: the real service (a subprocess) flies the simulator over MAVLink on loopback UDP, sees
through the simulated MJPEG camera with the shipped density model, and is judged on the
simulator's truth (who stood where at touchdown), never on what the service says."""

from __future__ import annotations

import asyncio

import pytest

from sim.flight import FlightSpec, fly

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

FLAVOURS = ["ardupilot", "px4"]


def _fly(spec: FlightSpec):
    result = asyncio.run(fly(spec))
    assert result.service_exit == 0, result.log_tail
    return result


def _explain(r) -> str:
    return (f"outcome {r.outcome}, touchdown {r.touchdown}, clearance {r.clearance_m}, "
            f"phases {r.phases}\n" + "\n".join(r.messages) + "\n--- service log tail ---\n"
            + r.log_tail)


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_failsafe_lands_with_nobody_within_r0(flavour, model_path):
    # The loop runs on wall-clock time on a shared machine, so one flight can end differently from
    # the next (frames dropped, walkers passing). A landing near anyone is never accepted; a clean
    # handback (the autopilot's own LAND) is safe but not the capability under test, so up to three
    # flights are flown for one safe landing in the free circle.
    results = []
    for attempt in range(3):
        r = _fly(FlightSpec(flavour=flavour, world="free_area", seed=2 + 10 * attempt,
                            altitude_m=18.0))
        results.append(r)
        assert r.outcome != "unsafe", _explain(r)
        if r.outcome == "safe":
            break
    assert r.outcome == "safe", "\n\n".join(_explain(x) for x in results)
    assert r.clearance_m >= r.spec.r0_m
    assert r.took_control and not r.handed_back


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_no_safe_zone_hands_back_and_the_autopilot_lands(flavour, model_path):
    r = _fly(FlightSpec(flavour=flavour, world="dense", seed=3, altitude_m=16.0,
                        service_set=("controller.select_timeout_s=6",)))
    # The companion never flew toward a zone: the autopilot's own LAND stayed in charge.
    assert not r.took_control, _explain(r)
    assert r.outcome == "handback", _explain(r)
    assert "APPROACH" not in r.phases


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_people_walking_into_the_target_make_it_retarget_or_hold(flavour, model_path):
    r = _fly(FlightSpec(flavour=flavour, world="intrusion", seed=4, altitude_m=18.0))
    assert r.outcome in ("safe", "handback"), _explain(r)
    assert r.took_control, _explain(r)
    # Walkers entered the zone during the approach/descent: the controller noticed.
    assert any("lost" in m or "holding" in m or "re-target" in m for m in r.messages), _explain(r)
    if r.outcome == "safe":
        assert r.clearance_m >= r.spec.r0_m


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_twenty_percent_packet_loss_still_lands_safely_or_hands_back(flavour, model_path):
    r = _fly(FlightSpec(flavour=flavour, world="free_area", seed=5, altitude_m=18.0,
                        packet_loss=0.2))
    assert r.outcome in ("safe", "handback"), _explain(r)
    if r.outcome == "safe":
        assert r.clearance_m >= r.spec.r0_m
