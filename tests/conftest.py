"""Shared test fixtures.

Data sets live in ``../shared`` beside the repository on developer machines and in CI; a user's
clone has none, so tests that need them skip with a reason instead of failing.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("COMPANION_SHARED", REPO.parent / "shared"))
MODEL = REPO / "companion" / "models" / "slz-density-v4.onnx"  # the default (companion.config.SHIPPED_MODEL)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared``, or a skip when it is absent (as in a user's fresh clone)."""
    if not (SHARED / "data").is_dir():
        pytest.skip(f"needs the shared data sets at {SHARED} (absent: this is a plain clone)")
    return SHARED


@pytest.fixture(scope="session")
def model_path() -> Path:
    """The shipped density model; it is committed, so its absence is a failure, not a skip."""
    assert MODEL.is_file(), f"the shipped density model {MODEL} is missing"
    return MODEL
