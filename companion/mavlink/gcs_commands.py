"""What a ground station asks the companion, answered: a COMMAND_ACK for every command.

Ground stations expect an answer to every ``COMMAND_LONG`` / ``COMMAND_INT`` they address to a
component (``UNSUPPORTED`` is an answer; silence makes them retry and then report a timeout).
``CommandServer`` listens for commands from every system on the companion's link and answers
those addressed to the companion's system and component:

- a registered command gets what its handler returns: ``ACCEPTED`` (and the messages asked for,
  sent after the ack, as ArduPilot and PX4 do), or ``DENIED`` / ``UNSUPPORTED`` / ``FAILED`` with
  the reason as a STATUSTEXT (within 50 characters, the same text at most once per
  ``TEXT_REPEAT_S``);
- any other command gets ``UNSUPPORTED``;
- a broadcast (target system 0 or target component 0, "every component") is answered only for
  commands the companion handles, and a handler may decline one (``None``): the trigger does,
  ``MAV_CMD_USER_1`` being user-defined, so only a command addressed to the companion itself is
  a trigger;
- commands for another system or component are not ours and get no answer; parameters that make
  no sense (NaN where an id is needed) are counted (``stats.malformed``) and refused, never raised.

Built in: the camera's description (``CAMERA_INFORMATION``, asked for by
``MAV_CMD_REQUEST_MESSAGE`` 259 or the legacy ``MAV_CMD_REQUEST_CAMERA_INFORMATION``) and the
live view (``VIDEO_STREAM_INFORMATION``, by ``MAV_CMD_REQUEST_MESSAGE`` 269 or
``MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION``) from a provider that returns the stream, or None
while there is none (then ``UNSUPPORTED``, "no live view configured"). Nothing here commands the
vehicle: the only command that leads to flight is the trigger, which the failsafe monitor
registers (``FailsafeMonitor.trigger_command``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.link import MavLink, Message, command_name, result_name
from companion.mavlink.statustext import send_statustext

log = logging.getLogger(__name__)

#: The same STATUSTEXT is not repeated within this many seconds (a retrying or flooding sender
#: must not fill the radio link with refusals).
TEXT_REPEAT_S = 2.0
NO_LIVE_VIEW_TEXT = "SLZ: no live view configured"


@dataclass(frozen=True)
class Reply:
    """The answer to one command: its MAV_RESULT, an optional STATUSTEXT saying why, the
    messages to send after the ack (the information asked for), and what to do once the ack is
    out (``then``: the trigger fires after its ACCEPTED has been sent)."""

    result: int
    text: str | None = None
    severity: int = m.MAV_SEVERITY_WARNING
    messages: tuple[Message, ...] = ()
    then: Callable[[], object] | None = None


#: ``handler(command message, receive time s, broadcast) -> Reply``, or None to stay silent
#: (a broadcast the handler does not take).
CommandHandler = Callable[[Message, float, bool], "Reply | None"]


@dataclass(frozen=True)
class CameraInfo:
    """The companion's camera as CAMERA_INFORMATION describes it.

    Resolution in pixels; focal length and sensor size in millimetres, NaN where unknown (the
    intrinsics are in pixels: millimetres need the sensor's width). Names are sent as 32 bytes
    each (UTF-8, cut at 32, NUL-padded).
    """

    width: int
    height: int
    focal_length_mm: float = math.nan
    sensor_width_mm: float = math.nan
    sensor_height_mm: float = math.nan
    vendor: str = "companion-slz"
    model: str = "SLZ downward camera"


@dataclass(frozen=True)
class VideoStream:
    """The companion's live view as VIDEO_STREAM_INFORMATION describes it.

    ``uri`` at most 160 bytes (MAVLink's field); resolution in pixels, framerate in Hz,
    ``hfov_deg`` the horizontal field of view in degrees, bitrate in bit/s (0 = unknown).
    ``stream_type`` is a MAVLink ``VIDEO_STREAM_TYPE`` and ``encoding`` a
    ``VIDEO_STREAM_ENCODING``: MAVLink has no MJPEG-over-HTTP type; the provider says which it
    serves.
    """

    uri: str
    width: int
    height: int
    framerate_hz: float
    name: str = "SLZ live view"
    stream_type: int = m.VIDEO_STREAM_TYPE_TCP_MPEG
    encoding: int = m.VIDEO_STREAM_ENCODING_UNKNOWN
    hfov_deg: float = 0.0
    bitrate_bps: int = 0

    def __post_init__(self) -> None:
        if not self.uri or len(self.uri.encode()) > 160:
            raise ValueError(f"video stream uri must be 1..160 bytes, got {self.uri!r}")
        if not (0 < self.width <= 65535 and 0 < self.height <= 65535):
            raise ValueError(f"video stream resolution {self.width}x{self.height} out of range")
        if not (math.isfinite(self.framerate_hz) and self.framerate_hz > 0):
            raise ValueError(f"video stream framerate must be > 0 Hz, got {self.framerate_hz!r}")


#: Returns the live view now, or None while there is none.
VideoStreamProvider = Callable[[], "VideoStream | None"]


def no_live_view() -> VideoStream | None:
    """The provider while the companion serves no live view."""
    return None


@dataclass
class CommandStats:
    received: int = 0    # commands seen on the link, from anyone to anyone
    not_ours: int = 0    # for another system or component: not answered
    answered: int = 0    # acks sent
    accepted: int = 0
    refused: int = 0     # DENIED / FAILED / UNSUPPORTED ... sent
    silent: int = 0      # broadcasts not taken
    malformed: int = 0   # parameters that made no sense (refused)


def _fixed(text: str, size: int) -> bytes:
    """``text`` as exactly ``size`` bytes (UTF-8, cut, NUL-padded): MAVLink's uint8_t[size]."""
    return text.encode()[:size].ljust(size, b"\0")


class CommandServer:
    """Answers the commands a ground station addresses to the companion (see the module)."""

    def __init__(self, link: MavLink, camera: CameraInfo | None = None,
                 video: VideoStreamProvider = no_live_view, *,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.link = link
        self.camera = camera
        self.video = video
        self.stats = CommandStats()
        self._clock = clock
        self._start = clock()
        self._texts: dict[str, float] = {}
        self._handlers: dict[int, CommandHandler] = {}
        if camera is not None:
            self.register(m.MAV_CMD_REQUEST_CAMERA_INFORMATION, self._request_camera_information)
        self.register(m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, self._request_video_stream)
        self.register(m.MAV_CMD_REQUEST_MESSAGE, self._request_message)

    def attach(self) -> None:
        """Listen for COMMAND_LONG and COMMAND_INT from every system."""
        self.link.subscribe("COMMAND_LONG", self.handle, any_source=True)
        self.link.subscribe("COMMAND_INT", self.handle, any_source=True)

    def register(self, command: int, handler: CommandHandler) -> None:
        """Answer ``command`` with ``handler`` (replaces an earlier one)."""
        self._handlers[command] = handler

    # -- dispatch ------------------------------------------------------------------------------

    def handle(self, msg: Message, t: float) -> None:
        """One COMMAND_LONG / COMMAND_INT received at monotonic ``t`` (s)."""
        self.stats.received += 1
        cfg = self.link.config
        ts, tc = int(msg.target_system), int(msg.target_component)
        if ts not in (0, cfg.system_id) or tc not in (0, cfg.component_id):
            self.stats.not_ours += 1
            return
        if (msg.get_srcSystem(), msg.get_srcComponent()) == (cfg.system_id, cfg.component_id):
            return  # our own, heard back
        broadcast = ts == 0 or tc == 0
        handler = self._handlers.get(int(msg.command))
        reply: Reply | None
        if handler is None:
            reply = None if broadcast else Reply(m.MAV_RESULT_UNSUPPORTED)
        else:
            try:
                reply = handler(msg, t, broadcast)
            except (ValueError, TypeError, OverflowError) as exc:
                self.stats.malformed += 1
                log.info("%s from system %d refused: %s", command_name(int(msg.command)),
                         msg.get_srcSystem(), exc)
                reply = None if broadcast else Reply(m.MAV_RESULT_DENIED)
        if reply is None:
            self.stats.silent += 1
            return
        self.reply(msg, reply)

    def reply(self, msg: Message, reply: Reply) -> None:
        """Ack ``msg`` to its sender with ``reply``, then its messages, then its text."""
        send_reply(self.link, msg, reply)
        self.stats.answered += 1
        if reply.result == m.MAV_RESULT_ACCEPTED:
            self.stats.accepted += 1
        else:
            self.stats.refused += 1
            log.info("%s from system %d: %s%s", command_name(int(msg.command)), msg.get_srcSystem(),
                     result_name(reply.result), f" ({reply.text})" if reply.text else "")
        if reply.text and self._text_due(reply.text):
            send_statustext(self.link, reply.text, reply.severity)
        if reply.then is not None:
            reply.then()

    def _text_due(self, text: str) -> bool:
        now = self._clock()
        if now - self._texts.get(text, -math.inf) < TEXT_REPEAT_S:
            return False
        if len(self._texts) > 64:
            self._texts.clear()
        self._texts[text] = now
        return True

    # -- built-in requests ---------------------------------------------------------------------

    def _request_message(self, msg: Message, t: float, broadcast: bool) -> Reply | None:
        msg_id = _message_id(msg.param1)
        if msg_id == m.MAVLINK_MSG_ID_CAMERA_INFORMATION and self.camera is not None:
            return Reply(m.MAV_RESULT_ACCEPTED, messages=(self.camera_information(),))
        if msg_id == m.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION:
            return self._video_reply(msg.param2, broadcast)
        return None if broadcast else Reply(m.MAV_RESULT_UNSUPPORTED)

    def _request_camera_information(self, msg: Message, t: float, broadcast: bool) -> Reply | None:
        if _message_id(msg.param1) == 0:
            return Reply(m.MAV_RESULT_ACCEPTED)  # param1 0: "no action"
        return Reply(m.MAV_RESULT_ACCEPTED, messages=(self.camera_information(),))

    def _request_video_stream(self, msg: Message, t: float, broadcast: bool) -> Reply | None:
        return self._video_reply(msg.param1, broadcast)

    def _video_reply(self, stream_param: float, broadcast: bool) -> Reply | None:
        stream_id = _message_id(stream_param)  # 0 = all streams, 1 = the first
        try:
            stream = self.video()
        except Exception:
            log.exception("the live view provider failed")
            return None if broadcast else Reply(m.MAV_RESULT_FAILED, "SLZ: live view info failed")
        if stream is None:
            return None if broadcast else Reply(m.MAV_RESULT_UNSUPPORTED, NO_LIVE_VIEW_TEXT)
        if stream_id not in (0, 1):
            return None if broadcast else Reply(m.MAV_RESULT_DENIED, f"SLZ: no video stream {stream_id}")
        return Reply(m.MAV_RESULT_ACCEPTED, messages=(self.video_stream_information(stream),))

    def camera_information(self) -> Message:
        """CAMERA_INFORMATION for the configured camera (``self.camera`` must be set)."""
        c = self.camera
        assert c is not None
        flags = m.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM if self._has_stream() else 0
        return self.link.mav.camera_information_encode(
            self._boot_ms(), _fixed(c.vendor, 32), _fixed(c.model, 32), 0,
            c.focal_length_mm, c.sensor_width_mm, c.sensor_height_mm, c.width, c.height,
            0, flags, 0, b"")

    def video_stream_information(self, s: VideoStream) -> Message:
        """VIDEO_STREAM_INFORMATION for stream 1 of 1, running."""
        return self.link.mav.video_stream_information_encode(
            1, 1, s.stream_type, m.VIDEO_STREAM_STATUS_FLAGS_RUNNING, s.framerate_hz, s.width,
            s.height, s.bitrate_bps, 0, int(round(s.hfov_deg)) % 65536, _fixed(s.name, 32),
            _fixed(s.uri, 160), s.encoding)

    def _has_stream(self) -> bool:
        try:
            return self.video() is not None
        except Exception:
            return False

    def _boot_ms(self) -> int:
        return int((self._clock() - self._start) * 1000) % 2**32


def _message_id(value: float) -> int:
    """A command parameter that holds an id: a whole number 0..2**24, else ValueError."""
    v = float(value)
    if not math.isfinite(v) or v < 0 or v > 2**24 or v != int(v):
        raise ValueError(f"{value!r} is not an id")
    return int(v)


def send_reply(link: MavLink, msg: Message, reply: Reply) -> None:
    """COMMAND_ACK for ``msg`` to its sender, then the reply's messages (its text is the caller's)."""
    link.send(link.mav.command_ack_encode(int(msg.command), reply.result, 0, 0,
                                          msg.get_srcSystem(), msg.get_srcComponent()))
    for out in reply.messages:
        link.send(out)
