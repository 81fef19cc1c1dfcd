"""Commands that tests run as processes of their own (mypy: 10-20 s on two cores; ``companion
...`` start-ups: a second or two each), started as soon as the session knows it will run the
tests that assert on them, instead of when those tests' turn comes.

They then run beside the tests before them (the fast lane is one process, mostly on one core:
the other is free), one at a time (tests/early_runner.py), and each test waits for its commands
and asserts on what they did as it always did: the same commands on the same inputs. A batch is
a function registered with :func:`batch` that writes its inputs into the folder it is given and
returns its commands; a test marked ``@pytest.mark.started_early("name")`` gets them done from
:func:`result`. tests/conftest.py starts the marked tests' batches once collection is done, in
the order of the tests, and ends what is still running at the session's end (a run stopped by
``-x``). Nothing is started early under ``--collect-only`` nor under pytest-xdist (every worker
collects every test, and only one runs each): :func:`result` then runs the batch on the spot,
its commands side by side.

A test whose claim is on what a computation of seconds returns (frames rendered and read by the
model, a photo world built), not on a process, can have it done the same way: :func:`call` is the
command that calls a module-level function with the same arguments in a process of its own, and
:func:`returned` gives what it returned (pickled there, unpickled here).
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
#: The longest a test waits for its batch, queue included (mypy alone takes 10-20 s).
TIMEOUT_S = 600.0


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


def call(out: Path, fn: Callable[..., Any], *args: Any) -> Run:
    """The command that calls ``fn`` (a module-level function) with ``args`` (JSON: numbers,
    strings, lists) in a process of its own and writes what it returns, pickled, to ``out``
    (tests/early_call.py)."""
    return Run([sys.executable, "-m", "tests.early_call", str(out), f"{fn.__module__}:{fn.__qualname__}",
                json.dumps(list(args))])


def returned(name: str, index: int = 0) -> Any:
    """What the function of ``name``'s ``index``-th command (:func:`call`) returned; its
    traceback if it raised."""
    done = result(name)[1][index]
    if done.returncode != 0:
        raise RuntimeError(f"{done.args} ended {done.returncode}:\n{done.stderr}")
    return pickle.loads(Path(done.args[3]).read_bytes())


@batch("mypy")
def _mypy(folder: Path) -> list[Run]:
    return [Run([str(BIN / "mypy")])]  # pyproject.toml's settings, from the repository's root


@dataclass(frozen=True)
class _Queued:
    folder: Path
    runs: list[Run]
    files: list[tuple[Path, Path, Path]]  # stdout, stderr, exit status of each run


_folders: list[Path] = []
_queued: dict[str, _Queued] = {}
_done: dict[str, tuple[Path, list[subprocess.CompletedProcess[str]]]] = {}
_runner: subprocess.Popen[bytes] | None = None


def _folder(name: str) -> Path:
    path = Path(tempfile.mkdtemp(prefix=f"early-{name}-"))
    _folders.append(path)
    return path


def start(names: list[str]) -> None:
    """Write the inputs of the batches ``names`` and hand their commands, in that order, to one
    runner process that runs them one at a time."""
    global _runner
    jobs = []
    for name in dict.fromkeys(names):
        if name in _queued or name in _done:
            continue
        folder = _folder(name)
        runs = BATCHES[name](folder)
        files = [(folder / f".out{k}", folder / f".err{k}", folder / f".status{k}") for k in range(len(runs))]
        _queued[name] = _Queued(folder, runs, files)
        jobs += [{"argv": run.argv, "cwd": str(run.cwd or REPO), "env": run.env if run.env is not None else dict(os.environ),
                  "out": str(out), "err": str(err), "status": str(status)}
                 for run, (out, err, status) in zip(runs, files, strict=True)]
    if not jobs:
        return
    spec = _folder("jobs") / "jobs.json"
    spec.write_text(json.dumps(jobs))
    _runner = subprocess.Popen([sys.executable, str(Path(__file__).with_name("early_runner.py")), str(spec)],
                               stdin=subprocess.DEVNULL, start_new_session=True)


def _wait_for(queued: _Queued) -> list[subprocess.CompletedProcess[str]]:
    deadline = time.monotonic() + TIMEOUT_S
    done = []
    for run, (out, err, status) in zip(queued.runs, queued.files, strict=True):
        while not status.exists():
            if _runner is not None and _runner.poll() is not None and not status.exists():
                raise RuntimeError(f"tests/early_runner.py ended ({_runner.returncode}) before {run.argv} was run")
            if time.monotonic() > deadline:
                raise TimeoutError(f"{run.argv} not done in {TIMEOUT_S:.0f} s")
            time.sleep(0.02)
        done.append(subprocess.CompletedProcess(run.argv, int(status.read_text()), out.read_text(), err.read_text()))
    return done


def _run_now(folder: Path, runs: list[Run]) -> list[subprocess.CompletedProcess[str]]:
    procs = [subprocess.Popen(run.argv, cwd=run.cwd or REPO, env=run.env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for run in runs]
    done = []
    for run, proc in zip(runs, procs, strict=True):
        out, err = proc.communicate(timeout=TIMEOUT_S)
        done.append(subprocess.CompletedProcess(run.argv, proc.returncode, out, err))
    return done


def result(name: str) -> tuple[Path, list[subprocess.CompletedProcess[str]]]:
    """``name``'s folder and what each of its commands did, in order: those of the early start
    waited for, or the batch run now; once done, the same for every test that asks (several
    tests may assert on one batch)."""
    if name not in _done:
        queued = _queued.pop(name, None)
        if queued is not None:
            _done[name] = (queued.folder, _wait_for(queued))
        else:
            folder = _folder(name)
            _done[name] = (folder, _run_now(folder, BATCHES[name](folder)))
    return _done[name]


def stop_all() -> None:
    """End the runner and what it runs (the session stopped before some tests ran), and remove
    every batch's folder."""
    global _runner
    if _runner is not None and _runner.poll() is None:
        try:
            os.killpg(_runner.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        _runner.wait()
    _runner = None
    _queued.clear()
    _done.clear()
    while _folders:
        shutil.rmtree(_folders.pop(), ignore_errors=True)
