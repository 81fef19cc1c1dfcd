"""``companion demo``: the whole system, end to end, on this machine.

Starts the simulator (a multicopter speaking MAVLink as ArduPilot Copter or PX4, hovering over a
crowd of walking people) and its camera, starts the real service as a subprocess against them with
the flight recorder on, makes the simulated battery go critical (the autopilot reports it in its
system status and starts its own LAND), and waits for the touchdown. The service's decisions are
printed as it records them (trigger, target, hold, handback, landing). Then the recording becomes
an H.264 video of what the service decided (zones, target, phase, height, time, each zone's
predicted clearance at touchdown), with the simulator's people marked as the truth, as long as the
flight, and a last card with the outcome and the nearest person; an H.264 evidence video
(``companion replay`` of the recording with its own settings: the people seen, the head-plane
view with the ground the map still holds, and the flight's own zones and target); and a summary
judged on the simulator's truth: where it touched down, the distance from there to the nearest
person at touchdown, and the time from the failsafe to touchdown.

The demo flies in real time beside whatever else this machine runs. When its service could not
keep the camera's rate (a **starved** flight, ``sim.flights.flight.starved``), the demo says so and
what it means: the decisions ran on fewer, later frames than on a vehicle, and the flight is no
measure of the method (the yardstick's flights fly in lockstep, where no CPU can starve them).
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import contextlib
import importlib
import io
import json
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from sim.flights.flight import (
    STARVED_FRAME_SHARE,
    STARVED_SHARE,
    TRUTH_PERIOD_S,
    FlightResult,
    FlightSpec,
    fly,
    reserve_port,
)
from sim.flights.spec import GROUNDS, parse_camera_and_photos

if TYPE_CHECKING:
    from companion.replay.flight_video import Outcome
    from sim.vehicle.simulator import Simulator
    from sim.world.crowd import World

#: Event kinds printed live: the failsafe trigger and the controller's decisions.
LIVE_KINDS = ("trigger", "controller")


def ground_station_line(port: int) -> str:
    """The one line that tells a pilot where to watch the demo with a ground station."""
    return (f"demo: watch it live with a ground station on udp 127.0.0.1:{port}, e.g. "
            f"mavproxy.py --master=udpout:127.0.0.1:{port} (then: set target_component 0) "
            "[docs/ground-station.md]")


def live_page_line(port: int) -> str:
    """The one line that tells where to watch the service's own page during the demo."""
    return (f"demo: the service's status page and live view: http://127.0.0.1:{port}/ "
            f"(open it in a browser now; it serves while the service runs)")


def live_settings(port: int) -> tuple[str, ...]:
    """The service settings that serve its page on loopback ``port`` (``companion run --set``)."""
    return ("live.enabled=true", "live.address=127.0.0.1", f"live.port={port}")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--flavour", choices=("ardupilot", "px4"), default="ardupilot",
                        help="autopilot the simulator behaves as (default ardupilot)")
    parser.add_argument("--seed", type=int, default=1, help="crowd seed (default 1)")
    parser.add_argument("--altitude", type=float, default=20.0,
                        help="hover altitude above home in metres (default 20)")
    parser.add_argument("--out", type=Path, default=Path("demo-out"),
                        help="output folder (default ./demo-out; git ignores it in a clone)")
    parser.add_argument("--no-video", action="store_true", help="skip the video")
    parser.add_argument("--live", action="store_true",
                        help="serve the service's status page and live view on loopback during the flight "
                             "and print its URL (docs/ground-station.md, \"The status page\")")
    parser.add_argument("--camera", default="pinhole:70", metavar="MODEL:HFOV",
                        help="the camera of the simulator and of the service as one: pinhole or fisheye "
                             "and the horizontal field of view in degrees (default pinhole:70; e.g. fisheye:160)")
    parser.add_argument("--ground", choices=GROUNDS, default="procedural",
                        help="'procedural' (drawn; default) or 'photo': real nadir photos as the ground "
                             "(docs/photo-world.md)")
    parser.add_argument("--photos", type=Path, default=None, metavar="DIR",
                        help="the photos of --ground photo (default ../shared/data/semantic_drone/full "
                             "beside the checkout)")
    parser.add_argument("--model", type=Path, default=None,
                        help="ONNX density model for the service (default: the shipped one)")


class EventFollower:
    """Prints the service's trigger and controller events as they reach its flight recording.

    The recorder writes each event line unbuffered (``companion.recording``), so reading the
    newest run's events files from where the last poll stopped gives them within a poll. Times
    are shown from the trigger (the recording's clock is this machine's monotonic clock).
    """

    def __init__(self, record_dir: Path, since: float, out: TextIO = sys.stdout, cause: str | None = None) -> None:
        self.record_dir, self.since, self.out, self.cause = record_dir, since, out, cause
        self._offsets: dict[Path, int] = {}
        self._partial: dict[Path, bytes] = {}
        self.trigger_t: float | None = None
        self.printed = 0

    def _run_dir(self) -> Path | None:
        runs = [p.parent for p in self.record_dir.glob("*/meta.json") if p.stat().st_mtime >= self.since - 1.0]
        return max(runs, default=None)

    def poll(self) -> None:
        run = self._run_dir()
        if run is None:
            return
        from companion.recording import stream_files

        for path in stream_files(run, "events"):
            start = self._offsets.get(path, 0)
            try:
                with open(path, "rb") as fh:
                    fh.seek(start)
                    data = fh.read()
            except OSError:
                continue
            self._offsets[path] = start + len(data)
            data = self._partial.pop(path, b"") + data
            *lines, rest = data.split(b"\n")
            if rest:
                self._partial[path] = rest  # a line being written: finish it next poll
            for line in lines:
                self._show(line)

    def _show(self, line: bytes) -> None:
        try:
            ev = json.loads(line)
        except ValueError:
            return
        if not isinstance(ev, dict) or ev.get("kind") not in LIVE_KINDS or not isinstance(ev.get("t"), (int, float)):
            return
        t = float(ev["t"])
        if ev["kind"] == "trigger":
            self.trigger_t = t if self.trigger_t is None else self.trigger_t
            text = f"failsafe trigger: {ev.get('reason', '?')} (from {ev.get('source', '?')})"
            if self.cause:
                text += f": {self.cause}"
        else:
            text = str(ev.get("text") or f"{ev.get('old')} -> {ev.get('phase')}")
        when = "" if self.trigger_t is None else f"{t - self.trigger_t:+6.1f} s "
        print(f"  {when}{text}", file=self.out, flush=True)
        self.printed += 1

    async def follow(self, period_s: float = 0.25) -> None:
        while True:
            self.poll()
            await asyncio.sleep(period_s)


async def _fly_following(spec: FlightSpec, follower: EventFollower, truth: Truth | None = None) -> FlightResult:
    task = asyncio.create_task(follower.follow())
    try:
        return await fly(spec, None if truth is None else truth.attach)
    finally:
        task.cancel()
        follower.poll()  # the last events (LANDED), written before the service stopped


#: What the demo says its trigger was: the failsafe the simulator raises (``FlightSpec.failsafe``),
#: as the README tells it; the service's own trigger line says which sign of it it acted on.
CAUSES = {"battery_critical": "the simulated battery went critical",
          "battery_low": "the simulated battery went low",
          "rc_loss": "the simulated RC link was lost", "gcs_loss": "the simulated ground-station link was lost"}


@dataclass
class Truth:
    """The simulator's people through the flight, on the recording's clock (this host's
    ``time.monotonic()``): sampled every ``TRUTH_PERIOD_S`` and at the touchdown, for the video's
    markers and its last card. Sampling only reads the world: the flight is unchanged."""

    t: list[float] = field(default_factory=list)
    people: list[np.ndarray] = field(default_factory=list)
    at_touchdown: np.ndarray | None = None

    def attach(self, world: World, sim: Simulator) -> None:
        def everyone() -> np.ndarray:
            fixed = world.fixed_people
            moving = world.positions()
            if fixed is None or len(fixed) == 0:
                return moving.copy()
            return np.vstack([moving, np.asarray(fixed, float).reshape(-1, 2)])

        def step(_dt: float) -> None:
            now = time.monotonic()
            if not self.t or now - self.t[-1] >= TRUTH_PERIOD_S:
                self.t.append(now)
                self.people.append(everyone())

        def touchdown() -> None:
            if self.at_touchdown is None:
                self.at_touchdown = everyone()

        sim.add_stepper(step)
        sim.on_touchdown(touchdown)

    def at(self, t: float) -> np.ndarray:
        """The people (N, 2 north, east m) at the last sample at or before ``t`` (the first
        sample before it)."""
        if not self.t:
            return np.empty((0, 2))
        i = max(0, bisect.bisect_right(self.t, t) - 1)
        return self.people[i]


def starved_lines(result: FlightResult) -> list[str]:
    """What the demo says of a starved flight (none for one that was not): the figures against
    their budget, and what they mean for the outcome."""
    if not result.starved:
        return []
    fps = result.spec.fps
    figures = []
    if result.processed_fps is not None:
        figures.append(f"{result.processed_fps:.1f} frames/s processed of the camera's {fps:g} "
                       f"(a flight needs {STARVED_SHARE * fps:g})")
    if result.frame_ms_p95 is not None:
        figures.append(f"{result.frame_ms_p95:.0f} ms a frame at the 95th percentile "
                       f"(budget {STARVED_FRAME_SHARE * 1000.0 / fps:.0f} ms)")
    return [f"STARVED: this machine did not give the service the CPU a vehicle's companion has: {'; '.join(figures)}.",
            "The service decided on fewer and later frames than it would on a vehicle, so this outcome and its times",
            "say what a starved companion does, not what the method does; the yardstick's figures come from lockstep",
            "flights (companion sim-scenarios --lockstep, docs/scale.md). Close other work and run the demo again."]


_VERDICTS = {"safe": ("LANDED SAFE", (0, 200, 0)), "unsafe": ("LANDED UNSAFE: someone within r0", (0, 0, 255)),
             "handback": ("HANDED BACK to the autopilot", (0, 140, 255)),
             "timeout": ("NO TOUCHDOWN in the flight's time", (0, 0, 255))}


def video_outcome(result: FlightResult, truth: Truth | None) -> Outcome:
    """The last card of the demo's video: the verdict, the touchdown lines, why it handed back,
    whether it was starved, and everyone where they stood at touchdown."""
    from companion.replay.flight_video import Outcome

    verdict, colour = _VERDICTS.get(result.outcome, (result.outcome.upper(), (255, 255, 255)))
    lines = list(touchdown_lines(result))
    reason = handback_reason(result)
    if reason is not None:
        lines.append(reason if len(reason) <= 90 else reason[:87] + "...")
    if result.starved:
        lines.append(f"STARVED flight ({result.processed_fps or 0:.1f} frames/s, p95 {result.frame_ms_p95 or 0:.0f} ms): "
                     "not a measure of the method")
    people = np.empty((0, 2)) if truth is None or truth.at_touchdown is None else truth.at_touchdown
    return Outcome(verdict, colour, tuple(lines), result.touchdown, people, result.spec.r0_m)


def handback_reason(result: FlightResult) -> str | None:
    """One line saying why the companion handed control back, from its HandedBack event."""
    for ev in reversed(result.events):
        if ev.get("event") == "handback":
            action = ev.get("action") or "its own failsafe"
            return f"handed back to the autopilot ({action}): {ev.get('reason') or ev.get('text') or 'no reason recorded'}"
    return None


def touchdown_lines(result: FlightResult) -> list[str]:
    """What the demo says of the touchdown, judged on the simulator's truth: where, who landed,
    the nearest person, what the vehicle came down on, and how long it took; none without one."""
    td = result.touchdown
    if td is None:
        return []
    who = "the autopilot" if result.handed_back or not result.took_control else "the companion"
    lines = [f"touchdown (landed by {who}) at north {td[0]:.1f} m, east {td[1]:.1f} m from home",
             f"nearest person at touchdown: {result.clearance_m:.1f} m (r_0 = {result.spec.r0_m:.1f} m)"]
    if result.touchdown_surfaces is not None:
        lines.append(f"touched down on {' and '.join(result.touchdown_surfaces)}"
                     + (" (NOT landable ground)" if result.unlandable_touchdown else ""))
    lines.append(f"failsafe to touchdown: {result.time_to_touchdown_s:.1f} s")
    return lines


def labelled_summary(result: FlightResult, r0_m: float) -> dict[str, Any]:
    """The summary with named fields (metres north/east of home) where the flight result has
    tuples; ``touchdown``'s old list form is kept as ``touchdown_ne`` for older readers."""
    summary = result.as_dict()
    summary["r0_m"] = r0_m
    td = result.touchdown
    summary["touchdown_ne"] = summary["touchdown"]
    summary["touchdown"] = None if td is None else {"north_m": round(td[0], 3), "east_m": round(td[1], 3)}
    fc = result.free_circle
    summary["free_circle"] = None if fc is None else {"north_m": round(fc[0], 3), "east_m": round(fc[1], 3),
                                                      "radius_m": round(fc[2], 3)}
    summary["handback_reason"] = handback_reason(result)
    # The starved flag's meaning beside it (None when it was not): summary.json says what the console says.
    summary["starved_note"] = " ".join(starved_lines(result)) or None
    return summary


def _write_zones(recording: Path, path: Path) -> int:
    """The service's per-frame zones and target (its ``zones`` events) as JSON Lines."""
    from companion.recording import RecordingReader

    n = 0
    with open(path, "w") as fh:
        for ev in RecordingReader(recording).events("zones"):
            fh.write(json.dumps(ev) + "\n")
            n += 1
    return n


def evidence_video(recording: Path, out: Path) -> Path | None:
    """``companion replay`` of ``recording`` with the settings it was flown with into the H.264
    video ``out`` (each frame beside its head-plane view): the evidence behind the decisions,
    beside the decision video, with the flight's own zones and target drawn (``--flight-zones``:
    the ids the console printed). None when the replay failed (said on stderr)."""
    from companion.cli import main as companion_main

    # Its summary goes to the JSON file; the demo's own lines stay the ones on the terminal.
    with contextlib.redirect_stdout(io.StringIO()):
        code = companion_main(["replay", str(recording), "--video-out", str(out), "--flight-zones",
                               "--summary-json", str(out.with_suffix(".json")), "--no-progress"])
    return out if code == 0 and out.is_file() else None


def _have(module: str) -> bool:
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def run(args: argparse.Namespace) -> int:
    if not args.no_video and not _have("av"):
        # Said before the two-minute flight, not after it.
        print("companion: demo: the video needs the optional package 'av': pip install 'companion-slz[tools]' "
              "(or run with --no-video)", file=sys.stderr)
        return 2
    checked = parse_camera_and_photos("companion: demo", args.camera, args.ground, args.photos)
    if isinstance(checked, str):
        print(checked, file=sys.stderr)
        return 2
    assert checked.camera is not None  # --camera has a default
    (lens, hfov), photos = checked.camera, checked.photos
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rec = out / "recording"
    # A PX4 flies with its home 1.48 m below its estimator's origin, as PX4's own SIH did.
    offset = -1.48 if args.flavour == "px4" else 0.0
    # A port for a ground station, claimed node-wide like the flight's own (sim.flights.flight.reserve_port).
    with reserve_port() as gcs, contextlib.ExitStack() as stack:
        service_set: tuple[str, ...] = () if args.model is None else (f"model.path={args.model}",)
        page = stack.enter_context(reserve_port(socket.SOCK_STREAM)) if args.live else None
        if page is not None:
            service_set = (*service_set, *live_settings(page.port))
        spec = FlightSpec(flavour=args.flavour, seed=args.seed, altitude_m=args.altitude,
                          home_origin_offset_m=offset, camera_model=lens, hfov_deg=hfov,
                          record_dir=rec, service_log=out / "service.log", service_set=service_set,
                          gcs_port=gcs.port, ground=args.ground, photos=photos)
        print(f"demo: {args.flavour} vehicle hovering {args.altitude:.0f} m over a crowd"
              + (" on real photos" if args.ground == "photo" else "") + "; the service "
              f"watches for {spec.watch_s:.0f} s, then the simulated battery goes critical (the autopilot "
              "reports it and starts its own LAND). The service's decisions, as it makes them (seconds "
              "from the trigger):", flush=True)
        print(ground_station_line(gcs.port), flush=True)
        if page is not None:
            print(live_page_line(page.port), flush=True)
        follower = EventFollower(rec, since=time.time(), cause=CAUSES.get(spec.failsafe))
        truth = Truth()
        try:
            result = asyncio.run(_fly_following(spec, follower, truth))
        except RuntimeError as exc:
            print(f"demo: {exc}", file=sys.stderr)
            return 1
    if follower.printed == 0:  # nothing was recorded live (no recording?): the judge's copy
        for msg in result.messages:
            print(f"  {msg}")
    summary = labelled_summary(result, spec.r0_m)
    recordings = sorted(p.parent for p in rec.glob("*/meta.json")) if rec.is_dir() else []
    if recordings:
        summary["recording"] = str(recordings[-1])
        summary["zones"] = str(out / "zones.jsonl")
        _write_zones(recordings[-1], out / "zones.jsonl")
    if not args.no_video and recordings:
        from companion.replay.flight_video import print_progress, write_h264

        video = out / "demo.mp4"
        print("demo: drawing the video of what the service decided, from its flight recording ...", flush=True)
        written = write_h264(recordings[-1], video, progress=print_progress(), people=truth.at,
                             outcome=video_outcome(result, truth))
        summary["video"] = str(written.path)
        print("demo: replaying the recording with the ground risk map for the evidence video ...", flush=True)
        evidence = evidence_video(recordings[-1], out / "evidence.mp4")
        summary["evidence_video"] = None if evidence is None else str(evidence)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    line = f"demo: outcome {result.outcome.upper()}"
    reason = summary["handback_reason"]
    if reason is not None:
        line += f"; the companion {reason}"
    print(line)
    for text in touchdown_lines(result):
        print(f"  {text}")
    for text in starved_lines(result):
        print(f"  {text}")
    print(f"  summary: {out / 'summary.json'}; service log: {out / 'service.log'}"
          + (f"; video: {summary.get('video')}" if summary.get("video") else "")
          + (f"; evidence: {summary.get('evidence_video')}" if summary.get("evidence_video") else ""))
    return 0 if result.outcome == "safe" else 1
