"""Fan one function out over many items: in this process, in worker processes, or on a Ray cluster.

The scenario runner (``companion sim-scenarios``) and batch replay (``companion replay`` with
several inputs) both need "run this for each item and hand me the results as they finish". This
module is that, once:

- ``workers=1`` without Ray: one after another, in this process (what a test or a debugger wants);
- ``workers=N``: a ``ProcessPoolExecutor`` of N processes started with ``spawn`` (each item gets
  a clean interpreter state: no inherited event loop, threads or sockets);
- ``ray_address``: each item is a Ray task needing ``cpus_per_task`` CPUs, on the cluster at that
  address; ``"auto"`` is ``ray.init()`` without an address: the cluster in ``RAY_ADDRESS`` or one
  started with ``ray start`` on this machine, else a local instance started here. Ray is the optional extra
  ``scale`` (``pip install '.[scale]'``); without it a clear :class:`ParallelError` says so.

``fn`` must be a module-level function (it is pickled) and its results picklable. An exception
raised by ``fn`` for one item is yielded as that item's result, never raised: one bad item does
not stop the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")


class ParallelError(RuntimeError):
    """The fan-out cannot start (Ray missing or unreachable, a bad worker count)."""


def default_workers(cpus_per_task: float = 1.0) -> int:
    """As many workers as the machine's CPUs hold at ``cpus_per_task`` each (at least 1)."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, int(cpus // max(cpus_per_task, 1e-9)))


def die_with_parent() -> None:
    """Make this process get SIGTERM when its parent dies (Linux; elsewhere a no-op, and a normal
    exit still cleans up). Two users: a flight's service (its ``preexec_fn``), so a killed
    ``sim-scenarios`` or cancelled Ray task leaves no service busy with a camera that is gone; and
    the pool's workers (their initializer), so a ``--workers N`` run killed by SIGTERM or SIGKILL
    no longer leaves its workers flying the seeds they held to the end (found on 2026-11-25: a
    killed run's two flights went on, services and all)."""
    if sys.platform != "linux":
        return
    import ctypes
    import signal

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def fan_out(fn: Callable[[T], R], items: Sequence[T], *, workers: int = 1, ray_address: str | None = None,
            cpus_per_task: float = 1.0) -> Iterator[tuple[T, R | BaseException]]:
    """``(item, fn(item))`` for every item, in the order they finish; an exception stands in for
    the result of an item whose call raised."""
    if workers < 1:
        raise ParallelError(f"workers must be >= 1, got {workers}")
    if ray_address is not None:
        yield from _ray(fn, items, ray_address, cpus_per_task)
    elif workers == 1 or len(items) <= 1:
        for item in items:
            try:
                yield item, fn(item)
            except Exception as exc:  # reported with the item, never stops the others
                yield item, exc
    else:
        ctx = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=ctx,
                                    initializer=die_with_parent) as pool:
            futures = {pool.submit(fn, item): item for item in items}
            try:
                for fut in cf.as_completed(futures):
                    error = fut.exception()
                    yield futures[fut], (error if error is not None else fut.result())
            finally:
                for fut in futures:
                    fut.cancel()


def _ray(fn: Callable[[T], R], items: Sequence[T], address: str, cpus_per_task: float
         ) -> Iterator[tuple[T, R | BaseException]]:
    try:
        import ray
    except ImportError:
        raise ParallelError("--ray needs Ray: pip install '.[scale]'") from None
    started_here = not ray.is_initialized()
    if started_here:
        try:
            if address == "auto":
                # RAY_ADDRESS or a `ray start` cluster on this machine, else a local instance on
                # loopback owned by this run (shut down at the end).
                ray.init(include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=address, log_to_driver=False)
        except Exception as exc:  # ConnectionError and Ray's own errors
            raise ParallelError(f"cannot reach the Ray cluster at {address!r}: {exc}") from None
    try:
        remote = ray.remote(num_cpus=cpus_per_task, max_retries=0)(fn)
        pending: dict[Any, T] = {remote.remote(item): item for item in items}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                item = pending.pop(ref)
                try:
                    yield item, ray.get(ref)
                except Exception as exc:  # ray.exceptions.RayTaskError wraps fn's exception
                    cause = getattr(exc, "cause", None)
                    yield item, cause if isinstance(cause, BaseException) else exc
    finally:
        if started_here:
            ray.shutdown()
