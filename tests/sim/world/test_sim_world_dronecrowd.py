"""Real people motion from the DroneCrowd trajectories (needs ../shared; the error without it doesn't)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.geometry.camera import Intrinsics, Mount, Pose
from sim.world.crowd import dronecrowd_world
from sim.world.dronecrowd import (
    DroneCrowdMotion,
    DroneCrowdUnavailable,
    cleaned,
    estimate_scale,
    load_tracks,
    stabilised,
    track_speeds,
)
from sim.world.ground import ProceduralGround
from sim.world.render import render_world


def test_absent_data_gives_a_clear_error(tmp_path) -> None:
    with pytest.raises(DroneCrowdUnavailable, match="licensed data set"):
        DroneCrowdMotion(112, gt_dir=tmp_path / "nowhere")
    with pytest.raises(DroneCrowdUnavailable, match="00003.mat"):
        DroneCrowdMotion(3, gt_dir=tmp_path)


@pytest.fixture(scope="module")
def gt(shared_dir):
    return shared_dir / "data" / "dronecrowd" / "gt"


def test_scale_from_walking_speed(gt) -> None:
    tracks = cleaned(stabilised(load_tracks(112, gt)))
    est = estimate_scale(tracks)
    # A 1920 px wide top-down view of a street market is tens to a couple of hundred metres wide.
    assert 0.02 < est.metres_per_pixel < 0.3
    assert est.n_walkers >= 20
    # By construction the walkers' median speed is the typical walking speed in metres.
    v = track_speeds(tracks) * est.metres_per_pixel
    assert np.median(v[v > np.median(v)]) == pytest.approx(1.3, rel=0.05)


def test_motion_source_in_metres(gt) -> None:
    m = DroneCrowdMotion(112, origin=(10.0, -20.0), gt_dir=gt)
    p = m.positions()
    assert len(p) > 100
    half_w = 960 * m.metres_per_pixel
    half_h = 540 * m.metres_per_pixel
    assert (np.abs(p[:, 0] - 10.0) <= half_h * 1.1).all()
    assert (np.abs(p[:, 1] + 20.0) <= half_w * 1.1).all()
    sp = m.speeds()
    moving = sp[np.isfinite(sp) & m.moving()]
    assert 0.8 < np.median(moving) < 2.0  # people walk, in m/s
    # Interpolated smoothly: at 25 steps per second nobody jumps more than a stride.
    ids0, p0 = m.ids(), m.positions()
    # 13 s: the whole 11.96 s clip, across its end, where play turns back, and on a second back
    # (further back plays the same frames, 0.04 s apart as on the way forward, the other way).
    for _ in range(325):
        m.step(1 / 25)
        ids1, p1 = m.ids(), m.positions()
        _, a, b = np.intersect1d(ids0, ids1, return_indices=True)
        assert np.hypot(*(p1[b] - p0[a]).T).max() < 0.5
        ids0, p0 = ids1, p1
    assert len(np.unique(ids0)) == len(ids0)


def test_world_renders_dronecrowd_people(gt) -> None:
    w = dronecrowd_world(112, gt_dir=str(gt))
    w.step(1.0)
    K = Intrinsics.from_fov(640, 480, 70.0)
    img = render_world(w, Pose(0, 0, 0, -40.0, 0, 0, 0), K, Mount(), ProceduralGround(1))
    assert img.shape == (480, 640, 3)
    assert w.nearest_person_distance((0.0, 0.0)) < 20.0
