"""``companion check-config FILE``: validate a configuration as ``companion run`` would, and print
the settings it resolves to.

It runs the start-up checks of ``companion run`` that need no vehicle and no camera: the file and
every key and value (``companion.config``), the signing key file, the camera source's form, and the
density model (loaded with onnxruntime, so a missing or malformed model is found here, not at the
first failsafe). It opens no socket and no camera.

Exit status: 0 when the service would start with it (the resolved settings go to stdout as TOML,
every key with its value, defaults and relative paths resolved); 2 with one line on stderr that
names the key or file otherwise, the same status ``companion run`` exits with on that error.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from companion import config as config_mod
from companion.config import ConfigError

EXIT_OK, EXIT_CONFIG = 0, 2


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", metavar="FILE", help="the TOML file companion run --config would read")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="set_",
                        help="override a key as companion run --set does (repeatable)")


def _toml_value(value: Any) -> str:
    if isinstance(value, dict):
        if not value:
            return "{}"
        return "{ " + ", ".join(f"{json.dumps(str(k))} = {_toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    # JSON's strings, numbers and true/false are TOML's too (the settings hold no NaN: validated).
    return json.dumps(value)


def to_toml(settings: dict[str, Any], prefix: str = "") -> list[str]:
    """``settings`` (Config.to_dict()) as TOML lines, one ``[table]`` per section."""
    leaf_keys = {key for key, _default, _doc in config_mod.all_keys()}
    leaves = {k: v for k, v in settings.items() if f"{prefix}{k}" in leaf_keys}
    sections = {k: v for k, v in settings.items() if k not in leaves}
    lines: list[str] = [f"[{prefix[:-1]}]"] if prefix and leaves else []
    lines += [f"{k} = {_toml_value(v)}" for k, v in leaves.items()]
    for name, sub in sections.items():
        lines += [""] + to_toml(sub, f"{prefix}{name}.")
    return lines


def check(cfg: config_mod.Config) -> None:
    """The start-up checks of ``companion run`` short of opening the link and the camera (a frames
    folder is read: at least one of its images must decode); raises
    ConfigError naming the key or file."""
    from companion.config import signing_key
    from companion.pipeline.density import DensityModelError
    from companion.service.camera import CameraError, check_source
    from companion.service.parts import load_landability, load_model

    signing_key(cfg)
    try:
        check_source(cfg.camera.source)
    except CameraError as exc:
        raise ConfigError(f"camera.source: {exc}") from None
    try:
        load_model(cfg)
    except DensityModelError as exc:
        raise ConfigError(f"model.path: {exc}") from None
    try:
        load_landability(cfg)
    except DensityModelError as exc:
        key = "" if str(exc).startswith("pipeline.") else "model.landability_path: "
        raise ConfigError(f"{key}{exc}") from None


def run(args: argparse.Namespace) -> int:
    try:
        overrides = dict(config_mod.parse_assignment(item) for item in args.set_)
        cfg = config_mod.load(args.config, overrides)
        check(cfg)
    except ConfigError as exc:
        print(f"companion: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    print(f"# {cfg.source}: valid; the settings companion run resolves from it")
    print("\n".join(to_toml(cfg.to_dict())))
    return EXIT_OK
