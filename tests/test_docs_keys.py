"""Every configuration key the documentation names exists, and every link it makes resolves.

The settings schema is ``companion/config/schema.py`` (``config.all_keys()``). The documents are the
README, CONTRIBUTING, ``docs/*.md``, the model card and ``companion.example.toml``. A key is
"named" when it is written as ``section.key`` in backticks (``pipeline.r0_m``, ``--set
camera.fps=15``), as a line of a TOML code block (checked under its ``[section]``, and the block
must validate), or as a commented-out ``key =`` line in the example file. A key listed as
removed (``config.REMOVED``, ``companion/config/removed.py``: a switch whose measurement lost, or tuning that became a constant)
may be named too, and only those: docs/measurements.md keeps their history. The example file
names live keys only.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from companion import config

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
DOCS = sorted([REPO / "README.md", REPO / "CONTRIBUTING.md", REPO / "companion" / "models" / "MODEL_CARD.md",
               *(REPO / "docs").glob("*.md")])
EXAMPLE = REPO / "companion.example.toml"

KEYS = {key for key, _default, _doc in config.all_keys()}
TABLE_KEYS = {key for key, default, _doc in config.all_keys() if isinstance(default, dict)}  # free-form tables
SECTIONS = {key.rsplit(".", 1)[0] for key in KEYS if "." in key}
REMOVED = set(config.REMOVED) | set(config.REMOVED_TABLES)
TOP = sorted({key.split(".")[0] for key in KEYS | REMOVED})
DOTTED = re.compile(r"(?<![\w./-])((?:" + "|".join(TOP) + r")(?:\.[a-z_0-9]+)+)(?![\w/-]|\.[a-z])")


def _live(dotted: str) -> bool:
    return dotted in KEYS or dotted in SECTIONS or any(dotted.startswith(t + ".") for t in TABLE_KEYS)


def _known(dotted: str) -> bool:
    """A live key or section, or one the schema lists as removed."""
    return _live(dotted) or dotted in REMOVED


def _backticked_keys(text: str) -> list[str]:
    out = []
    for span in re.findall(r"`([^`\n]+)`", text):
        out += [k for k in DOTTED.findall(span) if not re.search(r"\.(py|md|toml|onnx|json|jsonl)$", k)]
    return out


def _toml_blocks(text: str) -> list[str]:
    return re.findall(r"^```toml\n(.*?)^```", text, re.M | re.S)


def _flatten(table: dict[str, object], prefix: str = "") -> list[str]:
    out = []
    for key, value in table.items():
        dotted = prefix + key
        if isinstance(value, dict) and dotted not in TABLE_KEYS:
            out += _flatten(value, dotted + ".")
        else:
            out.append(dotted)
    return out


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_key_a_document_names_exists(doc: Path) -> None:
    text = doc.read_text()
    unknown = sorted({k for k in _backticked_keys(text) if not _known(k)})
    assert not unknown, f"{doc.name} names keys the settings do not have: {unknown}"
    for block in _toml_blocks(text):
        raw = tomllib.loads(block)
        unknown = sorted(k for k in _flatten(raw) if not _known(k))
        assert not unknown, f"{doc.name}: a TOML example sets keys the settings do not have: {unknown}"
        config.from_dict(_without_removed(raw))  # and the values are valid


def _without_removed(raw: dict[str, object], prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in raw.items():
        dotted = prefix + key
        if dotted in REMOVED:
            continue
        out[key] = _without_removed(value, dotted + ".") if isinstance(value, dict) and dotted not in TABLE_KEYS \
            else value
    return out


def test_the_examples_commented_out_keys_exist() -> None:
    section = ""
    for line in EXAMPLE.read_text().splitlines():
        if m := re.match(r"^\[([a-z_.0-9]+)\]", line):
            section = m.group(1)
            assert section in SECTIONS, f"[{section}] is not a section"
        elif m := re.match(r"^#\s*([a-z_0-9]+) = ", line):
            assert _live(f"{section}.{m.group(1)}"), f"commented-out key {section}.{m.group(1)} does not exist"
    assert _backticked_keys(EXAMPLE.read_text()) == [k for k in _backticked_keys(EXAMPLE.read_text()) if _live(k)]


def test_the_checker_catches_a_wrong_key() -> None:
    # The test above would pass on documents that name no key at all: show that it finds one.
    assert _backticked_keys("set `failsafe.gcs_sysids` or `--set camera.fps=15`; see `camera.py`") == [
        "failsafe.gcs_sysids", "camera.fps"]
    assert not _known("failsafe.gcs_sysids") and _known("camera.fps") and _known("model.overrides.color")
    # A removed key may be named (its history), a misspelt removed key may not.
    assert _known("controller.hold_looks") and not _live("controller.hold_looks")
    assert _known("pipeline.tracker.mu_1") and not _known("controller.hold_lookz")
    assert sum(len(_backticked_keys(d.read_text())) for d in DOCS) > 30  # the documents do name keys


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(doc: Path) -> None:
    text = doc.read_text()
    missing = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue
        if not (doc.parent / target.split("#")[0]).exists():
            missing.append(target)
    assert not missing, f"{doc.name} links to files not in the repository: {missing}"
