"""One frame's result as a JSON-ready record (the ``--jsonl`` schema of docs/replay.md).

Circles are given twice: in head-plane metres (``x``, ``y``, ``r``) and in input-image pixels
(``u``, ``v`` the centre, ``r_px`` the radius along the image x axis). ``r_px`` is half the image
distance between the projections of ``c - r d`` and ``c + r d``, where ``d`` is the unit plane
direction whose image at the centre runs along the image x axis (from the Jacobian of the
plane-to-image homography). Under ``--nadir`` this is exactly ``r / gsd``; for an oblique view it
is the ellipse's extent along the image row through its centre, to first order.

Values that do not exist (a centre behind the camera, a degenerate projection) are ``None``,
written as JSON ``null``: NaN never reaches the output.

Each proposal and track also carries ``edge``: what bounds it on that frame, ``"people"``,
``"surface"`` (ground the landability model calls unlandable) or ``"view"`` (the end of what the
camera sees); ``null`` without the landability model (``companion.pipeline.edges``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import fields
from typing import Any

import numpy as np

from companion.control.planner import ZoneCheck, ZonePlanner
from companion.control.touchdown import DescentProfile
from companion.geometry.camera import PlaneProjection
from companion.pipeline.circles import Circle
from companion.pipeline.slz import FrameResult
from companion.pipeline.tracker import Track

TIMING_KEYS = ("density", "occupancy", "projection", "fusion", "proposals", "tracking", "total")


def finite_or_none(value: float) -> float | None:
    v = float(value)
    return v if math.isfinite(v) else None


def plane_jacobian(proj: PlaneProjection, x: float, y: float) -> np.ndarray:
    """d(u, v)/d(x, y) of the plane-to-image projection at plane point (x, y): (2, 2), px/m
    (through a fisheye by central differences over 1 cm, the lens being no homography)."""
    if proj.lens is not None:
        e = 0.01
        p = proj.plane_to_image(np.array([[x - e, y], [x + e, y], [x, y - e], [x, y + e]]))
        return np.column_stack([(p[1] - p[0]) / (2 * e), (p[3] - p[2]) / (2 * e)])
    H = proj.H
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
    v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
    return np.array([[H[0, 0] - u * H[2, 0], H[0, 1] - u * H[2, 1]],
                     [H[1, 0] - v * H[2, 0], H[1, 1] - v * H[2, 1]]]) / w


def circle_in_image(proj: PlaneProjection, x: float, y: float, r: float
                    ) -> tuple[float | None, float | None, float | None]:
    """(u, v, r_px) of the plane circle (x, y, r) metres; entries are None where undefined."""
    uv = proj.plane_to_image(np.array([[x, y]]))[0]
    if not np.isfinite(uv).all():
        return None, None, None
    u, v = float(uv[0]), float(uv[1])
    with np.errstate(all="ignore"):
        J = plane_jacobian(proj, x, y)
        try:
            d = np.linalg.solve(J, [1.0, 0.0])
        except np.linalg.LinAlgError:
            return u, v, None
    n = float(np.hypot(*d))
    if not (math.isfinite(n) and n > 0):
        return u, v, None
    d = d / n
    ends = proj.plane_to_image(np.array([[x - r * d[0], y - r * d[1]], [x + r * d[0], y + r * d[1]]]))
    r_px = 0.5 * float(np.hypot(*(ends[1] - ends[0])))
    return u, v, finite_or_none(r_px)


def _circle_fields(proj: PlaneProjection, x: float, y: float, r: float) -> dict[str, Any]:
    u, v, r_px = circle_in_image(proj, x, y, r)
    return {"x": finite_or_none(x), "y": finite_or_none(y), "r": finite_or_none(r),
            "u": u, "v": v, "r_px": r_px}


def is_stable(track: Track, planner: ZonePlanner, now: float) -> bool:
    """The planner would keep this zone as a target at ``now``: confirmed by this frame and at
    least ``r0_m`` wide (or, low down, everything seen around it free). What may be landed on;
    not what is chosen, which is ``planner.choose``."""
    return planner.check_target(track.id, [track], now)[0] is ZoneCheck.OK


def proposal_record(proj: PlaneProjection, c: Circle) -> dict[str, Any]:
    return _circle_fields(proj, c.x, c.y, c.r)


def track_record(proj: PlaneProjection, tr: Track, planner: ZonePlanner, now: float,
                 height_m: float | None = None, descent: DescentProfile | None = None) -> dict[str, Any]:
    """One track's record. ``clearance_m``: the least clearance it can have at touchdown if the
    vehicle committed now from ``height_m`` (its radius less what a walker covers during the
    descent, ``DescentProfile``); null without a pose or a profile."""
    rec: dict[str, Any] = {"id": int(tr.id), "age": int(tr.age), "hits": int(tr.hits),
                           "stable": is_stable(tr, planner, now)}
    rec.update(_circle_fields(proj, tr.x, tr.y, tr.r))
    rec["misses"] = int(tr.misses)
    rec["r_filtered"] = finite_or_none(tr.r_filtered)
    rec["clearance_m"] = (None if height_m is None or descent is None
                          else finite_or_none(descent.clearance_at_touchdown(tr.r, height_m)))
    rec["edge"] = tr.edge or None
    return rec


def frame_target(result: FrameResult, planner: ZonePlanner) -> Track | None:
    """The zone the vehicle would fly to after this frame: the planner's choice among the tracks,
    as the landing controller makes it before a trigger (the one rule; the pipeline only
    reports tracks)."""
    return planner.choose(result.tracks, result.t)


def frame_record(index: int, result: FrameResult, planner: ZonePlanner, height_m: float | None = None,
                 descent: DescentProfile | None = None) -> dict[str, Any]:
    """The JSON Lines record of one processed frame (``index`` is its position in the input);
    ``height_m`` (metres above the ground, from the frame's pose) and ``descent`` give each
    track's ``clearance_m`` at touchdown."""
    proj = result.projection
    edges = getattr(result, "proposal_edges", None) or []
    target = frame_target(result, planner)
    timing = {k: finite_or_none(result.timings_ms.get(k, float("nan"))) for k in TIMING_KEYS}
    return {
        "frame": int(index),
        "t": finite_or_none(result.t),
        "proposals": [{**proposal_record(proj, c), "edge": edges[i] if i < len(edges) else None}
                      for i, c in enumerate(result.proposals)],
        "tracks": [track_record(proj, tr, planner, result.t, height_m, descent) for tr in result.tracks],
        "target": None if target is None else int(target.id),
        "timing_ms": timing,
    }


def recorded_track(d: dict[str, Any]) -> Track | None:
    """A track of a flight recording's ``zones`` event, or None when its fields do not fit this
    version's :class:`Track` (a recording from another version)."""
    names = {f.name for f in fields(Track)}
    try:
        return Track(**{k: v for k, v in d.items() if k in names})
    except TypeError:
        return None


def flight_zones(events: Iterable[dict[str, Any]]) -> dict[int, tuple[list[Track], int | None]]:
    """What the flight decided on each frame it processed, by camera frame index: the zones it
    tracked and the target it flew to (its ``zones`` events)."""
    out: dict[int, tuple[list[Track], int | None]] = {}
    for e in events:
        if e.get("kind") != "zones" or not isinstance(e.get("frame"), int):
            continue
        tracks = [t for t in (recorded_track(d) for d in e.get("tracks") or [] if isinstance(d, dict))
                  if t is not None]
        target = e.get("target")
        out[int(e["frame"])] = (tracks, target if isinstance(target, int) else None)
    return out
