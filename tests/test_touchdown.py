"""Time to touchdown and the clearance left then (issue 11: walking speed x blind time)."""

from __future__ import annotations

import math

import pytest

from companion.control.touchdown import DescentProfile


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
