"""The video of what the service decided, drawn from its flight recording (no offline re-run).

Each recorded frame is drawn with the zones the service was tracking on it and the target it
flew to (the ``zones`` events, matched to the frame by its camera index), the controller's phase
and last message (the ``controller`` events), the height above home (the frame's recorded pose)
and the time from the failsafe trigger (the ``trigger`` event); each zone is labelled with its
predicted clearance at touchdown if the vehicle committed on that frame (the flight's own descent
settings, from a fresh recorded rangefinder's height where there was one, as the controller
figured it: ``companion.control.touchdown.touchdown_basis``). The recording holds no density
or occupancy maps, so the service's view of people is not drawn: the picture is the decision, not
the evidence; ``companion replay`` re-runs the pipeline when the evidence is wanted. Where the
caller knows where people really were (the simulator's truth: ``people``), they are marked with
their own sign, apart from anything the service drew.

The video keeps the flight's time: a frame the service never recorded (a starved service records
fewer than the camera gives) shows the frame before it, so the video lasts as long as the
recording. An :class:`Outcome` is appended as a last card held for a few seconds: the verdict,
the nearest person at touchdown marked on a map of the truth.

The file is H.264 (yuv420p, ``+faststart``) in MP4 through PyAV (``companion.replay.h264``),
which web browsers play; PyAV is in the ``tools`` extra.
"""

from __future__ import annotations

import bisect
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion import config as settings
from companion.control.descent import judging_height
from companion.control.touchdown import DescentProfile, touchdown_basis
from companion.geometry.camera import GeometryError, PlaneProjection
from companion.pipeline.occupancy import FREE
from companion.pipeline.tracker import Track
from companion.recording import RecordingReader
from companion.replay import draw
from companion.replay.h264 import H264Writer
from companion.replay.records import flight_zones
from companion.replay.sources import RangefinderHeights

TITLE = "companion: what the service decided (its flight recording)"
HEADER_PX, FOOTER_PX = 28, 48
PHASE_COLOURS = {"MONITOR": draw.WHITE, "SELECT": draw.YELLOW, "APPROACH": draw.YELLOW, "DESCEND": draw.YELLOW,
                 "LAND": draw.YELLOW, "LANDED": draw.GREEN, "HOLD": (0, 140, 255), "HANDBACK": draw.RED}


#: The simulator's people (their truth), drawn apart from anything the service drew.
PERSON = (255, 0, 255)
#: Seconds the outcome card is held at the end of the video.
OUTCOME_HOLD_S = 3.0

#: Where people were at a recorded frame's time (``time.monotonic()`` s, the recording's clock):
#: an (N, 2) array of ground positions (north, east; metres from home, the frame of the poses).
PeopleAt = Callable[[float], np.ndarray]


@dataclass(frozen=True)
class VideoSummary:
    """What was written: the file, its frames (the recording's, the repeats that keep the
    flight's time and the outcome card's), their rate, and frames without a pose (drawn without
    zones: nothing to project them with)."""

    path: Path
    frames: int
    fps: float
    frames_without_pose: int
    recorded_frames: int = 0
    duration_s: float = 0.0


@dataclass(frozen=True)
class Outcome:
    """How the flight ended, judged on the truth, for the video's last card.

    verdict: the headline (e.g. "LANDED SAFE"); colour: its BGR colour; lines: what else to say
    (clearance, who landed, times). touchdown_ne: the touchdown point (north, east, m from home);
    people_ne: where everyone stood then, (N, 2) m; r0_m: the clearance a landing must keep."""

    verdict: str
    colour: tuple[int, int, int]
    lines: tuple[str, ...]
    touchdown_ne: tuple[float, float] | None
    people_ne: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    r0_m: float = 2.0


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


def _legend(img: np.ndarray, people: bool = False) -> None:
    x, y = img.shape[1] - 232, HEADER_PX + 18
    rows = 3 if people else 2
    cv2.rectangle(img, (x - 8, y - 14), (img.shape[1] - 4, y + 8 + 22 * (rows - 1)), (40, 40, 40), -1)
    cv2.circle(img, (x + 6, y - 4), 6, draw.BLUE, 2, cv2.LINE_AA)
    draw._label(img, "zone #id age, r / at touchdown", (x + 18, y), draw.WHITE, 0.42)
    cv2.circle(img, (x + 6, y + 18), 6, draw.YELLOW, 2, cv2.LINE_AA)
    draw._label(img, "target (flown to)", (x + 18, y + 22), draw.WHITE, 0.42)
    if people:
        _person(img, (x + 6, y + 40))
        draw._label(img, "person (simulator's truth)", (x + 18, y + 44), draw.WHITE, 0.42)


def _person(img: np.ndarray, at: tuple[int, int], size: int = 11) -> None:
    """A person of the truth: a magenta tilted cross on a dark one (no zone is drawn so)."""
    cv2.drawMarker(img, at, draw.BLACK, cv2.MARKER_TILTED_CROSS, size, 4, cv2.LINE_AA)
    cv2.drawMarker(img, at, PERSON, cv2.MARKER_TILTED_CROSS, size, 2, cv2.LINE_AA)


def mark_people(img: np.ndarray, ground: PlaneProjection, people_ne: np.ndarray) -> int:
    """Mark ``people_ne`` ((N, 2) north, east m) seen through ``ground`` (the projection of the
    ground plane) on ``img`` in place; the number inside the image."""
    if len(people_ne) == 0:
        return 0
    uv = ground.plane_to_image(np.asarray(people_ne, float).reshape(-1, 2))
    h, w = img.shape[:2]
    n = 0
    for u, v in uv:
        if np.isfinite(u) and np.isfinite(v) and 0 <= u < w and 0 <= v < h:
            _person(img, (int(round(u)), int(round(v))))
            n += 1
    return n


def annotate(frame_bgr: np.ndarray, tracks: list[Track], target_id: int | None, proj: PlaneProjection | None,
             phase: str, message: str, height_m: float | None, t_rel: float | None,
             descent: DescentProfile | None = None, touchdown_from_m: float | None = None,
             people: tuple[PlaneProjection | None, np.ndarray] | None = None,
             judge_m: float | None = None) -> np.ndarray:
    """One video frame: title bar, the frame with the tracks and target (each with its predicted
    clearance at touchdown when ``descent`` and the height are known: from ``touchdown_from_m``
    above the ground when given, a rangefinder's, else from ``height_m``), a legend, and a status
    line (phase, height above home in metres, time from the trigger in seconds, last message).
    ``people``: the ground plane's projection (None where the camera is on the ground) and the
    people's (N, 2) ground positions, marked as the truth (the legend says so). ``judge_m``: the
    flight's judging height (``descent.judging_height``); above it the labels show no clearance,
    as the status page does (from high up the figure is strongly negative and says nothing)."""
    h, w = frame_bgr.shape[:2]
    if proj is not None:
        clearances = None
        start = height_m if touchdown_from_m is None else touchdown_from_m
        if descent is not None and start is not None and (judge_m is None or start <= judge_m):
            clearances = draw.touchdown_clearances(tracks, descent, start)
        view = draw.draw_image_view(frame_bgr, np.full((h, w), FREE, np.uint8), proj, [], tracks, target_id,
                                    clearances=clearances)
    else:
        view = frame_bgr.copy()
    if people is not None and people[0] is not None:
        mark_people(view, people[0], people[1])
    out = np.zeros((h + HEADER_PX + FOOTER_PX, w, 3), np.uint8)
    out[HEADER_PX:HEADER_PX + h] = view
    draw._label(out, TITLE, (8, 19), draw.WHITE, 0.5)
    _legend(out, people is not None)
    y = HEADER_PX + h
    draw._label(out, phase, (8, y + 20), PHASE_COLOURS.get(phase, draw.WHITE), 0.6)
    height = "height ?" if height_m is None else f"height {height_m:5.1f} m"
    when = "before the trigger" if t_rel is None else f"{t_rel:5.1f} s after the trigger"
    draw._label(out, f"{height}   {when}", (130, y + 20), draw.WHITE, 0.5)
    if message:
        draw._label(out, message if len(message) <= 90 else message[:87] + "...", (8, y + 40), draw.WHITE, 0.42)
    return out


def timed_frames(recording: Path, people: PeopleAt | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """The annotated frames of a recording with their capture times (s, the recording's clock),
    in order; with ``people``, the people of the truth at each frame's time marked on it."""
    reader = RecordingReader(recording)
    events = list(reader.events())
    zones = flight_zones(events)
    timeline = _Timeline(events)
    head = float(((reader.meta.get("config") or {}).get("pipeline") or {}).get("head_height_m", 1.7))
    land_agl_m = 0.0
    judge: float | None = None
    try:
        cfg = settings.from_recording(reader.meta.get("config") or {})
        descent: DescentProfile | None = settings.descent_profile(cfg)
        land_agl_m = cfg.controller.land_agl_m
        judge = judging_height(settings.landing_config(cfg))
    except (settings.ConfigError, TypeError, ValueError):
        descent = None  # a recording from another version: zones without their clearance
    rangefinder = RangefinderHeights(e for e in events if e.get("kind") == "telemetry")
    for fr in reader.frames():
        tracks, target = zones.get(fr.index, ([], None))
        proj = ground = None
        if fr.pose is not None and reader.intrinsics is not None and reader.mount is not None:
            try:
                proj = PlaneProjection.from_pose(reader.intrinsics, reader.mount, fr.pose, head)
            except GeometryError:
                proj = None  # below the head plane (on the ground): nothing to project
            if people is not None:
                try:  # people stand on the ground (z = 0), seen from the frame's pose
                    ground = PlaneProjection.from_pose(reader.intrinsics, reader.mount, fr.pose, 0.0)
                except GeometryError:
                    ground = None
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
        marks = None if people is None else (ground, people(fr.t) if ground is not None else np.empty((0, 2)))
        yield fr.t, annotate(image, tracks, target, proj, phase, message, height, t_rel, profile, start, marks,
                             judge)


def frames(recording: Path, people: PeopleAt | None = None) -> Iterator[np.ndarray]:
    """The annotated frames of a recording, in order (one per recorded frame)."""
    for _, image in timed_frames(recording, people):
        yield image


def outcome_card(shape: tuple[int, ...], outcome: Outcome) -> np.ndarray:
    """The video's last card (``shape``: a video frame's): the verdict in its colour, what else
    there is to say, and a north-up map of the truth at touchdown: the touchdown point, the
    ``r_0`` circle around it, everyone standing near, the nearest person ringed with the
    distance to them."""
    h, w = shape[:2]
    img = np.full((h, w, 3), (46, 64, 46), np.uint8)  # dark grass: the ground, not a camera frame
    draw._label(img, "companion: the outcome, judged on the simulator's truth", (8, 19), draw.WHITE, 0.5)
    draw._label(img, outcome.verdict, (8, HEADER_PX + 26), outcome.colour, 0.8)
    for i, text in enumerate(outcome.lines):
        draw._label(img, text, (8, HEADER_PX + 52 + 20 * i), draw.WHITE, 0.48)
    if outcome.touchdown_ne is None:
        return img
    td = np.asarray(outcome.touchdown_ne, float)
    people = np.asarray(outcome.people_ne, float).reshape(-1, 2)
    d = np.hypot(people[:, 0] - td[0], people[:, 1] - td[1]) if len(people) else np.empty(0)
    nearest = int(np.argmin(d)) if len(d) else None
    # Metres shown from the touchdown to the map's edge: the nearest person and r_0 well inside.
    reach = max(8.0, 3.0 * outcome.r0_m, 1.4 * float(d[nearest]) if nearest is not None else 0.0)
    top = HEADER_PX + 52 + 20 * len(outcome.lines)
    cy, cx = (top + h) // 2, w // 2
    scale = max(1e-6, min((h - top) / 2 - 12, w / 2 - 12) / reach)  # px per metre

    def px(ne: np.ndarray) -> tuple[int, int]:  # north up, east right
        return int(round(cx + (ne[1] - td[1]) * scale)), int(round(cy - (ne[0] - td[0]) * scale))

    cv2.circle(img, (cx, cy), max(1, int(round(outcome.r0_m * scale))), draw.WHITE, 1, cv2.LINE_AA)
    draw._label(img, f"r0 {outcome.r0_m:.1f} m", (cx - int(outcome.r0_m * scale) - 4,
                                                 cy + int(outcome.r0_m * scale) + 16), draw.WHITE, 0.42)
    for p in people:
        u, v = px(p)
        if 0 <= u < w and top <= v < h:  # the map only, not over the words
            _person(img, (u, v))
    cv2.drawMarker(img, (cx, cy), draw.YELLOW, cv2.MARKER_CROSS, 16, 2, cv2.LINE_AA)
    draw._label(img, "touchdown", (cx + 8, cy - 8), draw.YELLOW, 0.45)
    if nearest is not None:
        q = px(people[nearest])
        cv2.line(img, (cx, cy), q, PERSON, 1, cv2.LINE_AA)
        cv2.circle(img, q, 12, PERSON, 2, cv2.LINE_AA)
        draw._label(img, f"nearest person {d[nearest]:.1f} m", (q[0] + 14, q[1] + 4), PERSON, 0.48)
    cv2.arrowedLine(img, (w - 24, top + 44), (w - 24, top + 12), draw.WHITE, 2, cv2.LINE_AA, tipLength=0.3)
    draw._label(img, "N", (w - 44, top + 26), draw.WHITE, 0.5)
    bar_m = draw.nice_length(reach / 2)
    x0, y0 = w - 20 - int(round(bar_m * scale)), h - 14
    cv2.line(img, (x0, y0), (w - 20, y0), draw.WHITE, 2)
    draw._label(img, f"{bar_m:g} m", (x0, y0 - 6), draw.WHITE, 0.42)
    _legend_person(img, (8, h - 14))
    return img


def _legend_person(img: np.ndarray, at: tuple[int, int]) -> None:
    _person(img, (at[0] + 6, at[1] - 4))
    draw._label(img, "person (simulator's truth)", (at[0] + 18, at[1]), draw.WHITE, 0.42)


def write_h264(recording: Path, out: Path, fps: float | None = None,
               progress: Callable[[int, int], None] | None = None, people: PeopleAt | None = None,
               outcome: Outcome | None = None) -> VideoSummary:
    """Render ``recording`` (one run folder) into the H.264 MP4 ``out`` at a constant ``fps``
    (default the recording's), keeping the flight's time: each output frame shows the newest
    recorded frame at or before its time, so a recording with fewer frames than the camera gave
    (a starved service) still lasts as long as the flight. ``people`` marks the truth's people;
    ``outcome`` is held as the last card for ``OUTCOME_HOLD_S``. ``progress(done, total)`` is
    called after each recorded frame. Raises ModuleNotFoundError (name ``av``) without PyAV."""
    reader = RecordingReader(recording)
    total = len(reader.rows())
    rate = float(fps or reader.meta.get("fps") or 10.0)
    no_pose = sum(1 for r in reader.rows() if r.get("pose") is None)
    recorded = written = 0
    t0: float | None = None
    last: np.ndarray | None = None
    with H264Writer(out, rate) as writer:
        for t, img in timed_frames(recording, people):
            t0 = t if t0 is None else t0
            # Output ticks before this frame's time (half a period of jitter allowed) show the one before.
            while last is not None and t0 + writer.frames / rate < t - 0.5 / rate:
                writer.write(last)
            last = img
            recorded += 1
            if progress is not None:
                progress(recorded, total)
        if last is not None:
            writer.write(last)
            if outcome is not None:
                card = outcome_card(last.shape, outcome)
                for _ in range(max(1, round(OUTCOME_HOLD_S * rate))):
                    writer.write(card)
        written = writer.frames
    return VideoSummary(out, written, rate, no_pose, recorded, written / rate)


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
