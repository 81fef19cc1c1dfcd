"""Landing-zone tracker (pipeline step 5)."""

import math
from dataclasses import dataclass

import pytest

from companion.pipeline.circles import Circle
from companion.pipeline.tracker import TrackerParams, ZoneTracker

DT = 0.1



@dataclass(frozen=True)
class Uniform:
    """One frame's clearance (``tracker.Clearance``): the same free and view radius (m) everywhere."""

    free: float
    view: float

    def at(self, x: float, y: float) -> tuple[float, float]:
        return self.free, self.view


@dataclass(frozen=True)
class Split:
    """``inside`` (free, view) within ``|x| < x_max`` (m), ``outside`` beyond."""

    x_max: float
    inside: tuple[float, float]
    outside: tuple[float, float]

    def at(self, x: float, y: float) -> tuple[float, float]:
        return self.inside if abs(x) < self.x_max else self.outside


def _run(tracker, frames, t0=0.0):
    out = []
    for k, circles in enumerate(frames):
        out.append(tracker.update(circles, t0 + k * DT))
    return out


def test_moving_circles_keep_their_ids():
    tr = ZoneTracker(TrackerParams(mu_2=3, max_tracks=5))
    starts = [(0.0, 0.0, 3.0), (12.0, 0.0, 2.5), (0.0, 12.0, 4.0)]
    vel = [(1.0, 0.0), (0.0, -1.2), (-0.8, 0.8)]
    ids_seen = None
    for k in range(60):
        t = k * DT
        circles = [Circle(x + vx * t, y + vy * t, r) for (x, y, r), (vx, vy) in zip(starts, vel)]
        tracks = tr.update(circles, t)
        if k >= 2:
            by_pos = {round(tk.r, 0): tk.id for tk in tracks}
            assert len(tracks) == 3
            if ids_seen is None:
                ids_seen = by_pos
            assert by_pos == ids_seen
    # The filter has learned the velocities: the prediction follows the zone.
    t1 = next(t for t in tr.tracks() if abs(t.r - 3.0) < 0.1)
    assert abs(t1.x - 1.0 * 59 * DT) < 0.3 and abs(t1.y) < 0.3


def test_missing_for_fewer_than_mu1_frames_keeps_the_track():
    p = TrackerParams(mu_1=3, mu_2=2)
    tr = ZoneTracker(p)
    z = Circle(5.0, 5.0, 3.0)
    _run(tr, [[z]] * 4)
    (track,) = tr.tracks()
    for k in range(p.mu_1):
        tracks = tr.update([], 1.0 + k * DT)
        assert [t.id for t in tracks] == [track.id]
        assert tracks[0].misses == k + 1
    # Back in view: same track, confirmed again.
    tracks = tr.update([z], 2.0)
    assert [t.id for t in tracks] == [track.id] and tracks[0].misses == 0
    # Missing more than mu_1 consecutive frames: deleted.
    for k in range(p.mu_1 + 1):
        tracks = tr.update([], 3.0 + k * DT)
    assert tracks == []
    assert tr.ended == 1


def test_a_new_zone_starts_a_track_only_after_mu2_frames():
    tr = ZoneTracker(TrackerParams(mu_2=4))
    z = Circle(0.0, 0.0, 2.0)
    for k in range(3):
        assert tr.update([z], k * DT) == []
    assert len(tr.update([z], 3 * DT)) == 1
    # A proposal that flickers (not consecutive) never becomes a track.
    tr2 = ZoneTracker(TrackerParams(mu_2=2))
    for k in range(10):
        assert tr2.update([z] if k % 2 == 0 else [], k * DT) == []


def test_at_most_max_tracks():
    tr = ZoneTracker(TrackerParams(mu_2=1, max_tracks=2))
    circles = [Circle(10.0 * i, 0.0, 2.0 + i) for i in range(4)]
    tracks = tr.update(circles, 0.0)
    assert len(tracks) == 2
    assert sorted(t.r for t in tracks) == [4.0, 5.0]  # the largest are born first


def test_ages_increase_and_hits_count():
    tr = ZoneTracker(TrackerParams(mu_2=1))
    z = Circle(0.0, 0.0, 2.0)
    ages = [tr.update([z], k * DT)[0].age for k in range(5)]
    assert ages == [0, 1, 2, 3, 4]
    assert tr.tracks()[0].hits == 5


def test_safe_radius_stays_inside_the_last_proposal():
    tr = ZoneTracker(TrackerParams(mu_2=1))
    for k in range(5):
        tr.update([Circle(0.0, 0.0, 5.0)], k * DT)
    # The zone suddenly shrinks: the filter lags, the reported radius does not.
    (t,) = tr.update([Circle(0.5, 0.0, 3.0)], 0.5)
    assert t.r_filtered > 3.0
    assert t.r + math.hypot(t.x - 0.5, t.y) <= 3.0 + 1e-9


def test_radius_never_negative():
    tr = ZoneTracker(TrackerParams(mu_2=1, mu_1=50, min_iou=0.0))
    r = 4.0
    for k in range(10):
        tr.update([Circle(0.0, 0.0, r)], k * DT)
        r = max(r - 0.4, 0.05)
    for k in range(40):
        (t,) = tr.update([], 1.0 + k * DT)
        assert t.r_filtered >= 0 and t.r >= 0


@pytest.mark.parametrize("kw", [dict(sigma_a=0), dict(r_std=(1, 1)), dict(min_iou=1.5),
                                dict(mu_2=0), dict(max_tracks=0), dict(motion="drift"),
                                dict(sigma_v=0.0), dict(sigma_v=math.nan)])
def test_bad_parameters_are_clear_errors(kw):
    with pytest.raises(ValueError, match="tracker"):
        TrackerParams(**kw)


def test_nan_time_is_a_clear_error():
    with pytest.raises(ValueError, match="finite"):
        ZoneTracker().update([], float("nan"))


def test_clearance_measures_the_radius_at_the_filtered_centre():
    tr = ZoneTracker(TrackerParams(mu_2=1))
    for k in range(5):
        tr.update([Circle(0.0, 0.0, 5.0)], k * DT)
    # The proposal's centre jumps (a noisy largest circle) but the ground about the filtered
    # centre is still free for 4.5 m on this frame: the zone keeps that radius, not a bound from
    # the jumped proposal.
    (t,) = tr.update([Circle(1.5, 0.0, 5.0)], 0.5, clearance=Uniform(4.5, 20.0))
    assert t.r == pytest.approx(4.5) and not t.view_limited
    (t,) = tr.update([Circle(1.5, 0.0, 5.0)], 0.6, clearance=Uniform(9.0, 20.0))
    assert t.r == pytest.approx(t.r_filtered)  # never wider than the filter's own radius


def test_free_ground_confirms_a_zone_no_proposal_matched():
    tr = ZoneTracker(TrackerParams(mu_2=1, mu_1=2))
    for k in range(3):
        (t0,) = tr.update([Circle(0.0, 0.0, 4.0)], k * DT, clearance=Uniform(4.0, 20.0),
                          r_min=2.0)
    # The largest circle jumped elsewhere (no overlap), but the ground under the zone is still
    # free for 3.5 m: the zone stays confirmed, with the radius measured there.
    tracks = tr.update([Circle(30.0, 0.0, 6.0)], 0.3,
                       clearance=Split(5.0, (3.5, 20.0), (6.0, 20.0)), r_min=2.0)
    zone = next(t for t in tracks if t.id == t0.id)
    assert zone.misses == 0 and zone.r == pytest.approx(3.5, abs=0.01)
    # Someone steps in: free for 1 m only, in a wide view. Not confirmed; gone after mu_1.
    for k in range(3):
        tracks = tr.update([], 0.4 + k * DT, clearance=Uniform(1.0, 20.0), r_min=2.0)
    assert all(t.id != t0.id for t in tracks)


def test_a_view_smaller_than_the_zone_confirms_what_it_sees():
    tr = ZoneTracker(TrackerParams(mu_2=1, mu_1=1))
    for k in range(3):
        (t0,) = tr.update([Circle(0.0, 0.0, 4.0)], k * DT, clearance=Uniform(4.0, 20.0),
                          r_min=2.0)
    # Low over the zone: the camera sees 1.5 m around the centre, all of it free.
    (t,) = tr.update([], 0.3, clearance=Uniform(1.5, 1.5), r_min=2.0)
    assert t.misses == 0 and t.view_limited and t.r == pytest.approx(1.5, abs=0.01)
    assert t.r_view == pytest.approx(1.5)
    # Something seen inside the small view is not "view-limited": the zone is not confirmed.
    (t,) = tr.update([], 0.4, clearance=Uniform(0.8, 1.5), r_min=2.0)
    assert t.misses == 1
    # A view too small to say anything confirms nothing.
    tr2 = ZoneTracker(TrackerParams(mu_2=1, mu_1=3))
    tr2.update([Circle(0.0, 0.0, 4.0)], 0.0)
    (t,) = tr2.update([], 0.1, clearance=Uniform(0.5, 0.5), r_min=2.0)
    assert t.misses == 1


def test_a_zone_that_is_ground_does_not_coast_on_a_velocity():
    """World frame (motion "position"): proposals that slide 1 m/s for 2 s (the view moving over a
    zone bounded by it) pull the zone only part of the way, and when they stop coming the zone
    stays where it was last seen; the paper's constant velocity learns the slide and keeps
    carrying the zone away (12-13 m in 4 s in a flight, docs/design.md "Zones are ground")."""
    ends = {}
    for motion in ("velocity", "position"):
        tr = ZoneTracker(TrackerParams(mu_2=2, mu_1=30, motion=motion, sigma_v=0.1))
        _run(tr, [[Circle(0.0, 0.0, 4.0)]] * 10)
        _run(tr, [[Circle(1.0 * k * DT, 0.0, 4.0)] for k in range(1, 21)], t0=1.0)
        (last_seen,) = tr.tracks()
        _run(tr, [[]] * 20, t0=3.0)  # missed for 2 s: the filter alone moves it
        (track,) = tr.tracks()
        ends[motion] = (last_seen.x, track.x)
    seen_v, end_v = ends["velocity"]
    seen_p, end_p = ends["position"]
    assert end_v - seen_v > 1.0  # coasting on the slide
    assert end_p == pytest.approx(seen_p, abs=1e-9)  # ground stays put
    assert seen_p < 2.0 * 0.75  # and it lagged the slide (2 m) rather than followed it


def test_the_velocity_models_noise_is_filterpys_discrete_white_noise_on_each_axis():
    # Q is written entry by entry for speed: it must be the textbook block, per axis (x, y, r)
    # with its rate, and F the constant-velocity step.
    import numpy as np
    from filterpy.common import Q_discrete_white_noise

    from companion.pipeline.tracker import _cv_matrices

    for dt, sigma_a in ((1 / 15, 0.5), (0.1, 2.0), (0.5, 0.01)):
        F, Q = _cv_matrices(dt, sigma_a)
        block = Q_discrete_white_noise(dim=2, dt=dt, var=sigma_a)
        for axis in range(3):
            rows = [axis, axis + 3]
            assert np.allclose(Q[np.ix_(rows, rows)], block, rtol=1e-12, atol=0)
            assert F[axis, axis + 3] == dt and F[axis, axis] == 1.0
        others = np.ones((6, 6), bool)
        for axis in range(3):
            others[np.ix_([axis, axis + 3], [axis, axis + 3])] = False
        assert not Q[others].any()
