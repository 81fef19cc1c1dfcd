"""The house rules, checked by the test command so that CI fails when one is broken: ruff's lint,
mypy (strict for the pure core), and the import contracts of docs/design.md ("Layers"), which
`lint-imports` checks from pyproject.toml. The last test breaks a contract on a copy of the tree
and expects the checker to say so."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests import early

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _tool(name: str) -> str:
    path = BIN / name
    if not path.exists():
        pytest.fail(f"{name} is not installed beside {sys.executable}: pip install -e '.[dev]'")
    return str(path)


def _run(args: list[str], cwd: Path = REPO, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=240, env=env)


def test_ruff_finds_nothing() -> None:
    res = _run([_tool("ruff"), "check", "."])
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.started_early("mypy")  # beside the tests before it (tests/early.py): same command, same check
def test_mypy_finds_nothing() -> None:
    _tool("mypy")
    (res,) = early.result("mypy")[1]
    assert res.returncode == 0, res.stdout + res.stderr


def test_import_contracts_hold() -> None:
    res = _run([_tool("lint-imports")])
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 broken" in res.stdout


@pytest.mark.parametrize("module, line, contract", [
    ("companion/control/planner.py", "import asyncio", "The core (geometry, pipeline, control) does no I/O"),
    ("companion/pipeline/tracker.py", "import companion.mavlink.link", "Layers: a lower layer never imports a higher one"),
    ("companion/mavlink/autopilot.py", "import companion.mavlink.px4", "MAVLink adapters"),
    ("sim/flights/flight.py", "import sim.flights.lockstep", "No import cycle"),
    ("sim/world/ground.py", "import sim.vehicle.kinematics", "The simulator's layers"),
])
def test_a_broken_contract_fails_the_check(tmp_path: Path, module: str, line: str, contract: str) -> None:
    for name in ("companion", "sim"):
        shutil.copytree(REPO / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    target = tmp_path / module
    text = target.read_text()
    head, sep, rest = text.partition("from __future__ import annotations\n")
    target.write_text(head + sep + f"\n{line}  # the forbidden import\n" + rest)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    res = _run([_tool("lint-imports")], cwd=tmp_path, env=env)
    assert res.returncode != 0, res.stdout
    # The named contract itself is reported broken (every contract's name is listed, kept or not).
    status = re.search(re.escape(contract) + r".*?\b(KEPT|BROKEN)\b", res.stdout.replace("\n", " "))
    assert status is not None and status.group(1) == "BROKEN", res.stdout
