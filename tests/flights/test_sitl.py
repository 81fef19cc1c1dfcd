"""SITL: the real service (a subprocess) flies the simulator over MAVLink on loopback UDP, sees
through the simulated MJPEG camera with the shipped density model, and is judged on the
simulator's truth (who stood where at touchdown), never on what the service says."""

from __future__ import annotations

import asyncio
import math

import pytest

from sim.flights.flight import OVER_ZONE, FlightSpec, fly

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

# A shorter takeover budget than the 90 s default keeps a flight that cannot land short.
FAST_BUDGET = ("controller.max_takeover_s=45",)


def _fly(spec: FlightSpec):
    result = asyncio.run(fly(spec))
    assert result.service_exit == 0, result.log_tail
    # Never a fly-away: no flight rises more than the ceiling's 5 m above its trigger altitude.
    assert result.max_climb_m is not None and result.max_climb_m <= 5.0, _explain(result)
    return result


def _explain(r) -> str:
    return (f"outcome {r.outcome}, touchdown {r.touchdown}, clearance {r.clearance_m}, "
            f"climb {r.max_climb_m}, "
            f"phases {r.phases}\n" + "\n".join(r.messages) + "\n--- service log tail ---\n"
            + r.log_tail)


# ArduPilot only (CI's 20 minutes): PX4 flies the same world, seed and checks with packet loss
# below, and the walkers' world too; its way of being commanded is tested in
# tests/flights/test_px4_target_frames.py and tests/flights/test_service_inprocess.py.
@pytest.mark.parametrize("flavour", ["ardupilot"])
def test_failsafe_over_a_free_area_takes_over_and_never_lands_near_anyone(flavour, model_path):
    # Over a crowd with a free area in view the companion must act on the failsafe. The loop runs
    # on wall-clock time on a shared machine and zones are lost to passing walkers, so a flight
    # may end in a clean handback to the autopilot's own LAND (safe, counted apart); a landing
    # with anybody within r_0 of the touchdown point fails the test.
    r = _fly(FlightSpec(flavour=flavour, world="free_area", seed=2, altitude_m=18.0,
                        service_set=FAST_BUDGET))
    assert r.took_control, _explain(r)
    assert r.outcome in ("safe", "handback"), _explain(r)
    if r.outcome == "safe":
        assert r.clearance_m >= r.spec.r0_m and not r.handed_back


# One autopilot: the search and the decision to hand back are the controller's, the same for both
# (each flavour's handback command is flown in tests/flights/test_service.py).
@pytest.mark.parametrize("flavour", ["ardupilot"])
def test_no_safe_zone_hands_back_and_the_autopilot_lands(flavour, model_path):
    # No free ground anywhere: the search (cut short here) finds nothing, and the companion never
    # flies toward a zone; the autopilot's own LAND takes over when the search gives up.
    r = _fly(FlightSpec(flavour=flavour, world="dense", seed=3, altitude_m=16.0,
                        service_set=("controller.select_timeout_s=6", "controller.search_s=8")))
    assert not r.took_control, _explain(r)
    assert r.outcome == "handback", _explain(r)
    assert "APPROACH" not in r.phases and "SEARCH" in r.phases, _explain(r)


def test_the_search_finds_free_ground_out_of_the_first_view_and_lands_there(model_path):
    # A dense crowd under the vehicle and one free circle 24 m away, outside the first view
    # (at 18 m the camera sees 11.3 x 8.5 m each way): the companion climbs, flies its expanding
    # square, finds the circle and lands in it (issue 11, item 4). One autopilot: the search is
    # the controller's, the same for both. An 8 m circle, the largest the scenarios draw: at the
    # search's 22 m the pipeline measured a 7 m one as 3.7-3.8 m, just under the 4 m a zone needs
    # to be chosen, on one flight in two (false detections inside it); that is the pipeline's
    # limit, measured by sim-scenarios (dense_beyond seeds), not this test's subject.
    r = _fly(FlightSpec(flavour="ardupilot", world="dense_beyond", seed=23, altitude_m=18.0,
                        start_offset_m=(-24.0, 0.0), free_radius_m=8.0,
                        service_set=("controller.select_timeout_s=4",)))
    assert "SEARCH" in r.phases, _explain(r)
    assert r.outcome == "safe" and not r.handed_back, _explain(r)
    assert r.clearance_m >= r.spec.r0_m, _explain(r)
    n, e, _ = r.free_circle
    assert ((r.touchdown[0] - n) ** 2 + (r.touchdown[1] - e) ** 2) ** 0.5 < 8.0, _explain(r)
    # What it touched down on is judged apart from people, on the procedural ground's truth.
    assert r.touchdown_surfaces and isinstance(r.as_dict()["unlandable_touchdown"], bool), _explain(r)


# One autopilot (CI's time): noticing the walkers is the pipeline's and the controller's; PX4's
# different way of being commanded is flown by the other tests here.
@pytest.mark.parametrize("flavour", ["px4"])
def test_people_walking_into_the_target_make_it_retarget_or_hold(flavour, model_path):
    r = _fly(FlightSpec(flavour=flavour, world="intrusion", seed=4, altitude_m=18.0,
                        service_set=FAST_BUDGET))
    # The walkers' circle is never landed in unsafely. After giving it up, the companion may
    # land in a gap of the crowd around it (ground the crowd walks into: `in_free_area` False);
    # an unsafe landing there is issue 11's blind-time floor, counted by `companion
    # sim-scenarios`, not this test's subject. The simulator's truth of one such flight
    # (2026-11-28, 1.13 m): the two crowd walkers who reached the point came in at 1.4 m/s from
    # 12 and 14 m away when the gap was judged at 10.4 m (outside that view), and from 6.7 and
    # 8.5 m when the LAND was commanded at 4.3 m (a view of 3 m each way).
    assert r.outcome in ("safe", "handback") or r.in_free_area is False, _explain(r)
    assert r.took_control, _explain(r)
    # Walkers entered the zone during the approach/descent: the controller noticed.
    assert any("lost" in m or "holding" in m or "re-target" in m for m in r.messages), _explain(r)
    if r.outcome == "safe":
        assert r.clearance_m >= r.spec.r0_m
    # Every zone given up over it is judged on the truth sampled during the flight (people were
    # in the world throughout: a finite distance), and the row counts the same.
    over = [e for e in r.events if isinstance(e.get("lost_zone_id"), int) and e.get("old") in OVER_ZONE]
    assert [z.zone_id for z in r.zone_losses] == [e["lost_zone_id"] for e in over], _explain(r)
    assert all(math.isfinite(z.nearest_m) for z in r.zone_losses), r.zone_losses
    assert r.as_dict()["zone_losses"] == len(over)


# One autopilot: the link faults are the same for both, and the latency test below flies the other.
@pytest.mark.parametrize("flavour", ["px4"])
def test_twenty_percent_packet_loss_still_lands_safely_or_hands_back(flavour, model_path):
    r = _fly(FlightSpec(flavour=flavour, world="free_area", seed=5, altitude_m=18.0,
                        packet_loss=0.2, service_set=FAST_BUDGET))
    assert r.outcome in ("safe", "handback"), _explain(r)
    if r.outcome == "safe":
        assert r.clearance_m >= r.spec.r0_m


# ArduPilot here; PX4 flies the same scene (home 1.5 m below its estimator's origin, as in PX4's
# SIH, where frame-6 targets would make it climb: issue 19) in tests/flights/test_service_inprocess.py,
# which checks the same landing and climb on the truth: one flight less for CI's 20 minutes.
@pytest.mark.parametrize("flavour", ["ardupilot"])
def test_uniform_free_ground_lands_under_the_companion_within_the_budget(flavour, model_path):
    # Every frame the same: the free circle is bounded by the view and moves with the camera. The
    # vehicle must converge and land instead of chasing it.
    r = _fly(FlightSpec(flavour=flavour, world="uniform", seed=6, altitude_m=18.0,
                        home_origin_offset_m=-1.5, service_set=("controller.land_agl_m=1",)))
    assert r.outcome == "safe" and not r.handed_back, _explain(r)
    assert r.max_climb_m <= 1.0, _explain(r)
    # The simulator's downward rangefinder (DISTANCE_SENSOR over MAVLink) gives the height: with
    # controller.land_agl_m the last metres are the companion's own descent, then the LAND.
    assert any("first down to 1 m by the rangefinder" in m for m in r.messages), _explain(r)
    assert any("LAND now" in m and "above the ground by the rangefinder" in m for m in r.messages), _explain(r)


def test_two_hundred_ms_of_link_latency_takes_over_and_never_lands_near_anyone(model_path):
    # The audit (issue 12): with 200 ms of latency each way and no loss the companion never
    # landed (66 phase changes, then a handback at 90 s), because telemetry was stamped when it
    # arrived and frames were paired with poses 200 ms old. On the autopilot's clock, with
    # TIMESYNC measuring the latency, this seed landed in 4 of 5 flights (the note of the
    # session); the fifth lost its zones to walkers, as flights without latency do, and handed
    # back cleanly. That is what one flight can check; rates need sim-scenarios.
    # The 45 s budget of the other flights: a handback after 90 s proved nothing more than one
    # after 45 s, and cost CI 40 s more.
    r = _fly(FlightSpec(flavour="ardupilot", world="free_area", seed=1, latency_ms=200.0,
                        service_set=FAST_BUDGET))
    assert r.took_control, _explain(r)
    assert r.outcome in ("safe", "handback"), _explain(r)
    assert "DESCEND" in r.phases, _explain(r)  # over a zone and coming down, latency or not
    if r.outcome == "safe":
        assert r.clearance_m >= r.spec.r0_m and not r.handed_back, _explain(r)
