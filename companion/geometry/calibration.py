"""Camera calibration files as OpenCV's own calibration tools write them.

OpenCV's calibration sample (``samples/cpp/calibration.cpp``) and its tutorial
(``camera_calibration.cpp``) save a ``cv2.FileStorage`` file (YAML, XML or JSON) holding
``camera_matrix`` (3x3, pixels), ``distortion_coefficients`` (k1, k2, p1, p2[, k3...] for the
pinhole; k1..k4 for the fisheye), ``image_width`` and ``image_height`` (pixels), and, from the
tutorial, ``fisheye_model`` (0/1). A plain JSON file with the same keys and the matrices as lists
of numbers is read too. Every value is checked: a calibration that cannot describe a camera is a
:class:`CalibrationError`, never a projection.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

PINHOLE_DIST_SIZES = (4, 5, 8, 12, 14)


class CalibrationError(ValueError):
    """A calibration file that cannot be read, or whose values cannot describe a camera."""


@dataclass(frozen=True)
class Calibration:
    """A camera's calibration: ``camera_matrix`` 3x3 (px), ``dist`` the distortion coefficients,
    ``width`` x ``height`` the image size (px) it is for; ``fisheye`` None when the file does not
    say which model it was calibrated with."""

    camera_matrix: np.ndarray
    dist: tuple[float, ...]
    width: int
    height: int
    fisheye: bool | None = None


def _names(key: str) -> tuple[str, ...]:
    # The sample writes lower case; the tutorial's older versions capitalised the words.
    return (key, "_".join(w.capitalize() for w in key.split("_")))


def _from_json(text: str) -> dict[str, Any] | None:
    """Plain JSON with lists; None when the file is FileStorage's own JSON (matrices as objects)."""
    try:
        data = json.loads(text)
    except ValueError:
        return None
    if not isinstance(data, dict):
        raise CalibrationError("the JSON file does not hold an object")
    if any(isinstance(data.get(n), dict) for k in ("camera_matrix", "distortion_coefficients")
           for n in _names(k)):
        return None
    return data


def _from_filestorage(path: Path) -> dict[str, Any]:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        # A parse error comes as cv2.error, or wrapped in a SystemError by the Python binding.
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
        last = (str(cause).strip().splitlines() or ["a parse error"])[-1]
        raise CalibrationError(f"OpenCV cannot read it ({last})") from None
    if not fs.isOpened():
        raise CalibrationError("OpenCV cannot read it as a FileStorage file (YAML, XML or JSON)")
    out: dict[str, Any] = {}
    try:
        for key in ("camera_matrix", "distortion_coefficients", "image_width", "image_height",
                    "fisheye_model"):
            for name in _names(key):
                node = fs.getNode(name)
                if node.empty() or node.isNone():
                    continue
                if node.isMap():
                    out[key] = node.mat()
                elif node.isSeq():
                    out[key] = [node.at(i).real() for i in range(node.size())]
                else:
                    out[key] = node.real()
                break
    finally:
        fs.release()
    return out


def _get(data: dict[str, Any], key: str) -> Any:
    for name in _names(key):
        if name in data:
            return data[name]
    return None


def load(path: str | Path) -> Calibration:
    """The calibration in ``path``; CalibrationError saying what is wrong with it."""
    p = Path(path)
    try:
        text = p.read_text(errors="replace")
    except OSError as exc:
        raise CalibrationError(exc.strerror or str(exc)) from None
    data = _from_json(text) if p.suffix.lower() == ".json" else None
    if data is None:
        data = _from_filestorage(p)
    K_raw, d_raw = _get(data, "camera_matrix"), _get(data, "distortion_coefficients")
    w_raw, h_raw = _get(data, "image_width"), _get(data, "image_height")
    for name, value in (("camera_matrix", K_raw), ("distortion_coefficients", d_raw),
                        ("image_width", w_raw), ("image_height", h_raw)):
        if value is None:
            raise CalibrationError(f"it has no {name}")
    try:
        K = np.asarray(K_raw, dtype=np.float64)
        d = np.asarray(d_raw, dtype=np.float64)
        width_f, height_f = float(w_raw), float(h_raw)
    except (TypeError, ValueError):
        raise CalibrationError("camera_matrix, distortion_coefficients, image_width and image_height "
                               "must be numbers") from None
    if K.size != 9:
        raise CalibrationError(f"camera_matrix must be 3x3, got {K.size} values")
    K = K.reshape(3, 3)
    if d.ndim > 2 or (d.ndim == 2 and min(d.shape) != 1):
        raise CalibrationError(f"distortion_coefficients must be a row or column, got shape {d.shape}")
    d = d.ravel()
    if not (np.isfinite(K).all() and np.isfinite(d).all() and math.isfinite(width_f) and math.isfinite(height_f)):
        raise CalibrationError("it has a NaN or infinite value")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"the focal lengths must be > 0 px, got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if abs(K[1, 0]) > 0 or abs(K[2, 0]) > 0 or abs(K[2, 1]) > 0 or K[2, 2] != 1.0:
        raise CalibrationError("camera_matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if abs(K[0, 1]) > 0:
        # The pipeline's cameras have square-cornered pixels; calibrate with cv2.fisheye.CALIB_FIX_SKEW.
        raise CalibrationError(f"camera_matrix has a skew of {K[0, 1]:g} px: calibrate with zero skew "
                               "(cv2.fisheye.CALIB_FIX_SKEW)")
    if width_f != int(width_f) or height_f != int(height_f) or width_f < 1 or height_f < 1:
        raise CalibrationError(f"image_width and image_height must be whole pixels > 0, got "
                               f"{width_f:g}x{height_f:g}")
    fisheye_raw = _get(data, "fisheye_model")
    fisheye = None if fisheye_raw is None else bool(float(fisheye_raw))
    sizes = (4,) if fisheye else PINHOLE_DIST_SIZES
    if d.size not in sizes:
        raise CalibrationError(f"distortion_coefficients must hold {' or '.join(map(str, sizes))} values"
                               f"{' (fisheye k1..k4)' if fisheye else ''}, got {d.size}")
    return Calibration(K, tuple(float(v) for v in d), int(width_f), int(height_f), fisheye)


def save(path: str | Path, camera_matrix: np.ndarray, dist: np.ndarray, width: int, height: int,
         fisheye: bool | None = None) -> None:
    """Write a calibration the way OpenCV's calibration sample does (``cv2.FileStorage``; the
    format from the suffix: .yaml/.yml, .xml or .json)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(width))
        fs.write("image_height", int(height))
        if fisheye is not None:
            fs.write("fisheye_model", int(fisheye))
        fs.write("camera_matrix", np.asarray(camera_matrix, np.float64))
        fs.write("distortion_coefficients", np.asarray(dist, np.float64).reshape(-1, 1))
    finally:
        fs.release()
