"""``companion bench``: per-stage latency of the pipeline at 640x480 and 1280x720.

Frames are synthetic crowds seen from a posed camera (20 m up, 70 deg horizontal field of view,
straight down, slowly drifting) so the geometry stages do real work. The post-density stages run
on the scene's ideal density map unless a model is given, in which case the model runs on the
rendered frame and its own output feeds the rest. ``live_view`` is what the service's live view
costs per drawn frame while a client watches (the figure and its JPEG; ``LIVE_MAX_FPS`` at most,
nothing without a client); it is not part of the pipeline's ``total``, and neither is
``landing_spot``, the point of the
largest zone farthest from where people were seen in the last 30 s, which a frame waits for while
the vehicle approaches its zone (``PLACE_LOOKBACK_S``, the frame's ``GroundView.spot``).
``landability`` is the landability model (the shipped one unless ``--no-landability``; it runs on
the same frame after the density model and is counted in ``total``, not in ``post_density``).
Figures are printed, never asserted: this machine is shared and timings are noisy, so compare
figures measured in one run.

By default the pipeline is set up as costly as the service can make it (the risk map measuring
calm and unwalked ground, and the people followed for the walkers' prediction, whatever the flight
defaults are). ``--configured`` (implied by ``--config FILE`` or ``--set KEY=VALUE``) times it as
the service's settings build it instead: their model and landability model (``--model``,
``--landability`` and the ``--no-`` options still win), ``model.threads`` (unless ``--threads``),
their pipeline and controller settings, and their camera (``camera.width x camera.height``, its
intrinsics, distortion and mount), at that one resolution: what a configuration costs on the
machine it will fly on.

``--peer FILE`` (e.g. ``../shared/peers/mcnn-shb.onnx``) times another density model on the same
frame in the same run, frame by frame in turn with the pipeline (the peer first, then the
pipeline's frame), with the same onnxruntime threads and spinning: ``peer_density`` is its density
time, and ``total_over_peer`` the ratio of the medians, the pipeline's whole frame (``total``) over
the peer's density (issue 60's cost target: at most 1/4 with the fisheye). Alternating frame by
frame lets the load of a shared machine fall on both alike.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from companion import config as settings
from companion import synthetic
from companion.config import SHIPPED_LANDABILITY, SHIPPED_MODEL
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.pipeline.people import PeopleParams
from companion.pipeline.riskmap import SpotRequest
from companion.pipeline.slz import STAGES, DensityFn, PipelineConfig, SLZPipeline, SurfaceFn
from companion.replay.live_figure import live_jpeg

RESOLUTIONS = ((640, 480), (1280, 720))


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {"median_ms": round(float(np.median(a)), 3),
            "p99_ms": round(float(np.percentile(a, 99)), 3)}


def bench_frame(width: int, height: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The bench's frame (a synthetic crowd with two free areas, BGR uint8) and its ideal
    density map."""
    scale = width / 640.0
    scene = synthetic.crowd_scene(width, height, n_people=int(150 * scale * scale),
                                  free=((0.3 * width, 0.5 * height, 0.15 * width),
                                        (0.75 * width, 0.3 * height, 0.1 * width)), seed=seed)
    return synthetic.render(scene, seed=seed), synthetic.point_density(scene)


def drifting_pose(t: float) -> Pose:
    """20 m up, drifting, with small attitude changes, so the grid and warps change every frame."""
    return Pose(t, 0.3 * t, 0.1 * t, -20.0, 0.03 * math.sin(t), 0.02 * math.cos(t), 0.1 * t)


def paced_frame_ms(pipe: SLZPipeline, frame: np.ndarray, fps: float, frames: int, warmup: int = 5) -> list[float]:
    """The pipeline's whole time per frame (its ``total``, ms) over ``frames`` frames run at a
    camera's pace: each frame starts one period (1/``fps``) after the last and the time left is
    slept, as a service's pipeline waits for its next frame. On a virtual machine this is slower
    than frames back to back (idle vCPUs woken, cold caches), and it is what a flight's service
    meets: ``companion sim-scenarios`` checks the machine with it before flying."""
    period = 1.0 / fps
    out: list[float] = []
    next_t = time.monotonic()
    for k in range(frames + warmup):
        t = k * period
        res = pipe.process(frame, t, drifting_pose(t))
        if k >= warmup:
            out.append(float(res.timings_ms["total"]))
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:  # behind: the next frame at once, the pace from there
            next_t = time.monotonic()
    return out


#: The costliest set-up (see the module docstring): the risk map measuring calm and unwalked
#: ground (in the tracking stage) and the people stage, whatever the flight defaults are.
COSTLIEST = PipelineConfig(calm=True, unwalked=True, people=PeopleParams())


def bench_resolution(width: int, height: int, frames: int, model: DensityFn | None = None, warmup: int = 5,
                     seed: int = 0, surface: SurfaceFn | None = None, pause_s: float = 0.0,
                     config: PipelineConfig = COSTLIEST, intrinsics: Intrinsics | None = None,
                     mount: Mount | None = None, peer: DensityFn | None = None) -> dict[str, dict[str, float]]:
    """Per-stage median and p99 milliseconds over ``frames`` frames at one resolution
    (``surface``: the landability model's callable, timed as ``landability``; ``pause_s``: a sleep
    before each frame, the time a camera's frame period or the models would leave between them;
    ``config``, ``intrinsics``, ``mount``: the pipeline's set-up, by default the costliest with a
    distortion-free 70 deg lens pointing straight down; ``peer``: another density model timed on
    the same frame just before each of the pipeline's frames, as ``peer_density``, with
    ``total_over_peer`` the ratio of the medians of ``total`` and ``peer_density``)."""
    frame, ideal = bench_frame(width, height, seed)
    density = model if model is not None else (lambda f: ideal)
    K = intrinsics if intrinsics is not None else Intrinsics.from_fov(width, height, 70.0)
    pipe = SLZPipeline(density, config, intrinsics=K, mount=mount if mount is not None else Mount(),
                       surface=surface)
    samples: dict[str, list[float]] = {}
    for k in range(frames + warmup):
        t = k / 15.0
        if pause_s > 0:
            time.sleep(pause_s)
        peer_ms = None
        if peer is not None:
            t0 = time.perf_counter()
            peer(frame)
            peer_ms = (time.perf_counter() - t0) * 1e3
        res = pipe.process(frame, t, drifting_pose(t))
        if k < warmup:
            continue
        if peer_ms is not None:
            samples.setdefault("peer_density", []).append(peer_ms)
        for name, ms in res.timings_ms.items():
            samples.setdefault(name, []).append(ms)
        # The live view's cost while a client watches (the service draws nothing otherwise): the
        # figure of this frame and its JPEG, as the service's live view makes them.
        t0 = time.perf_counter()
        live_jpeg(frame, res, res.tracks[0].id if res.tracks else None, "MONITOR  zones 0  no target  00:00:00")
        samples.setdefault("live_view", []).append((time.perf_counter() - t0) * 1e3)
        # What a frame waits for while the vehicle approaches its zone (PLACE_LOOKBACK_S):
        # the point of the largest zone farthest from where people were seen in the last 30 s.
        if res.tracks:
            zone = max(res.tracks, key=lambda tr: tr.r)
            t0 = time.perf_counter()
            # Within the part of it that keeps r0 plus radius_margin_m (4 m by default) around.
            assert res.ground is not None
            res.ground.spot(SpotRequest(zone.x, zone.y, max(0.0, zone.r - 4.0), 30.0, (zone.x, zone.y)))
            samples.setdefault("landing_spot", []).append((time.perf_counter() - t0) * 1e3)
    wanted = list(STAGES if model is not None else STAGES[1:]) + ["post_density"]
    if surface is not None:
        wanted.insert(1 if model is not None else 0, "landability")
    if model is not None or surface is not None:
        wanted.append("total")
    wanted += ["live_view", "landing_spot", "peer_density"]
    out = {name: _stats(samples[name]) for name in wanted if name in samples}
    if "peer_density" in out and "total" in out:
        out["total_over_peer"] = {"ratio": round(out["total"]["median_ms"] / out["peer_density"]["median_ms"], 4)}
    return out


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=200, help="frames per resolution (default 200)")
    parser.add_argument("--model", type=Path, default=None,
                        help="ONNX density model (default: the shipped model, when present)")
    parser.add_argument("--no-model", action="store_true",
                        help="time only the post-density stages on ideal density maps")
    parser.add_argument("--landability", type=Path, default=None,
                        help="ONNX landability model (default: the shipped one, when present)")
    parser.add_argument("--no-landability", action="store_true", help="leave the landability model out")
    parser.add_argument("--threads", type=int, default=None,
                        help="onnxruntime threads (default 2; with --configured, model.threads)")
    parser.add_argument("--spinning", action="store_true",
                        help="let onnxruntime's threads busy-wait between runs (off in the service)")
    parser.add_argument("--pause-ms", type=float, default=0.0,
                        help="sleep this long before each frame (default 0: frames back to back). The "
                             "stages run about 1.4 times slower once per frame period than back to back, "
                             "whatever fills the time between (the models, a sleep, a Python loop): "
                             "--no-model --pause-ms 40 shows the post-density stages as a flight runs them")
    parser.add_argument("--peer", type=Path, default=None,
                        help="another ONNX density model (e.g. ../shared/peers/mcnn-shb.onnx) timed on the same frame, "
                             "frame by frame in turn with the pipeline, same threads: peer_density and "
                             "total_over_peer (the whole frame over the peer's density)")
    parser.add_argument("--peer-preset", choices=("none", "mcnn"), default=None,
                        help="the peer's input settings (default: mcnn if its file name says mcnn, as companion eval)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--configured", action="store_true",
                        help="time the pipeline as the service's settings build it (the defaults, or --config "
                             "with --set), at the camera's resolution, instead of the costliest set-up")
    parser.add_argument("--config", metavar="FILE", help="the service's TOML configuration (implies --configured)")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="set_",
                        help="a setting over --config's, as for companion run (repeatable; implies --configured)")


def run(args: argparse.Namespace) -> int:
    if args.frames < 1:
        print("companion bench: --frames must be >= 1", file=sys.stderr)
        return 2
    if not (math.isfinite(args.pause_ms) and 0.0 <= args.pause_ms <= 1000.0):
        print("companion bench: --pause-ms must be between 0 and 1000", file=sys.stderr)
        return 2
    if args.threads is not None and not 1 <= args.threads <= 64:
        print("companion bench: --threads must be between 1 and 64", file=sys.stderr)
        return 2
    cfg = None
    if args.configured or args.config is not None or args.set_:
        try:
            overrides = dict(settings.parse_assignment(item) for item in args.set_)
            cfg = settings.load(args.config, overrides)
        except settings.ConfigError as exc:
            print(f"companion bench: {exc}", file=sys.stderr)
            return 2
    threads = args.threads if args.threads is not None else (cfg.model.threads if cfg is not None else 2)
    spinning = args.spinning
    model = None
    if not args.no_model:
        path = args.model or (Path(cfg.model.path) if cfg is not None else SHIPPED_MODEL)
        if args.model is not None or cfg is not None or path.is_file():
            from companion.pipeline.density import DensityModel, DensityModelError

            try:
                model = DensityModel(path, threads=threads, allow_spinning=spinning,
                                     overrides=cfg.model.overrides if cfg is not None else None)
            except DensityModelError as exc:
                print(f"companion bench: {exc}", file=sys.stderr)
                return 2
    surface = None
    if not args.no_landability and (cfg is None or cfg.model.landability or args.landability is not None):
        lpath = args.landability or (Path(cfg.model.landability_path) if cfg is not None else SHIPPED_LANDABILITY)
        if args.landability is not None or cfg is not None or lpath.is_file():
            from companion.pipeline.density import DensityModelError
            from companion.pipeline.landability import LandabilityModel

            try:
                levels = (cfg.pipeline.unlandable_levels or None) if cfg is not None else None
                surface = LandabilityModel(lpath, threads=threads, allow_spinning=spinning).unlandable(levels)
            except DensityModelError as exc:  # a LandabilityModelError too
                print(f"companion bench: {exc}", file=sys.stderr)
                return 2
    peer = None
    if args.peer is not None:
        from companion.evaluation.cli import PRESETS
        from companion.pipeline.density import DensityModel, DensityModelError

        preset = args.peer_preset or ("mcnn" if "mcnn" in args.peer.name.lower() else "none")
        try:
            peer = DensityModel(args.peer, threads=threads, allow_spinning=spinning, overrides=PRESETS[preset])
        except DensityModelError as exc:
            print(f"companion bench: peer: {exc}", file=sys.stderr)
            return 2
    pause_s = args.pause_ms / 1e3
    if cfg is None:
        result = {f"{w}x{h}": bench_resolution(w, h, args.frames, model, surface=surface, pause_s=pause_s,
                                               peer=peer)
                  for w, h in RESOLUTIONS}
    else:
        w, h = cfg.camera.width, cfg.camera.height
        pipe_cfg = settings.pipeline_config(cfg, model.spec if model is not None else None)
        result = {f"{w}x{h}": bench_resolution(w, h, args.frames, model, surface=surface, pause_s=pause_s,
                                               config=pipe_cfg, intrinsics=settings.intrinsics(cfg),
                                               mount=settings.mount(cfg), peer=peer)}
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"companion bench: {args.frames} frames per resolution, model: "
          f"{model.path if model is not None else 'none (ideal density maps)'}"
          + (f", {threads} thread(s), spinning {'on' if spinning else 'off'}" if model is not None else "")
          + f", landability: {surface.model.path if surface is not None else 'none'}"
          + (f", {args.pause_ms:g} ms pause before each frame" if args.pause_ms > 0 else "")
          + (f", peer: {peer.path} (same threads, frame by frame in turn)" if peer is not None else "")
          + (f"; set up as configured ({args.config or 'the defaults'}"
             + (f" with {len(args.set_)} --set" if args.set_ else "") + ")" if cfg is not None
             else "; the costliest set-up (calm, unwalked, people)"))
    for res_name, stages in result.items():
        print(f"\n{res_name}")
        print(f"  {'stage':<14}{'median ms':>11}{'p99 ms':>10}")
        for stage, s in stages.items():
            if "ratio" in s:
                continue
            print(f"  {stage:<14}{s['median_ms']:>11.2f}{s['p99_ms']:>10.2f}")
        if "total_over_peer" in stages:
            print(f"  whole frame over the peer's density (medians): {stages['total_over_peer']['ratio']:.3f}")
    return 0
