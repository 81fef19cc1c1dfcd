"""The ``companion.*`` metadata of an ONNX model file, written in place (onnx only, no torch:
calibration and quantisation run without the training extra's torch)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import onnx


def set_metadata(path: Path, meta: Mapping[str, object]) -> None:
    """Write (replace) ``companion.*`` style metadata_props of the ONNX file at ``path``."""
    proto = onnx.load(str(path))
    replace_metadata(proto, meta)
    onnx.save(proto, str(path))


def read_metadata(path: Path) -> dict[str, str]:
    """The metadata_props of the ONNX file at ``path``, key -> value."""
    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


def replace_metadata(proto: onnx.ModelProto, meta: Mapping[str, object]) -> None:
    """Replace the metadata_props of ``proto`` named in ``meta`` (a None value removes the key
    without writing it) and check the model, in memory: for a model about to be saved anyway."""
    keep = [p for p in proto.metadata_props if p.key not in meta]
    del proto.metadata_props[:]
    proto.metadata_props.extend(keep)
    for k, v in meta.items():
        if v is None:
            continue
        entry = proto.metadata_props.add()
        entry.key, entry.value = k, str(v)
    onnx.checker.check_model(proto)
