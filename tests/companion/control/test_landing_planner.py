"""The zone planner's re-check of the target during the descent."""

import pytest

from companion.control.planner import PlannerConfig, ZoneCheck, ZonePlanner
from companion.pipeline.circles import Circle
from companion.pipeline.tracker import Track, TrackerParams, ZoneTracker


def _track(r, view_limited=False, r_view=20.0, misses=0):
    return Track(id=7, x=1.0, y=2.0, r=r, r_filtered=r, age=30, hits=30, misses=misses,
                 born_t=0.0, last_t=10.0, view_limited=view_limited, r_view=r_view)


def test_small_zone_is_lost_when_something_is_seen_inside_r0():
    p = ZonePlanner(PlannerConfig(r0_m=2.0))
    verdict, _, why = p.check_target(7, [_track(1.5)], now=10.1)
    assert verdict is ZoneCheck.SMALL and "shrank" in why


def test_low_over_the_zone_a_small_view_that_is_all_free_still_holds():
    p = ZonePlanner(PlannerConfig(r0_m=2.0))
    verdict, _, _ = p.check_target(7, [_track(1.5, view_limited=True, r_view=1.5)], now=10.1)
    assert verdict is ZoneCheck.OK
    # ... but not a view too small to tell anything.
    verdict, _, _ = p.check_target(7, [_track(0.6, view_limited=True, r_view=0.6)], now=10.1)
    assert verdict is ZoneCheck.SMALL


def test_a_view_limited_zone_is_still_never_chosen_below_r0_plus_margin():
    p = ZonePlanner(PlannerConfig(r0_m=2.0, radius_margin_m=1.0, min_track_age_s=0.0,
                                  min_track_hits=1))
    assert p.choose([_track(1.5, view_limited=True, r_view=1.5)], now=10.1) is None
    assert p.choose([_track(3.5)], now=10.1).id == 7


def test_the_planner_picks_the_oldest_confirmed_zone_as_the_paper_does():
    # Moved from the tracker's tests: the tracker reports tracks, the planner alone picks the
    # target. With its age, hit and margin checks off, its rule is the paper's "oldest stable".
    def oldest_stable(tr, r_min, now):
        cfg = PlannerConfig(r0_m=r_min, radius_margin_m=0.0, min_track_age_s=0.0, min_track_hits=1)
        return ZonePlanner(cfg).choose(tr.tracks(), now)

    tr = ZoneTracker(TrackerParams(mu_2=1, mu_1=5))
    a, b, c = Circle(0.0, 0.0, 3.0), Circle(20.0, 0.0, 6.0), Circle(40.0, 0.0, 1.0)
    tr.update([a], 0.0)
    tr.update([a, b], 0.1)
    tr.update([a, b, c], 0.2)
    ida, idb = (t.id for t in tr.tracks()[:2])
    # The oldest wins even though b is larger.
    assert oldest_stable(tr, 2.0, 0.2).id == ida
    # a not confirmed by the latest frame: b, the next oldest, is the target.
    tr.update([b, c], 0.3)
    assert oldest_stable(tr, 2.0, 0.3).id == idb
    # c is too small ever to be picked.
    tr.update([c], 0.4)
    assert oldest_stable(tr, 2.0, 0.4) is None
    assert oldest_stable(tr, 0.5, 0.4).r == pytest.approx(1.0, abs=0.05)
