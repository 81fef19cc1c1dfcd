"""A frozen camera is caught however it freezes (issue 61, item 7): one alternating between two
frames, or a frozen image with a live clock drawn on it, delivered its frames as live (77 of 77)
because only the previous frame was compared. Real files and a real MJPEG server on loopback; the
live side is the simulator's own rendered frames, with its sensor noise and JPEG encoding, which
must all stay fresh, hovering over a static scene or standing on the ground."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.service.camera import CameraSource
from companion.service.freshness import MAX_CHANGED_CELLS, Freshness, changed_cells, signature
from sim.world.camera_server import SensorNoise
from sim.world.crowd import Circle, crowd_with_free_area
from sim.world.ground import ProceduralGround
from sim.world.render import render_world
from tests.companion.service.test_camera_sources import _collect, _ScriptedMjpegServer, _wait_until

INTRINSICS = Intrinsics.from_fov(640, 480, 90.0)
NADIR = Mount.from_degrees(0, -90, 0)
JPEG_QUALITY = 85  # the simulator camera's (sim.world.camera_server.CameraServer)


def _scene(seed: int = 3) -> tuple[object, ProceduralGround, tuple[float, float]]:
    """The flight tests' world: a crowd with a free circle on a lawn, and where the vehicle is."""
    ground = ProceduralGround(seed)
    cn, ce = ground.lawn_near(0.0, 0.0)
    world = crowd_with_free_area(seed=seed, free=Circle(cn, ce, 5.0), centre=(cn - 8.5, ce - 8.5))
    return world, ground, (cn - 8.5, ce - 8.5)


def _rendered(height_m: float, n: int, seed: int = 3) -> list[bytes]:
    """``n`` JPEG frames as the simulator's camera serves them from a vehicle holding perfectly
    still ``height_m`` above a world that does not move: read noise is all that changes."""
    world, ground, (north, east) = _scene(seed)
    base = render_world(world, Pose(0.0, north, east, -height_m, 0.0, 0.0, 0.3), INTRINSICS, NADIR, ground)
    noise = SensorNoise(1.5, seed)
    return [cv2.imencode(".jpg", noise(base), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1].tobytes()
            for _ in range(n)]


def _clock_frames(n: int) -> list[bytes]:
    """A frozen image (one rendered frame, its noise frozen in) with a live clock drawn on it
    each frame, encoded afresh each time as a camera's encoder would."""
    frozen = cv2.imdecode(np.frombuffer(_rendered(25.0, 1)[0], np.uint8), cv2.IMREAD_COLOR)
    out = []
    for k in range(n):
        img = frozen.copy()
        stamp = f"2026-12-06 05:{k // 600:02d}:{k // 10 % 60:02d}.{k % 10}00"
        cv2.putText(img, stamp, (10, 465), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2)
        out.append(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1].tobytes())
    return out


def _play_folder(folder: Path, frames: list[bytes]) -> tuple[CameraSource, list]:
    folder.mkdir()
    for i, data in enumerate(frames):
        (folder / f"f{i:04d}.jpg").write_bytes(data)
    cam = CameraSource(str(folder), fps=400)
    got = _collect(cam)
    cam.start()
    assert _wait_until(lambda: cam.ended, 20)
    cam.stop()
    return cam, got


@pytest.mark.parametrize("height_m", [25.0, 2.0, 0.3])
def test_the_simulators_frames_of_a_still_scene_stay_live(tmp_path: Path, height_m: float) -> None:
    """Hovering without a tremor over a scene where nothing moves, or standing on the ground:
    every frame is fresh (read noise changes every cell)."""
    frames = _rendered(height_m, 24)
    cam, got = _play_folder(tmp_path / "live", frames)
    assert cam.stats.repeated == 0 and cam.stats.stale == 0
    assert len(got) == 24 and cam.stats.frames == 24
    # Far from the threshold: no pair of them is anywhere near "the same but for a small region".
    sigs = [signature(g.image) for g in got[:6]]
    assert min(changed_cells(a, b) for i, a in enumerate(sigs) for b in sigs[:i]) > 0.9


def test_a_camera_alternating_between_two_frames_is_frozen(tmp_path: Path) -> None:
    a, b = _rendered(25.0, 2)
    cam, got = _play_folder(tmp_path / "alternating", [a, b] * 38 + [a])  # 77 frames
    assert len(got) == 2 and cam.stats.frames == 2
    # Every later b is identical to the last fresh frame (b); every later a is the history's.
    assert cam.stats.repeated == 75 and cam.stats.stale == 38


def test_a_frozen_image_with_a_live_clock_is_frozen(tmp_path: Path) -> None:
    frames = _clock_frames(77)
    first = cv2.imdecode(np.frombuffer(frames[0], np.uint8), cv2.IMREAD_COLOR)
    later = cv2.imdecode(np.frombuffer(frames[-1], np.uint8), cv2.IMREAD_COLOR)
    assert not np.array_equal(first, later)  # the clock did change, and only where it is drawn
    assert 0 < changed_cells(signature(first), signature(later)) <= MAX_CHANGED_CELLS
    cam, got = _play_folder(tmp_path / "clock", frames)
    assert len(got) == 1 and cam.stats.frames == 1  # the first could not be known for frozen
    assert cam.stats.repeated == 76 and cam.stats.stale == 76


def test_a_frozen_stream_with_a_clock_is_reported_frozen_not_lost() -> None:
    """Over MJPEG: live frames, then the encoder freezes on its picture and draws its clock."""
    live = _rendered(25.0, 5, seed=1)
    clock = _clock_frames(400)

    def script(conn: int):
        if conn == 1:
            yield from live
        yield from clock
        yield None

    server = _ScriptedMjpegServer(script, period=0.02)
    cam = CameraSource(server.url, stall_timeout_s=0.5, max_backoff_s=0.2)
    got = _collect(cam)
    try:
        cam.start()
        assert _wait_until(lambda: cam.stats.frames >= 6, 5)
        assert _wait_until(lambda: cam.frozen(), 5)
        assert not cam.delivering()
        assert cam.stats.frames == 6 and len(got) == 6  # five live ones and the first frozen one
        assert cam.stats.stale >= 10
    finally:
        cam.stop()
        server.close()


def test_the_history_remembers_only_fresh_frames() -> None:
    """A frozen camera is compared with its last live frames and its first frozen one, however
    long it stays frozen; a frame that differs from all of them everywhere is fresh again."""
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (480, 640, 3), dtype=np.uint8) for _ in range(3)]
    f = Freshness(history=2)
    assert [f.judge(frames[0]), f.judge(frames[0]), f.judge(frames[1]), f.judge(frames[0])] == \
        ["fresh", "repeat", "fresh", "stale"]
    assert f.judge(frames[2]) == "fresh"
    assert f.judge(frames[0]) == "fresh"  # out of a history of two: a ring this long is not caught
