"""Human-readable events for the ground station as STATUSTEXT.

A STATUSTEXT carries 50 bytes; longer texts are sent in chunks sharing a non-zero ``id`` with
``chunk_seq`` 0, 1, ... as MAVLink 2 specifies (the last chunk shorter than 50 bytes, or a
NUL-padded one, ends the text).
"""

from __future__ import annotations

import itertools

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.control.events import Event, HandedBack, Holding, Note, TargetChosen
from companion.mavlink.link import MavLink

STATUSTEXT_LEN = 50
_ids = itertools.count(1)


def statustext_chunks(text: str) -> list[bytes]:
    """The 50-byte (or shorter, final) UTF-8 chunks of ``text``, never splitting a character."""
    data = text.encode("utf-8")
    chunks: list[bytes] = []
    while data:
        cut = min(STATUSTEXT_LEN, len(data))
        while cut < len(data) and cut > 0 and (data[cut] & 0xC0) == 0x80:
            cut -= 1  # back up to a character boundary
        chunks.append(data[:cut])
        data = data[cut:]
    return chunks or [b""]


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


def send_statustext(link: MavLink, text: str, severity: int = m.MAV_SEVERITY_INFO) -> None:
    """Send ``text`` (any length) with MAV_SEVERITY ``severity``, chunked when over 50 bytes."""
    chunks = statustext_chunks(text)
    msg_id = 0 if len(chunks) == 1 else (next(_ids) % 65535) + 1
    for seq, chunk in enumerate(chunks):
        link.send(link.mav.statustext_encode(severity, chunk, msg_id, seq))
    if msg_id and len(chunks[-1]) == STATUSTEXT_LEN:
        link.send(link.mav.statustext_encode(severity, b"", msg_id, len(chunks)))  # terminator
