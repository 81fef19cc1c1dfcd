"""int8 static quantisation of the density model (onnxruntime), then the same calibration.

Issue 13 asks for int8 measured for its recall cost: this writes the quantised file, and
``companion eval`` / ``companion bench --model`` measure it beside the float one.

* Weights int8 per output channel in 7 bits (``reduce_range``), activations uint8 per tensor,
  ranges from MinMax over the calibration frames; in onnxruntime's QOperator form (``QLinearConv`` nodes, the default) or QDQ
  (``--format qdq``: QuantizeLinear/DequantizeLinear pairs the runtime fuses; other providers
  prefer it). Which is faster is measured, not assumed: the model card has the figures.
* **Why 7-bit weights**: on x86 CPUs without VNNI (AVX2 or AVX-512 alone, many mini-PCs and
  servers) onnxruntime multiplies uint8 activations by int8 weights with an instruction that adds
  two products into 16 bits and saturates. With full 8-bit weights the density map then depends on
  the CPU: on an AVX2-only host a file made this way gave a map 0.11 away from its own exact
  quantised arithmetic (QDQ run unfused) in places, against 0.01 with 7-bit weights, whose
  products cannot saturate (2 x 255 x 64 < 32768). A file shipped to unknown boards must score
  the same on all of them; VNNI and ARM kernels do not saturate either way, and lose one bit of
  weight precision.
* Calibration frames come **only from the training splits**: the semantic-drone photos outside
  the held-out fifth, DroneCrowd's training frames and ShanghaiTech B train, each through the
  model's own preprocessing (``DensityModel.preprocess``). Nothing the figures are reported on
  sets a range.
* The quantised file keeps the float model's ``companion.*`` metadata, then
  ``companion.training.calibrate`` chooses its own threshold (by ``--rule``, the calibration's
  rules: ``drone`` by default, ``v1`` for the first shipped model and its int8 file), count scale
  and ``min_person_px``: int8 moves the scores, so the float model's threshold would not mean the
  same recall.

    python -m companion.training.quantize --model companion/models/slz-density.onnx \\
        --out /tmp/slz-density-int8.onnx --shared ../shared --rule v1

Needs the ``train`` extra (``onnx``); onnxruntime's quantiser is part of onnxruntime.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import onnx

from companion.config import SHIPPED_MODEL
from companion.evaluation import datasets as D
from companion.pipeline.density import DensityModel
from companion.training.calibrate import DEFAULT_RULE, RULES, calibrate, rule_minimums
from companion.training.metadata import set_metadata

log = logging.getLogger("companion.training.quantize")

#: Calibration frames per source (semantic drone, ShanghaiTech B; DroneCrowd gives its five).
CALIB_PER_SOURCE = 24


def calibration_frames(shared: Path, per_source: int = CALIB_PER_SOURCE) -> list[np.ndarray]:
    """BGR frames from the training splits only, spread evenly over each source."""
    if per_source < 1:
        raise ValueError(f"per_source must be >= 1, got {per_source}")
    train_sd = D.semantic_drone(shared, "train")
    shb = D.shanghaitech_b(shared, "train")
    dc = D.dronecrowd_frames(shared, D.DRONECROWD_TRAIN)
    out: list[np.ndarray] = []
    for samples in (train_sd, shb):
        idx = np.linspace(0, len(samples) - 1, min(per_source, len(samples))).round().astype(int)
        out += [samples[i].image() for i in sorted(set(idx.tolist()))]
    out += [s.image() for s in dc]
    return out


class _Reader:
    """onnxruntime's CalibrationDataReader protocol over preprocessed frames."""

    def __init__(self, model: DensityModel, frames: list[np.ndarray], input_name: str):
        self._it: Iterator[dict[str, np.ndarray]] = ({input_name: model.preprocess(f)} for f in frames)

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._it, None)


FORMATS = ("qoperator", "qdq")


def quantize(model_path: Path, out: Path, shared: Path, per_source: int = CALIB_PER_SOURCE,
             threads: int = 2, calibrate_after: bool = True, fmt: str = "qoperator",
             rule: str = DEFAULT_RULE, min_recall: float | None = None,
             reduce_range: bool = True) -> dict[str, object]:
    """Write the int8 model of ``model_path`` to ``out`` in form ``fmt`` (``FORMATS``); returns
    its metadata (after calibration by ``rule`` and ``min_recall``, as
    ``companion.training.calibrate`` takes them, unless ``calibrate_after`` is false).
    ``reduce_range``: 7-bit weights, which no x86 kernel saturates (module docstring); False gives
    full 8-bit weights, exact only on VNNI and ARM kernels. A bad form or rule is a ValueError
    before anything is written."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    rule_minimums(rule, min_recall)
    model_path, out = Path(model_path), Path(out)
    fmodel = DensityModel(model_path, threads=threads)
    frames = calibration_frames(shared, per_source)
    log.info("calibrating activation ranges on %d training frames", len(frames))
    src = onnx.load(str(model_path))
    meta = {p.key: p.value for p in src.metadata_props}
    input_name = src.graph.input[0].name
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(model_path), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(out), _Reader(fmodel, frames, input_name),
                        quant_format=QuantFormat.QDQ if fmt == "qdq" else QuantFormat.QOperator,
                        per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        reduce_range=reduce_range, calibrate_method=CalibrationMethod.MinMax)
    bits = "7-bit" if reduce_range else "8-bit"
    meta["companion.quantization"] = (f"int8 static (onnxruntime {fmt}, {bits} weights per channel, activations "
                                      f"uint8 MinMax over {len(frames)} training frames) of {model_path.name}")
    set_metadata(out, meta)
    if not calibrate_after:
        return meta
    return calibrate(out, shared, threads, min_recall, rule)


def build_parser() -> argparse.ArgumentParser:
    """The command's arguments (see the module docstring)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, default=SHIPPED_MODEL,
                   help="the float ONNX model to quantize (default: the service's default model, %(default)s)")
    p.add_argument("--out", required=True, help="the int8 ONNX file to write")
    p.add_argument("--shared", default="../shared")
    p.add_argument("--per-source", type=int, default=CALIB_PER_SOURCE,
                   help="calibration frames per training source (default %(default)s)")
    p.add_argument("--format", choices=FORMATS, default="qoperator",
                   help="QLinearConv nodes (default) or QuantizeLinear/DequantizeLinear pairs")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--no-calibrate", action="store_true", help="keep the float model's threshold")
    p.add_argument("--rule", choices=sorted(RULES), default=DEFAULT_RULE,
                   help="the calibration rule that chooses the int8 file's threshold "
                        "(companion.training.calibrate; v1 for the first shipped model)")
    p.add_argument("--min-recall", type=float, default=None, help="v1 rule only (as calibrate takes it)")
    p.add_argument("--full-range", action="store_true",
                   help="8-bit weights: exact only where the CPU has VNNI or is ARM; on other x86 CPUs "
                        "onnxruntime's kernels saturate (the default, 7-bit weights, scores the same everywhere)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        quantize(Path(args.model), Path(args.out), Path(args.shared), args.per_source, args.threads,
                 not args.no_calibrate, args.format, args.rule, args.min_recall, not args.full_range)
    except ValueError as exc:
        print(f"companion.training.quantize: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
