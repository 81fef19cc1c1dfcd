"""The landability training's crops made on the device (``companion.training.tensor_crops``):
the geometry is the CPU path's (a crop of a photo at scale 1 is that photo's pixels), the level
map is sampled without inventing levels, the targets are shares, and training runs with it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")

from companion.training.tensor_crops import TensorCrops  # noqa: E402


def _photos(n: int = 3, h: int = 40, w: int = 60) -> tuple[list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]
    levels = [np.zeros((h, w), np.uint8) for _ in range(n)]
    for lv in levels:
        lv[:, w // 2:] = 2  # left half level 0, right half level 2; level 1 nowhere
    return images, levels


def _grid(tc: TensorCrops, size: int, cx: float, cy: float, scale: float = 1.0, angle: float = 0.0,
          mirror: float = 1.0) -> torch.Tensor:
    """The sampling grid of one crop with the given draws, by the same arithmetic as ``grids``."""
    r = torch.arange(size, dtype=torch.float32) - size / 2
    v, u = torch.meshgrid(r, r, indexing="ij")
    u = u * mirror
    x = cx + (math.cos(angle) * u - math.sin(angle) * v) / scale
    y = cy + (math.sin(angle) * u + math.cos(angle) * v) / scale
    return torch.stack([(2 * x + 1) / tc.w - 1, (2 * y + 1) / tc.h - 1], dim=-1)[None]


def test_a_crop_at_scale_one_is_the_photos_pixels_and_a_mirror_flips_it() -> None:
    images, levels = _photos()
    tc = TensorCrops(images, levels, 3)
    idx = torch.tensor([1])
    img, lv = tc.crop(idx, _grid(tc, 16, cx=30, cy=20))
    want = images[1][12:28, 22:38].transpose(2, 0, 1).astype(np.float32)
    assert np.allclose(img[0].numpy(), want, atol=1e-3)
    assert np.array_equal(lv[0].numpy(), levels[1][12:28, 22:38])
    flipped, _ = tc.crop(idx, _grid(tc, 16, cx=30, cy=20, mirror=-1.0))
    # Mirrored about the crop's centre column (size/2): column u shows the photo's column 2*cx - x.
    assert np.allclose(flipped[0, :, :, 1:].numpy(), want[:, :, ::-1][:, :, :-1], atol=1e-3)


def test_random_crops_keep_the_levels_and_give_shares_as_targets() -> None:
    images, levels = _photos()
    tc = TensorCrops(images, levels, 3)
    g = torch.Generator().manual_seed(0)
    x, y = tc.batch(32, 32, g)
    assert x.shape == (32, 3, 32, 32) and y.shape == (32, 3, 4, 4)
    assert torch.isfinite(x).all()
    assert torch.allclose(y.sum(dim=1), torch.ones(32, 4, 4))
    assert float(y[:, 1].max()) == 0.0  # level 1 is in no photo: nearest sampling invents none
    assert 0.2 < float(y[:, 0].mean()) < 0.8 and 0.2 < float(y[:, 2].mean()) < 0.8  # both halves, rotated
    _, lv = tc.crop(*tc.grids(8, 32, g))
    assert set(np.unique(lv.numpy())) <= {0, 2}
    # The same seed draws the same batch; another seed another.
    x2, _ = tc.batch(32, 32, torch.Generator().manual_seed(0))
    assert torch.equal(x, x2)
    x3, _ = tc.batch(32, 32, torch.Generator().manual_seed(1))
    assert not torch.equal(x, x3)


def test_photometric_changes_stay_in_range_and_change_the_crops() -> None:
    images, levels = _photos()
    tc = TensorCrops(images, levels, 3)
    g = torch.Generator().manual_seed(3)
    img, _ = tc.crop(*tc.grids(64, 16, g))
    out = tc.photometric(img, g)
    assert out.shape == img.shape and float(out.min()) >= 0.0 and float(out.max()) <= 255.0
    changed = (out - img).abs().flatten(1).amax(dim=1) > 1.0
    assert 0.5 < float(changed.float().mean()) <= 1.0  # most crops changed, by the CPU path's odds


def test_bad_inputs_are_refused() -> None:
    images, levels = _photos()
    with pytest.raises(ValueError, match="one size"):
        TensorCrops(images + [np.zeros((10, 10, 3), np.uint8)], levels + [np.zeros((10, 10), np.uint8)], 3)
    with pytest.raises(ValueError, match="level map each"):
        TensorCrops(images, levels[:1], 3)
    with pytest.raises(ValueError, match="multiple of the stride"):
        TensorCrops(images, levels, 3).batch(2, 30, torch.Generator())


def test_training_with_tensor_crops_runs_records_it_and_refuses_workers(tmp_path: Path, shared_dir: Path) -> None:
    from companion.pipeline.landability import LandabilityModel
    from companion.training import landability as T

    out = tmp_path / "t.onnx"
    rc = T.main(["--shared", str(shared_dir), "--out", str(out), "--steps", "3", "--batch", "4",
                 "--crop", "64", "--max-images", "9", "--tensor-crops"])
    assert rc == 0
    m = LandabilityModel(out, threads=1)
    assert m(np.zeros((64, 64, 3), np.uint8)).shape == (7, 8, 8)
    import onnxruntime as ort
    meta = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    assert " tensor_crops=1 " in meta["companion.training"]
    for bad in (["--tensor-crops", "--workers", "1"], ["--tensor-crops", "--hard-share", "0.2"]):
        assert T.main(["--shared", str(shared_dir), "--out", str(out), *bad]) == 2, bad
