"""``companion replay``: the pipeline offline over a recording, a video or a folder of frames.

Exit status: 0 when frames were processed, 1 when none could be, 2 for an unusable input, model,
projection or output (the message names the file and the problem). With several inputs (a
fleet's recordings, ``--out-dir``): 0 when every input replayed, 1 when some failed, 2 when none
could (see companion/replay/batch.py). See docs/replay.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion import config as settings
from companion.config import SHIPPED_LANDABILITY, SHIPPED_MODEL, Config, ConfigError
from companion.control.planner import ZonePlanner
from companion.geometry.camera import GeometryError, PlaneProjection
from companion.pipeline.density import DensityModel, DensityModelError
from companion.pipeline.landability import LandabilityModel, UnlandableMap
from companion.pipeline.slz import PipelineConfig, SLZPipeline
from companion.recording import RecordingError, RecordingReader
from companion.replay import batch
from companion.replay.homography import HomographyFileError, projection_from_file
from companion.replay.records import flight_zones
from companion.replay.runner import ReplayOutputError, ReplayOutputs, VideoOut, replay
from companion.replay.sources import KINDS, ReplayInputError, ReplaySource, open_input
from companion.replay.summary import format_summary


def _key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key.strip(), value.strip()


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="a flight recording, a video file, or a folder of image frames; "
                             "several (a fleet's recordings) need --out-dir; shell-style patterns "
                             "such as 'recordings/*/' are expanded")
    parser.add_argument("--input-kind", choices=KINDS, default="auto",
                        help="what INPUT is (default: guessed: folder of images = frames, video "
                             "suffix = video, else a recording)")
    parser.add_argument("--fps", type=float, default=None,
                        help="frame rate in Hz: frame times are index / fps (frames default 10; "
                             "videos default to their own rate)")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after N input frames")
    geo = parser.add_argument_group("projection (default: the recorded poses)")
    geo.add_argument("--nadir", action="store_true",
                     help="camera straight down; plane x = u * gsd, y = v * gsd (needs --gsd)")
    geo.add_argument("--gsd", type=float, default=None, help="metres per pixel on the head plane")
    geo.add_argument("--homography", type=Path, default=None,
                     help="3x3 image-to-head-plane matrix in metres (.npy, .txt/.csv, .json)")
    mdl = parser.add_argument_group("settings, model and pipeline (default: a recording's own "
                                    "settings, so that replay reproduces the pipeline that flew)")
    mdl.add_argument("--config", type=Path, default=None,
                     help="settings from this TOML file (as `companion run` reads it) instead of "
                          "the recording's")
    mdl.add_argument("--default-settings", action="store_true",
                     help="the built-in default settings instead of the recording's")
    mdl.add_argument("--set", dest="set_", action="append", default=[], metavar="KEY=VALUE",
                     help="override one setting (e.g. pipeline.r0_m=3); repeatable")
    mdl.add_argument("--model", type=Path, default=None,
                     help="ONNX density model (default: the recording's model when that file "
                          f"exists, else the shipped {SHIPPED_MODEL.name})")
    mdl.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2)")
    mdl.add_argument("--threshold", type=float, default=None,
                     help="occupancy threshold on D - min(D), = --set pipeline.occupancy_threshold "
                          "(default: the settings', else the model's recommended value, else 0)")
    mdl.add_argument("--r0", type=float, default=None,
                     help="smallest landing radius in metres, = --set pipeline.r0_m")
    mdl.add_argument("--head-height", type=float, default=None,
                     help="head-plane height above ground in metres, = --set pipeline.head_height_m")
    mdl.add_argument("--model-color", choices=("bgr", "rgb", "gray"), default=None,
                     help="override the model's input channel order")
    mdl.add_argument("--model-scale", default=None, help="override the multiplier on 0-255 pixels")
    mdl.add_argument("--model-stride", default=None, help="override the model's output stride")
    mdl.add_argument("--model-set", type=_key_value, action="append", default=[], metavar="KEY=VALUE",
                     help="any density-model setting (color, scale, mean, std, stride, ...); repeatable")
    out = parser.add_argument_group("outputs")
    out.add_argument("--jsonl", type=Path, default=None, help="write one JSON object per frame")
    out.add_argument("--masks", type=Path, default=None,
                     help="folder for per-frame occupancy PNGs (255 = occupied, 0 = free)")
    out.add_argument("--video-out", type=Path, default=None, help="annotated video (.mp4 or .avi)")
    out.add_argument("--video-fps", type=float, default=None,
                     help="frame rate of --video-out (default: the input's)")
    out.add_argument("--flight-zones", action="store_true",
                     help="in --video-out, draw the zones and the target the flight recorded (its ids, the zone it "
                          "flew to) over the replay's maps instead of the replay's own; the summary counts the "
                          "frames whose replayed zone ids differ from the flight's (recordings only)")
    out.add_argument("--summary-json", type=Path, default=None, help="also write the summary as JSON")
    out.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                     help="progress bar on stderr (default: only when stderr is a terminal)")
    many = parser.add_argument_group("several inputs (a fleet's recordings)")
    many.add_argument("--out-dir", type=Path, default=None,
                      help="one folder per input under DIR (frames.jsonl, summary.json, the video "
                           "with --videos) and the summary table DIR/summary.json, DIR/summary.csv; "
                           "required with several inputs")
    many.add_argument("--videos", action="store_true",
                      help=f"also write each input's annotated video (DIR/NAME/{batch.VIDEO_NAME})")
    many.add_argument("--workers", type=batch.parse_workers, default=1, metavar="N|auto",
                      help="replay N inputs at a time in worker processes (default 1: one after "
                           "another in this process; auto: as many as the CPUs hold at --threads each)")
    many.add_argument("--ray", default=None, metavar="ADDRESS|auto",
                      help="run each input as a Ray task on the cluster at ADDRESS (auto: the one "
                           "ray.init() finds, else a local Ray started here); needs the extra: "
                           "pip install '.[scale]'")


class _Fail(batch.InputFailed):
    """A user-facing error: message for stderr, exit status 2 (with several inputs: the message
    of the input's row)."""


def _projection(args: argparse.Namespace) -> PlaneProjection | None:
    if args.nadir and args.homography is not None:
        raise _Fail("--nadir and --homography are alternatives; give one")
    if args.gsd is not None and not args.nadir:
        raise _Fail("--gsd is only used with --nadir")
    if args.nadir:
        if args.gsd is None:
            raise _Fail("--nadir needs --gsd M (metres per pixel on the head plane)")
        try:
            return PlaneProjection.nadir(args.gsd)
        except GeometryError as exc:
            raise _Fail(f"--gsd: {exc}") from None
    if args.homography is not None:
        try:
            return projection_from_file(args.homography)
        except HomographyFileError as exc:
            raise _Fail(f"--homography: {exc}") from None
    return None


def _model_overrides(args: argparse.Namespace, cfg: Config) -> dict[str, Any]:
    given: dict[str, Any] = {**cfg.model.overrides, **dict(args.model_set)}
    for key in ("color", "scale", "stride"):
        value = getattr(args, f"model_{key}")
        if value is not None:
            given[key] = value
    return given


def _settings(args: argparse.Namespace, source: ReplaySource) -> tuple[Config, str]:
    """The settings to replay with and where they came from: the recording's own (the ones it
    flew with), unless ``--config`` or ``--default-settings`` says otherwise; then ``--set`` and
    the shorthand flags on top."""
    overrides: dict[str, Any] = {}
    for item in args.set_:
        key, value = settings.parse_assignment(item)
        overrides[key] = value
    for flag, key in (("threshold", "pipeline.occupancy_threshold"), ("r0", "pipeline.r0_m"),
                      ("head_height", "pipeline.head_height_m")):
        if getattr(args, flag) is not None:
            overrides[key] = getattr(args, flag)
    if args.config is not None and args.default_settings:
        raise _Fail("--config and --default-settings are alternatives; give one")
    recorded = source.meta.get("config") if source.kind == "recording" else None
    try:
        if args.config is not None:
            cfg, origin = settings.load(args.config, overrides), f"the file {args.config}"
        elif isinstance(recorded, dict) and not args.default_settings:
            cfg = settings.from_recording(recorded, overrides)
            origin = f"the recording ({source.path / 'meta.json'})"
        else:
            cfg = settings.load(None, overrides)
            origin = "the built-in defaults" + (" (the recording holds none)" if source.kind == "recording"
                                                and not args.default_settings else "")
    except ConfigError as exc:
        raise _Fail(f"settings: {exc}") from None
    if overrides:
        origin += " with " + ", ".join(f"{k}={v}" for k, v in overrides.items())
    return cfg, origin


def _load_model(args: argparse.Namespace, cfg: Config, from_recording: bool) -> DensityModel:
    if args.model is not None:
        path = args.model
    else:
        recorded = Path(cfg.model.path)
        path = recorded if from_recording and recorded.is_file() else SHIPPED_MODEL
        if not path.is_file():
            raise _Fail(f"the shipped density model {path} is missing; pass --model FILE")
    try:
        return DensityModel(path, threads=args.threads, overrides=_model_overrides(args, cfg))
    except DensityModelError as exc:
        raise _Fail(f"--model: {exc}") from None


def _load_surface(args: argparse.Namespace, cfg: Config, from_recording: bool) -> UnlandableMap | None:
    """The landability model when the settings switch it on (the recording's file when it is
    still there, else the shipped one), bound to ``pipeline.unlandable_levels``."""
    if not cfg.model.landability:
        return None
    recorded = Path(cfg.model.landability_path)
    path = recorded if (recorded.is_file() or not from_recording) else SHIPPED_LANDABILITY
    try:
        return LandabilityModel(path, threads=args.threads).unlandable(cfg.pipeline.unlandable_levels or None)
    except DensityModelError as exc:
        raise _Fail(f"model.landability_path: {exc}") from None


def _config(cfg: Config, model: DensityModel) -> PipelineConfig:
    try:
        return settings.pipeline_config(cfg, model.spec)
    except ValueError as exc:
        raise _Fail(str(exc)) from None


@dataclass(frozen=True)
class OutputPaths:
    """Where one replay writes (each optional): ``--jsonl``, ``--masks``, ``--video-out``."""

    jsonl: Path | None = None
    masks: Path | None = None
    video: Path | None = None


def _check_options(args: argparse.Namespace) -> PlaneProjection | None:
    """The option errors that do not depend on the input (raised before any input is opened);
    the fixed projection, if any."""
    if args.max_frames is not None and args.max_frames < 1:
        raise _Fail(f"--max-frames must be >= 1, got {args.max_frames}")
    return _projection(args)


def replay_input(args: argparse.Namespace, path: Path, out: OutputPaths,
                 progress: bool | None) -> dict[str, Any]:
    """Replay one input with the command's options into ``out``: the summary dict (with
    ``input``, ``model``, ``occupancy_threshold``, ``r_0`` and ``settings``); a problem with the
    input, the options, the model or an output raises :class:`_Fail` naming it. The one code path
    of a single replay and of each input of several."""
    projection = _check_options(args)
    try:
        source = open_input(path, args.input_kind, args.fps)
    except ReplayInputError as exc:
        raise _Fail(str(exc)) from None
    use_pose = projection is None
    if use_pose and source.kind != "recording":
        raise _Fail(f"{path} has no poses ({source.kind}): give --nadir --gsd M or "
                    "--homography FILE")
    if use_pose and source.intrinsics is None:
        raise _Fail(f"recording {path} has no camera intrinsics: give --nadir --gsd M or "
                    "--homography FILE")
    zones = None
    if getattr(args, "flight_zones", False):
        if source.kind != "recording":
            raise _Fail(f"--flight-zones needs a flight recording; {path} is a {source.kind}")
        try:
            zones = flight_zones(RecordingReader(path).events("zones"))
        except RecordingError as exc:
            raise _Fail(f"--flight-zones: {exc}") from None
    cfg, origin = _settings(args, source)
    model = _load_model(args, cfg, origin.startswith("the recording"))
    surface = _load_surface(args, cfg, origin.startswith("the recording"))
    config = _config(cfg, model)
    planner = ZonePlanner(settings.planner_config(cfg))
    pipe = SLZPipeline(model, config, intrinsics=source.intrinsics if use_pose else None,
                       mount=source.mount if use_pose else None, projection=projection, surface=surface)

    video = None
    if out.video is not None:
        rate = args.video_fps or source.fps or 10.0
        if not (math.isfinite(rate) and rate > 0):
            raise _Fail(f"--video-fps must be > 0, got {rate!r}")
        video = VideoOut(out.video, rate)
    jsonl = None
    try:
        if out.jsonl is not None:
            try:
                out.jsonl.parent.mkdir(parents=True, exist_ok=True)
                jsonl = open(out.jsonl, "w", encoding="utf-8")
            except OSError as exc:
                raise _Fail(f"--jsonl: cannot write {out.jsonl}: {exc}") from None
        if out.masks is not None and out.masks.exists() and not out.masks.is_dir():
            raise _Fail(f"--masks: {out.masks} exists and is not a folder")
        try:
            summary = replay(source, pipe, ReplayOutputs(jsonl, out.masks, video), use_pose,
                             max_frames=args.max_frames, progress=progress, planner=planner,
                             descent=settings.descent_profile(cfg), land_agl_m=cfg.controller.land_agl_m,
                             flight_zones=zones)
        except ReplayOutputError as exc:
            raise _Fail(str(exc)) from None
    finally:
        if jsonl is not None:
            jsonl.close()
    summary["input"] = {"path": str(path), "kind": source.kind}
    summary["model"] = str(model.path)
    summary["landability_model"] = None if surface is None else str(surface.model.path)
    summary["occupancy_threshold"] = config.occupancy.threshold
    summary["r_0"] = config.r0_m
    summary["settings"] = origin
    return summary


def write_summary_json(path: Path, summary: dict[str, Any], what: str = "--summary-json") -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    except OSError as exc:
        raise _Fail(f"{what}: cannot write {path}: {exc}") from None


def replay_job(job: batch.ReplayJob) -> dict[str, Any]:
    """One input of several (run by :func:`companion.parallel.fan_out`, maybe in another process):
    :func:`replay_input` into the input's folder, its ``summary.json`` written there."""
    if not logging.getLogger().handlers:  # a fresh worker process: log as `companion` does
        logging.basicConfig(level=getattr(logging, getattr(job.options, "log_level", "INFO")),
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    outputs = OutputPaths(jsonl=job.out / batch.FRAMES_NAME,
                          video=job.out / batch.VIDEO_NAME if job.videos else None)
    with batch.log_prefix(job.name):
        summary = replay_input(job.options, Path(job.input), outputs, job.progress)
    write_summary_json(job.out / batch.SUMMARY_NAME, summary, "summary")
    return summary


_ONE_FILE_OPTIONS = (("jsonl", "--jsonl"), ("masks", "--masks"), ("video_out", "--video-out"),
                     ("summary_json", "--summary-json"))


def _run_many(args: argparse.Namespace, inputs: list[batch.Input]) -> int:
    if args.out_dir is None:
        raise _Fail(f"{len(inputs)} inputs: give --out-dir DIR (one folder per input and a summary "
                    "table there)")
    for attr, flag in _ONE_FILE_OPTIONS:
        if getattr(args, attr) is not None:
            raise _Fail(f"{flag} names one file; with --out-dir every input gets its own "
                        f"(DIR/NAME/{batch.FRAMES_NAME}, {batch.SUMMARY_NAME}, --videos)")
    _check_options(args)
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise _Fail(f"--out-dir: {args.out_dir} exists and is not a folder")
    try:
        return batch.run(inputs, args, replay_job, out_dir=args.out_dir, videos=args.videos,
                         workers=args.workers, ray_address=args.ray, threads=args.threads)
    except batch.BatchError as exc:
        raise _Fail(str(exc)) from None


def _run(args: argparse.Namespace) -> int:
    inputs = batch.expand_inputs(args.inputs)
    if len(inputs) != 1 or args.out_dir is not None:
        return _run_many(args, inputs)
    if inputs[0].problem is not None:
        raise _Fail(inputs[0].problem)
    if args.videos:
        raise _Fail("--videos is for several inputs (with --out-dir); give --video-out FILE")
    path = Path(inputs[0].path)
    summary = replay_input(args, path, OutputPaths(args.jsonl, args.masks, args.video_out), args.progress)
    print(format_summary(summary))
    print(f"settings: from {summary['settings']}")
    if args.summary_json is not None:
        write_summary_json(args.summary_json, summary)
    if summary["frames"] == 0:
        print(f"companion replay: error: no frame of {path} could be processed "
              f"({summary['frames_skipped']} skipped)", file=sys.stderr)
        return 1
    return 0


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except _Fail as exc:
        print(f"companion replay: error: {exc}", file=sys.stderr)
        return 2
