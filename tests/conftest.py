"""Shared test fixtures.

Data sets live in ``../shared`` beside the repository on developer machines and in CI; a user's
clone has none, so tests that need them skip with a reason instead of failing.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests import early

REPO = Path(__file__).resolve().parents[1]
#: Every test that flies the simulator (marked ``sitl``, or starting a simulator or a flight) is in
#: this folder: the second lane of the test command (.ci/tests), after the fast lane.
FLIGHTS = Path(__file__).resolve().parent / "flights"
SHARED = Path(os.environ.get("COMPANION_SHARED", REPO.parent / "shared"))
MODEL = REPO / "companion" / "models" / "slz-density-v4.onnx"  # the default (companion.config.SHIPPED_MODEL)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared``, or a skip when it is absent (as in a user's fresh clone)."""
    if not (SHARED / "data").is_dir():
        pytest.skip(f"needs the shared data sets at {SHARED} (absent: this is a plain clone)")
    return SHARED


#: The held-out full-size semantic-drone photos the photo world is built from (``--photos``).
PHOTOS = SHARED / "data" / "semantic_drone" / "full"


def held_out_photos() -> str | None:
    """:data:`PHOTOS` resolved (as a string), or None when they are absent: for what runs
    outside a test (an early batch), where the :func:`photos` fixture's skip cannot."""
    return str(PHOTOS.resolve()) if (PHOTOS / "images").is_dir() else None


@pytest.fixture(scope="session")
def photos(shared_dir: Path) -> str:
    """The held-out full-size semantic-drone photos the photo world is built from (its
    ``--photos`` folder, as a string), or a skip when they are absent."""
    folder = held_out_photos()
    if folder is None:
        pytest.skip(f"needs the held-out full-size photos at {PHOTOS}")
    return folder


@pytest.fixture(scope="session")
def model_path() -> Path:
    """The shipped density model; it is committed, so its absence is a failure, not a skip."""
    assert MODEL.is_file(), f"the shipped density model {MODEL} is missing"
    return MODEL


#: Semantic-drone photos kept by ``few_photos_shared``: the first 25 by name, so 5 held out
#: (every fifth by sorted index, as in the full set) and 20 for training.
FEW_PHOTOS = 25


def few_photos_tree(shared: Path, root: Path) -> Path:
    """Lay out ``root`` as ``shared`` with only the first ``FEW_PHOTOS`` semantic-drone photos
    (and their class maps), every other file and data set as it is: links to the same files, laid
    out alike, so the loaders read it as they read ``shared``. Returns ``root``."""
    root.mkdir(parents=True)
    for entry in shared.iterdir():
        if entry.name != "data":
            (root / entry.name).symlink_to(entry)
    (root / "data").mkdir()
    for entry in (shared / "data").iterdir():
        if entry.name != "semantic_drone":
            (root / "data" / entry.name).symlink_to(entry)
    src = shared / "data" / "semantic_drone"
    dst = root / "data" / "semantic_drone"
    (dst / "images").mkdir(parents=True)
    (dst / "labels").mkdir()
    for entry in src.iterdir():
        if entry.is_file():
            (dst / entry.name).symlink_to(entry)
    for entry in (src / "labels").iterdir():
        if entry.suffix != ".png":  # classes.txt
            (dst / "labels" / entry.name).symlink_to(entry)
    for photo in sorted((src / "images").glob("*.jpg"))[:FEW_PHOTOS]:
        (dst / "images" / photo.name).symlink_to(photo)
        label = src / "labels" / f"{photo.stem}.png"
        (dst / "labels" / label.name).symlink_to(label)
    return root


@pytest.fixture(scope="session")
def few_photos_shared(shared_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``../shared`` with only the first ``FEW_PHOTOS`` semantic-drone photos (:func:`few_photos_tree`).
    For commands that load every photo of a split (the compositor's people and ground, seconds on
    the full set) where how many photos they draw from is not what a test shows. The held-out
    split's first photos are the full set's."""
    return few_photos_tree(shared_dir, tmp_path_factory.mktemp("few_photos") / "shared")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test marked ``sitl`` outside tests/flights would run in the fast lane (.ci/tests runs
    ``tests --ignore=tests/flights`` first): refuse it, naming where it belongs."""
    stray = [item.nodeid for item in items
             if item.get_closest_marker("sitl") is not None and not item.path.resolve().is_relative_to(FLIGHTS)]
    if stray:
        raise pytest.UsageError("tests marked sitl fly the simulator and belong in tests/flights/: "
                                + ", ".join(stray))


def pytest_collection_finish(session: pytest.Session) -> None:
    """Start the commands of the selected tests marked ``started_early`` (tests/early.py)."""
    if os.environ.get("PYTEST_XDIST_WORKER") or session.config.option.collectonly:
        return
    early.start([marker.args[0] for item in session.items
                 if (marker := item.get_closest_marker("started_early")) is not None])


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    early.stop_all()
