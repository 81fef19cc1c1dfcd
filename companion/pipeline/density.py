"""Step 1 of the pipeline: camera frame -> density map, with any ONNX density model on the CPU.

The model decides how it wants its pixels through ONNX ``metadata_props``; a config mapping
(``overrides``, keys without the ``companion.`` prefix) wins over the metadata, so models that
carry no metadata (e.g. the MCNN peer) run with a few settings:

=================================  ==========================================================
key                                meaning
=================================  ==========================================================
``companion.color``                channel order the model expects: ``bgr``, ``rgb`` or
                                   ``gray`` (default ``bgr``; ``gray`` for 1-channel inputs)
``companion.scale``                multiplier on 0-255 pixel values (default 1)
``companion.mean``                 comma-separated per-channel mean, subtracted after the scale
                                   (one value applies to all channels; default 0)
``companion.std``                  comma-separated per-channel std, divides after the mean
                                   (default 1)
``companion.stride``               input pixels per output pixel; if absent, inferred from
                                   the input/output shapes of a probe run at load time
``companion.input_multiple``       the frame is padded (bottom/right, edge pixels repeated) to
                                   a multiple of N; default: the stride. A model with a fixed
                                   input size gets the frame resized to that size instead
``companion.border_px``            the frame is extended by N pixels on every side by mirroring
                                   (``cv2.BORDER_REFLECT_101``, after the colour conversion and
                                   before the padding to ``input_multiple``) before the model
                                   sees it, and the map is cropped back; the model's zero
                                   padding then falls on mirrored ground instead of the frame's
                                   edge (a zero-padded network can see "people" in bands along
                                   the edges of empty ground). An integer 0-512, a multiple of
                                   the stride; default 0 (off); models with a fixed input size
                                   take 0 only. Costs (W+2N)(H+2N)/(WH) of the model's time
``companion.occupancy_threshold``  threshold for the occupancy step chosen on validation data;
                                   the pipeline's default when its config sets none
``companion.count_scale``          multiplier turning the map's sum into a people count
                                   (default 1: a true density map)
``companion.min_person_px``        the smallest person size (longer side of the person's box,
                                   in input pixels) from which the model's head recall reaches
                                   99.5 % at its occupancy threshold, measured on validation
                                   sets with real person sizes (``companion eval``); absent or
                                   ``none``: not measured or never reached. A caller trusts
                                   "free" only where people would appear at least this large
=================================  ==========================================================

The returned map is float32, 2-D, in output pixels: output pixel (i, j) covers input pixels
``[i*stride, (i+1)*stride) x [j*stride, (j+1)*stride)``; the mirrored border and the padding are
cropped off again, so the map covers exactly the frame (``ceil(H/stride) x ceil(W/stride)``).

Every problem with the model, its settings or a frame raises :class:`DensityModelError` (a
``ValueError``) naming the file and the problem; bad frames raise its subclass
:class:`FrameError` so a caller can count and drop them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import cv2
import numpy as np

PREFIX = "companion."
COLORS = ("bgr", "rgb", "gray")
KEYS = ("color", "scale", "mean", "std", "stride", "input_multiple", "occupancy_threshold", "count_scale",
        "min_person_px", "border_px")
#: The widest mirrored border (px per side) a model may ask for: more than any receptive field
#: that matters at the edge, and a bound on the cost ((W+2N)(H+2N)/(WH) of the model's time).
MAX_BORDER_PX = 512


class DensityModelError(ValueError):
    """The density model, its settings or its input cannot be used (message names file and problem)."""


class FrameError(DensityModelError):
    """A frame that the model cannot take (wrong shape, dtype, size): count it and drop it."""


@dataclass(frozen=True)
class DensitySpec:
    """How a model wants its input and what its output means.

    color: ``bgr``, ``rgb`` or ``gray``.
    scale: multiplier on 0-255 pixel values.
    mean, std: per-channel, applied after ``scale`` as ``(x * scale - mean) / std``.
    stride: input pixels per output pixel.
    input_multiple: frames are padded to a multiple of this many pixels.
    occupancy_threshold: the model's validated occupancy threshold, or None.
    count_scale: multiplier turning the sum of the map into a count of people.
    min_person_px: smallest person size (px, longer side of the person's box) at which the model's
        head recall reaches 99.5 % at its threshold, or None (not measured / not reached).
    border_px: input pixels mirrored onto every side of the frame before the model runs (and
        cropped off its map again); 0: none. A multiple of ``stride``.
    """

    color: str
    scale: float
    mean: tuple[float, ...]
    std: tuple[float, ...]
    stride: int
    input_multiple: int
    occupancy_threshold: float | None
    count_scale: float = 1.0
    min_person_px: float | None = None
    border_px: int = 0


def _floats(value: object, key: str) -> tuple[float, ...]:
    parts: Sequence[str | float]
    if isinstance(value, str):
        parts = [p for p in value.replace(" ", "").split(",") if p]
    elif isinstance(value, (int, float)):
        parts = [value]
    else:
        parts = list(value)  # type: ignore[call-overload]
    try:
        out = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        raise ValueError(f"{key} must be numbers, got {value!r}") from None
    if not out or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{key} must be finite numbers, got {value!r}")
    return out


def _positive_int(value: object, key: str) -> int:
    try:
        f = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{key} must be a positive integer, got {value!r}") from None
    if not f.is_integer() or f < 1:
        raise ValueError(f"{key} must be a positive integer, got {value!r}")
    return int(f)


def _border_px(value: object) -> int:
    """``border_px`` as an int in [0, MAX_BORDER_PX]; absent or empty: 0 (off)."""
    if value in (None, ""):
        return 0
    problem = f"border_px must be an integer number of pixels in [0, {MAX_BORDER_PX}], got {value!r}"
    if isinstance(value, bool):  # float(True) == 1.0 would slip through as a 1-px border
        raise ValueError(problem)
    try:
        f = float(str(value))  # metadata and CLI give text, a config gives numbers
    except ValueError:
        raise ValueError(problem) from None
    if not f.is_integer() or not 0 <= f <= MAX_BORDER_PX:  # NaN and inf are not integers
        raise ValueError(problem)
    return int(f)


def _parse(settings: Mapping[str, object], channels: int) -> dict[str, object]:
    """Validated settings (strings from metadata or CLI, or typed values from a config)."""
    out: dict[str, object] = {}
    color = str(settings.get("color", "gray" if channels == 1 else "bgr")).lower()
    if color not in COLORS:
        raise ValueError(f"color must be one of {', '.join(COLORS)}, got {color!r}")
    if (color == "gray") != (channels == 1):
        raise ValueError(f"color {color!r} does not fit a model input with {channels} channel(s)")
    out["color"] = color
    scale = _floats(settings.get("scale", 1.0), "scale")
    if len(scale) != 1 or scale[0] <= 0:
        raise ValueError(f"scale must be one number > 0, got {settings.get('scale')!r}")
    out["scale"] = scale[0]
    for key, default in (("mean", 0.0), ("std", 1.0)):
        vals = _floats(settings.get(key, default), key)
        if len(vals) == 1:
            vals = vals * channels
        if len(vals) != channels:
            raise ValueError(f"{key} needs 1 or {channels} values, got {len(vals)}")
        if key == "std" and min(vals) <= 0:
            raise ValueError(f"std values must be > 0, got {vals}")
        out[key] = vals
    out["stride"] = _positive_int(settings["stride"], "stride") if settings.get("stride") not in (None, "") else None
    if settings.get("input_multiple") not in (None, ""):
        out["input_multiple"] = _positive_int(settings["input_multiple"], "input_multiple")
    thr = settings.get("occupancy_threshold")
    if thr not in (None, "", "none", "None"):
        t = _floats(thr, "occupancy_threshold")
        if len(t) != 1 or t[0] < 0:
            raise ValueError(f"occupancy_threshold must be one number >= 0, got {thr!r}")
        out["occupancy_threshold"] = t[0]
    else:
        out["occupancy_threshold"] = None
    cs = _floats(settings.get("count_scale", 1.0), "count_scale")
    if len(cs) != 1 or cs[0] <= 0:
        raise ValueError(f"count_scale must be one number > 0, got {settings.get('count_scale')!r}")
    out["count_scale"] = cs[0]
    mp = settings.get("min_person_px")
    if mp in (None, "", "none", "None"):
        out["min_person_px"] = None
    else:
        try:
            v = _floats(mp, "min_person_px")
        except ValueError:
            v = ()
        if len(v) != 1 or not 0 < v[0] <= 10000:
            raise ValueError(f"min_person_px must be one number of pixels in (0, 10000] (or none), got {mp!r}")
        out["min_person_px"] = v[0]
    out["border_px"] = _border_px(settings.get("border_px"))
    return out


def _dim(d: object) -> int | None:
    return d if isinstance(d, int) and d > 0 else None


class DensityModel:
    """An ONNX density model ready to run on camera frames (onnxruntime, CPU).

    path: the ``.onnx`` file.
    threads: onnxruntime intra-op threads (the companion board's cores to spend on it).
    allow_spinning: let onnxruntime's pool threads busy-wait for the next run after each one.
        Off by default: on a 2-core board the spinning threads take the CPU from the stages
        after the density model and from the rest of the service, which run between two frames.
    overrides: settings that win over the model's metadata, keys as in the module docstring
        without the ``companion.`` prefix (the prefixed form is accepted too).
    """

    #: What the model is, in messages ("density model file ... does not exist").
    KIND = "density"

    def __init__(self, path: str | Path, threads: int = 2, overrides: Mapping[str, object] | None = None,
                 allow_spinning: bool = False) -> None:
        self.path = Path(path)
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise DensityModelError(f"{self.path}: threads must be an integer >= 1, got {threads!r}")
        given = {str(k).removeprefix(PREFIX): v for k, v in (overrides or {}).items()}
        unknown = sorted(set(given) - set(KEYS))
        if unknown:
            raise DensityModelError(
                f"{self.path}: unknown density model setting(s) {', '.join(unknown)}; known: {', '.join(KEYS)}"
            )
        if not self.path.is_file():
            raise DensityModelError(f"{self.KIND} model file {self.path} does not exist")

        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        spin = "1" if allow_spinning else "0"
        opts.add_session_config_entry("session.intra_op.allow_spinning", spin)
        opts.add_session_config_entry("session.inter_op.allow_spinning", spin)
        opts.log_severity_level = 3
        self.allow_spinning = bool(allow_spinning)
        try:
            self._session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for every parse failure
            raise DensityModelError(f"{self.path} is not a loadable ONNX model: {exc}") from exc

        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1:
            raise DensityModelError(f"{self.path}: expected one image input, the model has {len(inputs)}")
        inp = inputs[0]
        self.input_name: str = inp.name
        if inp.type != "tensor(float)":
            raise DensityModelError(f"{self.path}: input {inp.name!r} is {inp.type}, expected tensor(float)")
        if len(inp.shape) != 4 or _dim(inp.shape[1]) not in (1, 3):
            raise DensityModelError(
                f"{self.path}: input {inp.name!r} has shape {inp.shape}; expected an image tensor "
                "(N, C, H, W) with C = 1 or 3"
            )
        channels = int(inp.shape[1])
        out = outputs[0]
        self._check_output(out.name, list(out.shape))
        self._output_name = out.name
        self._fixed_hw = (_dim(inp.shape[2]), _dim(inp.shape[3]))

        meta = self._session.get_modelmeta().custom_metadata_map
        settings: dict[str, object] = {k.removeprefix(PREFIX): v for k, v in meta.items() if k.startswith(PREFIX)}
        settings.update(given)
        try:
            parsed = _parse(settings, channels)
        except ValueError as exc:
            raise DensityModelError(f"{self.path}: {exc}") from None
        self._channels = channels
        # _parse: a positive int, or None when not declared
        stride = cast("int | None", parsed["stride"])
        multiple = cast("int | None", parsed.get("input_multiple"))
        # A probe run finds the stride when it is not declared and proves the model runs at all.
        probe_hw = self._probe_size(int(stride or 1) * int(multiple or 1))
        out_hw = self._infer(np.zeros((1, channels, *probe_hw), np.float32)).shape[-2:]
        if stride is None:
            ratios = {probe_hw[0] / out_hw[0], probe_hw[1] / out_hw[1]}
            if len(ratios) != 1 or not float(next(iter(ratios))).is_integer():
                raise DensityModelError(
                    f"{self.path}: cannot infer the output stride from input {probe_hw} -> output {out_hw}; "
                    "set companion.stride"
                )
            stride = int(next(iter(ratios)))
        border = cast(int, parsed["border_px"])
        if border and any(self._fixed_hw):
            raise DensityModelError(
                f"{self.path}: border_px {border} needs a model that takes any frame size; this one takes a "
                f"fixed {self._fixed_hw[0] or 'any'}x{self._fixed_hw[1] or 'any'} input, so border_px must be 0"
            )
        if border % stride:
            # The crop takes whole output cells off the map: a border that is not a whole number
            # of cells would shift every cell against the frame.
            raise DensityModelError(
                f"{self.path}: border_px {border} must be a multiple of the model's stride {stride}"
            )
        self.spec = DensitySpec(
            color=str(parsed["color"]),
            scale=float(parsed["scale"]),  # type: ignore[arg-type]
            mean=parsed["mean"],  # type: ignore[arg-type]
            std=parsed["std"],  # type: ignore[arg-type]
            stride=int(stride),
            input_multiple=int(multiple or stride),
            occupancy_threshold=parsed["occupancy_threshold"],  # type: ignore[arg-type]
            count_scale=float(parsed["count_scale"]),  # type: ignore[arg-type]
            min_person_px=cast("float | None", parsed["min_person_px"]),
            border_px=border,
        )
        # (x * scale - mean) / std  ==  x * gain + offset, per channel
        std = np.asarray(self.spec.std, np.float64)
        self._gain = (self.spec.scale / std).astype(np.float32)
        self._offset = (-np.asarray(self.spec.mean, np.float64) / std).astype(np.float32)
        # The same float32 multiply and add for each of the 256 values a uint8 pixel can take,
        # looked up per pixel (``cv2.LUT``) instead of computed: the same bits, a third less time.
        values = np.arange(256, dtype=np.uint8)
        self._lut = np.empty((channels, 256), np.float32)
        for c in range(channels):
            np.multiply(values, self._gain[c], out=self._lut[c])
            self._lut[c] += self._offset[c]

    @property
    def any_size(self) -> bool:
        """Whether the model takes frames of any size at their own scale (a fully convolutional
        model), so that a crop of a frame gives the density of that part of it; a model with a
        fixed input resizes every frame, and a crop would change its scale."""
        return not any(self._fixed_hw)

    @property
    def min_person_px(self) -> float | None:
        """Smallest person size in input pixels (longer side of the person's box) at which this
        model finds 99.5 % of people at its threshold; None when the model does not say. Free area
        is trustworthy only where people would appear at least this large."""
        return self.spec.min_person_px

    def _probe_size(self, multiple: int) -> tuple[int, int]:
        side = multiple * max(1, math.ceil(64 / multiple))
        h, w = self._fixed_hw
        return (h or side, w or side)

    def _check_output(self, name: str, shape: list[object]) -> None:
        """Raise when the declared output is not one 2-D map (a subclass may want another)."""
        if len(shape) not in (2, 4) or (len(shape) == 4 and _dim(shape[1]) not in (1, None)):
            raise DensityModelError(
                f"{self.path}: output {name!r} has shape {shape}; expected a 2-D map (N, 1, h, w) or (h, w)"
            )
        if len(shape) == 4 and shape[1] != 1:
            raise DensityModelError(f"{self.path}: output {name!r} must have one channel, has shape {shape}")

    def _shape_output(self, y: np.ndarray) -> np.ndarray:
        """The map of one frame from the raw output (density: 2-D)."""
        if y.ndim == 4 and y.shape[:2] == (1, 1):
            y = y[0, 0]
        if y.ndim != 2:
            raise DensityModelError(f"{self.path}: output has shape {y.shape}, expected a 2-D map")
        return y

    def _infer(self, x: np.ndarray) -> np.ndarray:
        try:
            raw = self._session.run([self._output_name], {self.input_name: x})[0]
        except Exception as exc:
            raise DensityModelError(f"{self.path}: inference failed on input {x.shape}: {exc}") from exc
        return self._shape_output(np.asarray(raw)).astype(np.float32, copy=False)

    def _check_frame(self, frame: object) -> np.ndarray:
        if not isinstance(frame, np.ndarray):
            raise FrameError(f"{self.path}: frame must be a numpy array, got {type(frame).__name__}")
        if frame.dtype != np.uint8:
            raise FrameError(f"{self.path}: frame must be uint8, got {frame.dtype}")
        if frame.ndim == 3 and frame.shape[2] == 1:
            frame = frame[:, :, 0]
        if not (frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)):
            raise FrameError(f"{self.path}: frame must be HxWx3 BGR or HxW grey, got shape {frame.shape}")
        if frame.shape[0] < self.spec.stride or frame.shape[1] < self.spec.stride:
            raise FrameError(f"{self.path}: frame {frame.shape[:2]} is smaller than the stride {self.spec.stride}")
        return frame

    def preprocess(self, frame: np.ndarray) -> np.ndarray:
        """The (1, C, H', W') float32 tensor the model gets for ``frame`` (checked, converted, mirrored
        by ``border_px`` on every side, padded: :meth:`model_image`; then normalised)."""
        img = self.model_image(frame)
        # Each channel plane looked up (x * gain + offset, in float32, per value: ``_lut``) straight
        # into the NCHW buffer: a float HWC->CHW transpose copy costs ~10x more than the lookups.
        planes = [img] if img.ndim == 2 else cv2.split(img)
        x = np.empty((1, len(planes), *img.shape[:2]), np.float32)
        for c, plane in enumerate(planes):
            cv2.LUT(plane, self._lut[c], dst=x[0, c])
        return x

    def model_image(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` as the model sees it before normalisation: checked, in the model's colour order
        (HxW grey or HxWx3 uint8), resized to a fixed input, or else mirrored by ``border_px`` on
        every side and padded to ``input_multiple``."""
        frame = self._check_frame(frame)
        color = self.spec.color
        if color == "gray":
            img = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        elif frame.ndim == 2:
            img = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        else:
            img = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB) if color == "rgb" else frame
        fh, fw = self._fixed_hw
        if fh or fw:
            img = cv2.resize(img, (fw or img.shape[1], fh or img.shape[0]), interpolation=cv2.INTER_AREA)
        else:
            b = self.spec.border_px
            if b:
                # Mirrored ground under the model's zero padding instead of the frame's edge;
                # REFLECT_101 repeats no row, so the edge row is not doubled.
                img = cv2.copyMakeBorder(img, b, b, b, b, cv2.BORDER_REFLECT_101)
            m = self.spec.input_multiple
            ph, pw = -img.shape[0] % m, -img.shape[1] % m
            if ph or pw:
                img = cv2.copyMakeBorder(img, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
        return img

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        """Density map of ``frame`` (HxWx3 BGR or HxW grey uint8) as float32 (h', w')."""
        x = self.preprocess(frame)
        y = self._infer(x)
        if not any(self._fixed_hw):
            s = self.spec.stride
            h, w = math.ceil(frame.shape[0] / s), math.ceil(frame.shape[1] / s)
            k = self.spec.border_px // s  # whole cells of mirrored border on the top and left
            # The last two axes are the map's (a landability model's levels lead): crop those.
            y = y[..., k : k + h, k : k + w]
            if k and y.shape[-2:] != (h, w):
                raise DensityModelError(
                    f"{self.path}: output {tuple(y.shape)} after cropping border_px {self.spec.border_px} "
                    f"does not cover the {frame.shape[0]}x{frame.shape[1]} frame ({h}x{w} cells at stride {s})"
                )
        return np.ascontiguousarray(y)

    def count(self, density: np.ndarray) -> float:
        """People count estimated from a density map of this model (sum x ``count_scale``)."""
        return float(np.sum(density, dtype=np.float64) * self.spec.count_scale)


def resolve_threshold(setting: float | None, spec: DensitySpec | None) -> float:
    """The occupancy threshold to use: the user's ``setting`` when given (None = not set), else
    the model's validated ``occupancy_threshold`` (a model that carries one chosen on held-out
    data knows its own output scale better than the paper's 0), else the paper's 0. The one
    place this rule lives: the service, replay, evaluation and the pipeline all call it."""
    if setting is not None:
        return float(setting)
    model = None if spec is None else spec.occupancy_threshold
    return float(model) if model is not None else 0.0
