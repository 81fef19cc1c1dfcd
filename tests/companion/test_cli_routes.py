"""The simulator's commands reach `companion` through a declared route (the `companion.commands`
entry points of pyproject.toml), never by importing `sim` by name: listed where the simulator is
installed, a clear message (no traceback) where it is not or where a route is broken."""

from __future__ import annotations

import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from companion import cli
from tests import early

SIM_COMMANDS = ("demo", "sim", "sim-scenarios", "sim-compare")


def test_the_simulators_commands_are_routed_by_entry_points_and_listed() -> None:
    found = cli.routes()
    assert set(SIM_COMMANDS) <= set(found), "pip install -e '.[dev]' registers the entry points"
    for name in SIM_COMMANDS:
        route = found[name]
        assert route.command is not None and route.error is None and route.target.startswith("sim.commands:")
        assert name not in cli.COMMANDS  # the service's own table names nothing of the simulator
    names = cli.command_names(found)
    assert names[:len(cli.COMMANDS)] == list(cli.COMMANDS) and set(SIM_COMMANDS) <= set(names)
    help_text = cli.build_parser(None, found)[0].format_help()
    assert all(f"    {name} " in help_text for name in SIM_COMMANDS), help_text


def test_a_routed_command_runs_its_modules_configure(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        cli.main(["sim-scenarios", "--help"])
    assert exit_.value.code == 0
    assert "--lockstep" in capsys.readouterr().out


#: What a process that imports ``companion.cli`` with the simulator absent does.
WITHOUT_SIM = "import sys; sys.modules['sim'] = None; from companion.cli import main; "


@early.batch("cli-routes")
def _cli_routes(folder: Path) -> list[early.Run]:
    """This module's processes (each imports the package: they start side by side once the
    session knows it runs their tests, tests/early.py): the modules ``companion.cli`` imports;
    ``--help`` and ``demo`` without the simulator; ``check-config --help`` listing what it loaded."""
    imports = "import sys, companion.cli; print(sorted(m for m in sys.modules if m == 'sim' or m.startswith('sim.')))"
    check = ("import atexit, sys; atexit.register(lambda: print(sorted(m for m in sys.modules "
             "if m == 'sim' or m.startswith('sim.')), file=sys.stderr)); "
             "from companion.cli import main; main(['check-config', '--help'])")
    return [early.Run([sys.executable, "-c", code], cwd) for code, cwd in (
        (imports, None), (WITHOUT_SIM + "sys.exit(main(['--help']))", None),
        (WITHOUT_SIM + "sys.exit(main(['demo']))", None), (check, folder))]


@pytest.mark.started_early("cli-routes")
def test_the_command_line_imports_nothing_of_the_simulator() -> None:
    r = early.result("cli-routes")[1][0]
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


@pytest.mark.started_early("cli-routes")
def test_without_the_simulator_its_commands_are_not_listed_and_asking_for_one_says_why() -> None:
    # sys.modules["sim"] = None makes importing it fail exactly as an absent package does (WITHOUT_SIM).
    listing, asked = early.result("cli-routes")[1][1:3]
    assert listing.returncode == 0 and "check-config" in listing.stdout, listing.stderr
    assert "sim-scenarios" not in listing.stdout and "demo" not in listing.stdout, listing.stdout
    assert asked.returncode == 2 and "Traceback" not in asked.stderr, asked.stderr
    assert "'demo' comes from a package that is not installed here" in asked.stderr, asked.stderr


def test_a_broken_route_is_listed_as_unavailable_and_says_why(monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    eps = [EntryPoint("sim-broken", "sim.commands:NO_SUCH_COMMAND", cli.ROUTE_GROUP),
           EntryPoint("sim-not-a-command", "sim.commands:ModuleType", cli.ROUTE_GROUP),
           EntryPoint("run", "sim.commands:DEMO", cli.ROUTE_GROUP)]  # may not take over the service's own

    def entry_points(group: str) -> list[EntryPoint]:
        assert group == cli.ROUTE_GROUP
        return eps

    monkeypatch.setattr(cli, "entry_points", entry_points)
    found = cli.routes()
    assert set(found) == {"sim-broken", "sim-not-a-command"}
    assert "AttributeError" in (found["sim-broken"].error or "") and found["sim-broken"].installed
    assert "not a Command" in (found["sim-not-a-command"].error or "")
    assert "not available" in cli.build_parser(None, found)[0].format_help()
    assert cli.main(["sim-broken"]) == 2
    err = capsys.readouterr().err
    assert "'sim-broken' is declared (sim.commands:NO_SUCH_COMMAND) but cannot be loaded" in err, err
    assert "pip install -e ." in err


@pytest.mark.started_early("cli-routes")
def test_the_services_own_commands_load_nothing_of_the_simulator() -> None:
    # `companion run` (the daemon on the vehicle) and the other own commands never import sim.
    r = early.result("cli-routes")[1][3]
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip().splitlines()[-1] == "[]", r.stderr
