"""Time to touchdown and the clearance left then (issue 11: walking speed x blind time)."""

from __future__ import annotations

import math

import pytest

from companion.control.touchdown import DescentProfile, by_rangefinder, guaranteed_clearance, touchdown_basis


def test_time_to_touchdown_is_the_two_descents():
    p = DescentProfile(descend_speed_mps=1.5, land_alt_m=10.0, land_speed_mps=0.5)
    assert p.time_to_touchdown(25.0) == pytest.approx(15.0 / 1.5 + 10.0 / 0.5)
    assert p.time_to_touchdown(4.0) == pytest.approx(8.0)  # already under the LAND altitude
    assert p.time_to_touchdown(-1.0) == 0.0 and math.isnan(p.time_to_touchdown(math.nan))


def test_a_walker_reaches_the_zone_no_later_than_walking_allows():
    p = DescentProfile(walk_speed_mps=1.5, land_alt_m=10.0, land_speed_mps=0.5)
    # A 7 m free circle at 4 m: 8 s of LAND, 12 m of walking: somebody may be at its centre.
    assert p.clearance_at_touchdown(7.0, 4.0) == pytest.approx(7.0 - 12.0)
    assert p.clearance_at_touchdown(7.0, 1.0) == pytest.approx(4.0)


@pytest.mark.parametrize("field", ["descend_speed_mps", "land_speed_mps", "walk_speed_mps", "land_alt_m"])
def test_bad_profiles_are_refused(field):
    with pytest.raises(ValueError, match=field):
        DescentProfile(**{field: -1.0})


K_SIM = 0.75 * math.tan(math.radians(35.0))  # the simulator's 70 degree 4:3 camera: 0.525


def test_the_guarantee_is_what_was_last_seen_less_the_walk_since():
    still = DescentProfile(walk_speed_mps=1e-9, land_alt_m=10.0)
    # Nobody walks: the widest look (from the top) is what is guaranteed.
    assert guaranteed_clearance(still, 21.7, K_SIM) == pytest.approx(K_SIM * 20.0, abs=1e-6)
    # One height only (head plane): nothing seen, and the walk from there.
    p = DescentProfile(walk_speed_mps=1.5, land_alt_m=10.0, land_speed_mps=0.5)
    assert guaranteed_clearance(p, 1.7, K_SIM) == pytest.approx(-1.5 * 1.7 / 0.5)


def test_with_the_simulators_camera_no_descent_guarantees_r0_against_walkers():
    """The physics of docs/design.md: at the descent speeds multicopters fly (ArduPilot's default
    WPNAV_SPEED_DN 1.5 m/s, even 3 m/s) the camera's view shrinks about as fast as a walker closes
    in, so no worst-case promise comes from the vehicle's own camera."""
    for descend, land, land_alt in ((1.5, 0.5, 10.0), (1.5, 0.5, 2.0), (3.0, 1.0, 1.0)):
        p = DescentProfile(descend_speed_mps=descend, land_speed_mps=land, land_alt_m=land_alt, walk_speed_mps=1.5)
        for height in (10.0, 20.0, 25.0, 40.0):
            assert guaranteed_clearance(p, height, K_SIM) < 2.0, (descend, land, land_alt, height)
    # Only a dive well above walk_speed / k (2.9 m/s here) nearly to the ground would: 5 m/s to
    # 0.5 m and a 2 m/s touchdown, from 20 m, into the vortex-ring regime of a multicopter.
    dive = DescentProfile(descend_speed_mps=5.0, land_speed_mps=2.0, land_alt_m=0.5, walk_speed_mps=1.5)
    assert guaranteed_clearance(dive, 20.0, K_SIM) > 2.0


def test_guaranteed_clearance_refuses_nonsense():
    with pytest.raises(ValueError):
        guaranteed_clearance(DescentProfile(), math.nan, K_SIM)
    with pytest.raises(ValueError):
        guaranteed_clearance(DescentProfile(), 10.0, -1.0)


def test_by_the_rangefinder_the_autopilots_land_is_only_the_last_metres():
    # controller.land_agl_m: the companion's own descent goes on to 1 m by the rangefinder, the
    # autopilot's slow LAND flies only that metre.
    p = DescentProfile(descend_speed_mps=1.5, land_alt_m=4.0, land_speed_mps=0.5)
    low = by_rangefinder(p, 1.0)
    assert low.land_alt_m == 1.0 and low.time_to_touchdown(10.0) == pytest.approx(9.0 / 1.5 + 1.0 / 0.5)
    # Off, or not below the LAND height: the profile as it is.
    assert by_rangefinder(p, 0.0) is p and by_rangefinder(p, 4.0) is p and by_rangefinder(p, 6.0) is p


def test_the_touchdown_is_figured_from_a_fresh_rangefinder_else_from_above_home():
    p = DescentProfile(descend_speed_mps=1.5, land_alt_m=4.0, land_speed_mps=0.5)
    assert touchdown_basis(25.0, None, p, 1.0) == (25.0, p)
    assert touchdown_basis(25.0, math.nan, p, 1.0) == (25.0, p)  # no usable reading
    assert touchdown_basis(None, None, p, 1.0) == (None, p)
    # Ground 4 m above home under the vehicle: 21 m by the rangefinder, and the shorter LAND.
    assert touchdown_basis(25.0, 21.0, p, 1.0) == (21.0, by_rangefinder(p, 1.0))
    assert touchdown_basis(25.0, 21.0, p, 0.0) == (21.0, p)  # the setting off: the height still
