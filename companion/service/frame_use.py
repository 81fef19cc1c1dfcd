"""Why the frames that reach the service cannot be decided with, as its health names it.

The frame loop tells :class:`FrameUse` what became of each frame: used (through the pipeline to
the controller) or refused, with one of :data:`FRAME_REASONS` (:func:`pose_reason` when it had no
pose at its capture time, :func:`geometry_reason` when the pipeline could not place it); the health
loop asks it for the state (``companion.service.health.assess``), held a moment each way so that it
does not flap. On the ground (and below the people's heads) no frame can be used: the pipeline
places frames on the head plane (``pipeline.head_height_m``, 1.7 m by default).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from companion.geometry.camera import GeometryError, Mount, Pose, camera_extrinsics
from companion.mavlink.state import VehicleState

#: Why frames reach the service but cannot be decided with, as health names it (the state's name on
#: the ground station, in systemd's status and on the status page). Camera frozen is the camera's
#: (``assess(camera_frozen=...)``): its frames never reach the service.
NO_POSE = "no pose"                  # no attitude, position or home from the autopilot yet
STALE_POSE = "stale pose"            # telemetry, but none at the frames' capture times
ON_GROUND = "on the ground"          # the autopilot says landed (or disarmed)
LOW = "below the head plane"         # airborne, but the camera is under the people's heads
UNUSABLE = "frames unusable"         # the pipeline refused or failed on them
FRAME_REASONS = (NO_POSE, STALE_POSE, ON_GROUND, LOW, UNUSABLE)
#: The reasons that are where the vehicle is, not something wrong: the companion is on standby
#: (taking off and the last metres of a landing pass under the head plane).
STANDBY_REASONS = frozenset({ON_GROUND, LOW})


@dataclass
class FrameUse:
    """Whether the frames that reach the service are decided with, and if not, why.

    ``used`` is called for each frame that reached the controller, ``refused`` with its reason for
    each that did not. The state goes bad when frames have been refused for ``bad_after_s`` with
    none used in between, and good again when frames have been used for ``good_after_s`` with none
    refused in between: a frame in two without a pose keeps it good (the controller still decides,
    with fewer frames), and a pose that comes and goes does not make it flap. The reason told is the
    most common among the refusals of the last ``bad_after_s``. With no frame at all for
    ``expire_s`` it is unknown (None): the camera's own fault tells that.
    """

    bad_after_s: float = 1.0
    good_after_s: float = 1.0
    expire_s: float = 3.0
    reason: str | None = None  # the state: None while frames are used
    _refused: deque[tuple[float, str]] = field(default_factory=lambda: deque(maxlen=64))
    _refused_since: float | None = None  # first refusal since the last used frame
    _used_since: float | None = None     # first used frame since the last refusal
    _last_t: float = -math.inf

    def used(self, now: float) -> None:
        self._refused_since = None
        if self._used_since is None:
            self._used_since = now
        self._last_t = now

    def refused(self, reason: str, now: float) -> None:
        self._used_since = None
        if self._refused_since is None:
            self._refused_since = now
        self._refused.append((now, reason))
        self._last_t = now

    def state(self, now: float) -> str | None:
        """The reason frames cannot be used now, or None."""
        if now - self._last_t > self.expire_s:
            self.reason = None
        elif self.reason is None:
            if self._refused_since is not None and now - self._refused_since >= self.bad_after_s:
                self.reason = self._common(now)
        elif self._used_since is not None and now - self._used_since >= self.good_after_s:
            self.reason = None
        elif self._refused_since is not None:
            self.reason = self._common(now) or self.reason
        return self.reason

    def _common(self, now: float) -> str | None:
        recent = [r for t, r in self._refused if now - t <= self.bad_after_s]
        return max(FRAME_REASONS, key=recent.count) if recent else None


def pose_reason(state: VehicleState) -> str:
    """Why a frame had no pose: none known at all (no attitude, position or home), or telemetry
    that does not cover its capture time (stopped, late, or refused as out of order)."""
    if state.attitude is None or state.position is None or state.home is None:
        return NO_POSE
    return STALE_POSE


def geometry_reason(state: VehicleState, pose: Pose, mount: Mount, head_height_m: float) -> str:
    """Why the pipeline could not place a frame seen from ``pose``: the camera at or under the
    head plane (on the ground when the autopilot says landed, or disarmed), else unusable."""
    try:
        below = camera_extrinsics(pose, mount).position[2] >= -head_height_m
    except GeometryError:
        return UNUSABLE
    if not below:
        return UNUSABLE
    landed = state.landed is not None and state.landed.on_ground
    return ON_GROUND if landed or state.armed is False else LOW
