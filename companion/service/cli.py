"""``companion run``: the daemon's command line.

Exit codes: 0 after a clean stop (SIGTERM/SIGINT), 1 on a runtime failure (systemd restarts it),
2 on a configuration, model or camera-source error that a restart cannot fix (the unit's
``RestartPreventExitStatus=2``); the message names the key or file.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from typing import Any

from companion import config as config_mod
from companion.config import ConfigError

log = logging.getLogger("companion.service")

EXIT_OK, EXIT_FAILURE, EXIT_CONFIG = 0, 1, 2


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE",
                        help="TOML configuration (default: built-in defaults, the simulator's)")
    parser.add_argument("--link", metavar="URL", help="MAVLink URL, e.g. udpin:0.0.0.0:14550 (link.url)")
    parser.add_argument("--camera", metavar="SOURCE",
                        help="camera device, file, folder, URL or gst: pipeline (camera.source)")
    parser.add_argument("--model", metavar="FILE", help="ONNX density model (model.path)")
    parser.add_argument("--record", metavar="DIR", help="record the flight into DIR (recorder.enabled, .dir)")
    parser.add_argument("--flavour", choices=config_mod.FLAVOURS, help="autopilot dialect (link.flavour)")
    parser.add_argument("--shadow", action="store_true",
                        help="shadow mode: watch, decide and report what it would do, command nothing "
                             "(controller.shadow)")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="set_",
                        help="set any config key, e.g. --set camera.fps=15 (repeatable)")


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Dotted-key overrides from the command line (``--set`` last, so it wins)."""
    out: dict[str, Any] = {}
    for opt, key in (("link", "link.url"), ("camera", "camera.source"), ("model", "model.path"),
                     ("flavour", "link.flavour")):
        value = getattr(args, opt, None)
        if value is not None:
            out[key] = value
    if getattr(args, "shadow", False):
        out["controller.shadow"] = True
    if getattr(args, "record", None):
        out["recorder.enabled"] = True
        out["recorder.dir"] = args.record
    for item in getattr(args, "set_", []) or []:
        key, value = config_mod.parse_assignment(item)
        out[key] = value
    return out


def _apply_log_level(cfg: config_mod.Config) -> None:
    # --log-level on the command line wins; otherwise the config's log.level applies.
    if any(a == "--log-level" or a.startswith("--log-level=") for a in sys.argv[1:]):
        return
    logging.getLogger().setLevel(getattr(logging, cfg.log.level))


def run(args: argparse.Namespace) -> int:
    try:
        cfg = config_mod.load(args.config, overrides_from_args(args))
    except ConfigError as exc:
        print(f"companion: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    _apply_log_level(cfg)

    from companion.config import signing_key
    from companion.pipeline.density import DensityModelError
    from companion.service.app import Service
    from companion.service.camera import CameraError, check_source, classify
    from companion.service.parts import load_landability, load_model

    try:
        signing_key(cfg)
        classify(cfg.camera.source)
    except ConfigError as exc:
        print(f"companion: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except CameraError as exc:
        print(f"companion: camera error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    log.info("loading density model %s", cfg.model.path)
    try:
        model = load_model(cfg)
        if cfg.model.landability:
            log.info("loading landability model %s", cfg.model.landability_path)
        surface = load_landability(cfg)
    except DensityModelError as exc:  # the landability model's errors are DensityModelErrors too
        print(f"companion: model error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        check_source(cfg.camera.source)  # an empty frames folder: a start-up error, not a crash loop
    except CameraError as exc:
        print(f"companion: camera error: {exc}", file=sys.stderr)
        return EXIT_CONFIG

    async def main() -> int:
        return await Service(cfg, model, surface=surface).run()

    try:
        return asyncio.run(main())
    except ConfigError as exc:
        print(f"companion: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:
        return EXIT_OK
