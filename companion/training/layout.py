"""Lay a density model's channels out for onnxruntime's blocked convolutions; its map stays the same.

On x86-64, onnxruntime computes convolutions on channels in blocks (its NCHWc layout: 8 channels
with AVX2, 16 with AVX-512; mlas' ``NchwcBlockSize``). Where branches whose channel counts are not
multiples of the block are concatenated, it leaves that layout: each branch is reordered to plain
NCHW, concatenated, pooled in NCHW and reordered back. Versions 1, 2 and 4 of ``slz-density``
concatenate 10 + 14 + 16 channels; on the development machine (AVX-512) the reorders, the
concatenation and the pool in NCHW took 1.9 ms of version 4's 12.0 ms of kernels (onnxruntime's
profiler), 0.7 ms once blocked.

The rewrite gives each concatenated branch's last convolution zero filters and zero biases up to a
multiple of ``block`` channels, and the convolution that reads the concatenation (through nodes
that act on each channel alone: Relu, MaxPool, ...) zero weights for the added channels. Every
sum the model computes is the same as before (an added channel carries activation(0) and is
multiplied by 0), so the map is the same up to floating-point rounding: :func:`max_difference`
measures it on random inputs, and the command writes no file whose outputs differ by more than
``TOLERANCE``.

Where convolutions are not blocked (onnxruntime on ARM, unless built with its NEON NCHWc kernels)
the added channels are real work: version 4 aligned took 19.6 ms a frame against 18.3 ms plain,
with onnxruntime's blocked layout switched off on the development machine. So the aligned file is
shipped beside the plain one, and the service takes it on x86-64 only
(``companion.config.shipped_model``).

    python -m companion.training.layout --model companion/models/slz-density-v4.onnx \\
        --out companion/models/slz-density-v4-x86.onnx

Exit status: 0 written; 1 nothing to align (no file written; the reasons are printed);
2 bad input (no file, not an ONNX model, a bad option) or outputs that would differ.
Needs ``onnx`` (the ``train`` and ``dev`` extras); onnxruntime checks the result.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from companion.training.metadata import replace_metadata

#: Channels per block: 16 (AVX-512) is also a multiple of AVX2's 8.
BLOCK = 16
#: The most the aligned model's outputs may differ from the original's on random inputs (the
#: density map is a probability; version 4's differed by 5e-7).
TOLERANCE = 1e-5
#: Nodes between a branch's convolution and the concatenation: one value per element, shape kept
#: (an added channel holds f(0), whatever f is, and is multiplied by zero weights later).
ELEMENTWISE = frozenset({"Relu", "LeakyRelu", "Clip", "Sigmoid", "Tanh", "Identity", "Elu",
                         "HardSigmoid", "HardSwish", "Softplus"})
#: Nodes between the concatenation and the convolution that reads it: each channel alone.
CHANNELWISE = ELEMENTWISE | {"MaxPool", "AveragePool"}


class LayoutError(ValueError):
    """The model cannot be read, or the aligned model would compute something else."""


@dataclass(frozen=True)
class Aligned:
    """What :func:`align_concats` did: the new model (None when nothing changed) and one line per
    concatenation (how it was aligned, or why it was left as it was)."""

    model: onnx.ModelProto | None
    notes: tuple[str, ...]


def _attr(node: onnx.NodeProto, name: str, default: int) -> int:
    """An integer attribute of ``node`` (``default`` when absent or not an integer)."""
    for a in node.attribute:
        if a.name == name:
            value = onnx.helper.get_attribute_value(a)
            return int(value) if isinstance(value, (int, np.integer)) else default
    return default


def align_concats(model: onnx.ModelProto, block: int = BLOCK) -> Aligned:
    """A copy of ``model`` whose channel concatenations feed whole blocks of ``block`` channels
    (see the module docstring); ``model`` itself is not changed."""
    if block < 1:
        raise LayoutError(f"block must be >= 1 channel, got {block}")
    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    inits = {t.name: t for t in g.initializer}
    producer = {o: n for n in g.node for o in n.output}
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for n in g.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    graph_outputs = {o.name for o in g.output}

    def only_consumer(tensor: str) -> onnx.NodeProto | None:
        users = consumers.get(tensor, [])
        return users[0] if len(users) == 1 and tensor not in graph_outputs else None

    def own_weights(conv: onnx.NodeProto) -> bool:
        """The convolution's weights (and bias) are initializers no other node reads."""
        names = list(conv.input[1:3])
        return all(n in inits and len(consumers.get(n, [])) == 1 for n in names if n)

    notes: list[str] = []
    changed = False
    for cat in [n for n in g.node if n.op_type == "Concat"]:
        name = cat.name or cat.output[0]
        if _attr(cat, "axis", 0) not in (1, -3):
            notes.append(f"{name}: not along channels (axis {_attr(cat, 'axis', 0)}); left as it is")
            continue
        branches: list[onnx.NodeProto] = []
        for tensor in cat.input:
            node = producer.get(tensor)
            while node is not None and node.op_type in ELEMENTWISE and only_consumer(node.output[0]) is not None:
                node = producer.get(node.input[0])
            ok = (node is not None and node.op_type == "Conv" and _attr(node, "group", 1) == 1
                  and own_weights(node) and only_consumer(node.output[0]) is not None)
            if not ok:
                break
            assert node is not None
            branches.append(node)
        if len(branches) != len(cat.input):
            notes.append(f"{name}: an input is not a convolution followed by element-wise nodes only; left as it is")
            continue
        node = only_consumer(cat.output[0])
        while node is not None and node.op_type in CHANNELWISE:
            node = only_consumer(node.output[0])
        if node is None or node.op_type != "Conv" or _attr(node, "group", 1) != 1 or not own_weights(node):
            notes.append(f"{name}: its output does not go through channel-wise nodes into one convolution; "
                         "left as it is")
            continue
        reader = node
        widths = [int(inits[b.input[1]].dims[0]) for b in branches]
        if all(w % block == 0 for w in widths):
            notes.append(f"{name}: {' + '.join(map(str, widths))} channels, already whole blocks of {block}")
            continue
        w_reader = numpy_helper.to_array(inits[reader.input[1]])
        if w_reader.shape[1] != sum(widths):
            notes.append(f"{name}: the reading convolution takes {w_reader.shape[1]} channels, not "
                         f"{sum(widths)}; left as it is")
            continue
        columns, offset, padded = [], 0, []
        for conv, width in zip(branches, widths):
            extra = -width % block
            w = numpy_helper.to_array(inits[conv.input[1]])
            columns += [w_reader[:, offset:offset + width],
                        np.zeros((w_reader.shape[0], extra, *w_reader.shape[2:]), w_reader.dtype)]
            offset += width
            padded.append(width + extra)
            if not extra:
                continue
            inits[conv.input[1]].CopyFrom(numpy_helper.from_array(
                np.concatenate([w, np.zeros((extra, *w.shape[1:]), w.dtype)]), conv.input[1]))
            if len(conv.input) > 2 and conv.input[2]:
                b = numpy_helper.to_array(inits[conv.input[2]])
                inits[conv.input[2]].CopyFrom(numpy_helper.from_array(
                    np.concatenate([b, np.zeros(extra, b.dtype)]), conv.input[2]))
        inits[reader.input[1]].CopyFrom(numpy_helper.from_array(np.concatenate(columns, axis=1), reader.input[1]))
        notes.append(f"{name}: {' + '.join(map(str, widths))} -> {' + '.join(map(str, padded))} channels "
                     f"(zero filters), {reader.name or reader.output[0]} reads {sum(padded)}")
        changed = True
    if not changed:
        return Aligned(None, tuple(notes) or ("no concatenation of channels in the model",))
    # Intermediate shapes recorded by the exporter name the old channel counts: drop them all
    # (onnxruntime infers them again); the graph's inputs and outputs keep theirs.
    del g.value_info[:]
    onnx.checker.check_model(m)
    return Aligned(m, tuple(notes))


def max_difference(a: onnx.ModelProto, b: onnx.ModelProto, runs: int = 3, size: tuple[int, int] = (128, 160),
                   seed: int = 0) -> float:
    """The largest absolute difference between the outputs of ``a`` and ``b`` (onnxruntime, CPU)
    on ``runs`` random inputs of the first input's shape (``size`` = H, W where it is dynamic)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    sa = ort.InferenceSession(a.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    sb = ort.InferenceSession(b.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    inp = sa.get_inputs()[0]
    dims = [d if isinstance(d, int) and d > 0 else None for d in inp.shape]
    if len(dims) != 4:
        raise LayoutError(f"expected one image input (N, C, H, W), got shape {inp.shape}")
    shape = (1, dims[1] or 3, dims[2] or size[0], dims[3] or size[1])
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(runs):
        x = rng.normal(0.0, 1.0, shape).astype(np.float32)
        for ya, yb in zip(sa.run(None, {inp.name: x}), sb.run(None, {inp.name: x})):
            if ya.shape != yb.shape:
                return float("inf")
            worst = max(worst, float(np.max(np.abs(ya.astype(np.float64) - yb))))
    return worst


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m companion.training.layout",
                                description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--model", type=Path, required=True, help="the ONNX model to align")
    p.add_argument("--out", type=Path, required=True, help="where to write the aligned model")
    p.add_argument("--block", type=int, default=BLOCK, help=f"channels per block (default {BLOCK})")
    p.add_argument("--runs", type=int, default=3, help="random inputs the outputs are compared on (default 3)")
    args = p.parse_args(argv)
    if args.block < 1 or args.runs < 1:
        print("error: --block and --runs must be >= 1", file=sys.stderr)
        return 2
    if not args.model.is_file():
        print(f"error: no model at {args.model}", file=sys.stderr)
        return 2
    try:
        model = onnx.load(str(args.model))
        onnx.checker.check_model(model)
    except Exception as exc:  # onnx raises DecodeError, ValidationError, ... for a bad file
        print(f"error: {args.model} is not a readable ONNX model: {exc}", file=sys.stderr)
        return 2
    result = align_concats(model, args.block)
    for line in result.notes:
        print(line)
    if result.model is None:
        print(f"nothing to align in {args.model}; {args.out} not written")
        return 1
    try:
        diff = max_difference(model, result.model, runs=args.runs)
    except Exception as exc:  # onnxruntime's own exception types for a model it cannot run
        print(f"error: cannot run {args.model} to compare: {exc}", file=sys.stderr)
        return 2
    if not diff <= TOLERANCE:
        print(f"error: the aligned model's outputs differ by {diff:.3g} (> {TOLERANCE:g}); not written",
              file=sys.stderr)
        return 2
    # Replaces a layout note the input already had (a file aligned again), as every metadata write does.
    replace_metadata(result.model, {"companion.layout": f"concatenated channels in blocks of {args.block} "
                                    f"(companion.training.layout) from {args.model.name}; outputs within "
                                    f"{diff:.1e} of it"})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(result.model, str(args.out))
    print(f"wrote {args.out} (outputs within {diff:.1e} of {args.model.name} on {args.runs} random inputs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
