"""Flight recorder and RecordingReader with real frames, real video segments and real files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.recording import FlightRecorder, RecordingError, RecordingReader


def _frame(i: int, w: int = 160, h: int = 120) -> np.ndarray:
    """A frame unlike its neighbours at every scale (big blobs, fine noise), like real scenes."""
    rng = np.random.default_rng(i)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 2)
    for _ in range(6):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(10, 40)), tuple(int(v) for v in rng.integers(0, 255, 3)), -1)
    cv2.putText(img, str(i), (10, 60), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255), 3)
    return img


def _pose(i: int, t: float) -> Pose:
    return Pose(t, 0.5 * i, -0.25 * i, -30.0 + 0.1 * i, 0.01 * i, -0.02 * i, math.pi / 4 + 0.001 * i)


def _record(root: Path, n: int, segment_s: float = 1.0, max_mb: float = 100.0, dt: float = 0.1,
            **kw: object) -> tuple[FlightRecorder, Path]:
    rec = FlightRecorder(root, segment_s=segment_s, max_mb=max_mb, fps=10, queue_size=n + 1,
                         intrinsics=Intrinsics.from_fov(160, 120, 90), mount=Mount.from_degrees(0, -80, 5),
                         meta={"model": {"path": "models/x.onnx"}}, **kw)  # type: ignore[arg-type]
    path = rec.start()
    for i in range(n):
        t = 100.0 + dt * i
        # Frame 3 has no pose (stale pose): recorded with pose null.
        assert rec.add_frame(2 * i, t, _frame(i), None if i == 3 else _pose(i, t))
        rec.add_event("decision", t, state="MONITOR", tracks=[{"id": 1, "r": 3.5}])
    rec.close()
    return rec, path


def _similar(a: np.ndarray, b: np.ndarray) -> bool:
    return float(np.abs(a.astype(int) - b.astype(int)).mean()) < 8


def test_recording_reads_back_frame_by_frame_with_poses(tmp_path: Path) -> None:
    rec, path = _record(tmp_path, 25)
    assert rec.stats.frames == 25 and rec.stats.dropped == 0
    assert rec.stats.segments == 3  # 2.5 s of frames in 1 s segments
    reader = RecordingReader(path)
    assert reader.intrinsics == Intrinsics.from_fov(160, 120, 90)
    assert reader.mount == Mount.from_degrees(0, -80, 5)
    assert reader.meta["model"]["path"] == "models/x.onnx"
    frames = list(reader.frames())
    assert [f.index for f in frames] == [2 * i for i in range(25)]
    for i, f in enumerate(frames):
        assert f.t == pytest.approx(100.0 + 0.1 * i)
        assert f.frame_bgr.shape == (120, 160, 3)
        assert _similar(f.frame_bgr, _frame(i)), f"frame {i} does not match what was recorded"
        if i == 3:
            assert f.pose is None
        else:
            assert f.pose == _pose(i, 100.0 + 0.1 * i)
    # Frames are distinguishable, so a shifted pairing would have failed above.
    assert not _similar(frames[0].frame_bgr, _frame(1))
    events = list(reader.events("decision"))
    assert len(events) == 25 and events[0]["tracks"][0]["r"] == 3.5


def test_truncated_last_segment_and_half_written_line_are_tolerated(tmp_path: Path) -> None:
    _, path = _record(tmp_path, 25)
    last = sorted(path.glob("seg_*.avi"))[-1]
    data = last.read_bytes()
    last.write_bytes(data[: len(data) // 2])  # power cut mid-segment
    with open(path / "frames.jsonl", "a") as fh:
        fh.write('{"i": 50, "t": 10')  # half-written line
    reader = RecordingReader(path)
    frames = list(reader.frames())
    assert 20 <= len(frames) < 25
    for f in frames:
        i = f.index // 2
        assert _similar(f.frame_bgr, _frame(i))
    assert reader.stats.bad_lines == 1
    assert reader.stats.truncated + reader.stats.corrupt + len(frames) == 25


def test_disk_budget_deletes_oldest_segments(tmp_path: Path) -> None:
    # Each 160x120 MJPG frame is ~10-20 kB; a 0.1 MiB budget keeps only the newest segments.
    rec, path = _record(tmp_path, 40, segment_s=0.5, max_mb=0.1)
    segs = sorted(path.glob("seg_*.avi"))
    assert rec.stats.deleted > 0
    assert sum(p.stat().st_size for p in segs) <= 0.1 * 2**20 or len(segs) == 1
    assert not (path / "seg_00000.avi").exists()
    reader = RecordingReader(path)
    frames = list(reader.frames())
    assert frames and reader.stats.missing > 0
    assert frames[-1].index == 78  # the newest survived
    assert len(frames) + reader.stats.missing == 40


def test_bad_recordings_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="does not exist"):
        RecordingReader(tmp_path / "nope")
    with pytest.raises(RecordingError, match="meta.json is missing"):
        RecordingReader(tmp_path)
    _, path = _record(tmp_path / "r", 3)
    with pytest.raises(RecordingError, match="holds the runs"):
        RecordingReader(tmp_path / "r")
    (path / "meta.json").write_text("{not json")
    with pytest.raises(RecordingError, match=r"meta\.json is not valid JSON"):
        RecordingReader(path)
    (path / "meta.json").write_text(json.dumps({"format": "companion-recording", "version": 1}))
    (path / "frames.jsonl").unlink()
    with pytest.raises(RecordingError, match=r"frames\.jsonl is missing"):
        RecordingReader(path)


def test_full_queue_drops_and_counts(tmp_path: Path) -> None:
    rec = FlightRecorder(tmp_path, queue_size=1)
    assert not rec.add_frame(0, 0.0, _frame(0), None)  # not started: refused, not crashed
    rec.start()
    big = [_frame(i, 1280, 960) for i in range(30)]
    results = [rec.add_frame(i, 0.01 * i, big[i], None) for i in range(30)]
    rec.close()
    assert results.count(False) == rec.stats.dropped > 0
    assert rec.stats.frames == results.count(True)
    assert len(list(RecordingReader(rec.path).frames())) == rec.stats.frames  # type: ignore[arg-type]
