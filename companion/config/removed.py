"""The keys that are gone: every setting a user's old file may still name, with the value flights
use since and why it went.

A key is gone because it was a switch whose measurement lost (its history, and the command that
measured it, are in docs/measurements.md), or internal tuning that became a named constant beside
the code that uses it. Naming one is an error (exit 2 at start-up) that says so
(``companion.config.schema.removed_error``); a recording that holds one at the value flights now
use replays unchanged (``companion.config.schema.from_recording``). Kept apart from the schema so
that the live keys read without the history of the ones that left.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

_LOST = ("a default-off switch whose measurement lost; flights fly as they did with it off "
         "(docs/measurements.md has what was measured)")


@dataclass(frozen=True)
class Removed:
    """A removed key: the value every flight now uses, and why it is gone (where it went)."""

    value: Any
    why: str


def _lost(value: Any) -> Removed:
    return Removed(value, _LOST)


def _constant(value: Any, where: str) -> Removed:
    return Removed(value, f"internal tuning, now {where} = {value!r}")


#: Every removed key, dotted, with the value flights use since (docs/measurements.md, the
#: handoff of issue 58). ``tests/test_docs_keys.py`` lets the documents name these, and only these,
#: besides the live keys: the measurements keep their history.
REMOVED: dict[str, Removed] = {
    # Switches whose measurement lost (default off, or the loser of two modes).
    "controller.search_memory_s": _lost(0.0),
    "controller.hold_looks": _lost(False),
    "controller.avoid_lost_s": _lost(0.0),
    "controller.recentre_m": _lost(0.0),
    "controller.place_min_clear_m": _lost(0.0),
    "controller.place_descending": _lost(True),
    "controller.predict_people": _lost(False),
    "controller.predict_rejudge": _lost(True),
    "controller.predict_lead_s": _lost(2.0),
    "controller.predict_min_height_m": _lost(0.0),
    "controller.pose_uncertainty_m": _lost(0.5),
    "controller.min_quiet_s": _lost(0.0),
    "controller.min_unwalked_s": _lost(0.0),
    "pipeline.fusion": _lost("frame"),
    "pipeline.occupied_trail_s": _lost(0.0),
    "pipeline.quiet_margin_m": _lost(2.0),
    "pipeline.tracker.motion": _lost("position"),
    "pipeline.person_px_view": _lost("frame"),
    # Internal tuning: named constants next to the code that uses them, same values.
    "link.target_component": _constant(1, "companion.mavlink.link.LinkConfig.target_component (MAV_COMP_ID_AUTOPILOT1)"),
    "link.heartbeat_timeout_s": _constant(3.0, "companion.mavlink.link.LinkConfig.heartbeat_timeout_s"),
    "link.telemetry_rate_hz": _constant(20.0, "companion.mavlink.link.POSE_RATE_HZ"),
    "link.max_telemetry_lag_s": _constant(0.5, "companion.mavlink.clock.MAX_TELEMETRY_LAG_S"),
    "link.timesync_period_s": _constant(1.0, "companion.mavlink.timesync.TIMESYNC_PERIOD_S"),
    "model.allow_spinning": _constant(False, "companion.pipeline.density.DensityModel's allow_spinning "
                                             "(companion bench --spinning measures it)"),
    "pipeline.dilate_kernel": _constant(5, "companion.pipeline.occupancy.OccupancyParams.kernel"),
    "pipeline.dilate_iterations": _constant(2, "companion.pipeline.occupancy.OccupancyParams.iterations"),
    "pipeline.cell_size_m": _constant(0.1, "companion.pipeline.headplane.GridParams.cell"),
    "pipeline.max_extent_m": _constant(40.0, "companion.pipeline.headplane.GridParams.max_extent"),
    "pipeline.n_proposals": _constant(5, "companion.pipeline.tracker.TrackerParams.max_tracks (the paper's N_p)"),
    "pipeline.max_pose_age_s": _constant(0.25, "companion.mavlink.state.MAX_POSE_AGE_S"),
    "pipeline.occupied_hold_s": _constant(1.0, "companion.pipeline.riskmap.RiskMapConfig.hold_s"),
    "pipeline.map_memory_s": _constant(10.0, "companion.pipeline.riskmap.RiskMapConfig.memory_s"),
    "pipeline.map_half_extent_m": _constant(60.0, "companion.pipeline.riskmap.RiskMapConfig.half_extent_m"),
    "pipeline.tracker.sigma_a": _constant(0.5, "companion.pipeline.tracker.TrackerParams.sigma_a"),
    "pipeline.tracker.r_std": _constant([0.3, 0.3, 0.3], "companion.pipeline.tracker.TrackerParams.r_std"),
    "pipeline.tracker.min_iou": _constant(0.3, "companion.pipeline.tracker.TrackerParams.min_iou"),
    "pipeline.tracker.mu_1": _constant(3, "companion.pipeline.tracker.TrackerParams.mu_1"),
    "pipeline.tracker.mu_2": _constant(3, "companion.pipeline.tracker.TrackerParams.mu_2"),
    "pipeline.tracker.sigma_v": _constant(0.1, "companion.pipeline.tracker.GROUND_SIGMA_V"),
    "camera.vendor_name": _constant("companion-slz", "companion.mavlink.gcs_commands.CameraInfo.vendor"),
    "camera.model_name": _constant("SLZ downward camera", "companion.mavlink.gcs_commands.CameraInfo.model"),
    "controller.min_track_hits": _constant(3, "companion.control.planner.PlannerConfig.min_track_hits"),
    "controller.zone_max_age_s": _constant(1.0, "companion.control.planner.PlannerConfig.zone_max_age_s"),
    "controller.prefer_unwalked": _constant(True, "companion.config.compose.PREFER_UNWALKED"),
    "controller.steady_margin_m": _constant(0.5, "companion.control.planner.PlannerConfig.steady_margin_m"),
    "controller.calm_wait_s": _constant(15.0, "companion.control.landing.LandingConfig.calm_wait_s"),
    "controller.select_empty_s": _constant(3.0, "companion.config.compose.SELECT_EMPTY_S"),
    "controller.arrive_radius_m": _constant(1.0, "companion.control.landing.LandingConfig.arrive_radius_m"),
    "controller.descend_step_m": _constant(3.0, "companion.control.landing.LandingConfig.descend_step_m"),
    "controller.lose_after_frames": _constant(2, "companion.control.landing.LandingConfig.lose_after_frames"),
    "controller.place_lookback_s": _constant(30.0, "companion.config.compose.PLACE_LOOKBACK_S"),
    "recorder.segment_s": _constant(60.0, "companion.recording.FlightRecorder's segment_s"),
    "recorder.codec": _constant("MJPG", "companion.recording.FlightRecorder's codec"),
    "gcs.frame_budget_ms": Removed(0.0, "derived: a median pipeline time above the camera's frame period "
                                        "(1000 / camera.fps) reports 'model slow'"),
    "live.max_fps": _constant(5.0, "companion.service.web.LIVE_MAX_FPS"),
    "live.jpeg_quality": _constant(80, "companion.service.web.LiveView's jpeg_quality"),
    # A secret does not belong in a file that gets pasted into bug reports and recordings.
    "link.signing_key": Removed("", "a secret inline in the configuration file ends up in bug reports; "
                                    "put the 64-hex secret in a file only the service can read (chmod 600) "
                                    "and name that file with link.signing_key_file"),
}
#: Tables that are gone with all their keys.
REMOVED_TABLES = frozenset({"pipeline.tracker"})


__all__ = ["Removed", "REMOVED", "REMOVED_TABLES"]
