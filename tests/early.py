"""Commands that tests run as processes of their own (mypy: 10-20 s on two cores; ``companion
...`` start-ups: a second or two each), started as soon as the session knows it will run the
tests that assert on them, instead of when those tests' turn comes.

They then run beside the tests before them (the fast lane is one process, mostly on one core:
the other is free), and each test waits for its commands and asserts on what they did as it
always did: the same commands on the same inputs. A batch is a function registered with
:func:`batch` that writes its inputs into the folder it is given and returns its commands; a test
marked ``@pytest.mark.started_early("name")`` gets them done from :func:`result`. tests/conftest.py
starts the marked tests' batches once collection is done, and ends any still running at the
session's end (a run stopped by ``-x``). Nothing is started early under ``--collect-only`` nor
under pytest-xdist (every worker collects every test, and only one runs each): :func:`result`
then runs the batch on the spot.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
TIMEOUT_S = 240.0


@dataclass(frozen=True)
class Run:
    """One command: argv, run in ``cwd`` (default: the repository) with ``env`` (default: ours)."""

    argv: list[str]
    cwd: Path | None = None
    env: dict[str, str] | None = None


Batch = Callable[[Path], list[Run]]
BATCHES: dict[str, Batch] = {}


def batch(name: str) -> Callable[[Batch], Batch]:
    """Register a batch under ``name`` (a test module does so when it is imported)."""
    def register(fn: Batch) -> Batch:
        BATCHES[name] = fn
        return fn
    return register


@batch("mypy")
def _mypy(folder: Path) -> list[Run]:
    return [Run([str(BIN / "mypy")])]  # pyproject.toml's settings, from the repository's root


@dataclass
class _Started:
    folder: Path
    runs: list[Run]
    procs: list[tuple[subprocess.Popen[str], IO[str], IO[str]]] = field(default_factory=list)


_started: dict[str, _Started] = {}
_done: dict[str, tuple[Path, list[subprocess.CompletedProcess[str]]]] = {}
_folders: list[Path] = []


def _folder(name: str) -> Path:
    path = Path(tempfile.mkdtemp(prefix=f"early-{name}-"))
    _folders.append(path)
    return path


def _popen(run: Run) -> tuple[subprocess.Popen[str], IO[str], IO[str]]:
    # Output to temporary files: a pipe nobody reads until the test's turn would fill and stall it.
    out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
    proc = subprocess.Popen(run.argv, cwd=run.cwd or REPO, env=run.env, stdout=out, stderr=err, text=True)
    return proc, out, err


def start(name: str) -> None:
    """Write ``name``'s inputs and start its commands now."""
    if name in _started:
        return
    folder = _folder(name)
    runs = BATCHES[name](folder)
    started = _Started(folder, runs)
    _started[name] = started
    try:
        for run in runs:
            started.procs.append(_popen(run))
    except OSError:  # a tool that is not there: the test runs the batch itself, and says so
        _end(_started.pop(name))


def _end(started: _Started) -> None:
    for proc, out, err in started.procs:
        proc.kill()  # nothing to a process that has exited
        proc.wait()
        out.close()
        err.close()


def result(name: str) -> tuple[Path, list[subprocess.CompletedProcess[str]]]:
    """``name``'s folder and what each of its commands did, in order: those of the early start
    waited for, or the batch run now, its commands side by side; once done, the same for every
    test that asks (several tests may assert on one batch)."""
    if name in _done:
        return _done[name]
    started = _started.pop(name, None)
    if started is None:
        folder = _folder(name)
        started = _Started(folder, BATCHES[name](folder))
        started.procs = [_popen(run) for run in started.runs]
    try:
        done = []
        for run, (proc, out, err) in zip(started.runs, started.procs, strict=True):
            code = proc.wait(timeout=TIMEOUT_S)
            out.seek(0)
            err.seek(0)
            done.append(subprocess.CompletedProcess(run.argv, code, out.read(), err.read()))
        _done[name] = (started.folder, done)
        return _done[name]
    finally:
        _end(started)


def stop_all() -> None:
    """End the commands no test waited for, and remove every batch's folder."""
    _done.clear()
    while _started:
        _end(_started.popitem()[1])
    while _folders:
        shutil.rmtree(_folders.pop(), ignore_errors=True)

