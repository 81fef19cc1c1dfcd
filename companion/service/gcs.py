"""What the ground station sees of the companion: its health in the HEARTBEAT, its state changes
as STATUSTEXT, and a few numbers it can plot as NAMED_VALUE_FLOAT/INT.

MAVLink's conventions, as ArduPilot and PX4 follow them for their own components:

- the companion's HEARTBEAT is that of an onboard controller (``MAV_TYPE_ONBOARD_CONTROLLER``,
  ``MAV_AUTOPILOT_INVALID``, base and custom mode 0); its ``system_status`` says how it is:
  ``STANDBY`` until ready (model loaded, autopilot heard) and while the vehicle is on the ground
  (no frame can be used there), ``ACTIVE`` while it watches with everything working, ``CRITICAL``
  while it cannot do its job (camera not delivering or frozen, autopilot link lost, pipeline
  stuck, frames without a pose or otherwise unusable in the air): the autopilot's own failsafe is
  then the only one; (:func:`companion_state`);
- each change of state is one STATUSTEXT, sent once when it happens (never every frame), within
  50 characters, with the severity ground stations rank it by (:data:`CONDITIONS`); a condition
  that flaps is told at most once per ``min_gap_s``, and its last state is always told; the
  model's speed changes state only with hysteresis (:data:`SLOW_BAND`, :data:`SLOW_HOLD_S`);
- every text of the link (these, the landing's, the commands' answers) goes out through one paced
  outbox (``companion.mavlink.statustext.TextOutbox``: at most 4 in any 10 s, none repeated
  within 5 s, most severe first);
- the numbers (:data:`VALUE_NAMES`, at most 10 characters each; docs/ground-station-values.md) go
  out at ``gcs.values_hz``.

The decisions of the landing controller are sent by the landing runner (``event_severity``).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.events import Phase
from companion.mavlink.link import MavLink
from companion.mavlink.statustext import TextOutbox, TextPacer, attach_outbox, send_statustext
from companion.service.health import Health

log = logging.getLogger(__name__)

#: SLZ_PHASE: the controller's phase as a number a ground station can plot.
PHASE_CODES: dict[Phase, int] = {
    Phase.MONITOR: 0, Phase.SELECT: 1, Phase.APPROACH: 2, Phase.DESCEND: 3, Phase.LAND: 4,
    Phase.HOLD: 5, Phase.LANDED: 6, Phase.HANDBACK: 7, Phase.SEARCH: 8,
}

#: The model's speed, with hysteresis: it becomes slow once the median frame time has stayed
#: above the budget for SLOW_HOLD_S (s), and fast again once it has stayed under SLOW_BAND times
#: the budget for as long. Around the threshold (a median wandering 90-110 ms on a 100 ms
#: budget) it then says nothing rather than "model slow" / "model speed ok" every few seconds.
SLOW_BAND, SLOW_HOLD_S = 0.8, 5.0

#: SLZ_HEALTH bits.
HEALTH_CAMERA, HEALTH_LINK, HEALTH_STUCK, HEALTH_SLOW, HEALTH_FRAMES = 1, 2, 4, 8, 16

#: The named values, (name, MAVLink message, unit, meaning): the one list the docs table and the
#: tests read. Names are at most 10 characters (NAMED_VALUE_*.name is char[10]).
VALUE_NAMES: tuple[tuple[str, str, str, str], ...] = (
    ("SLZ_PHASE", "INT", "-", "landing controller phase: 0 MONITOR, 1 SELECT, 2 APPROACH, 3 DESCEND, "
                              "4 LAND, 5 HOLD, 6 LANDED, 7 HANDBACK, 8 SEARCH"),
    ("SLZ_ZONES", "INT", "-", "landing zones tracked on the last frame"),
    ("SLZ_HEALTH", "INT", "bits", "0 healthy; 1 camera not delivering or frozen, 2 autopilot link lost, "
                                  "4 pipeline stuck, 8 model slow, 16 frames not used (no pose, stale "
                                  "pose, on the ground, below the head plane, unusable)"),
    ("SLZ_TGT_R", "FLOAT", "m", "radius of the target zone (the one it flies to, or would fly to "
                                "now); NaN: none"),
    ("SLZ_CLEAR", "FLOAT", "m", "the target's least clearance at touchdown if it committed now "
                                "(radius less what a walker covers during the descent); NaN: none"),
    ("SLZ_FPS", "FLOAT", "Hz", "frames through the pipeline per second, over the last 20 frames"),
    ("SLZ_FRM_MS", "FLOAT", "ms", "median pipeline time per frame (density to tracks)"),
    ("SLZ_LAT_MS", "FLOAT", "ms", "median latency from a frame's capture to the controller's decision"),
)


def companion_state(ready: bool, health: Health) -> int:
    """The HEARTBEAT ``system_status`` (MAV_STATE) for the companion's state (see the module
    docstring). A slow model is no fault here: the companion still works, later; it is told by
    STATUSTEXT and SLZ_HEALTH."""
    if not ready or health.standby:
        return m.MAV_STATE_STANDBY
    return m.MAV_STATE_ACTIVE if health.ok else m.MAV_STATE_CRITICAL


@dataclass(frozen=True)
class Condition:
    """One thing the ground station is told about when it changes: the texts (within 50
    characters, ``{}`` filled with a detail) and MAV_SEVERITYs when it goes bad and when it is
    good again."""

    bad_text: str
    good_text: str
    bad_severity: int
    good_severity: int = m.MAV_SEVERITY_NOTICE
    retell: bool = False  # a new detail while bad is a change too ("no pose" -> "stale pose")


#: The conditions by key. The companion is a secondary system to the autopilot (whose own
#: failsafe stays armed), so losing its camera or pipeline is ERROR ("error in a secondary
#: system"), not CRITICAL; a slow model and a lost link (which may not even reach the ground
#: station) WARNING.
CONDITIONS: dict[str, Condition] = {
    "camera": Condition("SLZ: camera {}: no landing zones", "SLZ: camera back", m.MAV_SEVERITY_ERROR,
                        retell=True),
    # Frames arrive but cannot be decided with (companion.service.frame_use). On the ground that is
    # no fault ("ground", NOTICE; below the head plane too); in the air it is as bad as a lost camera.
    "frames": Condition("SLZ: frames not used: {}", "SLZ: frames used again", m.MAV_SEVERITY_ERROR, retell=True),
    "ground": Condition("SLZ: standby, {}", "SLZ: airborne, frames used", m.MAV_SEVERITY_NOTICE, retell=True),
    "link": Condition("SLZ: autopilot link lost", "SLZ: autopilot link back", m.MAV_SEVERITY_WARNING),
    "pipeline": Condition("SLZ: pipeline stuck {}", "SLZ: pipeline running again", m.MAV_SEVERITY_ERROR),
    "slow": Condition("SLZ: model slow: {}", "SLZ: model speed ok: {}", m.MAV_SEVERITY_WARNING),
}


@dataclass
class ConditionReporter:
    """Turns the conditions' states into STATUSTEXTs: one per change, a flapping condition at most
    one per ``min_gap_s`` (its state then is what is told). Pure bookkeeping: ``update`` returns
    (severity, text) to send."""

    min_gap_s: float = 5.0
    _told: dict[str, bool] = field(default_factory=dict)  # key -> bad, as last told
    _detail: dict[str, str] = field(default_factory=dict)  # key -> its detail, as last told
    _told_t: dict[str, float] = field(default_factory=dict)

    def update(self, bad: dict[str, tuple[bool, str]], now: float) -> list[tuple[int, str]]:
        """``bad``: key -> (is bad, detail for the text). A key not told yet is told only when bad
        (nobody needs "camera back" at start-up)."""
        out: list[tuple[int, str]] = []
        for key, (is_bad, detail) in bad.items():
            told = self._told.get(key)
            if told is None and not is_bad:
                self._told[key] = False
                continue
            cond = CONDITIONS[key]
            same = told == is_bad and not (is_bad and cond.retell and detail != self._detail.get(key))
            if same or now - self._told_t.get(key, -math.inf) < self.min_gap_s:
                continue
            text = (cond.bad_text if is_bad else cond.good_text).format(detail)
            out.append((cond.bad_severity if is_bad else cond.good_severity, text[:50]))
            self._told[key], self._told_t[key], self._detail[key] = is_bad, now, detail
        return out


@dataclass(frozen=True)
class Values:
    """The numbers of one report (see :data:`VALUE_NAMES`); NaN where there is none."""

    phase: Phase
    zones: int
    health_bits: int
    target_r_m: float
    clearance_m: float
    fps: float
    frame_ms: float
    latency_ms: float

    def messages(self, time_boot_ms: int) -> list[tuple[str, str, float]]:
        """(name, "INT"/"FLOAT", value) in :data:`VALUE_NAMES` order."""
        ints = {"SLZ_PHASE": PHASE_CODES[self.phase], "SLZ_ZONES": self.zones, "SLZ_HEALTH": self.health_bits}
        floats = {"SLZ_TGT_R": self.target_r_m, "SLZ_CLEAR": self.clearance_m, "SLZ_FPS": self.fps,
                  "SLZ_FRM_MS": self.frame_ms, "SLZ_LAT_MS": self.latency_ms}
        return [(name, kind, float(ints[name] if kind == "INT" else floats[name]))
                for name, kind, _, _ in VALUE_NAMES]


def _median(values: Iterable[float]) -> float:
    a = np.fromiter(values, float)
    return float(np.median(a)) if a.size else math.nan


class GroundStation:
    """The companion's side of the ground station's view (see the module docstring). The service
    calls ``frame`` after each processed frame, ``update`` from its health loop, and ``values``
    at ``gcs.values_hz``."""

    def __init__(self, link: MavLink, *, frame_budget_ms: float, min_gap_s: float = 5.0,
                 window: int = 20, pacer: TextPacer | None = None) -> None:
        self.link = link
        #: Every text on this link goes through it from now on (``send_statustext``).
        self.outbox = attach_outbox(link, TextOutbox(link, pacer))
        self.frame_budget_ms = frame_budget_ms
        self.ready = False
        self.conditions = ConditionReporter(min_gap_s)
        self._frame_ms: deque[float] = deque(maxlen=window)
        self._latency_ms: deque[float] = deque(maxlen=window)
        self._frame_t: deque[float] = deque(maxlen=window)
        self._t0 = time.monotonic()
        self._slow = False
        self._slow_flip_t: float | None = None  # since when the speed says the other state
        self.sent_texts: list[tuple[int, str]] = []
        link.system_status = m.MAV_STATE_STANDBY

    def say(self, text: str, severity: int, key: str = "") -> None:
        """One STATUSTEXT (chunked by ``send_statustext`` when over 50 characters), paced by the
        outbox; ``key`` names the condition it tells of (its newer news replaces it in the queue)."""
        self.sent_texts.append((severity, text))
        send_statustext(self.link, text, severity, key)

    def set_ready(self, texts: Iterable[str]) -> None:
        """Start-up is over: tell it (NOTICE) and report ACTIVE from now on."""
        self.ready = True
        self.link.system_status = m.MAV_STATE_ACTIVE
        for text in texts:
            self.say(text, m.MAV_SEVERITY_NOTICE)

    def frame(self, pipeline_ms: float, latency_ms: float, now: float) -> None:
        """One frame through the pipeline at ``now`` (monotonic s): its pipeline time and
        capture-to-decision latency (ms)."""
        self._frame_t.append(now)
        if math.isfinite(pipeline_ms):
            self._frame_ms.append(pipeline_ms)
        if math.isfinite(latency_ms):
            self._latency_ms.append(latency_ms)
        self._judge_speed(now)

    def _judge_speed(self, now: float) -> None:
        """The hysteresis of :attr:`slow` (:data:`SLOW_BAND`, :data:`SLOW_HOLD_S`)."""
        full = len(self._frame_ms) == self._frame_ms.maxlen
        ms = self.frame_ms
        other = (not full or ms < SLOW_BAND * self.frame_budget_ms) if self._slow else \
            (full and ms > self.frame_budget_ms)
        if not other:
            self._slow_flip_t = None
        elif self._slow_flip_t is None:
            self._slow_flip_t = now
        elif now - self._slow_flip_t >= SLOW_HOLD_S:
            self._slow, self._slow_flip_t = not self._slow, None

    @property
    def frame_ms(self) -> float:
        return _median(self._frame_ms)

    def fps(self, now: float) -> float:
        """Frames per second over the last frames; 0 when none came for a second or more."""
        ts = self._frame_t
        if not ts or now - ts[-1] > 1.0:
            return 0.0
        return math.nan if len(ts) < 2 or ts[-1] <= ts[0] else (len(ts) - 1) / (ts[-1] - ts[0])

    @property
    def slow(self) -> bool:
        """The median pipeline time over the last frames has been over budget for
        :data:`SLOW_HOLD_S` (a full window only: a first slow frame, the model warming up, is not
        a slow model), and not yet under :data:`SLOW_BAND` of it for as long."""
        return self._slow

    def health_bits(self, health: Health) -> int:
        keys = {f.key for f in health.faults}
        return ((HEALTH_CAMERA if "camera" in keys else 0) | (HEALTH_LINK if "link" in keys else 0)
                | (HEALTH_STUCK if "pipeline" in keys else 0) | (HEALTH_SLOW if self.slow else 0)
                | (HEALTH_FRAMES if "frames" in keys else 0))

    def update(self, health: Health, now: float) -> None:
        """The heartbeat's status from ``health``, and a STATUSTEXT for each condition that changed."""
        self.link.system_status = companion_state(self.ready, health)
        if not self.ready:
            return
        faults = {f.key: f for f in health.faults}
        stuck = faults.get("pipeline")
        camera, frames = faults.get("camera"), faults.get("frames")
        ms = self.frame_ms
        speed = "-" if math.isnan(ms) else f"{ms:.0f} ms/frame"
        state = {
            "camera": (camera is not None, "frozen" if camera is not None and "frozen" in camera.text else "lost"),
            "frames": (frames is not None and not frames.standby, "" if frames is None else frames.text),
            "ground": (frames is not None and frames.standby, "" if frames is None else frames.text),
            "link": ("link" in faults, ""),
            "pipeline": (stuck is not None, "" if stuck is None else stuck.text.removeprefix("pipeline stuck ")),
            "slow": (self.slow, f"{speed} > {self.frame_budget_ms:.0f} ms" if self.slow else speed),
        }
        for key, entry in state.items():  # one key at a time: each text carries its condition's key
            for severity, text in self.conditions.update({key: entry}, now):
                self.say(text, severity, key)

    def values(self, now: float, *, phase: Phase, zones: int, health: Health, target_r_m: float | None,
               clearance_m: float | None) -> Values:
        """Send the named values now and return them."""
        fps = self.fps(now)
        v = Values(phase, zones, self.health_bits(health),
                   math.nan if target_r_m is None else target_r_m,
                   math.nan if clearance_m is None else clearance_m,
                   fps, self.frame_ms, _median(self._latency_ms))
        ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        for name, kind, value in v.messages(ms):
            if kind == "INT":
                self.link.send(self.link.mav.named_value_int_encode(ms, name.encode(), int(value)))
            else:
                self.link.send(self.link.mav.named_value_float_encode(ms, name.encode(), value))
        return v
