"""The health verdict the service gives systemd: which faults stop the watchdog (internal: a
restart may cure them) and which are only reported (external: a restart cannot), and how few log
lines a long or flapping fault makes. The same policy in a real process under a NOTIFY_SOCKET:
``test_service.py::test_ready_watchdog_status_on_faults_and_clean_sigterm``."""

from __future__ import annotations

import logging

from companion.service.frame_use import FrameUse
from companion.service.health import PIPELINE_STUCK_S, FaultLog, Health, assess


def _ok(**kw: object) -> Health:
    args: dict[str, object] = {"link_connected": True, "camera_delivering": True, "busy_s": None}
    args.update(kw)
    return assess(**args)  # type: ignore[arg-type]


def test_healthy_feeds_the_watchdog_and_shows_the_normal_status() -> None:
    h = _ok()
    assert h.ok and h.feed_watchdog and h.reason == "ok"
    assert h.status("MONITOR: no zone") == "MONITOR: no zone"
    assert _ok(busy_s=PIPELINE_STUCK_S - 0.1).ok  # a slow frame is not a stuck pipeline


def test_external_faults_are_reported_and_the_watchdog_still_fed() -> None:
    """A camera unplugged or an autopilot gone silent: restarting cannot fix either and the
    service reconnects by itself, so systemd is told (STATUS=) but keeps getting its pings."""
    for h, text in ((_ok(camera_delivering=False), "camera not delivering"),
                    (_ok(link_connected=False), "no autopilot heartbeat")):
        assert not h.ok and h.feed_watchdog
        assert h.status("MONITOR: no zone") == f"degraded: {text}; MONITOR: no zone"
    both = _ok(camera_delivering=False, link_connected=False)
    assert both.feed_watchdog and [f.key for f in both.faults] == ["link", "camera"]
    assert both.reason == "no autopilot heartbeat; camera not delivering"


def test_an_internal_fault_stops_the_watchdog_whatever_else_holds() -> None:
    stuck = _ok(busy_s=PIPELINE_STUCK_S + 0.5)
    assert not stuck.ok and not stuck.feed_watchdog
    assert stuck.status("MONITOR: no zone") == f"unhealthy: pipeline stuck for {PIPELINE_STUCK_S + 0.5:.1f} s"
    worse = _ok(busy_s=60.0, camera_delivering=False)
    assert not worse.feed_watchdog and worse.faults[0].internal and worse.faults[0].key == "pipeline"
    assert worse.status("x").startswith("unhealthy: pipeline stuck for 60.0 s; camera not delivering")
    assert not assess(link_connected=True, camera_delivering=True, busy_s=2.0, stuck_after_s=1.0).feed_watchdog


def test_fault_log_begin_reminder_and_end() -> None:
    fl = FaultLog(remind_s=60.0, min_gap_s=10.0)
    cam = _ok(camera_delivering=False)
    assert fl.update(_ok(), 0.0) == []
    (level, line), = fl.update(cam, 1.0)
    assert level == logging.WARNING and line.startswith("camera not delivering (external fault")
    assert all(fl.update(cam, 1.0 + 0.25 * i) == [] for i in range(1, 200))  # 50 s: quiet
    (level, line), = fl.update(cam, 61.5)
    assert level == logging.WARNING and line.startswith("camera not delivering for 60 s")
    assert fl.update(cam, 62.0) == []
    (level, line), = fl.update(_ok(), 70.0)
    assert level == logging.INFO and line == "camera ok again after 69.0 s"
    (level, line), = fl.update(_ok(busy_s=6.0), 80.0)
    assert level == logging.ERROR and "internal fault: watchdog no longer fed" in line


def test_fault_log_a_flapping_fault_makes_few_lines_and_none_are_lost() -> None:
    """A camera that comes and goes every 0.5 s for a minute: a handful of lines, not 120 pairs,
    and the line after the quiet spell says how many times it began meanwhile."""
    fl = FaultLog(remind_s=60.0, min_gap_s=10.0)
    lines = []
    t = 0.0
    for i in range(120):
        lines += fl.update(_ok(camera_delivering=i % 2 == 1), t)
        t += 0.5
    assert len(lines) <= 2 * (60 / 10 + 1), lines
    begins = [line for _, line in lines if line.startswith("camera not delivering")]
    assert any("began" in line and "times since the last line" in line for line in begins), lines
    # Once it stops flapping but stays down, the operator hears about it within min_gap_s.
    down = _ok(camera_delivering=False)
    heard = []
    for _ in range(50):
        heard += fl.update(down, t)
        t += 0.25
    assert any(line.startswith("camera not delivering") for _, line in heard), heard


def test_frames_that_cannot_be_used_are_a_state_with_its_name() -> None:
    """No pose, a stale pose, below the head plane: external, reported, never "ok"; on the ground
    (or under the head plane) it is standby, not a fault; a missing pose is not told again while
    the link is down (that says why), nor any frame state while the camera itself is the fault."""
    for reason in ("no pose", "stale pose", "frames unusable"):
        h = _ok(frames=reason)
        assert not h.ok and h.feed_watchdog and not h.standby and h.reason == reason
        assert h.status("MONITOR: no zone") == f"degraded: {reason}; MONITOR: no zone"
    for reason in ("on the ground", "below the head plane"):
        h = _ok(frames=reason)
        assert not h.ok and h.standby and h.status("MONITOR: no zone") == f"standby: {reason}; MONITOR: no zone"
    assert _ok(frames="stale pose", link_connected=False).reason == "no autopilot heartbeat"
    assert _ok(frames="on the ground", camera_delivering=False).reason == "camera not delivering"
    assert _ok(camera_delivering=False, camera_frozen=True).reason == "camera frozen"


def test_frame_use_holds_a_moment_each_way_and_names_the_common_reason() -> None:
    fu = FrameUse(bad_after_s=1.0, good_after_s=1.0, expire_s=3.0)
    t = 0.0
    for _ in range(10):  # used at 10 Hz
        fu.used(t)
        t += 0.1
    assert fu.state(t) is None
    for _ in range(9):  # refused for 0.9 s: not yet
        fu.refused("stale pose", t)
        assert fu.state(t) is None
        t += 0.1
    fu.refused("no pose", t)
    fu.refused("stale pose", t)
    assert fu.state(t + 0.15) == "stale pose"  # 1 s of refusals; the most common reason
    # Every other frame used: it does not flap back to ok.
    for i in range(20):
        (fu.used if i % 2 else lambda now: fu.refused("stale pose", now))(t)
        assert fu.state(t) == "stale pose"
        t += 0.1
    for _ in range(10):  # used for 1 s: ok again
        fu.used(t)
        t += 0.1
    assert fu.state(t) is None
    # One refusal among used frames does not make it bad.
    fu.refused("on the ground", t)
    fu.used(t + 0.1)
    assert fu.state(t + 1.5) is None
    # No frame at all for expire_s: unknown (the camera's own fault tells it), not a stale reason.
    for _ in range(12):
        fu.refused("on the ground", t)
        t += 0.1
    assert fu.state(t) == "on the ground"
    assert fu.state(t + 3.5) is None
