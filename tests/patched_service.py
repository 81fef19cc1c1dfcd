"""Run the service of a simulated flight with some of its code patched, as a test needs to.

``patched_env(folder, code)`` writes ``code`` as a ``sitecustomize`` module (Python imports it
at start-up, before ``companion``) into ``folder`` and returns the ``FlightSpec.service_env``
that puts it first on the service's PYTHONPATH.
"""

from __future__ import annotations

import os
from pathlib import Path


def patched_env(folder: Path, code: str) -> tuple[tuple[str, str], ...]:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sitecustomize.py").write_text(code)
    pythonpath = os.pathsep.join(p for p in (str(folder), os.environ.get("PYTHONPATH", "")) if p)
    return (("PYTHONPATH", pythonpath),)
