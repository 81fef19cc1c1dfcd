"""ONNX export of the trained network, with the metadata the runner reads.

The metadata keys (``companion.*``) are documented in :mod:`companion.pipeline.density`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch

from companion.training import model as M
from companion.training.metadata import set_metadata


def base_metadata() -> dict[str, object]:
    return {
        "companion.color": M.COLOR,
        "companion.scale": repr(M.SCALE),
        "companion.mean": ",".join(str(v) for v in M.MEAN),
        "companion.std": ",".join(str(v) for v in M.STD),
        "companion.stride": M.STRIDE,
        "companion.input_multiple": M.STRIDE,
        "companion.output": "occupancy-probability",
    }


def export_onnx(net: torch.nn.Module, out: Path, extra: Mapping[str, object] | None = None) -> Path:
    """Fold batch norm, add the sigmoid, export with dynamic H and W, write the metadata."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    deploy = M.Exported(M.fold_batchnorm(net)).eval()
    dummy = torch.zeros(1, 3, 480, 640)
    with torch.no_grad():
        torch.onnx.export(
            deploy,
            (dummy,),
            str(out),
            input_names=["input"],
            output_names=["density"],
            dynamic_axes={"input": {0: "n", 2: "h", 3: "w"}, "density": {0: "n", 2: "h4", 3: "w4"}},
            opset_version=17,
            dynamo=False,
        )
    meta = base_metadata()
    meta["companion.parameters"] = M.count_parameters(net)
    meta.update(extra or {})
    set_metadata(out, meta)
    return out
