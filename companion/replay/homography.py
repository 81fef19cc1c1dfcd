"""Reading a user's fixed image-to-head-plane homography (pixels -> metres) from a file.

Accepted forms: ``.npy`` (a 3x3 array, or 9 numbers); ``.txt`` / ``.csv`` with 9 numbers in any
layout of commas and whitespace (typically 3 lines of 3); ``.json`` holding either a 3x3 nested
list, 9 numbers, or an object with the matrix under ``"H"``, ``"homography"`` or
``"image_to_plane"``. Shape and invertibility are checked by ``PlaneProjection``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from companion.geometry.camera import GeometryError, PlaneProjection

JSON_KEYS = ("H", "homography", "image_to_plane")


class HomographyFileError(ValueError):
    """A homography file that is missing, unreadable or not a usable 3x3 matrix."""


def _as_matrix(values: object, path: Path) -> np.ndarray:
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise HomographyFileError(f"{path}: the homography must be numbers") from None
    if a.size == 9 and a.ndim in (1, 2):
        a = a.reshape(3, 3)
    if a.shape != (3, 3):
        raise HomographyFileError(
            f"{path}: the homography must be a 3x3 matrix (9 numbers), got shape {a.shape}")
    return a


def read_homography(path: str | Path) -> np.ndarray:
    """The 3x3 float64 matrix stored in ``path`` (not yet checked for invertibility)."""
    path = Path(path)
    if not path.is_file():
        raise HomographyFileError(f"homography file {path} does not exist")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            values: object = np.load(path, allow_pickle=False)
        elif suffix == ".json":
            values = json.loads(path.read_text())
            if isinstance(values, dict):
                key = next((k for k in JSON_KEYS if k in values), None)
                if key is None:
                    raise HomographyFileError(
                        f"{path}: JSON object has none of the keys {', '.join(JSON_KEYS)}")
                values = values[key]
        else:
            tokens = [t for t in re.split(r"[\s,;]+", path.read_text()) if t]
            values = [float(t) for t in tokens]
    except HomographyFileError:
        raise
    except (OSError, ValueError) as exc:
        raise HomographyFileError(f"{path}: cannot read a homography: {exc}") from None
    return _as_matrix(values, path)


def projection_from_file(path: str | Path) -> PlaneProjection:
    """The fixed projection of a homography file; errors name the file."""
    H = read_homography(path)
    try:
        return PlaneProjection.from_image_to_plane(H)
    except GeometryError as exc:
        raise HomographyFileError(f"{path}: {exc}") from None
