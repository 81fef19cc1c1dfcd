"""The real PX4's last metres (issue 62, item 5), in the simulated PX4.

On PX4 1.15.4 SIH the companion lost its zone ("no longer tracked") a metre or two above the
ground, climbed back to 10-12 m, and did so three times until its 90 s budget handed back; SIH's
relative altitude on the ground reads -1.3 to +1.8 m. The simulated PX4 with its altitude reading
1.3 m low (``alt_bias_m``) over uniform ground does the same on the controller of main: the zone,
judged at the judging height, leaves the tracks at about 4.5 m on every descent (the view the
pipeline computes from the wrong height is too small to keep it), and the companion climbs back
four times and hands back. Low over a judged zone, leaving the tracks is no reason to climb;
only somebody seen within r0 under the vehicle is. One lockstep flight (a few minutes of CPU).
"""

from __future__ import annotations

import dataclasses

import pytest

from sim.flights.lockstep import fly_in_process
from sim.flights.scenarios import scenario

pytestmark = [pytest.mark.timeout(1200)]


def test_px4_reading_its_altitude_low_lands_over_its_judged_zone_without_climbing_back(model_path) -> None:
    spec = dataclasses.replace(scenario(3, "px4"), world="uniform", alt_bias_m=-1.3)
    r = fly_in_process(spec)
    assert r.service_exit == 0, r.log_tail
    # Judged, then down to the LAND and landed: no HOLD after the descent began (main: DESCEND,
    # HOLD four times, then HANDBACK at the 90 s budget).
    assert r.phases[-2:] == ["LAND", "LANDED"], (r.phases, r.messages)
    assert "HOLD" not in r.phases[r.phases.index("DESCEND"):], (r.phases, r.messages)
    assert r.outcome == "safe", (r.outcome, r.messages)
    assert any("nobody seen within r0: landing committed" in m for m in r.messages), r.messages
