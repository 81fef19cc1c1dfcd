"""Lockstep flights: the simulator and the real service on one simulated clock, one flight per process.

A real-time flight (``sim.flights.flight``) runs the service as ``companion run`` in a subprocess and the
simulator on the wall clock. Whatever the operating system schedules decides when a frame is
processed and when a command lands, so the same seed does not always fly the same flight: two
sequential runs of ArduPilot seeds 1-50 changed 3 verdicts (docs/scale.md), and a busy machine
changes more. That is the right test of the service as it runs on a vehicle; it is the wrong tool
for telling whether a change to the landing logic changed a verdict.

A **lockstep** flight is the same flight made repeatable:

- the simulator, its camera and world, and the service (``companion.service.app.Service``, built
  from the same settings ``companion run`` would get, talking MAVLink over loopback UDP with the
  same link code) run in one process, on one event loop, :class:`VirtualTimeLoop`;
- that loop's clock is simulated: when nothing is ready to run and no datagram or byte is waiting
  on a socket, it jumps to its next timer instead of sleeping. ``time.monotonic()`` (and
  ``monotonic_ns``) read that clock for the duration of the flight (:func:`simulated_clock`), so
  every timestamp the service and the simulator take is on it;
- work the service and the camera hand to a worker thread (the pipeline's frame, the render) runs
  at once on the loop's thread, and its result arrives :data:`COMPUTE_S` of simulated time later:
  every frame costs the same time however long the CPU took, so no flight is starved and the
  ordering of everything is fixed;
- frames go from the simulated camera to the service's camera source on the loop
  (``sim.flights.inprocess.PushCamera``), JPEG-encoded and decoded as over MJPEG, with the capture time the MJPEG
  stream's ``X-Timestamp`` carries.

What it does not model: the service's real processing time (a flight on a slow CPU) and a starved
machine; those stay the real-time flights' job. Python's hash seed is fixed in the flight's process
(``PYTHONHASHSEED=0``) so nothing iterates a set in another order, and so is where the clock
starts (``FlightSpec.clock_start_s``, :data:`sim.flights.results.LOCKSTEP_CLOCK_START_S` by default): it
used to start at the real ``time.monotonic()``, the machine's uptime, and a flight's times then
rounded differently in their last bits from one hour to the next, which was enough to change
verdicts (seed 2 on ArduPilot: unsafe at 0.52, 0.74 or 1.33 m, or safe at 5.6 m, by the start
alone). Another start is the same scene flown again with that rounding changed: how far a
flight's verdict is from chance (``companion sim-scenarios --clock-start``).

``python -m sim.flights.lockstep`` flies one pickled :class:`~sim.flights.spec.FlightSpec` read from stdin and
writes the pickled :class:`~sim.flights.spec.FlightResult` to stdout: each flight gets a fresh process
(its clock and ``time.monotonic`` are the process's), whatever runs it (one after another, a
worker pool, a Ray task). :func:`fly_in_process` is that, from the parent's side.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import pickle
import selectors
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

from companion.parallel import die_with_parent
from sim.flights.flight import fly
from sim.flights.results import LOCKSTEP_CLOCK_START_S
from sim.flights.spec import FlightResult, FlightSpec

log = logging.getLogger("sim.flights.lockstep")

#: Simulated time (s) each piece of work handed to a worker thread takes: the service's frame
#: through the pipeline, the camera's render and encode. About what a frame costs the service on
#: the 2-core development VM (31-38 ms at the 95th percentile in real-time flights, docs/scale.md),
#: so a decision comes as late after its frame as it would on such a machine.
COMPUTE_S = 0.03
#: When nothing at all is scheduled (only another thread could wake the loop): real seconds to
#: wait for it before looking again.
IDLE_WAIT_S = 0.05
#: Real seconds a lockstep flight's process may take before it is killed: the guard against a
#: hung flight. A drawn flight of 150 simulated seconds takes 1-2 minutes of CPU; a photo world's
#: dense crowd 2.5-4 (PX4 seed 1: 156 s, 243 s before session 30), and on the 2-core machine
#: shared four ways that became more than 900 s of wall time: such a flight was lost, not flown
#: (docs/measurements.md, session 30).
PROCESS_TIMEOUT_S = 1800.0


class _JumpingSelector(selectors.BaseSelector):
    """A selector that, when no file is ready, moves its loop's clock to the next timer rather
    than waiting for it. Loopback UDP and TCP deliver at send, so "nothing readable now" means
    nothing is on its way."""

    def __init__(self, loop: VirtualTimeLoop) -> None:
        self._real = selectors.DefaultSelector()
        self._loop = loop

    def register(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        return self._real.register(fileobj, events, data)

    def unregister(self, fileobj: Any) -> selectors.SelectorKey:
        return self._real.unregister(fileobj)

    def modify(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        return self._real.modify(fileobj, events, data)

    def get_map(self) -> Any:
        return self._real.get_map()

    def close(self) -> None:
        self._real.close()

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        ready = self._real.select(0)
        if ready or timeout == 0:
            return ready
        if timeout is None:
            return self._real.select(IDLE_WAIT_S)
        self._loop.advance(timeout)
        return []


class VirtualTimeLoop(asyncio.SelectorEventLoop):
    """An event loop on a simulated clock (seconds, starting at ``start``, by default
    ``sim.flights.results.LOCKSTEP_CLOCK_START_S``, never the real ``time.monotonic()``: a flight's
    verdict can turn on how its times round, docs/scale.md): idle time is skipped, and
    ``run_in_executor`` (``asyncio.to_thread``) runs the function at once on the loop's thread and
    gives its result ``compute_s`` later."""

    #: What ``sim.flights.flight.fly`` checks before it flies a lockstep spec.
    lockstep = True

    def __init__(self, compute_s: float = COMPUTE_S, start: float | None = None) -> None:
        self._now = LOCKSTEP_CLOCK_START_S if start is None else float(start)
        self.compute_s = float(compute_s)
        self.work_items = 0  # pieces of work run for worker threads
        super().__init__(selector=_JumpingSelector(self))
        if not compute_s >= 0:
            self.close()
            raise ValueError(f"compute_s must be >= 0, got {compute_s!r}")

    def time(self) -> float:
        return self._now

    def advance(self, dt: float) -> None:
        """Move the clock ``dt`` seconds on (never back)."""
        if dt > 0:
            self._now += dt

    def run_in_executor(self, executor: Any, func: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:  # type: ignore[override]
        fut: asyncio.Future[Any] = self.create_future()
        self.work_items += 1
        try:
            value = func(*args)
        except (SystemExit, KeyboardInterrupt):
            raise
        except BaseException as exc:  # the caller's await raises it, as from a thread
            self.call_later(self.compute_s, _settle, fut, None, exc)
        else:
            self.call_later(self.compute_s, _settle, fut, value, None)
        return fut


def _settle(fut: asyncio.Future[Any], value: Any, exc: BaseException | None) -> None:
    if fut.done():  # its awaiter was cancelled meanwhile
        return
    if exc is not None:
        fut.set_exception(exc)
    else:
        fut.set_result(value)


@contextlib.contextmanager
def simulated_clock(loop: VirtualTimeLoop) -> Iterator[None]:
    """``time.monotonic()`` and ``time.monotonic_ns()`` read ``loop``'s clock inside the block
    (the service and the simulator stamp telemetry, frames and events with them)."""
    saved = time.monotonic, time.monotonic_ns
    time.monotonic = loop.time
    time.monotonic_ns = lambda: int(loop.time() * 1e9)
    try:
        yield
    finally:
        time.monotonic, time.monotonic_ns = saved


def fly_lockstep(spec: FlightSpec, compute_s: float = COMPUTE_S) -> FlightResult:
    """Fly ``spec`` on the simulated clock in this process (its ``time.monotonic`` is the
    flight's while it flies) and judge it as ``sim.flights.flight.fly`` does. Run it in a process of its
    own (:func:`fly_in_process`): the service's threads and clock are the process's."""
    spec = dataclasses.replace(spec, lockstep=True)
    loop = VirtualTimeLoop(compute_s, start=spec.clock_start_s)
    try:
        with simulated_clock(loop):
            asyncio.set_event_loop(loop)
            try:
                return loop.run_until_complete(fly(spec))
            finally:
                pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
                for task in pending:
                    task.cancel()
                if pending:
                    loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
                loop.run_until_complete(loop.shutdown_asyncgens())
    finally:
        asyncio.set_event_loop(None)
        loop.close()


class LockstepError(RuntimeError):
    """A lockstep flight's process failed (its stderr's tail says why)."""


def fly_in_process(spec: FlightSpec, timeout_s: float = PROCESS_TIMEOUT_S) -> FlightResult:
    """Fly ``spec`` in lockstep in a fresh process (``python -m sim.flights.lockstep``) and return its
    result; raises LockstepError when that process fails."""
    # The flight's process is also its service's: the spec's service_env applies to it.
    env = {**os.environ, **dict(spec.service_env), "PYTHONHASHSEED": "0"}
    env.pop("NOTIFY_SOCKET", None)
    env.pop("WATCHDOG_USEC", None)
    try:
        done = subprocess.run([sys.executable, "-m", "sim.flights.lockstep"], input=pickle.dumps(spec),
                              capture_output=True, env=env, timeout=timeout_s, preexec_fn=die_with_parent)
    except subprocess.TimeoutExpired as exc:
        raise LockstepError(f"the lockstep flight took more than {timeout_s:g} s") from exc
    if done.returncode != 0:
        tail = done.stderr.decode(errors="replace").strip().splitlines()[-15:]
        raise LockstepError(f"the lockstep flight's process exited {done.returncode}:\n" + "\n".join(tail))
    result = pickle.loads(done.stdout)
    if not isinstance(result, FlightResult):
        raise LockstepError(f"the lockstep flight's process returned {type(result).__name__}")
    return result


def main() -> int:
    """Read a pickled FlightSpec on stdin, fly it in lockstep, write the pickled FlightResult."""
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    spec = pickle.loads(sys.stdin.buffer.read())
    if not isinstance(spec, FlightSpec):
        print(f"sim.flights.lockstep: expected a pickled FlightSpec, got {type(spec).__name__}", file=sys.stderr)
        return 2
    result = fly_lockstep(spec)
    sys.stdout.buffer.write(pickle.dumps(result))
    sys.stdout.buffer.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
