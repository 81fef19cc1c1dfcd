"""Failsafe kinds and link faults the tests inject into the simulator.

Link faults act per datagram and per direction: ``tx`` is simulator -> peer (telemetry, acks),
``rx`` is peer -> simulator (commands, setpoints). Latency in seconds, loss as a probability 0..1.
"""

from __future__ import annotations

import asyncio
import math
import random
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum


class Failsafe(str, Enum):
    """Failsafes the autopilot can raise by itself (and the tests can inject)."""

    BATTERY_LOW = "battery_low"
    BATTERY_CRITICAL = "battery_critical"
    RC_LOSS = "rc_loss"
    GCS_LOSS = "gcs_loss"


@dataclass
class LinkFaults:
    """Loss probability and added one-way latency (s) for each direction of a link."""

    loss_tx: float = 0.0
    loss_rx: float = 0.0
    latency_tx_s: float = 0.0
    latency_rx_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("loss_tx", "loss_rx"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be a probability in [0, 1], got {v!r}")
        for name in ("latency_tx_s", "latency_rx_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be >= 0 seconds, got {v!r}")

    @classmethod
    def symmetric(cls, loss: float = 0.0, latency_s: float = 0.0) -> LinkFaults:
        return cls(loss, loss, latency_s, latency_s)


class FaultInjector:
    """Drops and delays datagrams according to the current ``LinkFaults``.

    A seeded generator keeps runs repeatable; delayed datagrams keep their order because every
    one in a direction gets the same latency.
    """

    def __init__(self, faults: LinkFaults | None = None, seed: int | None = None) -> None:
        self.faults = faults or LinkFaults()
        self._rng = random.Random(seed)
        self.dropped_tx = 0
        self.dropped_rx = 0

    def _pass(self, data: bytes, loss: float, latency: float,
              deliver: Callable[[bytes], None]) -> bool:
        if loss > 0.0 and self._rng.random() < loss:
            return False
        if latency > 0.0:
            asyncio.get_running_loop().call_later(latency, deliver, data)
        else:
            deliver(data)
        return True

    def outgoing(self, data: bytes, deliver: Callable[[bytes], None]) -> None:
        f = self.faults
        if not self._pass(data, f.loss_tx, f.latency_tx_s, deliver):
            self.dropped_tx += 1

    def incoming(self, data: bytes, deliver: Callable[[bytes], None]) -> None:
        f = self.faults
        if not self._pass(data, f.loss_rx, f.latency_rx_s, deliver):
            self.dropped_rx += 1
