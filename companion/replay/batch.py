"""``companion replay`` over several inputs (a fleet's recordings): one folder each, one table.

Each input is replayed by the same function as a single replay (``cli.replay_job`` ->
``cli.replay_input``), through :func:`companion.parallel.fan_out`: one after another in this
process, in ``--workers`` processes, or as Ray tasks. An input that fails is an error row of the
table; it never stops the others.

Layout under ``--out-dir DIR``::

    DIR/summary.json, DIR/summary.csv     the table: one row per input (COLUMNS)
    DIR/<NAME>/frames.jsonl               the input's per-frame records (as --jsonl)
    DIR/<NAME>/summary.json               its summary (as --summary-json)
    DIR/<NAME>/video.mp4                  its annotated video, with --videos

``NAME`` is the input's last path component, made unique by prepending parent folders (then a
``-2``, ``-3`` suffix) and safe by replacing other characters than letters, digits, ``_`` and
``-`` with ``_``.

Exit status: 0 when every input replayed, 1 when some failed but at least one replayed, 2 when
none could. An input "replayed" when at least one of its frames was processed.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import glob
import json
import logging
import os
import re
import sys
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.parallel import ParallelError, default_workers, fan_out

log = logging.getLogger(__name__)

FRAMES_NAME = "frames.jsonl"
SUMMARY_NAME = "summary.json"
VIDEO_NAME = "video.mp4"
TABLE_JSON = "summary.json"
TABLE_CSV = "summary.csv"

#: The summary table's columns (DIR/summary.csv's header, the keys of DIR/summary.json's rows).
COLUMNS = ("input", "name", "kind", "status", "frames", "frames_skipped", "frames_with_target",
           "target_switches", "time_on_target_s", "settings", "error")

OK, ERROR = "ok", "error"


class InputFailed(Exception):
    """One input cannot be replayed; the message (naming the file and the problem) is its row's
    ``error``."""


class BatchError(RuntimeError):
    """The batch cannot run at all (output folder not writable, Ray missing or unreachable)."""


def parse_workers(text: str) -> int | str:
    """``--workers``: an integer >= 1, or ``auto``."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 1 or auto, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {n}")
    return n


@dataclass(frozen=True)
class Input:
    """One input as given (or as a pattern expanded to); ``problem`` when it is unusable as such."""

    path: str
    problem: str | None = None


_MAGIC = re.compile(r"[*?[]")


def expand_inputs(args: Sequence[str]) -> list[Input]:
    """The inputs named by ``args``: a shell-style pattern (``*``, ``?``, ``[...]``, ``**``) that
    the shell left alone and that is no existing path is expanded here (sorted); one matching
    nothing is kept as an unusable input. A path given twice is replayed once."""
    out: list[Input] = []
    seen: set[str] = set()
    for text in args:
        if _MAGIC.search(text) and not os.path.lexists(text):
            matches = sorted(glob.glob(text, recursive=True))
            if not matches:
                out.append(Input(text, f"no input matches the pattern {text!r}"))
                continue
        else:
            matches = [text]
        for m in matches:
            key = os.path.normcase(os.path.abspath(m))
            if key in seen:
                log.warning("%s is given more than once: replayed once", m)
                continue
            seen.add(key)
            out.append(Input(m))
    return out


_UNSAFE = re.compile(r"[^A-Za-z0-9_-]+")


def _clean(part: str) -> str:
    return _UNSAFE.sub("_", part).strip("_")


def output_names(paths: Sequence[str]) -> list[str]:
    """A unique, file-system-safe folder name for each path (see the module docstring)."""
    parts = [tuple(c for c in map(_clean, Path(os.path.abspath(p)).parts[1:]) if c) or ("input",)
             for p in paths]
    distinct = list(dict.fromkeys(parts))  # the same path twice: numbered below, not lengthened
    depth = dict.fromkeys(distinct, 1)
    while True:
        short = {pp: "_".join(pp[-depth[pp]:]) for pp in distinct}
        counts = Counter(n.casefold() for n in short.values())
        grow = [pp for pp, n in short.items() if counts[n.casefold()] > 1 and depth[pp] < len(pp)]
        if not grow:
            break
        for pp in grow:
            depth[pp] += 1
    used: set[str] = set()
    unique = []
    for n in (short[pp] for pp in parts):
        name, k = n, 1
        while name.casefold() in used:
            k += 1
            name = f"{n}-{k}"
        used.add(name.casefold())
        unique.append(name)
    return unique


@dataclass(frozen=True)
class ReplayJob:
    """One input to replay (picklable: it travels to worker processes and Ray tasks).

    options: the command's parsed options, shared by every input; out: the input's folder;
    progress: its progress bar (None: when stderr is a terminal)."""

    index: int
    input: str
    name: str
    out: Path
    videos: bool
    options: argparse.Namespace
    progress: bool | None


@contextlib.contextmanager
def log_prefix(name: str) -> Iterator[None]:
    """Log records handled meanwhile start with ``name:`` (which input a skipped frame is of)."""
    class Prefix(logging.Filter):
        def filter(self, record: logging.LogRecord) -> bool:
            if not hasattr(record, "replay_input"):
                record.replay_input = name
                record.msg = f"{name}: {record.msg}"
            return True

    prefix = Prefix()
    handlers = list(logging.getLogger().handlers)
    for h in handlers:
        h.addFilter(prefix)
    try:
        yield
    finally:
        for h in handlers:
            h.removeFilter(prefix)


def _error_text(exc: BaseException) -> str:
    if isinstance(exc, InputFailed):
        return str(exc)
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def row(job_input: str, name: str, result: dict[str, Any] | BaseException | str) -> dict[str, Any]:
    """The table row of one input from its summary, the exception its replay raised, or the
    problem that kept it from starting."""
    r: dict[str, Any] = dict.fromkeys(COLUMNS)
    r.update(input=job_input, name=name)
    if not isinstance(result, dict):
        r.update(status=ERROR, error=result if isinstance(result, str) else _error_text(result))
        return r
    r.update(kind=result["input"]["kind"], settings=result["settings"],
             **{k: result[k] for k in ("frames", "frames_skipped", "frames_with_target", "target_switches")},
             time_on_target_s=round(float(result["time_on_target_s"]), 3))
    if result["frames"] == 0:
        r.update(status=ERROR,
                 error=f"no frame of {job_input} could be processed ({result['frames_skipped']} skipped)")
    else:
        r["status"] = OK
    return r


def exit_status(rows: Sequence[dict[str, Any]]) -> int:
    """0: every input replayed; 1: some failed, at least one replayed; 2: none could."""
    ok = sum(r["status"] == OK for r in rows)
    return 0 if ok == len(rows) and rows else 1 if ok else 2


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """The table as aligned text, then each input's settings and each error."""
    head = ("input", "folder", "kind", "status", "frames", "skipped", "with target", "switches",
            "on target s")

    def cell(v: Any, spec: str = "") -> str:
        return "-" if v is None else format(v, spec)

    body = [(r["input"], r["name"], cell(r["kind"]), r["status"], cell(r["frames"]),
             cell(r["frames_skipped"]), cell(r["frames_with_target"]), cell(r["target_switches"]),
             cell(r["time_on_target_s"], ".2f")) for r in rows]
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    numeric = range(4, len(head))

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.rjust(w) if i in numeric else c.ljust(w)
                         for i, (c, w) in enumerate(zip(cells, widths))).rstrip()

    lines = [line(head), *map(line, body)]
    settings = [f"  {r['name']}: from {r['settings']}" for r in rows if r["settings"]]
    if settings:
        lines += ["settings:", *settings]
    errors = [f"  {r['name']}: {r['error']}" for r in rows if r["error"]]
    if errors:
        lines += ["errors:", *errors]
    ok = sum(r["status"] == OK for r in rows)
    lines.append(f"{len(rows)} input(s): {ok} replayed, {len(rows) - ok} failed")
    return "\n".join(lines)


def write_table(out_dir: Path, rows: Sequence[dict[str, Any]], status: int) -> None:
    """DIR/summary.json (``{"inputs", "ok", "failed", "exit_status", "columns", "rows"}``) and
    DIR/summary.csv (the header COLUMNS, one line per input; empty cells for none)."""
    ok = sum(r["status"] == OK for r in rows)
    doc = {"inputs": len(rows), "ok": ok, "failed": len(rows) - ok, "exit_status": status,
           "columns": list(COLUMNS), "rows": list(rows)}
    try:
        (out_dir / TABLE_JSON).write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
        with open(out_dir / TABLE_CSV, "w", encoding="utf-8", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=COLUMNS)
            writer.writeheader()
            for r in rows:
                writer.writerow({k: "" if r[k] is None else r[k] for k in COLUMNS})
    except OSError as exc:
        raise BatchError(f"--out-dir: cannot write the summary in {out_dir}: {exc}") from None


def run(inputs: Sequence[Input], options: argparse.Namespace,
        replay_one: Callable[[ReplayJob], dict[str, Any]], *, out_dir: Path, videos: bool,
        workers: int | str, ray_address: str | None, threads: int) -> int:
    """Replay every input with ``replay_one`` (a module-level function: it is pickled), print the
    table, write it under ``out_dir``; the exit status (see :func:`exit_status`)."""
    names = output_names([i.path for i in inputs])
    n_workers = default_workers(max(threads, 1)) if workers == "auto" else int(workers)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BatchError(f"--out-dir: cannot create {out_dir}: {exc}") from None
    rows: dict[int, dict[str, Any]] = {}
    jobs = []
    for i, (inp, name) in enumerate(zip(inputs, names)):
        if inp.problem is not None:
            rows[i] = row(inp.path, name, inp.problem)
    todo = [i for i in range(len(inputs)) if i not in rows]
    in_process = ray_address is None and (n_workers == 1 or len(todo) <= 1)
    # Progress bars from several processes would garble each other: off unless asked for.
    progress = options.progress if in_process or options.progress is not None else False
    for i in todo:
        jobs.append(ReplayJob(i, inputs[i].path, names[i], out_dir / names[i], videos, options, progress))
    where = ("in this process" if in_process else f"on Ray ({ray_address})" if ray_address
             else f"in {min(n_workers, len(jobs))} worker processes")
    print(f"companion replay: {len(inputs)} input(s) into {out_dir}, {where}", file=sys.stderr)
    done = 0
    for i in rows:
        done += 1
        print(f"[{done}/{len(inputs)}] {names[i]}: error: {rows[i]['error']}", file=sys.stderr)
    try:
        for job, result in fan_out(replay_one, jobs, workers=n_workers, ray_address=ray_address,
                                   cpus_per_task=float(max(threads, 1))):
            rows[job.index] = r = row(job.input, job.name, result)
            done += 1
            what = (f"ok, {r['frames']} frame(s), target on {r['frames_with_target']}"
                    if r["status"] == OK else f"error: {r['error']}")
            print(f"[{done}/{len(inputs)}] {job.name}: {what}", file=sys.stderr)
            if isinstance(result, BaseException) and not isinstance(result, InputFailed):
                log.error("%s: replay failed unexpectedly", job.input, exc_info=result)
    except ParallelError as exc:
        raise BatchError(str(exc)) from None
    table = [rows[i] for i in range(len(inputs))]
    status = exit_status(table)
    print(format_table(table))
    write_table(out_dir, table, status)
    print(f"summary: {out_dir / TABLE_JSON}, {out_dir / TABLE_CSV}")
    return status
