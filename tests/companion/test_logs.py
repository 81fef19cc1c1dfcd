"""Rate-limited repeated warnings (companion.logs): the first line at once, then one line per
interval per key carrying the count of what it stands for; a fake clock, real logging."""

from __future__ import annotations

import logging

import pytest

from companion.logs import RateLimitedLog, flush_all, warn_every


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _lines(caplog: pytest.LogCaptureFixture, name: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == name]


def test_first_line_then_one_summary_per_interval(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    clock = Clock()
    rl = RateLimitedLog(logging.getLogger("t.flood"), interval_s=10.0, clock=clock)
    # A flood like the audit's: 40,661 rejected messages in 22 s, one call each.
    written = 0
    for i in range(40_661):
        clock.now = 1000.0 + 22.0 * i / 40_661
        written += rl.warning("reject", "link: rejected message from sysid %d", 42)
    lines = _lines(caplog, "t.flood")
    assert written == len(lines) == 3  # t=0, t=10, t=20
    assert lines[0] == "link: rejected message from sysid 42"
    assert lines[1].startswith("link: rejected message from sysid 42 (")
    assert lines[1].endswith(" more like this in the last 10 s)")
    n1 = int(lines[1].split("(")[1].split()[0])
    n2 = int(lines[2].split("(")[1].split()[0])
    assert 18_000 < n1 < 19_000 and 18_000 < n2 < 19_000
    # What is still held back is written by flush(), and every occurrence is accounted for.
    assert rl.suppressed("reject") > 0
    assert rl.flush() == 1
    n3 = int(_lines(caplog, "t.flood")[3].split("(")[1].split()[0])
    assert 3 + n1 + n2 + (n3 + 1) == 40_661  # the flushed line is itself one of those held back
    assert rl.suppressed("reject") == 0 and rl.flush() == 0
    for r in caplog.records:
        assert r.levelno == logging.WARNING
        assert r.filename == "test_logs.py"  # the caller's line, not companion/logs.py


def test_keys_are_independent_and_quiet_keys_log_every_time(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    clock = Clock()
    rl = RateLimitedLog(logging.getLogger("t.keys"), interval_s=5.0, clock=clock)
    assert rl.warning("a", "disk full: %s", "x")
    assert rl.error(("reject", 7), "from %d", 7)
    assert not rl.warning("a", "disk full: %s", "y")
    assert rl.info("b", "other")
    clock.now += 5.0
    assert rl.warning("a", "disk full: %s", "z")
    clock.now += 60.0
    assert rl.warning("a", "disk full: %s", "w")  # nothing held back: no summary
    assert _lines(caplog, "t.keys") == [
        "disk full: x", "from 7", "other", "disk full: z (1 more like this in the last 5 s)", "disk full: w"]
    assert [r.levelno for r in caplog.records if r.name == "t.keys"][1] == logging.ERROR


def test_warn_every_keeps_state_per_logger_and_key(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    log = logging.getLogger("t.warn_every")
    results = [warn_every(log, "crc", 3600.0, "bad CRC from %s", "127.0.0.1:14550") for _ in range(100)]
    assert results[0] and not any(results[1:])
    assert warn_every(log, "other", 3600.0, "another key")
    assert warn_every(logging.getLogger("t.warn_every.b"), "crc", 3600.0, "another logger")
    assert _lines(caplog, "t.warn_every") == ["bad CRC from 127.0.0.1:14550", "another key"]
    assert [r.filename for r in caplog.records] == ["test_logs.py"] * 3
    assert warn_every(log, "zero", 0.0, "interval 0: %d", 1) and warn_every(log, "zero", 0.0, "interval 0: %d", 2)
    assert flush_all() >= 1  # the 99 held-back "crc" lines (other tests' loggers may add theirs)
    assert _lines(caplog, "t.warn_every")[-1] == "bad CRC from 127.0.0.1:14550 (98 more like this in the last 0 s)"
    assert flush_all() == 0


def test_keys_are_bounded_and_bad_formats_do_not_raise(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    clock = Clock()
    rl = RateLimitedLog(logging.getLogger("t.bounded"), interval_s=10.0, max_keys=4, clock=clock)
    for i in range(1000):  # keys from untrusted input (addresses, ids): memory stays bounded
        rl.warning(("peer", i), "unknown peer %d", i)
    assert len(rl._keys) == 4
    assert rl.warning("fmt", "needs %d and %s", 1)  # wrong argument count: logged, not raised
    assert not rl.warning("fmt", "needs %d and %s", 1)
    clock.now += 10.0
    assert rl.warning("fmt", "needs %d and %s", 1)
    assert "needs %d and %s (1,) (1 more like this" in _lines(caplog, "t.bounded")[-1]
    with pytest.raises(ValueError):
        RateLimitedLog(logging.getLogger("t"), interval_s=-1.0)
