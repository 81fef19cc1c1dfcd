"""The blocked layout of a density model (``companion.training.layout``): the same map, a different
arrangement of channels; the shipped x86-64 file is version 4's, and the service picks it there only."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx", reason="the layout tool needs onnx (the 'dev' and 'train' extras)")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from companion import config  # noqa: E402
from companion.geometry.camera import Intrinsics, Mount, Pose  # noqa: E402
from companion.pipeline.density import DensityModel  # noqa: E402
from companion.training.layout import TOLERANCE, align_concats, main, max_difference  # noqa: E402
from sim.world.crowd import default_world  # noqa: E402
from sim.world.ground import ProceduralGround  # noqa: E402
from sim.world.render import render_world  # noqa: E402


def _branchy(widths: tuple[int, ...] = (3, 5, 8), shared_weight: bool = False,
             second_reader: bool = False, input_shape: tuple[int | None, ...] = (1, 3, None, None)) -> onnx.ModelProto:
    """A C-CNN-like model: conv branches of ``widths`` channels -> Relu -> Concat -> MaxPool ->
    Conv -> Sigmoid, random weights (seeded). An ``input_shape`` of three dimensions (C, H, W) is
    unsqueezed to a batch of one before the branches."""
    rng = np.random.default_rng(1)
    nodes, inits = [], []
    image = "input"
    if len(input_shape) == 3:
        inits.append(numpy_helper.from_array(np.array([0], np.int64), "axes"))
        nodes.append(helper.make_node("Unsqueeze", ["input", "axes"], ["batch"], name="batch"))
        image = "batch"
    for k, (w, size) in enumerate(zip(widths, (5, 3, 1, 3, 5))):
        wname = "w0" if shared_weight else f"w{k}"
        if not shared_weight or k == 0:
            inits.append(numpy_helper.from_array(rng.normal(0, 0.3, (w, 3, size, size)).astype(np.float32), wname))
        inits.append(numpy_helper.from_array(rng.normal(0, 0.1, w).astype(np.float32), f"b{k}"))
        nodes += [helper.make_node("Conv", [image, wname, f"b{k}"], [f"c{k}"], name=f"branch{k}",
                                   kernel_shape=[size, size], pads=[size // 2] * 4, strides=[2, 2]),
                  helper.make_node("Relu", [f"c{k}"], [f"r{k}"], name=f"relu{k}")]
    total = sum(widths)
    inits += [numpy_helper.from_array(rng.normal(0, 0.2, (4, total, 3, 3)).astype(np.float32), "wr"),
              numpy_helper.from_array(rng.normal(0, 0.1, 4).astype(np.float32), "br"),
              numpy_helper.from_array(rng.normal(0, 0.2, (1, 4, 1, 1)).astype(np.float32), "wh")]
    nodes += [helper.make_node("Concat", [f"r{k}" for k in range(len(widths))], ["cat"], name="cat", axis=1),
              helper.make_node("MaxPool", ["cat"], ["pool"], name="pool", kernel_shape=[2, 2], strides=[2, 2]),
              helper.make_node("Conv", ["pool", "wr", "br"], ["body"], name="reader", kernel_shape=[3, 3],
                               pads=[1, 1, 1, 1]),
              helper.make_node("Relu", ["body"], ["body_r"], name="body_relu"),
              helper.make_node("Conv", ["body_r", "wh"], ["head"], name="head"),
              helper.make_node("Sigmoid", ["head"], ["density"], name="sigmoid")]
    outputs = [helper.make_tensor_value_info("density", TensorProto.FLOAT, [1, 1, None, None])]
    if second_reader:
        nodes.append(helper.make_node("Identity", ["cat"], ["cat_copy"], name="copy"))
        outputs.append(helper.make_tensor_value_info("cat_copy", TensorProto.FLOAT, [1, None, None, None]))
    graph = helper.make_graph(nodes, "branchy", [helper.make_tensor_value_info("input", TensorProto.FLOAT,
                                                                               list(input_shape))],
                              outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def test_aligning_pads_each_branch_to_whole_blocks_and_keeps_the_outputs() -> None:
    model = _branchy()
    before = model.SerializeToString()
    aligned = align_concats(model, block=8)
    assert aligned.model is not None
    assert model.SerializeToString() == before, "the input model must not be changed"
    inits = {t.name: numpy_helper.to_array(t) for t in aligned.model.graph.initializer}
    assert [inits[f"w{k}"].shape[0] for k in range(3)] == [8, 8, 8]
    assert [inits[f"b{k}"].shape[0] for k in range(3)] == [8, 8, 8]
    assert inits["wr"].shape == (4, 24, 3, 3)
    # The added filters and the reader's added columns are zeros; the original ones are in place.
    original = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    assert np.array_equal(inits["w0"][:3], original["w0"]) and not inits["w0"][3:].any()
    assert np.array_equal(inits["wr"][:, 8:13], original["wr"][:, 3:8]) and not inits["wr"][:, 13:16].any()
    assert aligned.notes == ("cat: 3 + 5 + 8 -> 8 + 8 + 8 channels (zero filters), reader reads 24",)
    diff = max_difference(model, aligned.model, runs=3, size=(64, 96))
    assert diff <= TOLERANCE
    # ... and a model that really differs is told apart by the same measure.
    bad = onnx.ModelProto()
    bad.CopyFrom(aligned.model)
    for t in bad.graph.initializer:
        if t.name == "br":
            t.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(t) + 1.0, "br"))
    assert max_difference(model, bad, runs=1, size=(64, 96)) > 1e-3


def test_models_it_cannot_prove_equal_are_left_as_they_are() -> None:
    aligned = align_concats(_branchy((8, 16, 8)), block=8)
    assert aligned.model is None and "already whole blocks of 8" in aligned.notes[0]
    shared = align_concats(_branchy(shared_weight=True, widths=(3, 3, 3)), block=8)
    assert shared.model is None and "left as it is" in shared.notes[0]
    exposed = align_concats(_branchy(second_reader=True), block=8)
    assert exposed.model is None and "left as it is" in exposed.notes[0]


def test_the_command_writes_only_a_proven_model_and_says_why_not(tmp_path: Path, capsys) -> None:
    src = tmp_path / "m.onnx"
    onnx.save(_branchy(), str(src))
    assert main(["--model", str(tmp_path / "missing.onnx"), "--out", str(tmp_path / "o.onnx")]) == 2
    assert "no model at" in capsys.readouterr().err
    (tmp_path / "junk.onnx").write_bytes(b"not a protobuf at all")
    assert main(["--model", str(tmp_path / "junk.onnx"), "--out", str(tmp_path / "o.onnx")]) == 2
    assert "not a readable ONNX model" in capsys.readouterr().err
    assert main(["--model", str(src), "--out", str(tmp_path / "o.onnx"), "--block", "0"]) == 2
    assert not (tmp_path / "o.onnx").exists()
    plain = tmp_path / "aligned8.onnx"
    onnx.save(_branchy((8, 8, 8)), str(plain))
    assert main(["--model", str(plain), "--out", str(tmp_path / "o.onnx"), "--block", "8"]) == 1
    assert "nothing to align" in capsys.readouterr().out and not (tmp_path / "o.onnx").exists()
    assert main(["--model", str(src), "--out", str(tmp_path / "o.onnx"), "--block", "8"]) == 0
    out = onnx.load(str(tmp_path / "o.onnx"))
    meta = {p.key: p.value for p in out.metadata_props}
    assert meta["companion.layout"].startswith("concatenated channels in blocks of 8")


def test_a_model_it_cannot_run_to_compare_is_exit_2_and_not_written(tmp_path: Path, capsys) -> None:
    # The padding itself reads only the graph, but nothing is written unproven: a model whose
    # input is not an image batch (N, C, H, W) is not run on random frames to compare.
    src = tmp_path / "flat.onnx"
    onnx.save(_branchy(input_shape=(3, None, None)), str(src))
    assert main(["--model", str(src), "--out", str(tmp_path / "o.onnx"), "--block", "8"]) == 2
    err = capsys.readouterr().err
    assert "cannot run" in err and "(N, C, H, W)" in err
    assert not (tmp_path / "o.onnx").exists()


def _frame() -> np.ndarray:
    """A rendered 640x480 frame of a crowd from 15 m (the simulator's camera)."""
    world = default_world(seed=3)
    world.step(2.0)
    pose = Pose(0.0, 0.0, 0.0, -15.0, 0.0, 0.0, 0.0)
    return render_world(world, pose, Intrinsics.from_fov(640, 480, 70.0), Mount(), ProceduralGround(3))


def test_the_shipped_x86_file_is_version_4_in_blocks() -> None:
    plain, blocked = config.PLAIN_MODEL, config.X86_MODEL
    assert plain.is_file() and blocked.is_file()
    a, b = DensityModel(plain, threads=1), DensityModel(blocked, threads=1)
    assert a.spec == b.spec  # threshold, border, normalisation: the same metadata
    frame = _frame()
    da, db = a(frame), b(frame)
    assert da.shape == db.shape and float(np.abs(da - db).max()) <= TOLERANCE
    assert da.max() > a.spec.occupancy_threshold, "the frame should hold people the model sees"
    meta_a = {p.key: p.value for p in onnx.load(str(plain)).metadata_props}
    meta_b = {p.key: p.value for p in onnx.load(str(blocked)).metadata_props}
    assert meta_b.pop("companion.layout").startswith("concatenated channels in blocks of 16")
    assert meta_a == meta_b  # the trained parameter count included: the zeros were not trained
    again = align_concats(onnx.load(str(blocked)))
    assert again.model is None and "already whole blocks of 16" in again.notes[0]
    # Made by the command from the plain file: the same weights where they were, zeros elsewhere.
    remade = align_concats(onnx.load(str(plain))).model
    assert remade is not None
    have = {t.name: hashlib.sha256(t.raw_data or numpy_helper.to_array(t).tobytes()).hexdigest()
            for t in onnx.load(str(blocked)).graph.initializer}
    made = {t.name: hashlib.sha256(t.raw_data or numpy_helper.to_array(t).tobytes()).hexdigest()
            for t in remade.graph.initializer}
    assert have == made


@pytest.mark.parametrize(("machine", "expected"), [("x86_64", "x86"), ("AMD64", "x86"), ("aarch64", "plain"),
                                                   ("arm64", "plain"), ("armv7l", "plain"), ("i686", "plain")])
def test_the_service_takes_the_blocked_file_on_64_bit_x86_only(machine: str, expected: str) -> None:
    want = config.X86_MODEL if expected == "x86" else config.PLAIN_MODEL
    assert config.shipped_model(machine) == want
