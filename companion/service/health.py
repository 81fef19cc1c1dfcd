"""Per-stage timings and the health summary the service logs and reports to systemd."""

from __future__ import annotations

from collections import defaultdict, deque
from dataclasses import dataclass, field

import numpy as np


@dataclass
class StageTimings:
    """Rolling window of per-stage durations in milliseconds (the last ``window`` frames)."""

    window: int = 200
    _samples: dict[str, deque[float]] = field(default_factory=lambda: defaultdict(deque))

    def add(self, timings_ms: dict[str, float]) -> None:
        for name, ms in timings_ms.items():
            buf = self._samples[name]
            buf.append(float(ms))
            while len(buf) > self.window:
                buf.popleft()

    def summary(self) -> dict[str, tuple[float, float]]:
        """stage -> (median, 95th percentile) milliseconds over the window."""
        out = {}
        for name, buf in self._samples.items():
            if buf:
                a = np.fromiter(buf, float)
                out[name] = (float(np.median(a)), float(np.percentile(a, 95)))
        return out

    def format(self) -> str:
        return " ".join(f"{k}={med:.1f}/{p95:.1f}ms" for k, (med, p95) in self.summary().items())


@dataclass
class FrameCounters:
    """What happened to camera frames in the service, since start.

    processed: went through the pipeline and reached the controller. no_pose: had no pose fresh
    enough at their capture time (not used for decisions). bad: rejected by the pipeline (corrupt
    shape, geometry that cannot be projected) and dropped. errors: the pipeline failed otherwise.
    """

    processed: int = 0
    no_pose: int = 0
    bad: int = 0
    errors: int = 0
