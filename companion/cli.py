"""The companion command line: a service that lands a drone away from people.

Each sub-command lives in its own module, which provides ``configure(parser)`` to add its
arguments and ``run(args) -> int`` to execute it. Modules are imported only when their command
runs, so ``companion bench`` does not pay for the MAVLink stack and a broken optional part cannot
stop the others from starting.

The service's own commands are listed here (``COMMANDS``). Other packages add theirs through a
declared route, the ``companion.commands`` entry point group (pyproject.toml): each entry names a
:class:`Command`, a help line and a loader. The simulator's (``demo``, ``sim``, ``sim-scenarios``,
``sim-compare``) come that way from ``sim.commands``, so they are listed only where the simulator
is installed, and this module imports nothing of it.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from types import ModuleType

from companion import __version__

# The service's own commands: name -> (module, one-line help).
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("companion.service.cli", "run the service against a flight controller (the daemon)"),
    "replay": ("companion.replay.cli", "run the pipeline offline over a recording, video or frames"),
    "eval": ("companion.evaluation.cli", "measure a density model on the crowd data sets"),
    "bench": ("companion.bench", "measure per-stage latency of the pipeline"),
    "train-landability": ("companion.training.landability",
                          "train the landability model (water, vehicles, trees, roofs) on the semantic-drone photos"),
    "signing-key": ("companion.mavlink.keygen", "make a MAVLink signing key file for the link"),
    "check-config": ("companion.service.check_config",
                     "validate a configuration file and print the settings it resolves to"),
}

#: The entry point group through which other packages add commands (pyproject.toml,
#: ``[project.entry-points."companion.commands"]``): name = "module:Command object".
ROUTE_GROUP = "companion.commands"


@dataclass(frozen=True)
class Command:
    """A command another package adds to ``companion`` (an entry point of :data:`ROUTE_GROUP`):
    its one-line help, and ``load``, which imports and returns the module with
    ``configure(parser)`` and ``run(args) -> int``; called only when the command runs."""

    help: str
    load: Callable[[], ModuleType]


@dataclass(frozen=True)
class Route:
    """One declared route as found: the command, or why it cannot be loaded (``error``).
    ``installed`` is False when the package it points into is not installed at all."""

    name: str
    target: str  # the entry point's value, "module:attribute"
    command: Command | None
    error: str | None = None
    installed: bool = True


def routes() -> dict[str, Route]:
    """The commands other packages declare (:data:`ROUTE_GROUP`), by name, loading only their
    light descriptors. A name the service already has is not taken over; a route whose target
    cannot be loaded is kept with its reason, to be said when it is asked for."""
    found: dict[str, Route] = {}
    for ep in entry_points(group=ROUTE_GROUP):
        if ep.name in COMMANDS or ep.name in found:
            continue
        try:
            command = ep.load()
        except ModuleNotFoundError as exc:
            top = ep.value.split(":")[0]
            missing_package = bool(exc.name) and (top == exc.name or top.startswith(f"{exc.name}."))
            found[ep.name] = Route(ep.name, ep.value, None, f"{exc.name} is not installed",
                                   installed=not missing_package)
            continue
        except (ImportError, AttributeError) as exc:
            found[ep.name] = Route(ep.name, ep.value, None, f"{type(exc).__name__}: {exc}")
            continue
        if not isinstance(command, Command):
            found[ep.name] = Route(ep.name, ep.value, None, f"{ep.value} is a {type(command).__name__}, not a Command")
            continue
        found[ep.name] = Route(ep.name, ep.value, command)
    return found


def _route_error(route: Route) -> str:
    if not route.installed:
        return (f"'{route.name}' comes from a package that is not installed here ({route.error}; "
                f"declared as {route.target})")
    return (f"'{route.name}' is declared ({route.target}) but cannot be loaded: {route.error}; "
            "reinstall the package (pip install -e .)")


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


def command_names(found: dict[str, Route] | None = None) -> list[str]:
    """Every command ``companion`` offers here: its own, then those routed to it that load."""
    found = routes() if found is None else found
    return [*COMMANDS, *(name for name, route in found.items() if route.installed)]


def build_parser(chosen: str | None, found: dict[str, Route] | None = None
                 ) -> tuple[argparse.ArgumentParser, object | None]:
    """The parser, with the arguments of ``chosen`` (the one command that will run) filled in;
    ``found``: the routed commands (:func:`routes`, read when None)."""
    found = routes() if found is None else found
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0],
                                     epilog="'companion COMMAND --help' describes each command.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _add_log_level(parser, "INFO")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen_module = None
    # name -> (help, loader, the package whose absence means "not in this build")
    loaders: dict[str, tuple[str, Callable[[], ModuleType], str]] = {
        name: (help_text, functools.partial(importlib.import_module, module_name), module_name)
        for name, (module_name, help_text) in COMMANDS.items()}
    for name, route in found.items():
        if route.command is not None:
            loaders[name] = (route.command.help, route.command.load, route.target.split(".")[0])
    for name, route in found.items():
        if route.command is None and (route.installed or name == chosen):
            p = sub.add_parser(name, help=f"(not available: {route.error})", description=_route_error(route))
            _add_log_level(p, argparse.SUPPRESS)
            p.set_defaults(_unavailable=_route_error(route))
    for name, (help_text, load, package) in loaders.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        _add_log_level(p, argparse.SUPPRESS)
        if name != chosen:
            continue
        try:
            chosen_module = load()
        except ModuleNotFoundError as exc:
            extra = missing_extra(exc)
            if extra is not None:
                p.description = f"{help_text}. Not available here: {extra}"
                p.set_defaults(_unavailable=f"'{name}': {extra}")
                continue
            if not (exc.name and package.startswith(exc.name)):
                raise
            p.set_defaults(_unavailable=f"'{name}' is not available in this build ({exc.name} missing)")
            continue
        chosen_module.configure(p)
    return parser, chosen_module


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    routed = {ep.name for ep in entry_points(group=ROUTE_GROUP)}  # names only: nothing imported
    chosen = next((a for a in argv if a in COMMANDS or a in routed), None)
    # One of the service's own commands (the daemon above all) loads nothing another package declares.
    found = {} if chosen in COMMANDS else routes()
    parser, module = build_parser(chosen, found)
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
