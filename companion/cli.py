"""The companion command line: a service that lands a drone away from people.

Each sub-command lives in its own module, which provides ``configure(parser)`` to add its
arguments and ``run(args) -> int`` to execute it. Modules are imported only when their command
runs, so ``companion bench`` does not pay for the MAVLink stack and a broken optional part cannot
stop the others from starting.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from companion import __version__

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("companion.service.cli", "run the service against a flight controller (the daemon)"),
    "demo": ("sim.flights.demo", "fly the simulator over a crowd, trigger a failsafe and land safely"),
    "replay": ("companion.replay.cli", "run the pipeline offline over a recording, video or frames"),
    "eval": ("companion.evaluation.cli", "measure a density model on the crowd data sets"),
    "bench": ("companion.bench", "measure per-stage latency of the pipeline"),
    "train-landability": ("companion.training.landability",
                          "train the landability model (water, vehicles, trees, roofs) on the semantic-drone photos"),
    "sim": ("sim.flights.standalone", "run the simulated vehicle and camera on their own"),
    "sim-scenarios": ("sim.flights.scenarios", "fly N seeded random scenarios and report safety figures"),
    "sim-compare": ("sim.evidence.compare", "compare two sim-scenarios results files seed by seed, with exact tests"),
    "signing-key": ("companion.mavlink.keygen", "make a MAVLink signing key file for the link"),
    "check-config": ("companion.service.check_config",
                     "validate a configuration file and print the settings it resolves to"),
}

#: Optional packages -> the extra that installs them (pyproject.toml). A command that needs one
#: that is missing says which extra to install, instead of a traceback.
EXTRAS: dict[str, str] = {
    "tqdm": "tools", "av": "tools", "torch": "train", "onnx": "train", "ray": "scale",
    "mavsdk": "dev",
}


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The message for a missing optional package, or None when ``exc`` is not about one."""
    top = (exc.name or "").split(".")[0]
    if top not in EXTRAS:
        return None
    return (f"this command needs the optional package '{top}': "
            f"pip install 'companion-slz[{EXTRAS[top]}]'")


def _add_log_level(parser: argparse.ArgumentParser, default: object) -> None:
    parser.add_argument(
        "--log-level",
        default=default,
        type=str.upper,
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging level for stderr (journald under systemd); default INFO",
    )


def build_parser(chosen: str | None) -> tuple[argparse.ArgumentParser, object | None]:
    """The parser, with the arguments of ``chosen`` (the one command that will run) filled in."""
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0],
                                     epilog="'companion COMMAND --help' describes each command.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _add_log_level(parser, "INFO")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen_module = None
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        _add_log_level(p, argparse.SUPPRESS)
        if name != chosen:
            continue
        try:
            chosen_module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            extra = missing_extra(exc)
            if extra is not None:
                p.description = f"{help_text}. Not available here: {extra}"
                p.set_defaults(_unavailable=f"'{name}': {extra}")
                continue
            if not (exc.name and module_name.startswith(exc.name)):
                raise
            p.set_defaults(_unavailable=f"'{name}' is not available in this build ({exc.name} missing)")
            continue
        chosen_module.configure(p)
    return parser, chosen_module


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    chosen = next((a for a in argv if a in COMMANDS), None)
    parser, module = build_parser(chosen)
    if chosen is not None and module is None:
        # The command's own arguments are unknown without its module: say what to install.
        args, _unknown = parser.parse_known_args(argv)
    else:
        args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if args.command is None:
        parser.print_help()
        return 2
    if getattr(args, "_unavailable", None) or module is None:
        print(f"companion: {getattr(args, '_unavailable', 'command not available')}", file=sys.stderr)
        return 2
    try:
        return int(module.run(args) or 0)  # type: ignore[attr-defined]
    except ModuleNotFoundError as exc:  # an optional package imported only on the way (e.g. av)
        message = missing_extra(exc)
        if message is None:
            raise
        print(f"companion: {args.command}: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
