"""The demo's video: what the service decided, drawn from a real flight recording, as H.264 that
browsers play (yuv420p in MP4), decoded back with PyAV to check what it shows."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from companion.geometry.camera import Intrinsics, Mount, PlaneProjection, Pose
from companion.pipeline.tracker import Track
from companion.recording import FlightRecorder
from companion.replay import flight_video

av = pytest.importorskip("av", reason="PyAV is in the tools extra (pip install -e '.[tools]')")

K = Intrinsics.from_fov(320, 240, 70)


def _track(tid: int, x: float, y: float, r: float) -> Track:
    return Track(id=tid, x=x, y=y, r=r, r_filtered=r, age=20, hits=20, misses=0, view_limited=False,
                 r_view=20.0, born_t=100.0, last_t=101.0)


def _recording(root: Path, n: int = 30, ranges: tuple[tuple[float, int], ...] = ()) -> Path:
    """``ranges``: recorded downward DISTANCE_SENSOR readings (time s, distance cm)."""
    rec = FlightRecorder(root, fps=10, queue_size=n + 1, intrinsics=K, mount=Mount(),
                         # Judged from 20 m (the default judges at 10 m, above which the labels
                         # carry no clearance): these frames fly at 14-20 m.
                         meta={"config": {"pipeline": {"head_height_m": 1.7},
                                          "controller": {"land_agl_m": 1.0, "descend_alt_m": 20.0}}})
    path = rec.start()
    for t, cm in ranges:
        rec.add_event("telemetry", t, msg="DISTANCE_SENSOR", orientation=25, current_distance=cm,
                      min_distance=20, max_distance=4000)
    grey = np.full((240, 320, 3), 90, np.uint8)  # plain ground: every colour on it is the drawing's
    target = _track(3, 2.0, 1.0, 4.0)
    rec.add_event("trigger", 100.5, reason="battery critical", source="battery")
    for i in range(n):
        t = 100.0 + 0.1 * i
        assert rec.add_frame(i, t, grey, Pose(t, 0.0, 0.0, -20.0 + 0.2 * i, 0.0, 0.0, 0.0))
        rec.add_event("zones", t, frame=i, tracks=[asdict(target), asdict(_track(5, -6.0, -6.0, 2.5))],
                      target=3 if t >= 100.6 else None, timings_ms={"total": 30.0})
        if i == 6:
            rec.add_event("controller", t, event="target", old="SELECT", phase="APPROACH",
                          text="SLZ: landing at zone 3, 2.2 m away, radius 4.0 m", zone_id=3)
    rec.close()
    return path


def test_the_video_is_h264_a_browser_plays_and_shows_the_decision(tmp_path: Path) -> None:
    path = _recording(tmp_path / "rec")
    seen: list[tuple[int, int]] = []
    summary = flight_video.write_h264(path, tmp_path / "demo.mp4", progress=lambda d, t: seen.append((d, t)))
    assert summary.frames == 30 and summary.frames_without_pose == 0 and seen[-1] == (30, 30)
    with av.open(str(summary.path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        decoded = [f.to_ndarray(format="bgr24") for f in container.decode(stream)]
    assert len(decoded) == 30
    h = flight_video.HEADER_PX
    assert decoded[0].shape == (240 + h + flight_video.FOOTER_PX, 320, 3)

    def yellow_on_circle(img: np.ndarray, i: int) -> int:
        # Pixels on the target's outline (the head plane seen from frame i's pose) that are yellow.
        pose = Pose(0.0, 0.0, 0.0, -20.0 + 0.2 * i, 0.0, 0.0, 0.0)
        proj = PlaneProjection.from_pose(K, Mount(), pose, 1.7)
        uv = proj.plane_to_image(np.array([[2.0 + 4.0 * np.cos(a), 1.0 + 4.0 * np.sin(a)]
                                           for a in np.linspace(0, 2 * np.pi, 36, endpoint=False)]))
        hits = 0
        for u, v in uv:
            px = img[h + int(round(v)), int(round(u))].astype(int)
            hits += px[2] > 150 and px[1] > 150 and px[0] < 120
        return hits

    # Before the target is chosen (t < 100.6) the zone is drawn blue; from then on yellow.
    assert yellow_on_circle(decoded[2], 2) == 0
    assert yellow_on_circle(decoded[20], 20) >= 18
    # The status line changes with the phase: MONITOR before the controller's event, then APPROACH.
    footer_before = decoded[2][h + 240:]
    footer_after = decoded[20][h + 240:]
    assert np.abs(footer_before.astype(int) - footer_after.astype(int)).sum() > 0


def test_zones_carry_their_clearance_at_touchdown_from_the_flights_own_descent(tmp_path: Path) -> None:
    # The label says what the controller judges: the zone's radius less what a walker covers
    # while the vehicle comes down from this frame's height, with the recording's settings.
    path = _recording(tmp_path / "rec")
    frames = list(flight_video.frames(path))
    assert len(frames) == 30
    from companion import config as settings
    from companion.replay import draw
    profile = settings.descent_profile(settings.from_recording({"pipeline": {"head_height_m": 1.7}}))
    c = profile.clearance_at_touchdown(4.0, 20.0)
    tr = _track(3, 2.0, 1.0, 4.0)
    assert draw._track_text(tr, c).endswith(f"4.0 / {c:+.1f} m")
    # Drawn without the settings the label is shorter: the frames differ right of the label.
    pose = Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0)
    proj = PlaneProjection.from_pose(K, Mount(), pose, 1.7)
    grey = np.full((240, 320, 3), 90, np.uint8)
    with_c = flight_video.annotate(grey, [tr], 3, proj, "APPROACH", "", 20.0, 1.0, profile)
    without = flight_video.annotate(grey, [tr], 3, proj, "APPROACH", "", 20.0, 1.0, None)
    assert np.abs(with_c.astype(int) - without.astype(int)).sum() > 0


def test_no_clearance_is_labelled_above_the_judging_height() -> None:
    # As the status page: from above the judging height the clearance at touchdown is strongly
    # negative and says nothing about the zone, so the label gives the zone alone.
    from companion import config as settings
    profile = settings.descent_profile(settings.from_recording({"pipeline": {"head_height_m": 1.7}}))
    tr = _track(3, 0.5, 0.3, 4.0)  # its centre and label in view from both heights
    grey = np.full((240, 320, 3), 90, np.uint8)
    for height in (20.0, 8.0):
        pose = Pose(0.0, 0.0, 0.0, -height, 0.0, 0.0, 0.0)
        proj = PlaneProjection.from_pose(K, Mount(), pose, 1.7)
        judged = flight_video.annotate(grey, [tr], 3, proj, "DESCEND", "", height, 1.0, profile, judge_m=10.0)
        bare = flight_video.annotate(grey, [tr], 3, proj, "DESCEND", "", height, 1.0, None)
        assert np.array_equal(judged, bare) == (height > 10.0)


def test_a_frame_without_a_pose_is_drawn_without_zones(tmp_path: Path) -> None:
    rec = FlightRecorder(tmp_path / "rec", fps=10, queue_size=4, intrinsics=K, mount=Mount())
    path = rec.start()
    for i in range(3):
        rec.add_frame(i, 100.0 + 0.1 * i, np.full((240, 320, 3), 90, np.uint8), None)
    rec.close()
    summary = flight_video.write_h264(path, tmp_path / "v.mp4")
    assert summary.frames == 3 and summary.frames_without_pose == 3


def test_the_demo_evidence_video_replays_the_recording_as_flown(tmp_path: Path) -> None:
    # Issue 11, item 6: the demo also shows the evidence, the head-plane panel beside each frame,
    # re-run by `companion replay` from the recording with the shipped model.
    import cv2

    from sim.flights.demo import evidence_video

    path = _recording(tmp_path / "rec", n=6)
    out = evidence_video(path, tmp_path / "evidence.mp4")
    assert out == tmp_path / "evidence.mp4"
    cap = cv2.VideoCapture(str(out))
    n, first = 0, None
    while True:
        ok, img = cap.read()
        if not ok:
            break
        first = img if first is None else first
        n += 1
    assert n == 6 and first is not None
    assert first.shape[0] == 240 and first.shape[1] > 320 + 200  # the head-plane panel beside
    import json
    summary = json.loads((tmp_path / "evidence.json").read_text())
    assert summary["frames"] == 6 and summary["settings"].startswith("the recording")  # as flown
    # A recording that cannot be replayed gives None and the demo goes on.
    assert evidence_video(tmp_path / "nothing-here", tmp_path / "x.mp4") is None


def test_the_video_figures_clearance_from_the_recorded_rangefinder_as_the_controller_did(tmp_path: Path) -> None:
    # Live, a fresh downward rangefinder gives the height the controller figures touchdown from
    # and, with controller.land_agl_m, the shorter LAND: the video's labels follow it on the
    # frames it was fresh for (a reading at 100.15 s: frames 2-6, at most 0.5 s old), only there.
    from companion import config as settings
    from companion.control.touchdown import by_rangefinder
    from companion.recording import RecordingReader

    plain = list(flight_video.frames(_recording(tmp_path / "plain", n=10)))
    path = _recording(tmp_path / "ranged", n=10, ranges=((100.15, 1500),))
    ranged = list(flight_video.frames(path))
    differ = [i for i, (a, b) in enumerate(zip(plain, ranged)) if np.abs(a.astype(int) - b.astype(int)).sum() > 0]
    assert differ == [2, 3, 4, 5, 6]
    # Frame 4 drawn by hand as the controller figured it: 15 m by the rangefinder, the LAND from
    # 1 m; the status line keeps the height above home.
    fr = next(f for f in RecordingReader(path).frames() if f.index == 4)
    assert fr.pose is not None
    flown = settings.from_recording({"pipeline": {"head_height_m": 1.7},
                                     "controller": {"land_agl_m": 1.0, "descend_alt_m": 20.0}})
    profile = by_rangefinder(settings.descent_profile(flown), 1.0)
    proj = PlaneProjection.from_pose(K, Mount(), fr.pose, 1.7)
    tracks = [_track(3, 2.0, 1.0, 4.0), _track(5, -6.0, -6.0, 2.5)]
    expect = flight_video.annotate(fr.frame_bgr, tracks, None, proj, "MONITOR", "", -fr.pose.down, None,
                                   profile, 15.0)
    assert np.array_equal(expect, ranged[4])


def _decode(path: Path) -> tuple[str, list[np.ndarray]]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return stream.codec_context.name, [f.to_ndarray(format="bgr24") for f in container.decode(stream)]


def _magenta(img: np.ndarray) -> np.ndarray:
    """The truth's person markers (PERSON, magenta): high blue and red, low green."""
    b, g, r = (img[..., k].astype(int) for k in range(3))
    return (b > 180) & (r > 180) & (g < 90)


def test_a_starved_recording_still_lasts_as_long_as_the_flight(tmp_path: Path) -> None:
    # Issue 62: a starved service records 6 frames a second, not 10; the video at 10 frames a
    # second showed them faster than they happened and ended before the flight did.
    rec = FlightRecorder(tmp_path / "rec", fps=10, queue_size=40, intrinsics=K, mount=Mount())
    path = rec.start()
    times = [100.0 + k / 6.0 for k in range(24)]  # 4 s of flight at 6 frames/s
    for i, t in enumerate(times):
        assert rec.add_frame(i, t, np.full((240, 320, 3), 90, np.uint8), Pose(t, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0))
    rec.close()
    summary = flight_video.write_h264(path, tmp_path / "v.mp4")
    codec, decoded = _decode(summary.path)
    assert codec == "h264" and summary.recorded_frames == 24
    span = times[-1] - times[0]
    assert len(decoded) == summary.frames and abs(len(decoded) / 10.0 - span) <= 0.15  # not 2.4 s
    assert summary.duration_s >= span


def test_people_of_the_truth_are_marked_and_the_last_card_tells_the_outcome(tmp_path: Path) -> None:
    path = _recording(tmp_path / "rec", n=10)
    person = np.array([[4.0, -3.0]])  # north, east of home: in view from 20 m

    def people(t: float) -> np.ndarray:
        return person

    outcome = flight_video.Outcome("LANDED SAFE", (0, 200, 0), ("nearest person at touchdown: 5.0 m",),
                                   (0.0, 0.0), np.array([[3.0, 4.0], [20.0, 20.0]]), 2.0)
    summary = flight_video.write_h264(path, tmp_path / "v.mp4", people=people, outcome=outcome)
    codec, decoded = _decode(summary.path)
    assert codec == "h264" and len(decoded) == 10 + round(flight_video.OUTCOME_HOLD_S * 10)
    # Frame 0: the person is marked where the ground plane puts them (the marker, magenta, is no
    # colour the service's overlays use), and the legend names the sign.
    h = flight_video.HEADER_PX
    ground = PlaneProjection.from_pose(K, Mount(), Pose(0.0, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0), 0.0)
    u, v = (int(round(c)) for c in ground.plane_to_image(person)[0])
    frame0 = decoded[0]
    assert _magenta(frame0[h + v - 6:h + v + 7, u - 6:u + 7]).sum() >= 6
    legend = frame0[h:h + 80, 320 - 232:]
    assert _magenta(legend).sum() >= 6
    without = next(flight_video.frames(path))
    assert _magenta(without).sum() == 0  # no truth given, nothing marked
    # The last frame is the outcome card: the verdict in green, the nearest person ringed.
    last = decoded[-1]
    expected = flight_video.outcome_card(decoded[0].shape, outcome)
    assert np.abs(last.astype(int) - expected.astype(int)).mean() < 6  # as drawn, through the codec
    green = (expected[..., 1] > 150) & (expected[..., 0] < 80) & (expected[..., 2] < 80)
    assert green[h:h + 40].sum() > 40  # the verdict's words
    assert _magenta(expected).sum() > 100  # the nearest person's ring and line, the others' crosses


def test_labels_stay_inside_the_frame_and_do_not_ghost() -> None:
    from companion.replay import draw

    img = np.full((240, 320, 3), 90, np.uint8)
    text = "#15 age 64, 4.7 / -14.4 m TARGET"
    # Asked to start 20 px from the right edge: moved left so that all of it is inside.
    box = draw._label(img, text, (300, 120), draw.YELLOW)
    x0, y0, x1, y1 = box
    assert 0 <= x0 < x1 <= 319 and 0 <= y0 < y1 <= 239
    (tw, th), _ = __import__("cv2").getTextSize(text, draw.FONT, 0.5, 1)
    assert x1 - x0 >= tw  # the whole text, not cut at the edge
    yellow = (img[..., 2] > 150) & (img[..., 1] > 150) & (img[..., 0] < 120)
    cols = np.flatnonzero(yellow.any(axis=0))
    assert cols.min() >= x0 and cols.max() <= x1
    # One stroke: nothing dark drawn outside the box (the old outline, thicker and so wider
    # text, ran past the coloured text and showed as a second copy: "TARGETT").
    dark = img.sum(axis=2) < 90 * 3 - 30
    outside = dark.copy()
    outside[y0:y1 + 1, x0:x1 + 1] = False
    assert not outside.any()
    # Near the top-left corner too.
    x0, y0, _, _ = draw._label(img, "N", (-5, 2), draw.WHITE)
    assert x0 >= 0 and y0 >= 0


def test_the_evidence_video_is_h264_and_draws_the_flights_own_zones(tmp_path: Path) -> None:
    # Issue 62: evidence.mp4 was MPEG-4 Part 2 (browsers do not play it) and drew the replay's
    # own zones, whose ids and target were not the ones the flight printed.
    import json

    from sim.flights.demo import evidence_video

    path = _recording(tmp_path / "rec", n=10)
    out = evidence_video(path, tmp_path / "evidence.mp4")
    assert out is not None
    codec, decoded = _decode(out)
    assert codec == "h264" and len(decoded) == 10
    summary = json.loads((tmp_path / "evidence.json").read_text())
    assert summary["flight_zones"]["frames"] == 10  # every frame drawn with the flight's zones

    def yellow_on_target(img: np.ndarray, i: int) -> int:
        # The flight's target, zone 3, on the image view (frame i's pose): yellow once it was chosen.
        proj = PlaneProjection.from_pose(K, Mount(), Pose(0.0, 0.0, 0.0, -20.0 + 0.2 * i, 0.0, 0.0, 0.0), 1.7)
        uv = proj.plane_to_image(np.array([[2.0 + 4.0 * np.cos(a), 1.0 + 4.0 * np.sin(a)]
                                           for a in np.linspace(0, 2 * np.pi, 36, endpoint=False)]))
        return sum(int(img[int(round(v)), int(round(u)), 2] > 150 and img[int(round(v)), int(round(u)), 1] > 150
                       and img[int(round(v)), int(round(u)), 0] < 120) for u, v in uv)

    assert yellow_on_target(decoded[2], 2) == 0  # before the flight chose it: not the target
    assert yellow_on_target(decoded[8], 8) >= 18  # the flight's target from t = 100.6 s


def test_the_replay_counts_the_frames_whose_zone_ids_are_not_the_flights(tmp_path: Path) -> None:
    # A recording whose zones events are what the pipeline tracks on its frames (as a flight's
    # are: the same frames, times and settings) replays with the same ids on every frame; one
    # frame recorded with another id is counted.
    import json

    from companion.cli import main

    grey = np.full((240, 320, 3), 90, np.uint8)
    first = FlightRecorder(tmp_path / "a", fps=10, queue_size=12, intrinsics=K, mount=Mount())
    a = first.start()
    poses = [Pose(100.0 + 0.1 * i, 0.0, 0.0, -20.0, 0.0, 0.0, 0.0) for i in range(8)]
    for i, pose in enumerate(poses):
        assert first.add_frame(i, pose.t, grey, pose)
    first.close()
    # People alone: the landability model calls the plain grey ground a roof (no landing point).
    people_only = ["--set", "model.landability=false"]
    assert main(["replay", str(a), "--jsonl", str(tmp_path / "a.jsonl"), "--no-progress", *people_only]) == 0
    tracked = {r["frame"]: r["tracks"] for r in map(json.loads, (tmp_path / "a.jsonl").read_text().splitlines())}
    assert any(tracked.values())  # the plain ground is one free zone, tracked from the second frame

    def flown(root: Path, wrong_frame: int | None) -> Path:
        rec = FlightRecorder(root, fps=10, queue_size=12, intrinsics=K, mount=Mount())
        path = rec.start()
        for i, pose in enumerate(poses):
            assert rec.add_frame(i, pose.t, grey, pose)
            # As the service records them: each track whole (dataclasses.asdict), by its id.
            tracks = [asdict(_track(t["id"] + (100 if i == wrong_frame else 0), t["x"], t["y"], t["r"]))
                      for t in tracked.get(i, [])]
            rec.add_event("zones", pose.t, frame=i, tracks=tracks, target=None)
        rec.close()
        return path

    for wrong, differ in ((None, 0), (5, 1)):
        path = flown(tmp_path / f"rec{wrong}", wrong)
        summary_path = tmp_path / f"s{wrong}.json"
        assert main(["replay", str(path), "--flight-zones", "--video-out", str(tmp_path / f"e{wrong}.mp4"),
                     "--summary-json", str(summary_path), "--no-progress", *people_only]) == 0
        assert json.loads(summary_path.read_text())["flight_zones"] == {"frames": 8, "ids_differ": differ}
    # Not a recording: refused, naming the option.
    assert main(["replay", str(tmp_path / "e0.mp4"), "--flight-zones", "--nadir", "--gsd", "0.05"]) == 2
