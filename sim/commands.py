"""The simulator's commands of ``companion``, routed to it by entry points (pyproject.toml,
``[project.entry-points."companion.commands"]``), so that ``companion`` lists them only where the
simulator is installed and never imports it by name.

Each is a help line and a loader of the module that configures and runs it (``configure(parser)``,
``run(args) -> int``); ``companion --help`` imports only this module, and a command's module is
imported when that command runs.
"""

from __future__ import annotations

from types import ModuleType

from companion.cli import Command


def _demo() -> ModuleType:
    from sim.flights import demo

    return demo


def _standalone() -> ModuleType:
    from sim.flights import standalone

    return standalone


def _scenarios() -> ModuleType:
    from sim.flights import scenarios

    return scenarios


def _compare() -> ModuleType:
    from sim.evidence import compare

    return compare


DEMO = Command("fly the simulator over a crowd, trigger a failsafe and land safely", _demo)
SIM = Command("run the simulated vehicle and camera on their own", _standalone)
SIM_SCENARIOS = Command("fly N seeded random scenarios and report safety figures", _scenarios)
SIM_COMPARE = Command("compare two sim-scenarios results files seed by seed, with exact tests", _compare)
