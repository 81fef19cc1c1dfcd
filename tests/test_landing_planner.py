"""The zone planner's re-check of the target during the descent."""

from companion.control.planner import PlannerConfig, ZoneCheck, ZonePlanner
from companion.pipeline.tracker import Track


def _track(r, view_limited=False, r_view=20.0, misses=0):
    return Track(id=7, x=1.0, y=2.0, r=r, r_filtered=r, age=30, hits=30, misses=misses,
                 born_t=0.0, last_t=10.0, view_limited=view_limited, r_view=r_view)


def test_small_zone_is_lost_when_something_is_seen_inside_r0():
    p = ZonePlanner(PlannerConfig(r0_m=2.0))
    verdict, _, why = p.check_target(7, [_track(1.5)], now=10.1)
    assert verdict is ZoneCheck.LOST and "shrank" in why


def test_low_over_the_zone_a_small_view_that_is_all_free_still_holds():
    p = ZonePlanner(PlannerConfig(r0_m=2.0))
    verdict, _, _ = p.check_target(7, [_track(1.5, view_limited=True, r_view=1.5)], now=10.1)
    assert verdict is ZoneCheck.OK
    # ... but not a view too small to tell anything.
    verdict, _, _ = p.check_target(7, [_track(0.6, view_limited=True, r_view=0.6)], now=10.1)
    assert verdict is ZoneCheck.LOST


def test_a_view_limited_zone_is_still_never_chosen_below_r0_plus_margin():
    p = ZonePlanner(PlannerConfig(r0_m=2.0, radius_margin_m=1.0, min_track_age_s=0.0,
                                  min_track_hits=1))
    assert p.choose([_track(1.5, view_limited=True, r_view=1.5)], now=10.1) is None
    assert p.choose([_track(3.5)], now=10.1).id == 7
