"""``companion demo``: the whole system, end to end, on this machine.

Starts the simulator (a multicopter speaking MAVLink as ArduPilot Copter or PX4, hovering over a
crowd of walking people) and its camera, starts the real service as a subprocess against them with
the flight recorder on, raises a battery failsafe, and waits for the touchdown. Then it replays the
recording into an annotated video (people red, proposals green, tracks blue, target yellow) and
writes a summary judged on the simulator's truth: where it touched down, the distance from there
to the nearest person at touchdown, and the time from the failsafe to touchdown.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path

from sim.flight import FlightSpec, fly, reserve_port


def ground_station_line(port: int) -> str:
    """The one line that tells a pilot where to watch the demo with a ground station."""
    return (f"demo: watch it live with a ground station on udp 127.0.0.1:{port}, e.g. "
            f"mavproxy.py --master=udpout:127.0.0.1:{port} (then: set target_component 0) "
            "[docs/ground-station.md]")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--flavour", choices=("ardupilot", "px4"), default="ardupilot",
                        help="autopilot the simulator behaves as (default ardupilot)")
    parser.add_argument("--seed", type=int, default=1, help="crowd seed (default 1)")
    parser.add_argument("--altitude", type=float, default=20.0,
                        help="hover altitude above home in metres (default 20)")
    parser.add_argument("--out", type=Path, default=Path("demo-out"),
                        help="output folder (default ./demo-out)")
    parser.add_argument("--no-video", action="store_true", help="skip the annotated video")
    parser.add_argument("--model", type=Path, default=None,
                        help="ONNX density model for the service (default: the shipped one)")


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rec = out / "recording"
    # A PX4 flies with its home 1.48 m below its estimator's origin, as PX4's own SIH did.
    offset = -1.48 if args.flavour == "px4" else 0.0
    # A port for a ground station, claimed node-wide like the flight's own (sim.flight.reserve_port).
    with reserve_port() as gcs:
        spec = FlightSpec(flavour=args.flavour, seed=args.seed, altitude_m=args.altitude,
                          home_origin_offset_m=offset,
                          record_dir=rec, service_log=out / "service.log",
                          service_set=() if args.model is None else (f"model.path={args.model}",),
                          gcs_port=gcs.port)
        print(f"demo: {args.flavour} vehicle hovering {args.altitude:.0f} m over a crowd; the service "
              f"watches for {spec.watch_s:.0f} s, then the battery failsafe fires", flush=True)
        print(ground_station_line(gcs.port), flush=True)
        try:
            result = asyncio.run(fly(spec))
        except RuntimeError as exc:
            print(f"demo: {exc}", file=sys.stderr)
            return 1
    for msg in result.messages:
        print(f"  {msg}")
    summary = result.as_dict()
    summary["r0_m"] = spec.r0_m
    summary["free_circle"] = result.free_circle
    recordings = sorted(p.parent for p in rec.glob("*/meta.json")) if rec.is_dir() else []
    if not args.no_video and recordings:
        from companion.cli import main as companion_main

        video = out / "demo.mp4"
        print("demo: rendering the annotated video from the flight recording ...", flush=True)
        code = companion_main(["replay", str(recordings[-1]), "--video-out", str(video),
                               "--jsonl", str(out / "zones.jsonl"),
                               "--summary-json", str(out / "replay-summary.json"),
                               "--no-progress", "--r0", str(spec.r0_m)]
                              + ([] if args.model is None else ["--model", str(args.model)]))
        summary["video"] = str(video) if code == 0 else None
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    td = result.touchdown
    print(f"demo: outcome {result.outcome.upper()}")
    if td is not None:
        print(f"  touchdown at north {td[0]:.1f} m, east {td[1]:.1f} m from home")
        print(f"  nearest person at touchdown: {result.clearance_m:.1f} m (r_0 = {spec.r0_m:.1f} m)")
        print(f"  failsafe to touchdown: {result.time_to_touchdown_s:.1f} s")
    print(f"  summary: {out / 'summary.json'}; service log: {out / 'service.log'}"
          + (f"; video: {summary.get('video')}" if summary.get("video") else ""))
    return 0 if result.outcome == "safe" else 1
