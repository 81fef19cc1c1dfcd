"""The recording's JSON Lines streams (the frame index and the events): how a line is encoded
(numpy values, dataclasses and paths made plain; NaN and inf written as null) and how a stream is
written as numbered chunks of a budget's piece each, one unbuffered write per line."""

from __future__ import annotations

import io
import json
import logging
import math
import os
import threading
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

#: The package's one logger, named as the single module was, so that log lines and filters on
#: ``companion.recording`` read the same whichever part of the recorder speaks.
log = logging.getLogger("companion.recording")


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "__dataclass_fields__"):
        return asdict(o)
    return str(o)


def _dumps(obj: Any) -> str:
    def clean(v: Any) -> Any:  # JSON has no NaN/inf: write null rather than an unreadable file
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    return json.dumps(clean(json.loads(json.dumps(obj, default=_json_default))), separators=(",", ":"))



class _Chunks:
    """One JSON Lines stream written as ``<stem>-00000.jsonl``, ``-00001``, ...: a chunk is
    finished once it holds ``piece`` bytes, and handed to ``finished(path, size)``. Unbuffered:
    one write per line, nothing held back to fail later in close(). A failed or short write
    raises OSError after cutting the chunk back to its last whole line."""

    def __init__(self, folder: Path, stem: str, piece: int,
                 finished: Callable[[Path, int], None]) -> None:
        self.folder, self.stem, self.piece, self._finished = folder, stem, piece, finished
        self._fh: io.FileIO | None = None
        self._path: Path | None = None
        self._size = 0
        self._no = 0
        self._closed = False
        self._lock = threading.Lock()

    def write(self, line: str) -> None:
        data = (line + "\n").encode("utf-8")
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.stem} stream is closed")
            fh = self._fh
            if fh is None:
                path = self.folder / f"{self.stem}-{self._no:05d}.jsonl"
                fh = self._fh = open(path, "ab", buffering=0)
                self._path, self._size = path, fh.tell()
                self._no += 1
            try:
                n = fh.write(data)
                if n != len(data):
                    raise OSError(f"short write to {self._path} ({n} of {len(data)} bytes): disk full?")
            except OSError:
                try:
                    os.ftruncate(fh.fileno(), self._size)  # no half line left behind
                except OSError:
                    pass
                raise
            self._size += len(data)
            if self._size >= self.piece:
                self._finish()

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Finish the open chunk; never raises."""
        with self._lock:
            self._closed = True
            self._finish()

    def _finish(self) -> None:
        fh, path, size = self._fh, self._path, self._size
        self._fh, self._path, self._size = None, None, 0
        if fh is None or path is None:
            return
        try:
            fh.close()
        except OSError as exc:
            log.warning("recorder: closing %s: %s", path, exc)
        self._finished(path, size)
