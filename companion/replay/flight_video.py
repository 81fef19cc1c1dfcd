"""The video of what the service decided, drawn from its flight recording (no offline re-run).

Each recorded frame is drawn with the zones the service was tracking on it and the target it
flew to (the ``zones`` events, matched to the frame by its camera index), the controller's phase
and last message (the ``controller`` events), the height above home (the frame's recorded pose)
and the time from the failsafe trigger (the ``trigger`` event); each zone is labelled with its
predicted clearance at touchdown if the vehicle committed on that frame (the flight's own descent
settings, from a fresh recorded rangefinder's height where there was one, as the controller
figured it: ``companion.control.touchdown.touchdown_basis``). The recording holds no density
or occupancy maps, so people are not marked: the picture is the decision, not the evidence;
``companion replay`` re-runs the pipeline when the evidence is wanted.

The file is H.264 (yuv420p, ``+faststart``) in MP4 through PyAV, which web browsers play; PyAV
is in the ``tools`` extra and imported only here.
"""

from __future__ import annotations

import bisect
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion import config as settings
from companion.control.touchdown import DescentProfile, touchdown_basis
from companion.geometry.camera import GeometryError, PlaneProjection
from companion.pipeline.occupancy import FREE
from companion.pipeline.tracker import Track
from companion.recording import RecordingReader
from companion.replay import draw
from companion.replay.sources import RangefinderHeights

TITLE = "companion: what the service decided (its flight recording)"
HEADER_PX, FOOTER_PX = 28, 48
PHASE_COLOURS = {"MONITOR": draw.WHITE, "SELECT": draw.YELLOW, "APPROACH": draw.YELLOW, "DESCEND": draw.YELLOW,
                 "LAND": draw.YELLOW, "LANDED": draw.GREEN, "HOLD": (0, 140, 255), "HANDBACK": draw.RED}


@dataclass(frozen=True)
class VideoSummary:
    """What was written: the file, its frames, their rate, and frames without a pose (drawn
    without zones: nothing to project them with)."""

    path: Path
    frames: int
    fps: float
    frames_without_pose: int


def _track(d: dict[str, Any]) -> Track | None:
    names = {f.name for f in fields(Track)}
    try:
        return Track(**{k: v for k, v in d.items() if k in names})
    except TypeError:
        return None  # a recording from another version: draw what can be drawn


class _Timeline:
    """The controller's phase and last message, and the trigger time, at any capture time."""

    def __init__(self, events: list[dict[str, Any]]) -> None:
        ctrl = sorted((e for e in events if e.get("kind") == "controller" and isinstance(e.get("t"), (int, float))),
                      key=lambda e: float(e["t"]))
        self._t = [float(e["t"]) for e in ctrl]
        self._ev = ctrl
        triggers = [float(e["t"]) for e in events if e.get("kind") == "trigger" and isinstance(e.get("t"), (int, float))]
        self.trigger_t = min(triggers) if triggers else None

    def at(self, t: float) -> tuple[str, str]:
        i = bisect.bisect_right(self._t, t)
        if i == 0:
            return "MONITOR", ""
        ev = self._ev[i - 1]
        return str(ev.get("phase", "MONITOR")), str(ev.get("text", ""))


def _legend(img: np.ndarray) -> None:
    x, y = img.shape[1] - 232, HEADER_PX + 18
    cv2.rectangle(img, (x - 8, y - 14), (img.shape[1] - 4, y + 30), (40, 40, 40), -1)
    cv2.circle(img, (x + 6, y - 4), 6, draw.BLUE, 2, cv2.LINE_AA)
    draw._label(img, "zone #id age, r / at touchdown", (x + 18, y), draw.WHITE, 0.42)
    cv2.circle(img, (x + 6, y + 18), 6, draw.YELLOW, 2, cv2.LINE_AA)
    draw._label(img, "target (flown to)", (x + 18, y + 22), draw.WHITE, 0.42)


def annotate(frame_bgr: np.ndarray, tracks: list[Track], target_id: int | None, proj: PlaneProjection | None,
             phase: str, message: str, height_m: float | None, t_rel: float | None,
             descent: DescentProfile | None = None, touchdown_from_m: float | None = None) -> np.ndarray:
    """One video frame: title bar, the frame with the tracks and target (each with its predicted
    clearance at touchdown when ``descent`` and the height are known: from ``touchdown_from_m``
    above the ground when given, a rangefinder's, else from ``height_m``), a legend, and a status
    line (phase, height above home in metres, time from the trigger in seconds, last message)."""
    h, w = frame_bgr.shape[:2]
    if proj is not None:
        clearances = None
        start = height_m if touchdown_from_m is None else touchdown_from_m
        if descent is not None and start is not None:
            clearances = draw.touchdown_clearances(tracks, descent, start)
        view = draw.draw_image_view(frame_bgr, np.full((h, w), FREE, np.uint8), proj, [], tracks, target_id,
                                    clearances=clearances)
    else:
        view = frame_bgr.copy()
    out = np.zeros((h + HEADER_PX + FOOTER_PX, w, 3), np.uint8)
    out[HEADER_PX:HEADER_PX + h] = view
    draw._label(out, TITLE, (8, 19), draw.WHITE, 0.5)
    _legend(out)
    y = HEADER_PX + h
    draw._label(out, phase, (8, y + 20), PHASE_COLOURS.get(phase, draw.WHITE), 0.6)
    height = "height ?" if height_m is None else f"height {height_m:5.1f} m"
    when = "before the trigger" if t_rel is None else f"{t_rel:5.1f} s after the trigger"
    draw._label(out, f"{height}   {when}", (130, y + 20), draw.WHITE, 0.5)
    if message:
        draw._label(out, message if len(message) <= 90 else message[:87] + "...", (8, y + 40), draw.WHITE, 0.42)
    return out


def frames(recording: Path) -> Iterator[np.ndarray]:
    """The annotated frames of a recording, in order."""
    reader = RecordingReader(recording)
    events = list(reader.events())
    zones = {int(e["frame"]): e for e in events if e.get("kind") == "zones" and isinstance(e.get("frame"), int)}
    timeline = _Timeline(events)
    head = float(((reader.meta.get("config") or {}).get("pipeline") or {}).get("head_height_m", 1.7))
    land_agl_m = 0.0
    try:
        cfg = settings.from_recording(reader.meta.get("config") or {})
        descent: DescentProfile | None = settings.descent_profile(cfg)
        land_agl_m = cfg.controller.land_agl_m
    except (settings.ConfigError, TypeError, ValueError):
        descent = None  # a recording from another version: zones without their clearance
    rangefinder = RangefinderHeights(e for e in events if e.get("kind") == "telemetry")
    for fr in reader.frames():
        z = zones.get(fr.index, {})
        tracks = [t for t in (_track(d) for d in z.get("tracks", []) if isinstance(d, dict)) if t is not None]
        proj = None
        if fr.pose is not None and reader.intrinsics is not None and reader.mount is not None:
            try:
                proj = PlaneProjection.from_pose(reader.intrinsics, reader.mount, fr.pose, head)
            except GeometryError:
                proj = None  # below the head plane (on the ground): nothing to project
        phase, message = timeline.at(fr.t)
        t_rel = None if timeline.trigger_t is None or fr.t < timeline.trigger_t else fr.t - timeline.trigger_t
        height = None if fr.pose is None else -fr.pose.down
        # The clearance as the controller figured it live: from a fresh rangefinder's height,
        # the descent going on down to land_agl_m by it.
        agl = rangefinder.at(fr.t)
        start, profile = touchdown_basis(height, agl, descent, land_agl_m) if descent is not None else (height, None)
        image = fr.frame_bgr
        if reader.intrinsics is not None and image.shape[:2] != (reader.intrinsics.height, reader.intrinsics.width):
            image = cv2.resize(image, (reader.intrinsics.width, reader.intrinsics.height))
        yield annotate(image, tracks, z.get("target") if isinstance(z.get("target"), int) else None,
                       proj, phase, message, height, t_rel, profile, start)


def write_h264(recording: Path, out: Path, fps: float | None = None,
               progress: Callable[[int, int], None] | None = None) -> VideoSummary:
    """Render ``recording`` (one run folder) into the H.264 MP4 ``out``; ``progress(done, total)``
    is called after each frame. Raises ModuleNotFoundError (name ``av``) without PyAV."""
    import av  # the tools extra

    reader = RecordingReader(recording)
    total = len(reader.rows())
    rate = float(fps or reader.meta.get("fps") or 10.0)
    no_pose = sum(1 for r in reader.rows() if r.get("pose") is None)
    out.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    with av.open(str(out), "w", options={"movflags": "+faststart"}) as container:
        stream: Any = None
        for img in frames(recording):
            if stream is None:
                stream = container.add_stream("libx264", rate=round(rate))
                # yuv420p wants even sizes; browsers play only this pixel format.
                stream.width, stream.height = img.shape[1] // 2 * 2, img.shape[0] // 2 * 2
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "23", "preset": "veryfast"}
            img = img[:stream.height, :stream.width]
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="bgr24")):
                container.mux(packet)
            n += 1
            if progress is not None:
                progress(n, total)
        if stream is not None:
            for packet in stream.encode():
                container.mux(packet)
    return VideoSummary(out, n, rate, no_pose)


def print_progress(stream: Any = sys.stderr) -> Callable[[int, int], None]:
    """A progress callback: a tqdm bar on a terminal, else a line every 10 %."""
    if stream.isatty():
        from tqdm import tqdm  # the tools extra

        bar: dict[str, Any] = {}

        def update(done: int, total: int) -> None:
            if "bar" not in bar:
                bar["bar"] = tqdm(total=total, unit="frame", desc="rendering", file=stream)
            bar["bar"].update(1)
            if done >= total:
                bar["bar"].close()
        return update
    last = [-1]

    def line(done: int, total: int) -> None:
        tenth = done * 10 // max(total, 1)
        if tenth != last[0] and (tenth > last[0]):
            last[0] = tenth
            print(f"  rendering: {done}/{total} frames ({100 * done // max(total, 1)} %)", file=stream, flush=True)
    return line
