"""Training parts: targets, augmentation geometry, the network and its ONNX export."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.training.augment import GeomAug, photometric, random_crop
from companion.training.targets import box_target, point_target


def test_box_target_peaks_at_the_box_centre() -> None:
    t = box_target((50, 80), np.array([[10, 10, 30, 20]]))
    assert t.max() == pytest.approx(1.0, abs=0.03)  # centre falls between pixel centres
    r, c = np.unravel_index(t.argmax(), t.shape)
    assert (r, c) in {(14, 19), (14, 20), (15, 19), (15, 20)}
    assert t[15, 10] == pytest.approx(np.exp(-2), abs=0.03)  # box edge at two sigma
    assert box_target((5, 5), np.zeros((0, 4))).sum() == 0


def test_point_target_adapts_sigma_to_crowding() -> None:
    lone = point_target((100, 100), np.array([[50.0, 50.0]]))
    crowd_pts = np.array([[50, 50], [56, 50], [50, 56], [44, 50], [50, 44]], np.float32)
    crowd = point_target((100, 100), crowd_pts)
    assert (lone > 0.5).sum() > (crowd > 0.5).sum() / 5  # a lone head spreads wider than one in a crowd
    assert point_target((20, 20), np.array([[5.0, 5.0]]), sigma=2.0)[5, 5] > 0.9


def test_crop_keeps_image_and_target_aligned() -> None:
    img = np.zeros((200, 300, 3), np.uint8)
    img[95:105, 145:155] = 255
    tgt = box_target((200, 300), np.array([[145, 95, 155, 105]]))
    rng = np.random.default_rng(3)
    for _ in range(10):
        ci, ct = random_crop(img, tgt, np.array([[150.0, 100.0]]), 64, GeomAug((0.5, 2.0), True, 1.0), rng)
        assert ci.shape == (64, 64, 3) and ct.shape == (64, 64)
        if ct.max() > 0.5 and ci.max() > 200:
            bright = np.argwhere(ci[..., 0] > 128).mean(axis=0)
            peak = np.argwhere(ct > 0.5 * ct.max()).mean(axis=0)
            assert np.abs(bright - peak).max() < 3


def test_photometric_keeps_shape_and_dtype() -> None:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    for _ in range(20):
        out = photometric(img, rng)
        assert out.shape == img.shape and out.dtype == np.uint8


def test_network_size_and_export_metadata(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from companion.pipeline.density import DensityModel
    from companion.training.export import export_onnx
    from companion.training.model import SLZDensityNet, count_parameters

    torch.manual_seed(0)
    net = SLZDensityNet()
    assert count_parameters(net) < 100_000
    net.eval()
    path = export_onnx(net, tmp_path / "m.onnx", {"companion.occupancy_threshold": "0.2"})
    m = DensityModel(path)
    assert (m.spec.color, m.spec.stride, m.spec.input_multiple, m.spec.occupancy_threshold) == ("bgr", 4, 4, 0.2)
    x = np.random.default_rng(0).integers(0, 256, (64, 96, 3), dtype=np.uint8)
    with torch.no_grad():
        ref = torch.sigmoid(net(torch.from_numpy(m.preprocess(x))))[0, 0].numpy()
    np.testing.assert_allclose(m(x), ref, atol=1e-4)  # batch-norm folding changes nothing


# --- synthetic crowds, hard negatives and the training command (issue 13) -------------------


def test_training_runs_a_few_steps_on_cpu_with_synthetic_data(tmp_path: Path, shared_dir: Path) -> None:
    """The real command, from the compositor and hard negatives plus a few real images, on the CPU;
    the exported model loads through the runner with its provenance note."""
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.pipeline.density import DensityModel
    from companion.training.train import main

    out = tmp_path / "m.onnx"
    rc = main(["--shared", str(shared_dir), "--out", str(out), "--work", str(tmp_path / "work"),
               "--steps", "3", "--batch", "4", "--crop", "64", "--threads", "1", "--max-images", "4",
               "--synthetic-share", "0.5", "--negative-share", "0.25", "--device", "cpu", "--no-calibrate"])
    assert rc == 0 and (tmp_path / "work" / "last.pt").is_file()
    m = DensityModel(out, threads=1)
    assert m.spec.stride == 4 and m.min_person_px is None  # not calibrated: no size claim
    import onnx

    note = {p.key: p.value for p in onnx.load(str(out)).metadata_props}["companion.training"]
    assert "synthetic_share=0.5" in note and "negative_share=0.25" in note and "device=cpu" in note
    d = m(np.zeros((64, 96, 3), np.uint8))
    assert d.shape == (16, 24) and np.isfinite(d).all()


def test_batches_from_synthetic_and_negative_sources(shared_dir: Path) -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training.train import NegativeSource, SyntheticSource, all_sources, make_batch

    sources = all_sources(shared_dir, 0.6, 0.4, max_images=4)
    assert [type(s) for s in sources] == [SyntheticSource, NegativeSource]  # real share 0: no real source
    rng = np.random.default_rng(0)
    x, y = make_batch([sources[1]], 6, 64, rng)
    assert tuple(x.shape) == (6, 3, 64, 64) and float(y.max()) == 0.0  # hard negatives: no target at all
    x, y = make_batch([sources[0]], 6, 64, rng)
    assert float(y.max()) > 0.5  # synthetic crowds: people


def test_training_rejects_bad_shares_and_a_missing_cuda(tmp_path: Path, shared_dir: Path, capsys) -> None:
    torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training.train import main

    base = ["--shared", str(shared_dir), "--out", str(tmp_path / "m.onnx"), "--work", str(tmp_path), "--steps", "1"]
    assert main([*base, "--synthetic-share", "0.7", "--negative-share", "0.5"]) == 2
    assert "must be <= 1" in capsys.readouterr().err
    assert main([*base, "--negative-share", "-0.1"]) == 2
    assert "negative share must be in [0, 1]" in capsys.readouterr().err
    assert main([*base, "--max-images", "-1"]) == 2
    assert "max images must be >= 0" in capsys.readouterr().err
    assert main([*base, "--negative-share", "0.1", "--negative-kinds", "path-edge,puddle"]) == 2
    assert "unknown hard-negative kind 'puddle'" in capsys.readouterr().err
    assert main([*base, "--negative-kinds", "path-edge"]) == 2  # kinds of a share of 0: a mistake
    assert "needs --negative-share > 0" in capsys.readouterr().err
    assert main([*base, "--device", "tpu"]) == 2
    assert "--device" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main([*base, "--device", "cuda"]) == 2
        assert "no CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "m.onnx").exists()


def test_exported_model_carries_threshold_and_min_person_size(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch", reason="export needs torch (the 'train' extra; not a dev dependency)")
    from companion.pipeline.density import DensityModel
    from companion.training.export import export_onnx, set_metadata
    from companion.training.model import SLZDensityNet

    torch.manual_seed(0)
    path = export_onnx(SLZDensityNet().eval(), tmp_path / "m.onnx",
                       {"companion.occupancy_threshold": "0.07", "companion.min_person_px": "12"})
    m = DensityModel(path)
    assert (m.spec.occupancy_threshold, m.min_person_px, m.spec.min_person_px) == (0.07, 12.0, 12.0)
    set_metadata(path, {"companion.min_person_px": None})  # calibration found no size: the key goes
    assert DensityModel(path).min_person_px is None
