"""Step 1b of the pipeline: camera frame -> per-cell probabilities of ground risk levels.

A second small ONNX model beside the density model (the density model and its people figures are
untouched). It maps a frame to ``(L, ceil(H/stride), ceil(W/stride))`` probabilities, one channel
per *risk level* (softmax over levels, so a cell's channels sum to 1). The levels group the classes
of the data set the model was trained on; the grouping travels in the model's metadata and is
validated at load. The pipeline never sees the levels themselves: :meth:`LandabilityModel.unlandable`
gives it a callable returning, per cell, the probability that the ground there belongs to any of a
configured set of unlandable levels (``pipeline.unlandable_levels``).

Metadata (prefix ``companion.``), besides the input keys of :mod:`companion.pipeline.density`
(``color``, ``scale``, ``mean``, ``std``, ``stride``, ``input_multiple``, ``border_px``: a mirrored
border is cropped off the last two axes of the ``(L, h, w)`` output as off a density map):

==================================  =========================================================
key                                 meaning
==================================  =========================================================
``companion.output``                must be ``risk-level-probabilities``
``companion.levels``                JSON list, one entry per output channel in order:
                                    ``{"name": "water", "classes": ["water", "pool"]}``;
                                    names unique, lower-case ``[a-z0-9_-]``; a class in one
                                    level at most; at least two levels
``companion.landable_level``        the name of the one level that is fit to land on
``companion.unlandable_threshold``  a cell is unlandable where the probability of the
                                    unlandable levels exceeds this (0-1), chosen on
                                    validation data toward "unlandable"; absent: 0.5
``companion.class_set``             what the class names refer to (e.g. ``semantic-drone``)
==================================  =========================================================

Every problem raises :class:`LandabilityModelError` (a :class:`DensityModelError`, so start-up
paths that stop on a bad density model stop on this one too, exit 2), naming the file.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.pipeline.density import PREFIX, DensityModel, DensityModelError, _dim

OUTPUT_KIND = "risk-level-probabilities"
#: Used when the model carries no ``unlandable_threshold``: the even split of a probability.
DEFAULT_THRESHOLD = 0.5
_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")


class LandabilityModelError(DensityModelError):
    """The landability model or its metadata cannot be used (message names file and problem)."""


@dataclass(frozen=True)
class RiskLevel:
    """One risk level: its name and the data set's classes grouped in it."""

    name: str
    classes: tuple[str, ...]


@dataclass(frozen=True)
class LandabilitySpec:
    """What a landability model's output means.

    levels: one per output channel, in channel order.
    landable: the name of the level fit to land on.
    threshold: probability (0-1) of the unlandable levels above which a cell is unlandable.
    class_set: what the class names in ``levels`` refer to.
    """

    levels: tuple[RiskLevel, ...]
    landable: str
    threshold: float
    class_set: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(lv.name for lv in self.levels)

    def default_unlandable(self) -> tuple[str, ...]:
        """Every level but the landable one."""
        return tuple(n for n in self.names if n != self.landable)


def parse_levels(text: object) -> tuple[RiskLevel, ...]:
    """The risk levels of a ``companion.levels`` value; ValueError saying what is wrong."""
    if not isinstance(text, str):
        raise ValueError(f"levels must be a JSON text, got {type(text).__name__}")
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"levels is not valid JSON ({exc.msg} at char {exc.pos})") from None
    if not isinstance(raw, list) or len(raw) < 2:
        raise ValueError("levels must be a JSON list of at least two {\"name\", \"classes\"} objects")
    out: list[RiskLevel] = []
    seen_classes: dict[str, str] = {}
    for i, entry in enumerate(raw):
        if not isinstance(entry, dict) or set(entry) != {"name", "classes"}:
            raise ValueError(f"levels[{i}] must be an object with exactly the keys name and classes, got {entry!r}")
        name, classes = entry["name"], entry["classes"]
        if not isinstance(name, str) or not _NAME.match(name):
            raise ValueError(f"levels[{i}].name must be a lower-case name ([a-z0-9_-], 1-32 chars), got {name!r}")
        if name in (lv.name for lv in out):
            raise ValueError(f"levels[{i}].name {name!r} appears twice")
        if not isinstance(classes, list) or not all(isinstance(c, str) and c for c in classes):
            raise ValueError(f"levels[{i}].classes ({name}) must be a list of class names, got {classes!r}")
        for c in classes:
            if c in seen_classes:
                raise ValueError(f"class {c!r} is in two levels: {seen_classes[c]} and {name}")
            seen_classes[c] = name
        out.append(RiskLevel(name, tuple(classes)))
    return tuple(out)


def parse_spec(meta: dict[str, str]) -> LandabilitySpec:
    """The :class:`LandabilitySpec` of a model's ``companion.*`` metadata (keys without the
    prefix); ValueError naming the key."""
    kind = meta.get("output")
    if kind != OUTPUT_KIND:
        raise ValueError(f"companion.output must be {OUTPUT_KIND!r} for a landability model, got {kind!r}")
    if "levels" not in meta:
        raise ValueError("companion.levels is missing: the model does not say what its channels mean")
    try:
        levels = parse_levels(meta["levels"])
    except ValueError as exc:
        raise ValueError(f"companion.{exc}") from None
    landable = meta.get("landable_level")
    if landable not in [lv.name for lv in levels]:
        raise ValueError(f"companion.landable_level must name one of the levels "
                         f"{', '.join(lv.name for lv in levels)}, got {landable!r}")
    thr_text = meta.get("unlandable_threshold")
    if thr_text in (None, ""):
        thr = DEFAULT_THRESHOLD
    else:
        try:
            thr = float(str(thr_text))
        except ValueError:
            thr = math.nan
        if not (math.isfinite(thr) and 0.0 <= thr < 1.0):
            raise ValueError(f"companion.unlandable_threshold must be a number in [0, 1), got {thr_text!r}")
    return LandabilitySpec(levels, str(landable), thr, str(meta.get("class_set", "")))


class UnlandableMap:
    """Callable frame -> (h', w') float32 probability that a cell's ground is in any of
    ``levels`` (the sum of their channels): what the pipeline's occupancy step thresholds.

    threshold: the model's ``unlandable_threshold`` (the pipeline's default).
    """

    def __init__(self, model: LandabilityModel, channels: tuple[int, ...], names: tuple[str, ...]) -> None:
        self.model = model
        self.channels = channels
        self.names = names
        self.threshold = model.landability.threshold

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        probs = self.model(frame)
        if not self.channels:
            return np.zeros(probs.shape[1:], np.float32)
        return np.ascontiguousarray(probs[list(self.channels)].sum(axis=0, dtype=np.float32))


class LandabilityModel(DensityModel):
    """An ONNX landability model on camera frames (onnxruntime, CPU): ``model(frame)`` is the
    ``(L, h', w')`` float32 level probabilities, cells as in :mod:`companion.pipeline.density`.

    path: the ``.onnx`` file. threads: onnxruntime intra-op threads.
    """

    KIND = "landability"

    def __init__(self, path: str | Path, threads: int = 2, allow_spinning: bool = False) -> None:
        try:
            super().__init__(path, threads, allow_spinning=allow_spinning)
        except LandabilityModelError:
            raise
        except DensityModelError as exc:
            raise LandabilityModelError(str(exc)) from None
        meta = self._session.get_modelmeta().custom_metadata_map
        try:
            self.landability = parse_spec({k.removeprefix(PREFIX): v for k, v in meta.items()
                                           if k.startswith(PREFIX)})
        except ValueError as exc:
            raise LandabilityModelError(f"{self.path}: {exc}") from None
        n = len(self.landability.levels)
        if self._channels_out != n:
            raise LandabilityModelError(f"{self.path}: the model gives {self._channels_out} channels but "
                                        f"companion.levels names {n} levels")

    def _check_output(self, name: str, shape: list[object]) -> None:
        if len(shape) != 4 or (shape[0] not in (1,) and _dim(shape[0]) is not None):
            raise LandabilityModelError(f"{self.path}: output {name!r} has shape {shape}; expected "
                                        "(N, L, h, w) level probabilities")

    def _shape_output(self, y: np.ndarray) -> np.ndarray:
        if y.ndim != 4 or y.shape[0] != 1 or y.shape[1] < 2:
            raise LandabilityModelError(f"{self.path}: output has shape {y.shape}, expected (1, L, h, w) with L >= 2")
        self._channels_out = int(y.shape[1])
        out: np.ndarray = y[0]
        return out

    def levels_index(self, names: Sequence[str]) -> tuple[int, ...]:
        """Channel indices of the named levels; LandabilityModelError naming an unknown one."""
        known = self.landability.names
        bad = [n for n in names if n not in known]
        if bad:
            raise LandabilityModelError(f"{self.path}: no risk level named {', '.join(map(repr, bad))}; "
                                        f"the model's levels are {', '.join(known)}")
        return tuple(sorted({known.index(n) for n in names}))

    def unlandable(self, names: Sequence[str] | None = None) -> UnlandableMap:
        """The pipeline's callable for the levels ``names`` (None: all but the landable level)."""
        chosen = tuple(names) if names is not None else self.landability.default_unlandable()
        return UnlandableMap(self, self.levels_index(chosen), chosen)
