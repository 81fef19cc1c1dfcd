"""The physics of the last metres, per camera: what a vertical descent can guarantee at touchdown.

``python -m sim.evidence.last_metres [--camera pinhole:70 --camera fisheye:160 ...] [--size 640x480]``

For each camera (its footprint ratio, ``Intrinsics.seen_ratio``: ground radius seen all round the
point below per metre above the head plane) and each descent (the stepped descent's speed, the
height the autopilot's LAND starts at, the LAND's speed), prints the clearance a landing begun at
10, 20 and 25 m can guarantee at touchdown against people heading for the point from just beyond
the view (``control.touchdown.guaranteed_clearance``: the best over the heights passed of what the
camera sees all round less what a walker covers in the time left), at walking speed (1.5 m/s, the
service's ``pipeline.walk_speed_mps``) and at a runner's (2.4 m/s). Negative: nobody seen can be
ruled out. docs/design.md, "The physics of the last metres", is this table.

Pure arithmetic over the service's own functions: no world, no flight.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass

from companion.control.touchdown import DescentProfile, guaranteed_clearance
from companion.geometry.camera import Intrinsics
from sim.flights.spec import parse_camera

CAMERAS = ("pinhole:70", "pinhole:110", "fisheye:160")
HEIGHTS_M = (10.0, 20.0, 25.0)
SPEEDS_MPS = (1.5, 2.4)


@dataclass(frozen=True)
class Descent:
    """A descent: ``descend_mps`` down to ``land_from_m`` above the ground, then the LAND at
    ``land_mps``; ``label`` says whose it is."""

    descend_mps: float
    land_from_m: float
    land_mps: float
    label: str


DESCENTS = (
    Descent(1.5, 10.0, 0.5, "ArduPilot's defaults: LAND from 10 m at 0.5 m/s"),
    Descent(1.5, 1.0, 0.5, "1.5 m/s to 1 m by the rangefinder, LAND at 0.5"),
    Descent(1.5, 4.0, 1.0, "the simulator's, no rangefinder: 1.5 m/s to 4 m, LAND at 1.0"),
    Descent(1.5, 1.0, 1.0, "the simulator's, rangefinder: 1.5 m/s to 1 m, LAND at 1.0"),
    Descent(3.0, 1.0, 1.0, "3 m/s to 1 m, LAND at 1.0"),
    Descent(5.0, 0.5, 2.0, "5 m/s to 0.5 m, LAND at 2.0"),
)


def camera(spec: str, width: int, height: int) -> Intrinsics:
    """``MODEL:HFOV`` (``sim-scenarios --camera``'s own parser and checks) at ``width x height``."""
    model, hfov = parse_camera(spec)
    return Intrinsics.from_fov(width, height, hfov, model)


def table(cameras: Sequence[str] = CAMERAS, size: tuple[int, int] = (640, 480)) -> list[dict[str, object]]:
    """One row per camera, walker speed and descent: the guaranteed clearance (m) from each of
    ``HEIGHTS_M``."""
    rows: list[dict[str, object]] = []
    for spec in cameras:
        ratio = camera(spec, *size).seen_ratio()
        for speed in SPEEDS_MPS:
            for d in DESCENTS:
                profile = DescentProfile(d.descend_mps, d.land_from_m, d.land_mps, speed)
                rows.append({"camera": spec, "ratio": ratio, "walk_mps": speed, "descent": d.label,
                             "guaranteed_m": [guaranteed_clearance(profile, h, ratio) for h in HEIGHTS_M]})
    return rows


def markdown(rows: list[dict[str, object]]) -> str:
    """One table per walker speed: a row per descent, a column per camera, each cell the
    guaranteed clearance from each of ``HEIGHTS_M`` (m, "from 10 / 20 / 25 m")."""
    cams = list(dict.fromkeys(str(r["camera"]) for r in rows))
    ratio = {str(r["camera"]): float(r["ratio"]) for r in rows}  # type: ignore[arg-type]
    heights = " / ".join(f"{h:g}" for h in HEIGHTS_M)
    out: list[str] = []
    for speed in dict.fromkeys(r["walk_mps"] for r in rows):
        out += [f"People at {speed:g} m/s; guaranteed clearance at touchdown (m) from {heights} m:", "",
                "| descent | " + " | ".join(f"{c} ({ratio[c]:.3f})" for c in cams) + " |",
                "| --- | " + " | ".join("---" for _ in cams) + " |"]
        for label in dict.fromkeys(r["descent"] for r in rows):
            cells = []
            for c in cams:
                (r,) = [r for r in rows if r["camera"] == c and r["walk_mps"] == speed and r["descent"] == label]
                cells.append(" / ".join(f"{v:+.1f}" for v in r["guaranteed_m"]))  # type: ignore[attr-defined]
            out.append(f"| {label} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out).rstrip() + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.evidence.last_metres", description=__doc__.split("\n")[0])
    ap.add_argument("--camera", action="append", help="MODEL:HFOV (repeatable; default the three of issue 60)")
    ap.add_argument("--size", default="640x480", help="WIDTHxHEIGHT (default 640x480)")
    args = ap.parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
        rows = table(args.camera or CAMERAS, (w, h))
    except ValueError as exc:
        ap.error(str(exc))
    print(markdown(rows), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
