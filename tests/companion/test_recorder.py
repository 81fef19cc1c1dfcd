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


def _disk_use(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


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
    with open(sorted(path.glob("frames-*.jsonl"))[-1], "a") as fh:
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
    # Each 160x120 MJPG frame is ~7-16 kB; a 0.08 MiB budget keeps only the newest segments,
    # and (with these frames' sizes) an index chunk that outlives some segments of its frames.
    rec, path = _record(tmp_path, 40, segment_s=0.5, max_mb=0.08)
    assert rec.stats.deleted > 0
    assert _disk_use(tmp_path) <= 0.08 * 2**20
    assert not (path / "seg_00000.avi").exists()
    reader = RecordingReader(path)
    frames = list(reader.frames())
    assert frames and reader.stats.missing > 0
    assert frames[-1].index == 78  # the newest survived
    # Frames whose index chunk went too are not listed at all.
    assert len(frames) + reader.stats.missing <= 40


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
    for p in path.glob("frames*.jsonl"):
        p.unlink()
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


def _disk_use_now(root: Path) -> int:
    """Bytes under root while the recorder may be deleting files."""
    total = 0
    for p in root.rglob("*"):
        try:
            if p.is_file():
                total += p.stat().st_size
        except FileNotFoundError:
            continue
    return total


# The documented slack over max_mb: the item that completes a piece in each stream. Here one
# 160x120 MJPG frame (under 20 kB) plus the encoder's buffered bytes and the .avi index, one frame
# index line (~600 B) and one event line (~300 B): 32 KiB covers them.
SLACK = 32 * 1024


def test_total_within_budget_with_an_event_flood(tmp_path: Path) -> None:
    budget = 1 * 2**20
    _record(tmp_path, 5)  # an earlier run: its files are the oldest, deleted first
    earlier = {p.parent for p in tmp_path.glob("*/meta.json")}
    rec = FlightRecorder(tmp_path, segment_s=60, max_mb=1, fps=10, queue_size=400)
    path = rec.start()
    peak = 0
    n_events = 0
    for i in range(300):  # ~4 MiB of video and ~6 MiB of events against a 1 MiB budget
        t = 200.0 + 0.1 * i
        rec.add_frame(i, t, _frame(i % 40, 320, 240), _pose(i, t))
        for _ in range(60):  # kinds that are never downsampled: all of it must be written
            rec.add_event("zones", t, seq=n_events, frame=i, tracks=[{"id": 1, "r": 3.5, "xy": [1.5, -2.25]}] * 3)
            n_events += 1
        if i % 10 == 0:
            peak = max(peak, _disk_use_now(tmp_path))
    rec.close()
    assert rec.stats.frames == 300 and rec.stats.errors == 0 and rec.stats.downsampled == 0
    assert rec.stats.events == n_events
    peak = max(peak, _disk_use(tmp_path))
    assert peak <= budget + SLACK, f"{peak} bytes on disk against a budget of {budget}"
    assert _disk_use(tmp_path) <= budget  # finished: no room kept for open files
    assert rec.stats.deleted > 0
    assert not (earlier & {p.parent for p in tmp_path.glob("*/meta.json")}), "the emptied run was not removed"
    # The newest events survive, in order, with no gap: the oldest went first.
    reader = RecordingReader(path)
    seqs = [e["seq"] for e in reader.events("zones")]
    assert seqs and seqs[-1] == n_events - 1
    assert seqs == list(range(seqs[0], n_events))
    assert seqs[0] > 0  # and some were deleted: the flood was far over budget
    frames = list(reader.frames())
    assert frames and frames[-1].index == 299
    assert _similar(frames[-1].frame_bgr, _frame(299 % 40, 320, 240))


def test_telemetry_is_downsampled_and_safety_events_never(tmp_path: Path) -> None:
    rec = FlightRecorder(tmp_path)
    path = rec.start()
    written = {"ATTITUDE": 0, "GLOBAL_POSITION_INT": 0}
    for i in range(500):  # 10 s of event time: ATTITUDE at 50 Hz, GLOBAL_POSITION_INT at 10 Hz
        t = 1000.0 + 0.02 * i
        written["ATTITUDE"] += rec.add_event("telemetry", t, msg="ATTITUDE", roll=0.01 * i)
        if i % 5 == 0:
            written["GLOBAL_POSITION_INT"] += rec.add_event("telemetry", t, msg="GLOBAL_POSITION_INT", lat=i)
        for kind in ("trigger", "phase", "controller", "zones"):
            assert rec.add_event(kind, t, i=i)
    # A burst of STATUSTEXT lines at one instant passes whole (two seconds' worth of tokens).
    burst = [rec.add_event("telemetry", 1005.0, msg="STATUSTEXT", text=f"PreArm: {k}") for k in range(8)]
    rec.close()
    assert all(burst)
    # 5 Hz sustained for 10 s, plus the 2 s burst allowance at the start.
    assert 50 <= written["ATTITUDE"] <= 5 * 10 + 10 + 1
    assert 50 <= written["GLOBAL_POSITION_INT"] <= 5 * 10 + 10 + 1
    assert rec.stats.downsampled == (500 - written["ATTITUDE"]) + (100 - written["GLOBAL_POSITION_INT"])
    reader = RecordingReader(path)
    tele = list(reader.events("telemetry"))
    assert len(tele) == written["ATTITUDE"] + written["GLOBAL_POSITION_INT"] + 8
    for kind in ("trigger", "phase", "controller", "zones"):
        assert [e["i"] for e in reader.events(kind)] == list(range(500)), f"{kind} events were dropped"
    # Kept ATTITUDE lines are spread over the whole 10 s, not bunched at the start.
    att = [e["t"] for e in tele if e["msg"] == "ATTITUDE"]
    assert att[-1] > 1009.5
    with pytest.raises(ValueError, match="never downsampled"):
        FlightRecorder(tmp_path, event_rates_hz={"trigger": 1.0})
    every = FlightRecorder(tmp_path / "all", event_rates_hz={})
    every.start()
    assert all(every.add_event("telemetry", 0.0, msg="ATTITUDE") for _ in range(100))
    every.close()
    assert every.stats.downsampled == 0


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_full_disk_is_counted_logged_once_and_never_raises(tmp_path: Path,
                                                           caplog: pytest.LogCaptureFixture) -> None:
    """/dev/full answers every write with ENOSPC: the frame index and the events go there."""
    rec = FlightRecorder(tmp_path, queue_size=64, event_rates_hz={})
    path = rec.start()
    for stem in ("frames", "events"):
        (path / f"{stem}-00000.jsonl").symlink_to("/dev/full")
    caplog.set_level("INFO", logger="companion.recording")
    results = [rec.add_event("zones", 0.01 * i, i=i) for i in range(1000)]
    for i in range(20):
        assert rec.add_frame(i, 0.1 * i, _frame(i), None)
    rec.close()  # must not raise
    rec.close()  # nor a second time
    assert not any(results)
    assert rec.stats.events == 0 and rec.stats.frames == 0
    assert rec.stats.errors == 1000 + 20
    lines = [r.getMessage() for r in caplog.records if r.name == "companion.recording"]
    event_lines = [m for m in lines if "cannot write event" in m]
    frame_lines = [m for m in lines if "not recorded" in m]
    # One line at the first failure, one summary at close: not one per failure.
    assert len(event_lines) == 2 and "No space left on device" in event_lines[0]
    assert "(998 more like this in the last" in event_lines[1]
    assert len(frame_lines) == 2 and "(18 more like this in the last" in frame_lines[1]
    # After close nothing is written and nothing raises.
    assert not rec.add_event("trigger", 1.0, reason="x")
    assert not rec.add_frame(99, 9.9, _frame(0), None)


def test_format_1_recordings_still_read(tmp_path: Path) -> None:
    """Recordings made before chunks: one frames.jsonl, one events.jsonl, version 1."""
    _, path = _record(tmp_path, 12)
    for stem in ("frames", "events"):
        chunks = sorted(path.glob(f"{stem}-*.jsonl"))
        (path / f"{stem}.jsonl").write_text("".join(p.read_text() for p in chunks))
        for p in chunks:
            p.unlink()
    meta = json.loads((path / "meta.json").read_text())
    (path / "meta.json").write_text(json.dumps({**meta, "version": 1}))
    reader = RecordingReader(path)
    assert [f.index for f in reader.frames()] == [2 * i for i in range(12)]
    assert len(list(reader.events("decision"))) == 12


def test_a_recording_holds_no_signing_secret(tmp_path: Path) -> None:
    """Issue 12, item 8: the secret was written in clear into every recording's meta.json. The
    service records ``cfg.to_dict()``; nothing the recorder writes may hold the key, in hex or raw."""
    from companion import config

    key_file = tmp_path / "signing.key"
    key_hex = "5e" * 16 + "a7" * 16
    key_file.write_text(key_hex + "\n")
    for source in ({"link.signing_key_file": str(key_file)},):
        cfg = config.load(None, source)
        assert config.signing_key(cfg) == bytes.fromhex(key_hex)
        root = tmp_path / "rec"
        rec = FlightRecorder(root, fps=10, meta={"config": cfg.to_dict()})
        rec.start()
        rec.add_frame(0, 100.0, _frame(0), _pose(0, 100.0))
        rec.add_event("telemetry", 100.0, msg="HEARTBEAT", data={"type": 2})
        rec.close()
        files = [p for p in root.rglob("*") if p.is_file()]
        assert any(p.name == "meta.json" for p in files)
        for p in files:
            data = p.read_bytes()
            assert key_hex.encode() not in data and bytes.fromhex(key_hex) not in data, p


def test_a_cameras_jpegs_are_recorded_as_they_came_and_replayed_to_the_same_pixels(tmp_path: Path) -> None:
    # An MJPEG camera's frame carries the bytes it was decoded from: recorded as they are (no
    # second encoding), and read back they decode to exactly the image the service had. Frames
    # without bytes, or with bytes that are not a JPEG, are encoded once.
    rec = FlightRecorder(tmp_path, segment_s=10.0, fps=10, queue_size=16)
    path = rec.start()
    sent: list[np.ndarray] = []
    for i in range(6):
        jpeg = cv2.imencode(".jpg", _frame(i), [cv2.IMWRITE_JPEG_QUALITY, 70])[1].tobytes()
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        extra = {0: {}, 1: {"jpeg": cv2.imencode(".png", image)[1].tobytes()}}.get(i, {"jpeg": jpeg})
        assert rec.add_frame(i, 100.0 + 0.1 * i, image, None, **extra)
        sent.append(image)
    rec.close()
    assert rec.stats.frames == 6 and rec.stats.jpeg_as_sent == 4
    frames = list(RecordingReader(path).frames())
    assert [f.index for f in frames] == list(range(6))
    for f in frames[2:]:
        assert np.array_equal(f.frame_bgr, sent[f.index])
    for f in frames[:2]:
        assert _similar(f.frame_bgr, sent[f.index])


def test_a_whole_frame_that_does_not_decode_is_counted_corrupt_and_the_rest_still_read(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    # Bit rot inside one stored JPEG (its chunk whole, its bytes garbage): that frame is skipped
    # and counted, the frames after it in the same segment still read.
    _, path = _record(tmp_path, 6, segment_s=10.0)
    (seg,) = path.glob("seg_*.avi")
    data = bytearray(seg.read_bytes())
    at = [i for i in range(len(data)) if data[i:i + 4] == b"00dc"][2]  # the third frame's chunk
    size = int.from_bytes(data[at + 4:at + 8], "little")
    data[at + 8 + 3:at + 8 + size] = bytes(size - 3)  # keeps the start-of-image marker only
    seg.write_bytes(bytes(data))
    reader = RecordingReader(path)
    with caplog.at_level("WARNING", logger="companion.recording"):
        frames = list(reader.frames())
    assert [f.index // 2 for f in frames] == [0, 1, 3, 4, 5]
    assert reader.stats.corrupt == 1 and reader.stats.truncated == 0
    assert any("frame 4 in seg_00000.avi cannot be decoded" in r.getMessage() for r in caplog.records)
