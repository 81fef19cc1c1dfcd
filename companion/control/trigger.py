"""Why a safe landing was asked for: the controller's only way out of MONITOR.

The failsafe monitor (``companion.mavlink.failsafe``) builds these from telemetry, a ground-station
command or a local request; the controller only reads them.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class TriggerSource(str, enum.Enum):
    BATTERY = "battery"
    SYSTEM_STATUS = "system_status"
    AUTOPILOT_MODE = "autopilot_land"
    GCS_COMMAND = "gcs_command"
    LOCAL = "local_trigger"


@dataclass(frozen=True)
class Trigger:
    """Why a safe landing was asked for: human-readable ``reason``, its ``source``, monotonic ``t`` (s)."""

    reason: str
    source: TriggerSource
    t: float
