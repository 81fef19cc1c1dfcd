"""The ONNX density runner: shipped model, the MCNN peer via overrides, metadata, every error path."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from companion.pipeline.density import DensityModel, DensityModelError, DensitySpec, FrameError


def _save(tmp_path: Path, graph: onnx.GraphProto, meta: dict[str, str] | None = None, name: str = "m.onnx") -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in (meta or {}).items():
        e = model.metadata_props.add()
        e.key, e.value = k, v
    onnx.checker.check_model(model)
    path = tmp_path / name
    onnx.save(model, str(path))
    return path


def first_channel_model(tmp_path: Path, meta: dict[str, str] | None = None, channels: int = 3) -> Path:
    """(N, C, H, W) -> 1x1 conv picking channel 0 -> 2x2 average pool -> (N, 1, H/2, W/2)."""
    w = np.zeros((1, channels, 1, 1), np.float32)
    w[0, 0] = 1.0
    graph = helper.make_graph(
        [
            helper.make_node("Conv", ["x", "w"], ["c"]),
            helper.make_node("AveragePool", ["c"], ["y"], kernel_shape=[2, 2], strides=[2, 2]),
        ],
        "pick",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", channels, "h", "w"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", 1, "h2", "w2"])],
        [numpy_helper.from_array(w, "w")],
    )
    return _save(tmp_path, graph, meta)


def identity_model(tmp_path: Path, in_shape: list, out_shape: list | None = None, op: str = "Identity", **attrs) -> Path:
    graph = helper.make_graph(
        [helper.make_node(op, ["x"], ["y"], **attrs)],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, in_shape)],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, out_shape or in_shape)],
    )
    return _save(tmp_path, graph)


def bgr_frame(h: int, w: int, b: int = 10, g: int = 20, r: int = 30) -> np.ndarray:
    f = np.empty((h, w, 3), np.uint8)
    f[..., 0], f[..., 1], f[..., 2] = b, g, r
    return f


# --- the shipped models (float, its int8 form and the GPU-trained version 2, when shipped) ---

INT8 = Path(__file__).resolve().parents[3] / "companion" / "models" / "slz-density-int8.onnx"
V1 = Path(__file__).resolve().parents[3] / "companion" / "models" / "slz-density.onnx"
V2 = Path(__file__).resolve().parents[3] / "companion" / "models" / "slz-density-v2.onnx"
V3 = Path(__file__).resolve().parents[3] / "companion" / "models" / "slz-density-v3.onnx"
V5 = Path(__file__).resolve().parents[3] / "companion" / "models" / "slz-density-v5.onnx"


@pytest.fixture
def v1_path() -> Path:
    """Version 1, shipped beside the default: a real model that declares no border (the default,
    version 4, declares 16 px), for the tests of the border itself."""
    assert V1.is_file(), f"version 1 ({V1}) is shipped and missing"
    return V1


@pytest.fixture(params=["float", "v1", "int8", "v2", "v3", "v5"])
def shipped_model(request, model_path: Path) -> Path:
    """Each density model the package ships: the runner tests hold for the default (version 4),
    version 1 (the first default), its int8 form and versions 2, 3 and 5 (beside the default)."""
    if request.param == "float":
        return model_path
    extra = {"v1": V1, "int8": INT8, "v2": V2, "v3": V3, "v5": V5}[request.param]
    if not extra.is_file():
        pytest.skip(f"no {request.param} model shipped ({extra.name})")
    return extra



@pytest.mark.parametrize("hw", [(480, 640), (720, 1280)])
def test_shipped_model_gives_stride_4_map(shipped_model: Path, hw: tuple[int, int]) -> None:
    m = DensityModel(shipped_model, threads=2)
    assert isinstance(m.spec, DensitySpec)
    assert m.spec.stride == 4 and m.spec.input_multiple == 4 and m.spec.color == "bgr"
    assert m.spec.occupancy_threshold is not None and 0 < m.spec.occupancy_threshold < 1
    rng = np.random.default_rng(0)
    d = m(rng.integers(0, 256, (*hw, 3), dtype=np.uint8))
    assert d.dtype == np.float32 and d.shape == (hw[0] // 4, hw[1] // 4)
    assert np.isfinite(d).all() and d.min() >= 0 and d.max() <= 1  # sigmoid occupancy score


def test_the_shipped_int8_file_scores_like_the_float_one_on_this_cpu(shared_dir: Path) -> None:
    """The int8 file's map on the held-out DroneCrowd frame, on whatever CPU runs this: within a
    few hundredths of the float model it was quantised from (version 1). Its first form (8-bit
    weights) was 0.11 away on an x86 CPU without VNNI, where onnxruntime's kernels saturate, and
    left more ground free there than on the machine it was measured on (MODEL_CARD.md, "int8")."""
    from companion.evaluation.datasets import dronecrowd_frames

    if not INT8.is_file():
        pytest.skip(f"no int8 model shipped ({INT8.name})")
    frame = dronecrowd_frames(shared_dir, ["img017012"])[0].image()
    a, b = DensityModel(V1, threads=1)(frame), DensityModel(INT8, threads=1)(frame)
    assert float(np.abs(a - b).max()) < 0.06, float(np.abs(a - b).max())


def test_shipped_model_sees_people_in_a_drone_photo(shipped_model: Path, shared_dir: Path) -> None:
    from companion.evaluation.datasets import semantic_drone

    s = next(x for x in semantic_drone(shared_dir, "val") if len(x.points) >= 3)
    img = s.image()
    d = DensityModel(shipped_model)(img)
    assert d.shape == (-(-img.shape[0] // 4), -(-img.shape[1] // 4))
    rows, cols = (s.points[:, 1] // 4).astype(int), (s.points[:, 0] // 4).astype(int)
    # People score far above the frame's median cell.
    assert np.median(d[rows, cols]) > 10 * np.median(d)


def test_odd_frame_sizes_are_padded_and_cropped_back(shipped_model: Path) -> None:
    d = DensityModel(shipped_model)(np.full((501, 750, 3), 128, np.uint8))
    assert d.shape == (126, 188)


def test_grey_frame_runs_on_a_colour_model(shipped_model: Path) -> None:
    assert DensityModel(shipped_model)(np.full((64, 64), 90, np.uint8)).shape == (16, 16)


# --- the MCNN peer through overrides -----------------------------------------------------------


def test_mcnn_peer_runs_with_overrides(shared_dir: Path) -> None:
    from companion.evaluation.datasets import shanghaitech_b

    m = DensityModel(shared_dir / "peers" / "mcnn-shb.onnx", overrides={"color": "gray", "scale": 1, "stride": 4})
    assert m.spec.color == "gray" and m.spec.stride == 4 and m.spec.occupancy_threshold is None
    assert m(np.zeros((480, 640, 3), np.uint8)).shape == (120, 160)
    s = shanghaitech_b(shared_dir, "test")[0]
    count = m.count(m(s.image()))
    assert 0.5 * len(s.points) < count < 2 * len(s.points)  # a working counter (35.6 for 23 here), not noise


def test_mcnn_stride_is_inferred_when_not_given(shared_dir: Path) -> None:
    m = DensityModel(shared_dir / "peers" / "mcnn-shb.onnx", overrides={"color": "gray"})
    assert m.spec.stride == 4 and m.spec.input_multiple == 4


# --- metadata, overrides and preprocessing on a tiny exact model ---------------------------


META = {"companion.color": "bgr", "companion.scale": "0.01", "companion.mean": "0.05,0,0",
        "companion.std": "0.5", "companion.occupancy_threshold": "0.25", "companion.count_scale": "2"}


def test_metadata_drives_preprocessing(tmp_path: Path) -> None:
    m = DensityModel(first_channel_model(tmp_path, META))
    assert m.spec == DensitySpec("bgr", 0.01, (0.05, 0.0, 0.0), (0.5, 0.5, 0.5), 2, 2, 0.25, 2.0)
    d = m(bgr_frame(8, 12))
    assert d.shape == (4, 6)
    np.testing.assert_allclose(d, (10 * 0.01 - 0.05) / 0.5, rtol=1e-6)  # blue channel first
    assert m.count(d) == pytest.approx(2 * d.sum())


def test_overrides_win_over_metadata(tmp_path: Path) -> None:
    m = DensityModel(first_channel_model(tmp_path, META),
                     overrides={"color": "rgb", "companion.mean": 0, "std": "1", "occupancy_threshold": 0.5})
    assert (m.spec.color, m.spec.mean, m.spec.std, m.spec.occupancy_threshold) == ("rgb", (0.0,) * 3, (1.0,) * 3, 0.5)
    np.testing.assert_allclose(m(bgr_frame(4, 4)), 30 * 0.01)  # red channel first now


def test_frame_is_padded_to_the_input_multiple(tmp_path: Path) -> None:
    m = DensityModel(first_channel_model(tmp_path), overrides={"input_multiple": 8})
    assert m.preprocess(bgr_frame(30, 30)).shape == (1, 3, 32, 32)
    assert m(bgr_frame(30, 30)).shape == (15, 15)


def test_fixed_size_model_gets_a_resized_frame(tmp_path: Path) -> None:
    path = identity_model(tmp_path, [1, 1, 16, 16], [1, 1, 8, 8], op="AveragePool", kernel_shape=[2, 2], strides=[2, 2])
    m = DensityModel(path)
    assert m.spec.color == "gray" and m.spec.stride == 2
    assert m(np.full((100, 60), 7, np.uint8)).shape == (8, 8)


# --- error paths --------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DensityModelError, match="does not exist"):
        DensityModel(tmp_path / "nope.onnx")


def test_not_onnx(tmp_path: Path) -> None:
    bad = tmp_path / "model.onnx"
    bad.write_text("this is not a protobuf")
    with pytest.raises(DensityModelError, match="not a loadable ONNX model") as exc:
        DensityModel(bad)
    assert str(bad) in str(exc.value)


@pytest.mark.parametrize(
    "shape,match",
    [(["n", 3, "h"], "image tensor"), (["n", 2, "h", "w"], "image tensor"), (["n", "c", "h", "w"], "image tensor")],
)
def test_input_not_an_image(tmp_path: Path, shape: list, match: str) -> None:
    with pytest.raises(DensityModelError, match=match):
        DensityModel(identity_model(tmp_path, shape))


def test_output_not_a_2d_map(tmp_path: Path) -> None:
    # Identity keeps 3 channels: (N, 3, H, W) is not a single-channel map.
    with pytest.raises(DensityModelError, match="2-D map|one channel"):
        DensityModel(identity_model(tmp_path, ["n", 3, "h", "w"]))


def test_output_of_unexpected_rank(tmp_path: Path) -> None:
    path = identity_model(tmp_path, ["n", 1, "h", "w"], ["n", "h", "w"], op="Squeeze")
    with pytest.raises(DensityModelError, match="2-D map"):
        DensityModel(path)


def test_non_integer_stride_cannot_be_inferred(tmp_path: Path) -> None:
    path = identity_model(tmp_path, [1, 1, 64, 64], [1, 1, 21, 21], op="AveragePool", kernel_shape=[3, 3], strides=[3, 3])
    with pytest.raises(DensityModelError, match="cannot infer the output stride"):
        DensityModel(path)


def test_unknown_override_key(tmp_path: Path) -> None:
    with pytest.raises(DensityModelError, match="unknown density model setting.*colour"):
        DensityModel(first_channel_model(tmp_path), overrides={"colour": "rgb"})


@pytest.mark.parametrize(
    "overrides,match",
    [({"color": "hsv"}, "color must be one of"), ({"color": "gray"}, "does not fit"), ({"std": "1,0,1"}, "std"),
     ({"mean": "1,2"}, "mean needs"), ({"scale": -1}, "scale"), ({"stride": 2.5}, "stride"),
     ({"occupancy_threshold": -0.1}, "occupancy_threshold"), ({"scale": "abc"}, "scale")],
)
def test_bad_override_values(tmp_path: Path, overrides: dict, match: str) -> None:
    with pytest.raises(DensityModelError, match=match):
        DensityModel(first_channel_model(tmp_path), overrides=overrides)


def test_bad_metadata_value_names_the_file(tmp_path: Path) -> None:
    path = first_channel_model(tmp_path, {"companion.color": "purple"})
    with pytest.raises(DensityModelError, match="m.onnx.*color"):
        DensityModel(path)


def _with_metadata(src: Path, dst: Path, meta: dict[str, str]) -> Path:
    proto = onnx.load(str(src))
    for k, v in meta.items():
        e = proto.metadata_props.add()
        e.key, e.value = k, v
    onnx.save(proto, str(dst))
    return dst


def test_shipped_model_copy_carries_min_person_size(model_path: Path, tmp_path: Path) -> None:
    """A copy of the shipped network with a minimum person size in its metadata (the shipped file
    itself stays as it is): the runner reads it, beside the threshold, and a config can override it."""
    shipped = DensityModel(model_path)
    path = _with_metadata(model_path, tmp_path / "copy.onnx", {"companion.min_person_px": "24"})
    m = DensityModel(path)
    assert m.min_person_px == 24.0 and m.spec.min_person_px == 24.0
    assert m.spec.occupancy_threshold == shipped.spec.occupancy_threshold
    assert DensityModel(path, overrides={"min_person_px": 30}).min_person_px == 30.0
    assert DensityModel(path, overrides={"min_person_px": "none"}).min_person_px is None
    assert DensityModel(first_channel_model(tmp_path)).min_person_px is None  # absent: no claim


@pytest.mark.parametrize("value", ["abc", "-3", "0", "nan", "inf", "1e9", "3,4", ""])
def test_malformed_min_person_px_is_a_clear_error_at_load(tmp_path: Path, value: str) -> None:
    path = first_channel_model(tmp_path, {"companion.min_person_px": value})
    if value == "":  # an empty value is "not given", as for every other key
        assert DensityModel(path).min_person_px is None
        return
    with pytest.raises(DensityModelError, match=r"m\.onnx.*min_person_px must be one number of pixels"):
        DensityModel(path)


def test_bad_thread_count(tmp_path: Path) -> None:
    with pytest.raises(DensityModelError, match="threads"):
        DensityModel(first_channel_model(tmp_path), threads=0)


@pytest.mark.parametrize("spinning", [False, True])
def test_spinning_is_off_unless_asked_and_the_output_does_not_change(model_path: Path, spinning: bool) -> None:
    # Spinning pool threads busy-wait after each run; off by default so the stages after the
    # model (and the rest of a 2-core board) get the CPU between frames.
    model = DensityModel(model_path, allow_spinning=spinning)
    opts = model._session.get_session_options()
    want = "1" if spinning else "0"
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == want
    assert opts.get_session_config_entry("session.inter_op.allow_spinning") == want
    frame = np.random.default_rng(3).integers(0, 255, (96, 128, 3), dtype=np.uint8)
    np.testing.assert_allclose(model(frame), DensityModel(model_path, allow_spinning=not spinning)(frame), rtol=1e-6)


@pytest.mark.parametrize(
    "frame,match",
    [(np.zeros((8, 8, 3), np.float32), "uint8"), (np.zeros((8, 8, 4), np.uint8), "shape"),
     (np.zeros((2, 8, 8, 3), np.uint8), "shape"), ([[0, 1], [2, 3]], "numpy array"),
     (np.zeros((1, 8, 3), np.uint8), "smaller than the stride")],
)
def test_bad_frames(tmp_path: Path, frame: object, match: str) -> None:
    m = DensityModel(first_channel_model(tmp_path))
    with pytest.raises(FrameError, match=match):
        m(frame)  # type: ignore[arg-type]


# --- border_px: the frame mirrored before the model sees it ----------------------------------

LANDABILITY = Path(__file__).resolve().parents[3] / "companion" / "models" / "slz-landability.onnx"


def _mirrored_reference(plain: DensityModel, frame: np.ndarray, border: int) -> np.ndarray:
    """What a border of ``border`` px must give: ``plain`` (a model, or its landability subclass,
    with no border) run on the frame mirrored by hand (REFLECT_101, then padded by the runner as
    any frame), its map cropped by border/stride cells on every side back to the frame's
    ceil(H/stride) x ceil(W/stride) cells."""
    assert plain.spec.border_px == 0
    stride = plain.spec.stride
    mirrored = cv2.copyMakeBorder(frame, border, border, border, border, cv2.BORDER_REFLECT_101)
    full = plain(mirrored)
    k, h, w = border // stride, -(-frame.shape[0] // stride), -(-frame.shape[1] // stride)
    return full[..., k : k + h, k : k + w]


def test_border_0_is_bit_identical_to_a_model_without_the_key(v1_path: Path, tmp_path: Path) -> None:
    frame = np.random.default_rng(5).integers(0, 256, (101, 150, 3), dtype=np.uint8)
    plain = DensityModel(v1_path, threads=1)
    assert plain.spec.border_px == 0
    copy = _with_metadata(v1_path, tmp_path / "b0.onnx", {"companion.border_px": "0"})
    for m in (DensityModel(v1_path, threads=1, overrides={"border_px": 0}), DensityModel(copy, threads=1)):
        assert m.spec == plain.spec
        np.testing.assert_array_equal(m.preprocess(frame), plain.preprocess(frame))
        np.testing.assert_array_equal(m(frame), plain(frame))


@pytest.mark.parametrize("hw", [(96, 128), (101, 150)])
def test_border_mirrors_the_frame_and_crops_the_map_back(v1_path: Path, hw: tuple[int, int]) -> None:
    frame = np.random.default_rng(6).integers(0, 256, (*hw, 3), dtype=np.uint8)
    plain = DensityModel(v1_path, threads=1)
    m = DensityModel(v1_path, threads=1, overrides={"border_px": 16})
    assert m.spec.border_px == 16 and m.spec.stride == 4
    # 16 px each side, then the bottom/right padding to the multiple of 4 as without a border
    assert m.preprocess(frame).shape == (1, 3, hw[0] + 32 + (-hw[0] % 4), hw[1] + 32 + (-hw[1] % 4))
    d = m(frame)
    assert d.shape == plain(frame).shape == (-(-hw[0] // 4), -(-hw[1] // 4)) and d.flags.c_contiguous
    np.testing.assert_array_equal(d, _mirrored_reference(plain, frame, 16))
    assert not np.array_equal(d, plain(frame))  # the edge cells do change


def test_border_from_metadata_and_a_grey_frame(v1_path: Path, tmp_path: Path) -> None:
    path = _with_metadata(v1_path, tmp_path / "b8.onnx", {"companion.border_px": "8"})
    m = DensityModel(path, threads=1)
    assert m.spec.border_px == 8
    assert DensityModel(path, threads=1, overrides={"border_px": 0}).spec.border_px == 0  # a config wins
    grey = np.random.default_rng(7).integers(0, 256, (64, 80), dtype=np.uint8)
    plain = DensityModel(v1_path, threads=1)
    np.testing.assert_array_equal(m(grey), _mirrored_reference(plain, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), 8))


def test_border_on_the_tiny_model_crops_whole_cells(tmp_path: Path) -> None:
    # Stride 2, one pixel per colour: the mirrored frame must come back cell for cell.
    m = DensityModel(first_channel_model(tmp_path), overrides={"border_px": 4, "scale": 1})
    frame = np.zeros((6, 10, 3), np.uint8)
    frame[..., 0] = np.arange(60, dtype=np.uint8).reshape(6, 10)
    assert m.preprocess(frame).shape == (1, 3, 14, 18)
    want = frame[..., 0].astype(np.float32).reshape(3, 2, 5, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(m(frame), want, rtol=1e-6)


def test_landability_model_takes_a_border_too(tmp_path: Path) -> None:
    """The landability subclass's (L, h, w) output is cropped on its last two axes."""
    from companion.pipeline.landability import LandabilityModel

    if not LANDABILITY.is_file():
        pytest.skip(f"no landability model shipped ({LANDABILITY.name})")
    plain = LandabilityModel(LANDABILITY, threads=1)
    s = plain.spec.stride
    path = _with_metadata(LANDABILITY, tmp_path / "land.onnx", {"companion.border_px": str(2 * s)})
    m = LandabilityModel(path, threads=1)
    frame = np.random.default_rng(8).integers(0, 256, (90, 130, 3), dtype=np.uint8)
    p = m(frame)
    assert m.spec.border_px == 2 * s and p.shape == plain(frame).shape == (len(m.landability.levels), -(-90 // s),
                                                                           -(-130 // s))
    np.testing.assert_array_equal(p, _mirrored_reference(plain, frame, 2 * s))


@pytest.mark.parametrize(
    "value,match",
    [(-4, r"border_px must be an integer number of pixels in \[0, 512\], got -4"),
     (3, "border_px 3 must be a multiple of the model's stride 4"),
     ("abc", "border_px must be an integer.*'abc'"), (1000, r"border_px .*\[0, 512\], got 1000"),
     (4.5, "border_px must be an integer"), ("nan", "border_px must be an integer"), (True, "border_px must be")],
)
def test_bad_border_values(v1_path: Path, value: object, match: str) -> None:
    with pytest.raises(DensityModelError, match=match) as exc:
        DensityModel(v1_path, overrides={"border_px": value})
    assert str(v1_path) in str(exc.value)


def test_bad_border_in_metadata_names_the_file(tmp_path: Path) -> None:
    path = first_channel_model(tmp_path, {"companion.border_px": "3"})  # stride 2: not a whole cell
    with pytest.raises(DensityModelError, match=r"m\.onnx: border_px 3 must be a multiple of the model's stride 2"):
        DensityModel(path)


def test_fixed_size_model_refuses_a_border(tmp_path: Path) -> None:
    path = identity_model(tmp_path, [1, 1, 16, 16], [1, 1, 8, 8], op="AveragePool", kernel_shape=[2, 2], strides=[2, 2])
    assert DensityModel(path, overrides={"border_px": 0}).spec.border_px == 0
    with pytest.raises(DensityModelError, match="border_px 2 needs a model that takes any frame size.*16x16"):
        DensityModel(path, overrides={"border_px": 2})


def test_border_through_the_service_config(v1_path: Path) -> None:
    """``model.overrides`` is handed to the runner as it is: ``border_px`` needs nothing more."""
    from companion import config
    from companion.service.parts import load_model

    cfg = config.load(overrides={"model.path": str(v1_path), "model.overrides.border_px": 16})
    assert load_model(cfg).spec.border_px == 16


# --- calibrate --border-px ------------------------------------------------------------------


def test_calibrate_refuses_a_bad_border_before_anything_is_read(v1_path: Path, tmp_path: Path, capsys) -> None:
    from companion.training.calibrate import main

    copy = _with_metadata(v1_path, tmp_path / "c.onnx", {})
    before = copy.read_bytes()
    assert main(["--model", str(copy), "--shared", str(tmp_path / "no-data"), "--border-px", "6"]) == 2
    assert "border_px 6 must be a multiple of the model's stride 4" in capsys.readouterr().err
    assert copy.read_bytes() == before


def test_calibrate_writes_the_border_it_calibrated_with(v1_path: Path, shared_dir: Path, tmp_path: Path,
                                                         monkeypatch) -> None:
    """A full calibration reads every validation set (minutes): here every set is the same two
    semantic-drone photos, enough to show that --border-px reaches the model and the file."""
    import companion.training.calibrate as cal
    from companion.evaluation import datasets as D

    two = D.semantic_drone(shared_dir, "val")[:2]
    shb = D.shanghaitech_b(shared_dir, "train")[:8]
    seen: list[int] = []
    monkeypatch.setattr(D, "shanghaitech_b", lambda shared, split: shb)
    monkeypatch.setattr(cal, "validation_sets", lambda shared, names=(): {n: two for n in names})
    monkeypatch.setattr(cal, "size_sets", lambda shared, synthetic=None: {"semantic_drone_val": two})
    real = cal.evaluate_set

    def spy(name, samples, model, threshold, *args, **kwargs):
        seen.append(model.spec.border_px)
        return real(name, samples, model, threshold, *args, **kwargs)

    monkeypatch.setattr(cal, "evaluate_set", spy)
    copy = _with_metadata(v1_path, tmp_path / "c.onnx", {})
    assert cal.main(["--model", str(copy), "--shared", str(shared_dir), "--threads", "1", "--border-px", "16"]) == 0
    props = {p.key: p.value for p in onnx.load(str(copy)).metadata_props}
    assert props["companion.border_px"] == "16" and "border_px 16" in props["companion.calibration"]
    assert "companion.occupancy_threshold" in props and seen and set(seen) == {16}
    assert DensityModel(copy).spec.border_px == 16
    # Without the option: calibrated with the border the model declares, the key left as it is.
    seen.clear()
    meta = cal.calibrate(copy, shared_dir, threads=1)
    assert "companion.border_px" not in meta and set(seen) == {16}
    assert {p.key: p.value for p in onnx.load(str(copy)).metadata_props}["companion.border_px"] == "16"
