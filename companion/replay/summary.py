"""The end-of-replay summary: counts, throughput, per-stage latency, track and target churn."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

STAGE_KEYS = ("density", "occupancy", "projection", "proposals", "tracking", "total")


@dataclass
class SummaryBuilder:
    """Fed one processed frame at a time; ``build`` gives the summary dict.

    A target switch is the landing target changing from one track id to another (losing the
    target to none is not a switch; the next target, if a different id, is).

    Time on target: a frame's target is held from its time until the next processed frame's (a
    gap of skipped frames counts as held, as the controller keeps its target); the last frame
    holds it for the median interval between processed frames (0 for a single frame). For
    evenly spaced frames with none skipped this is ``frames_with_target / fps``.
    """

    frames: int = 0
    skipped: int = 0
    skip_reasons: Counter = field(default_factory=Counter)
    #: Telemetry lines of the input dropped as unusable, by reason (not frames).
    telemetry_dropped: dict[str, int] = field(default_factory=dict)
    timings: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in STAGE_KEYS})
    switches: int = 0
    frames_with_target: int = 0
    first_t: float | None = None
    last_t: float | None = None
    _last_target: int | None = None
    on_target_s: float = 0.0
    intervals: list[float] = field(default_factory=list)
    _held: bool = False

    def add_frame(self, t: float, timings_ms: dict[str, float], target_id: int | None) -> None:
        self.frames += 1
        if self.first_t is None:
            self.first_t = t
        if self.last_t is not None and math.isfinite(t - self.last_t):
            dt = max(0.0, t - self.last_t)
            self.intervals.append(dt)
            if self._held:
                self.on_target_s += dt
        self.last_t = t
        self._held = target_id is not None
        for k in STAGE_KEYS:
            v = timings_ms.get(k)
            if v is not None and math.isfinite(v):
                self.timings[k].append(float(v))
        if target_id is not None:
            self.frames_with_target += 1
            if self._last_target is not None and target_id != self._last_target:
                self.switches += 1
            self._last_target = target_id

    def add_skip(self, reason: str) -> None:
        self.skipped += 1
        self.skip_reasons[reason] += 1

    def build(self, wall_s: float, tracks_born: int, tracks_ended: int) -> dict[str, Any]:
        span_s = (self.last_t - self.first_t) if self.first_t is not None and self.last_t is not None else 0.0
        latency = {}
        for k, vals in self.timings.items():
            a = np.asarray(vals, dtype=float)
            latency[k] = ({"median": float(np.median(a)), "p99": float(np.percentile(a, 99))}
                          if a.size else {"median": None, "p99": None})
        return {
            "frames": self.frames,
            "frames_skipped": self.skipped,
            "skip_reasons": dict(self.skip_reasons),
            "wall_s": wall_s,
            "frames_per_s": self.frames / wall_s if wall_s > 0 else None,
            "replay_span_s": span_s,
            "latency_ms": latency,
            "tracks_born": int(tracks_born),
            "tracks_ended": int(tracks_ended),
            "frames_with_target": self.frames_with_target,
            "target_switches": self.switches,
            "target_switches_per_min": self.switches / (span_s / 60.0) if span_s > 0 else None,
            "time_on_target_s": self.time_on_target_s(),
            "telemetry_dropped": dict(self.telemetry_dropped),
        }

    def time_on_target_s(self) -> float:
        """Seconds a target was held (see the class docstring)."""
        last = float(np.median(self.intervals)) if self._held and self.intervals else 0.0
        return self.on_target_s + last


def _fmt(v: float | None, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def format_summary(s: dict[str, Any]) -> str:
    """Human-readable lines for stdout."""
    lines = [
        f"frames: {s['frames']} processed, {s['frames_skipped']} skipped",
        f"throughput: {_fmt(s['frames_per_s'])} frames/s ({s['wall_s']:.2f} s wall, "
        f"{s['replay_span_s']:.2f} s of input)",
        "latency ms (median / p99):",
    ]
    for k, v in s["latency_ms"].items():
        lines.append(f"  {k:<11} {_fmt(v['median'], '8.2f')} / {_fmt(v['p99'], '.2f')}")
    lines.append(f"tracks: {s['tracks_born']} born, {s['tracks_ended']} ended")
    lines.append(f"target: on {s['frames_with_target']} frame(s), {s['target_switches']} switch(es), "
                 f"{_fmt(s['target_switches_per_min'], '.2f')} per minute")
    for reason, n in s["skip_reasons"].items():
        lines.append(f"skipped {n}: {reason}")
    for reason, n in s.get("telemetry_dropped", {}).items():
        lines.append(f"telemetry dropped {n}: {reason}")
    return "\n".join(lines)
