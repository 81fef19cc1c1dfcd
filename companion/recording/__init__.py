"""Flight recorder: frames as video segments plus JSON Lines of poses, telemetry and decisions.

One folder per run under the recorder's ``dir``::

    20261121T130000Z/
        meta.json             format version, intrinsics, mount, model, config, codec, start times
        frames-00000.jsonl    the frame index, one line per recorded frame: {"i", "t", "seg", "k", "pose"}
        events-00000.jsonl    telemetry, triggers, state changes, decisions: {"t", "kind", ...}
        seg_00000.avi         video segments (MJPG .avi or mp4v .mp4)

``i`` is the camera's frame index, ``t`` its capture time (monotonic seconds, the clock of the
vehicle state), ``seg``/``k`` the segment file and the frame's position in it, ``pose`` the vehicle
pose paired with the frame (world NED metres, radians) or null. A frame line is written only
after its image is in the segment, so every line points at a frame that was handed to the encoder.
The frame index and the events are each a stream of numbered *chunks*, read in number order.
Format 1 (recordings made before chunks) had one ``frames.jsonl`` and one ``events.jsonl``;
:class:`RecordingReader` reads both layouts.

Disk budget (``max_mb``, MiB): everything the recorder writes under ``dir``, every run, counts:
video, frame index, events and meta.json. Every file is written in pieces of ``piece`` =
``max_mb``/16 (at least 4 KiB, at most 64 MiB): a video segment ends after ``segment_s`` or when
its size on disk reaches a piece, a chunk when it reaches a piece. When a file is finished, the
oldest finished files (any kind, any run; a run left with only its meta.json is removed whole)
are deleted until the finished files fit in ``max_mb`` less the room of the files still to be
written (a video segment, a frame chunk, an events chunk; none once ``close()`` has finished
them): a piece each, and for the segment twice its writer's buffer too (the size on disk lags by
up to one buffer, and the rest reaches the disk when the segment ends): 8 KiB for MJPG, whose
JPEG bytes go straight to the file (``companion.avi``, ``AVI_BUFFER``), 256 KiB for OpenCV's
mp4v encoder (``ENCODER_BUFFER``). So the total never passes ``max_mb`` by more than the item
that completes a piece in each stream (one frame, one index line, one event line) and the
container index written when a segment ends -- the slack the tests allow. After ``close()`` the
total is within ``max_mb``. A frame whose segment or index chunk was deleted is skipped by the
reader.

Events are downsampled per kind and message type (``event_rates_hz``, default telemetry at
5 Hz): a token bucket on the events' own time ``t`` keeps at most that rate sustained, with
bursts of up to two seconds' worth (a burst of STATUSTEXT lines passes whole), and counts the
rest in ``stats.downsampled``. Trigger, phase, controller and zones events are never dropped.

Writing happens in one background thread behind a short queue: the service never waits for the
disk, and a frame that finds the queue full is counted in ``stats.dropped`` and not recorded.
Events are written by the caller (one ``write`` of a line). No write raises: a failure (ENOSPC
on a full disk, EIO, anything) is counted in ``stats.errors``, logged at most once per
10 s per kind of failure (:mod:`companion.logs`), a partly written line is cut off again, and
recording goes on with the next frame or event. ``close()`` never raises.

The parts, one concept each: ``layout`` (the format shared by both sides), ``chunks`` (the JSON
Lines streams), ``writer`` (:class:`FlightRecorder`: segments, events, the budget) and ``reader``
(:class:`RecordingReader`, used by replay and the simulator's judge). Every public name is
importable from ``companion.recording``.
"""

from companion.recording.layout import (
    FORMAT_VERSION,
    SUFFIX,
    THUMB,
    THUMB_TOLERANCE,
    RecordingError,
    pose_from_dict,
    pose_to_dict,
    stream_files,
    thumbnail,
)
from companion.recording.reader import ReadStats, RecordedFrame, RecordingReader
from companion.recording.writer import (
    BURST_S,
    DEFAULT_EVENT_RATES_HZ,
    ENCODER_BUFFER,
    JPEG_QUALITY,
    LOG_EVERY_S,
    NEVER_DOWNSAMPLED,
    PIECE_MAX,
    PIECE_MIN,
    FlightRecorder,
    MiB,
    RecorderStats,
)

__all__ = ["FlightRecorder", "RecordingReader", "RecordedFrame", "RecordingError", "RecorderStats",
           "pose_to_dict", "pose_from_dict", "stream_files", "ReadStats", "thumbnail", "FORMAT_VERSION",
           "SUFFIX", "THUMB", "THUMB_TOLERANCE", "JPEG_QUALITY", "MiB", "PIECE_MIN", "PIECE_MAX",
           "ENCODER_BUFFER", "DEFAULT_EVENT_RATES_HZ", "NEVER_DOWNSAMPLED", "BURST_S", "LOG_EVERY_S"]
