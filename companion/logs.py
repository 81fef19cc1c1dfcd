"""Rate-limited logging for messages that can repeat thousands of times a second.

Why: in the audit of issue 12, a flood of rejected MAVLink messages wrote one WARNING per message
(40,661 lines in 22 s), and journald's own rate limit then dropped lines wholesale, the failsafe
trigger lines among them: the evidence went missing exactly when it mattered. A message that can
repeat at the rate of its cause (a packet, a frame, a disk write) is logged through this module
instead: the first occurrence at once, then at most one line per interval per *key*, carrying the
count of the repeats it stands for::

    WARNING link: rejected a message from sysid 42 (1234 more like this in the last 10 s)

Two ways to use it, same behaviour:

* one call, state kept per (logger, key) in this module (WARNING level)::

      from companion.logs import warn_every
      warn_every(log, "bad-crc", 10.0, "link: bad CRC from %s", addr)
      ...
      flush_all()  # at shutdown: write the counts still held back

* an object per component (its own keys and interval, any level: ``warning``, ``error``,
  ``info``, ``log(level, ...)``; ``clock`` can be injected in tests)::

      from companion.logs import RateLimitedLog
      self._rl = RateLimitedLog(log, interval_s=10.0)
      self._rl.warning("disk-full", "recorder: cannot write event: %s", exc)
      ...
      self._rl.flush()  # at shutdown: write the counts still held back

``key`` names the kind of repeat (any hashable: a string, or a tuple such as ``("reject",
msgid)``); messages with the same key share one budget, whatever their arguments, so the line
written is the newest occurrence's. Keep keys to a small set (the kind of problem, not the
sender's address or anything else a flood can vary): every new key writes its first line at once.
``msg``/``args`` are as for :meth:`logging.Logger.log` (%-style, formatted only when a line is
written; a format that does not fit its arguments is written as is, never raised). Each call
returns True when it wrote a line. Repeats are counted, never lost silently: a count still held
back is written by the next occurrence after the interval, or by :meth:`RateLimitedLog.flush`.
At most ``max_keys`` keys are remembered (the oldest forgotten first), so keys built from
untrusted input cannot grow memory without bound. Thread-safe.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass

__all__ = ["RateLimitedLog", "flush_all", "warn_every"]

SUMMARY = " (%d more like this in the last %.0f s)"


@dataclass
class _Key:
    last_emit: float  # clock time of the last line written for this key
    suppressed: int = 0  # occurrences held back since then
    level: int = logging.WARNING
    msg: str = ""  # the newest held-back occurrence (for flush), formatted only if written
    args: tuple[object, ...] = ()


class RateLimitedLog:
    """Logs through ``logger`` at most one line per ``interval_s`` seconds per key (see the module
    docstring). ``clock`` is a monotonic clock in seconds (``time.monotonic`` by default)."""

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0, *, max_keys: int = 1024,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if interval_s < 0:
            raise ValueError(f"interval_s must be >= 0, got {interval_s}")
        if max_keys < 1:
            raise ValueError(f"max_keys must be >= 1, got {max_keys}")
        self.logger = logger
        self.interval_s = float(interval_s)
        self.max_keys = int(max_keys)
        self._clock = clock
        self._keys: dict[Hashable, _Key] = {}
        self._lock = threading.Lock()

    def log(self, level: int, key: Hashable, msg: str, *args: object,
            interval_s: float | None = None) -> bool:
        """Log ``msg % args`` at ``level`` unless a line for ``key`` was written less than
        ``interval_s`` (default: the object's) ago; then only count it. True when written."""
        return self._log(level, key, msg, args, interval_s)

    def warning(self, key: Hashable, msg: str, *args: object) -> bool:
        return self._log(logging.WARNING, key, msg, args)

    def error(self, key: Hashable, msg: str, *args: object) -> bool:
        return self._log(logging.ERROR, key, msg, args)

    def info(self, key: Hashable, msg: str, *args: object) -> bool:
        return self._log(logging.INFO, key, msg, args)

    def _log(self, level: int, key: Hashable, msg: str, args: tuple[object, ...],
             interval_s: float | None = None) -> bool:
        # Called by exactly one public function, so stacklevel 3 names the caller of that one.
        interval = self.interval_s if interval_s is None else float(interval_s)
        now = self._clock()
        with self._lock:
            state = self._keys.get(key)
            if state is not None and now - state.last_emit < interval:
                state.suppressed += 1
                state.level, state.msg, state.args = level, msg, args
                return False
            if state is None:
                if len(self._keys) >= self.max_keys:
                    del self._keys[next(iter(self._keys))]  # the oldest key
                self._keys[key] = _Key(now)
                suppressed, elapsed = 0, 0.0
            else:
                suppressed, elapsed = state.suppressed, now - state.last_emit
                state.last_emit, state.suppressed, state.msg, state.args = now, 0, "", ()
        if suppressed:
            self.logger.log(level, "%s" + SUMMARY, _format(msg, args), suppressed, elapsed, stacklevel=3)
        else:
            self.logger.log(level, "%s", _format(msg, args), stacklevel=3)
        return True

    def suppressed(self, key: Hashable) -> int:
        """Occurrences of ``key`` held back since its last line (0 for an unknown key)."""
        with self._lock:
            state = self._keys.get(key)
            return 0 if state is None else state.suppressed

    def flush(self) -> int:
        """Write one summary line for every key with repeats held back (e.g. at shutdown), at
        once, whatever the interval; returns how many lines were written."""
        now = self._clock()
        pending: list[tuple[int, str, tuple[object, ...], int, float]] = []
        with self._lock:
            for state in self._keys.values():
                if state.suppressed:
                    pending.append((state.level, state.msg, state.args, state.suppressed,
                                    now - state.last_emit))
                    state.last_emit, state.suppressed, state.msg, state.args = now, 0, "", ()
        for level, msg, args, n, elapsed in pending:  # the line shown is the newest of the n
            if n > 1:
                self.logger.log(level, "%s" + SUMMARY, _format(msg, args), n - 1, elapsed, stacklevel=2)
            else:
                self.logger.log(level, "%s", _format(msg, args), stacklevel=2)
        return len(pending)


def _format(msg: str, args: tuple[object, ...]) -> str:
    try:
        return msg % args if args else msg
    except (TypeError, ValueError):  # a bad format string must not raise from a log call
        return f"{msg} {args!r}"


_shared: dict[str, RateLimitedLog] = {}
_shared_lock = threading.Lock()


def warn_every(logger: logging.Logger, key: Hashable, interval_s: float, msg: str, *args: object) -> bool:
    """Log a WARNING through ``logger`` at most once per ``interval_s`` seconds per ``key``, with the
    count of the repeats held back (see the module docstring). State is kept in this module per
    logger name and key. True when a line was written."""
    with _shared_lock:
        limiter = _shared.get(logger.name)
        if limiter is None or limiter.logger is not logger:
            limiter = _shared[logger.name] = RateLimitedLog(logger, interval_s)
    return limiter._log(logging.WARNING, key, msg, args, interval_s)


def flush_all() -> int:
    """Write the counts :func:`warn_every` still holds back, for every logger (e.g. at shutdown);
    returns how many lines were written."""
    with _shared_lock:
        limiters = list(_shared.values())
    return sum(limiter.flush() for limiter in limiters)
