"""Human-readable events for the ground station as STATUSTEXT, paced so that none is lost.

A STATUSTEXT carries 50 bytes; longer texts (at most :data:`MAX_TEXT` characters, cut at a space
beyond that) are sent in chunks sharing a non-zero ``id`` with ``chunk_seq`` 0, 1, ... as
MAVLink 2 specifies: a chunk with a NUL in it (shorter than 50 bytes) ends the text, so every
chunk but the last is cut at a space and padded with spaces to the full 50 bytes, and each one
after the first begins with the text's prefix (``SLZ: ``), so that a ground station that shows
chunks one by one (MAVProxy) shows words, each line marked as the companion's, and one that
joins them (QGroundControl, MAVSDK, PX4's own log) shows the whole text.

Pacing (:class:`TextPacer`, :class:`TextOutbox`): the texts of one link go out one at a time
from a queue, most severe first, at most :data:`MAX_PER_WINDOW` in any :data:`WINDOW_S`, at
least :data:`MIN_GAP_S` apart, the chunks of one text :data:`CHUNK_GAP_S` apart; the same text
is not said twice within :data:`REPEAT_S`, and a queued NOTICE or INFO older than
:data:`STALE_S` is dropped (counted) rather than told late. Why: PX4 forwards what the companion
sends through one small buffer per link (``Mavlink::pass_message``: room for two
``mavlink_message_t``, 583 bytes) emptied one message per pass of that link's loop, and drops
what does not fit; a trigger's two texts (five chunks) and the eight named values sent on the
same phase change did not fit (docs/ground-station.md, "Pacing").
"""

from __future__ import annotations

import asyncio
import itertools
import math
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.events import Event, HandedBack, Holding, Note, TargetChosen
from companion.mavlink.link import MavLink

STATUSTEXT_LEN = 50
#: The longest text told (characters); a longer one is cut at a space and ends in "...".
MAX_TEXT = 150
#: The prefixes a continuation chunk repeats (the companion's texts begin with one of them).
PREFIXES = ("SLZ: ", "SHADOW: ")
#: Pacing (s): at most MAX_PER_WINDOW texts in any WINDOW_S, MIN_GAP_S apart, chunks CHUNK_GAP_S
#: apart (PX4's forwarding buffer holds one chunk and a burst of named values at a time), no
#: text twice within REPEAT_S, a queued NOTICE/INFO dropped once STALE_S old.
MAX_PER_WINDOW, WINDOW_S, MIN_GAP_S, CHUNK_GAP_S, REPEAT_S, STALE_S = 4, 10.0, 1.0, 0.05, 5.0, 15.0
#: Texts waiting at most; beyond it the least severe, oldest, is dropped (counted).
MAX_QUEUE = 8
_ids = itertools.count(1)


def fit_text(text: str, limit: int = MAX_TEXT) -> str:
    """``text`` within ``limit`` characters: cut at the last space before it, ending in "..."."""
    if len(text) <= limit:
        return text
    head = text[:limit - 3]
    cut = head.rfind(" ")
    return (head[:cut] if cut > limit // 2 else head).rstrip(" ,;:") + "..."


def _cut(data: bytes, room: int) -> int:
    """Where to end a chunk of at most ``room`` bytes of ``data``: after the last space within it
    (when one lies in its second half), else at a character boundary."""
    if len(data) <= room:
        return len(data)
    if data[room:room + 1] == b" ":
        return room  # a word ends exactly there
    space = data.rfind(b" ", 0, room)
    if space >= room // 2:
        return space + 1
    cut = room
    while cut > 0 and (data[cut] & 0xC0) == 0x80:
        cut -= 1  # back up to a character boundary
    return cut


def statustext_chunks(text: str) -> list[bytes]:
    """The UTF-8 chunks of ``text`` (see the module docstring): each cut at a space where it can
    be, never inside a character, every one but the last padded with spaces to 50 bytes, each
    after the first beginning with the text's prefix."""
    data = text.encode("utf-8")
    if len(data) <= STATUSTEXT_LEN:
        return [data]
    prefix = next((p.encode() for p in PREFIXES if text.startswith(p)), b"")
    chunks: list[bytes] = []
    while data:
        lead = prefix if chunks else b""
        cut = _cut(data, STATUSTEXT_LEN - len(lead))
        chunks.append(lead + data[:cut])
        data = data[cut:].lstrip(b" ")
    return [c.ljust(STATUSTEXT_LEN) for c in chunks[:-1]] + [chunks[-1]]


def event_severity(event: Event) -> int:
    """The MAV_SEVERITY of a controller event, as ground stations rank them: a handback that
    commands the autopilot's failsafe is CRITICAL (the companion gave up; the autopilot lands or
    returns on its own), the trigger, a hold, a pilot's takeover and a failed command WARNING,
    a chosen target and the other phase changes NOTICE, any other note INFO."""
    if isinstance(event, HandedBack):
        return m.MAV_SEVERITY_CRITICAL if event.action else m.MAV_SEVERITY_WARNING
    if event.warning or isinstance(event, Holding):
        return m.MAV_SEVERITY_WARNING
    if isinstance(event, TargetChosen) or event.changed:
        return m.MAV_SEVERITY_NOTICE
    if isinstance(event, Note):
        return m.MAV_SEVERITY_INFO
    return m.MAV_SEVERITY_NOTICE


def shadow_text(text: str) -> str:
    """The ground station's text of a decision taken in shadow mode: "SHADOW: " in place of the
    usual "SLZ: " (the same 50 characters a plain event has, as far as it goes)."""
    body = text[len("SLZ: "):] if text.startswith("SLZ: ") else text
    return f"SHADOW: {body}"


def join_chunks(chunks: list[str]) -> str:
    """The text whose chunks (``statustext_chunks``, decoded, in order) are ``chunks``: what a
    ground station that joins them shows, less the padding and the repeated prefix."""
    if len(chunks) <= 1:
        return "".join(chunks)
    prefix = next((p for p in PREFIXES if chunks[0].startswith(p)), "")
    parts = [chunks[0].rstrip(" ")] + [c.removeprefix(prefix).rstrip(" ") if prefix else c for c in chunks[1:]]
    if not prefix:
        return "".join(parts)
    return " ".join(p for p in parts if p)


def statustext_messages(link: MavLink, text: str, severity: int) -> list[object]:
    """The STATUSTEXT messages of ``text`` (within :data:`MAX_TEXT`), in order: its chunks, and an
    empty terminator when the last chunk fills its 50 bytes."""
    chunks = statustext_chunks(fit_text(text))
    msg_id = 0 if len(chunks) == 1 else (next(_ids) % 65535) + 1
    msgs = [link.mav.statustext_encode(severity, chunk, msg_id, seq) for seq, chunk in enumerate(chunks)]
    if msg_id and len(chunks[-1]) == STATUSTEXT_LEN:
        msgs.append(link.mav.statustext_encode(severity, b"", msg_id, len(chunks)))  # terminator
    return msgs


def send_statustext(link: MavLink, text: str, severity: int = m.MAV_SEVERITY_INFO, key: str = "",
                    last: bool = False) -> None:
    """Tell ``text`` with MAV_SEVERITY ``severity``: through the link's :class:`TextOutbox` when
    it has one (the service's), paced (``key``: see :class:`TextPacer`); else at once, its
    chunks back to back. ``last``: the service's last words (it is stopping and nothing could
    send them later): at once, past the queue."""
    outbox = _outboxes.get(link)
    if outbox is not None:
        if last:
            outbox.told(text, severity)  # at once, whatever the pace: it counts in it all the same
        else:
            outbox.offer(text, severity, key)
        return
    for msg in statustext_messages(link, text, severity):
        link.send(msg)


@dataclass
class TextPacer:
    """Which text goes out when (the module docstring's rules): pure bookkeeping on the times it
    is given (monotonic s). ``offer`` queues a text; ``take`` gives the next one due, if any;
    ``next_at`` says when one will be. A text offered with a ``key`` (a condition: the model's
    speed, the camera) replaces a queued one of the same key, its news being newer, and is sent no
    sooner than ``repeat_s`` after the last of its key: at most two in any ``window_s``."""

    max_per_window: int = MAX_PER_WINDOW
    window_s: float = WINDOW_S
    min_gap_s: float = MIN_GAP_S
    repeat_s: float = REPEAT_S
    stale_s: float = STALE_S
    max_queue: int = MAX_QUEUE
    #: Texts not told: said within repeat_s (``repeats``); stale, replaced by newer news of their
    #: key, or pushed out of a full queue (``dropped``).
    repeats: int = 0
    dropped: int = 0
    _queue: list[tuple[int, int, float, str, str]] = field(default_factory=list)  # severity, order, t, text, key
    _sent: list[tuple[float, str]] = field(default_factory=list)  # (t, text) within repeat/window
    _key_t: dict[str, float] = field(default_factory=dict)  # key -> when its last text went
    _order: itertools.count[int] = field(default_factory=itertools.count)

    def offer(self, text: str, severity: int, now: float, key: str = "") -> bool:
        """Queue ``text``; False (counted) when the same text was told or is waiting within
        ``repeat_s``."""
        text = fit_text(text)
        if any(t == text and now - ts < self.repeat_s for ts, t in self._sent) or \
                any(q[3] == text and now - q[2] < self.repeat_s for q in self._queue):
            self.repeats += 1
            return False
        if key:
            kept = [q for q in self._queue if q[4] != key]
            self.dropped += len(self._queue) - len(kept)
            self._queue = kept
        self._queue.append((severity, next(self._order), now, text, key))
        if len(self._queue) > self.max_queue:  # the least severe (highest number), oldest, goes
            self._queue.remove(max(self._queue, key=lambda q: (q[0], -q[1])))
            self.dropped += 1
        return True

    def _free_at(self, q: tuple[int, int, float, str, str]) -> float:
        return self._key_t.get(q[4], -math.inf) + self.repeat_s if q[4] else -math.inf

    def next_at(self, now: float) -> float | None:
        """When the next queued text may go (``now`` or later), or None with none waiting."""
        keep = [q for q in self._queue if q[0] <= m.MAV_SEVERITY_WARNING or now - q[2] <= self.stale_s]
        self.dropped += len(self._queue) - len(keep)
        self._queue = keep
        if not self._queue:
            return None
        recent = [ts for ts, _ in self._sent if now - ts < self.window_s]
        at = now if not recent else max(now, recent[-1] + self.min_gap_s)
        if len(recent) >= self.max_per_window:
            at = max(at, recent[-self.max_per_window] + self.window_s)
        return max(at, min(self._free_at(q) for q in self._queue))

    def allowance(self, now: float) -> int:
        """How many texts may go at once at ``now`` without passing ``max_per_window`` in the
        last ``window_s`` (the service's last words at stop, which cannot wait their turn)."""
        return max(0, self.max_per_window - sum(1 for ts, _ in self._sent if now - ts < self.window_s))

    def told(self, text: str, now: float) -> None:
        """``text`` went out at ``now`` past the queue (the stop's own text): it counts in the window."""
        self._sent = [(ts, t) for ts, t in self._sent if now - ts < max(self.window_s, self.repeat_s)]
        self._sent.append((now, fit_text(text)))

    def take(self, now: float) -> tuple[int, str] | None:
        """The most severe queued text free to go (the oldest of those) when one may go at
        ``now``, else None."""
        at = self.next_at(now)
        if at is None or at > now:
            return None
        best = min((q for q in self._queue if self._free_at(q) <= now), key=lambda q: (q[0], q[1]))
        self._queue.remove(best)
        self._sent = [(ts, t) for ts, t in self._sent if now - ts < max(self.window_s, self.repeat_s)]
        self._sent.append((now, best[3]))
        if best[4]:
            self._key_t[best[4]] = now
        return best[0], best[3]

    def drain(self, now: float) -> list[tuple[int, str]]:
        """Empty the queue (the service is stopping): the (severity, text) that ``allowance``
        lets go at ``now``, most severe first and the oldest of a severity first; the rest are
        dropped (counted in ``dropped``)."""
        waiting = sorted(self._queue, key=lambda q: (q[0], q[1]))
        self._queue = []
        room = self.allowance(now)
        self.dropped += max(0, len(waiting) - room)
        return [(severity, text) for severity, _, _, text, _ in waiting[:room]]


class TextOutbox:
    """The link's texts, paced (:class:`TextPacer`) and sent from the event loop: ``offer``
    queues and schedules the next send with ``loop.call_later``, so no task needs running.
    ``sent`` keeps (time, severity, text) of each text told, for tests and the status page."""

    def __init__(self, link: MavLink, pacer: TextPacer | None = None,
                 clock: Callable[[], float] = time.monotonic, chunk_gap_s: float = CHUNK_GAP_S) -> None:
        self.link = link
        self.pacer = pacer or TextPacer()
        self.clock = clock
        self.chunk_gap_s = chunk_gap_s
        self.sent: list[tuple[float, int, str]] = []
        self._timer: asyncio.TimerHandle | None = None
        self._busy_until = -float("inf")  # the chunks of the text being sent go out until then

    def offer(self, text: str, severity: int, key: str = "") -> None:
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no event loop (a plain script): nothing could send it later
            self.sent.append((self.clock(), severity, fit_text(text)))
            for msg in statustext_messages(self.link, text, severity):
                self.link.send(msg)
            return
        if self.pacer.offer(text, severity, self.clock(), key):
            self._schedule(loop)

    def _schedule(self, loop: asyncio.AbstractEventLoop) -> None:
        now = self.clock()
        at = self.pacer.next_at(now)
        if at is None or self._timer is not None:
            return
        self._timer = loop.call_later(max(0.0, max(at, self._busy_until) - now), self._flush, loop)

    def _flush(self, loop: asyncio.AbstractEventLoop) -> None:
        self._timer = None
        now = self.clock()
        item = self.pacer.take(now) if now >= self._busy_until else None
        if item is not None:
            severity, text = item
            self.sent.append((now, severity, text))
            msgs = statustext_messages(self.link, text, severity)
            self.link.send(msgs[0])
            for i, msg in enumerate(msgs[1:], 1):
                loop.call_later(i * self.chunk_gap_s, self.link.send, msg)
            self._busy_until = now + (len(msgs) - 1) * self.chunk_gap_s
        self._schedule(loop)


    def flush_all(self) -> int:
        """The service is stopping: send at once the texts still waiting that the pace allows in
        the last ``window_s`` (most severe first; nothing could send them later), and drop the
        rest (counted in the pacer's ``dropped``): a stop must not burst past the 4 texts in any
        10 s a ground station is promised. The number sent."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        last = self.pacer.drain(self.clock())
        for severity, text in last:
            self.told(text, severity)
        return len(last)

    def told(self, text: str, severity: int) -> None:
        """Send ``text`` now, past the queue, and count it in the pace."""
        now = self.clock()
        self.pacer.told(text, now)
        self.sent.append((now, severity, fit_text(text)))
        for msg in statustext_messages(self.link, text, severity):
            self.link.send(msg)


_outboxes: weakref.WeakKeyDictionary[MavLink, TextOutbox] = weakref.WeakKeyDictionary()


def attach_outbox(link: MavLink, outbox: TextOutbox | None = None) -> TextOutbox:
    """Give ``link`` a paced outbox (every ``send_statustext`` on it goes through it from now on)."""
    box = outbox or TextOutbox(link)
    _outboxes[link] = box
    return box


def outbox_of(link: MavLink) -> TextOutbox | None:
    """The link's outbox, if it has one."""
    return _outboxes.get(link)
