"""Training crops made on the training device: the landability model's crops without the CPU.

On a lent GPU the landability training was bound by making crops (about 810 crops/s from 7 CPU
worker processes, 0.08 s a step; the GPU waited: ``LANDABILITY_CARD.md``). The semantic-drone
photos are small (750x500) and few (320 in the training split, 0.36 GB with their level maps), so
they can sit on the device whole, and a batch of crops is one ``grid_sample`` there.

:class:`TensorCrops` draws the same kinds of change as the CPU path
(:func:`companion.training.landability.level_crop` and
:func:`companion.training.augment.photometric`): a scale drawn log-uniformly in 0.35-1.4, any
rotation, a mirror half the time, reflected borders; the level map sampled with nearest neighbour
(no level invented at a boundary); then brightness and contrast, white balance, saturation and a
hue turn, grey, blur and noise with the CPU path's odds and ranges. Two differ on purpose: the hue
turn is a rotation of the chroma plane (YIQ), not OpenCV's HSV hue shift, and the blur is one
of four fixed Gaussian kernels (sigma 0.4-1.2), not a sigma drawn per crop. It runs on a CPU too
(the tests), just not faster than the CPU path there.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from companion.training import model as M

#: The blur kernels' sigmas (pixels): the CPU path draws sigma uniformly in 0.4-1.2.
BLUR_SIGMAS = (0.4, 0.65, 0.9, 1.2)

# RGB <-> YIQ (the hue turn rotates I and Q). The photos are BGR; the matrices are applied to
# the channels reversed and back.
_RGB2YIQ = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
_YIQ2RGB = torch.linalg.inv(_RGB2YIQ)


def _gauss_kernels(sigmas: tuple[float, ...], radius: int = 3) -> torch.Tensor:
    """(K, 2r+1) normalised 1-D Gaussian kernels."""
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    k = torch.stack([torch.exp(-0.5 * (x / s) ** 2) for s in sigmas])
    return k / k.sum(dim=1, keepdim=True)


class TensorCrops:
    """The training photos and their level maps on ``device``; :meth:`batch` makes crops there.

    ``images``: BGR uint8 photos of one size (H, W, 3); ``levels``: their level maps (H, W) of
    level codes 0..``n_levels``-1. ``stride`` is the network's cell (the soft target's pixels a
    cell)."""

    def __init__(self, images: list[np.ndarray], levels: list[np.ndarray], n_levels: int,
                 device: torch.device | str = "cpu", stride: int = 8) -> None:
        if not images or len(images) != len(levels):
            raise ValueError(f"need photos with one level map each, not {len(images)} and {len(levels)}")
        shapes = {im.shape[:2] for im in images} | {lv.shape for lv in levels}
        if len(shapes) != 1:
            raise ValueError(f"tensor crops need photos and level maps of one size, not {sorted(shapes)}")
        self.device = torch.device(device)
        self.n_levels, self.stride = int(n_levels), int(stride)
        self.images = torch.from_numpy(np.stack(images)).to(self.device).permute(0, 3, 1, 2).contiguous()  # N,3,H,W u8
        self.levels = torch.from_numpy(np.stack(levels)).to(self.device)[:, None].contiguous()  # N,1,H,W u8
        self.h, self.w = int(self.images.shape[2]), int(self.images.shape[3])
        self.mean = torch.tensor(M.MEAN, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(M.STD, device=self.device).view(1, 3, 1, 1)
        self.kernels = _gauss_kernels(BLUR_SIGMAS).to(self.device)
        self.rgb2yiq, self.yiq2rgb = _RGB2YIQ.to(self.device), _YIQ2RGB.to(self.device)

    def grids(self, n: int, size: int, g: torch.Generator,
              scale: tuple[float, float] = (0.35, 1.4)) -> tuple[torch.Tensor, torch.Tensor]:
        """(photo indices (n,), sampling grids (n, size, size, 2) in grid_sample's normalised
        coordinates): each crop pixel's place in its photo after a random scale ``s`` (crop
        pixels per photo pixel, as the CPU path), rotation, mirror and centre."""
        d = self.device
        idx = torch.randint(0, self.images.shape[0], (n,), generator=g, device=d)
        s = torch.exp(torch.empty(n, device=d).uniform_(math.log(scale[0]), math.log(scale[1]), generator=g))
        ang = torch.empty(n, device=d).uniform_(0, 2 * math.pi, generator=g)
        mirror = torch.where(torch.rand(n, generator=g, device=d) < 0.5, -1.0, 1.0)
        cx = torch.rand(n, generator=g, device=d) * self.w
        cy = torch.rand(n, generator=g, device=d) * self.h
        # Crop pixel (u, v), its centre at (size-1)/2 as OpenCV's (size/2 with pixel centres at
        # integers is within half a pixel of it), to the photo: un-mirror, un-rotate, un-scale.
        r = torch.arange(size, device=d, dtype=torch.float32) - size / 2
        v, u = torch.meshgrid(r, r, indexing="ij")
        u = u[None] * mirror[:, None, None]
        v = v[None].expand_as(u)
        c, sn = torch.cos(ang)[:, None, None], torch.sin(ang)[:, None, None]
        x = cx[:, None, None] + (c * u - sn * v) / s[:, None, None]
        y = cy[:, None, None] + (sn * u + c * v) / s[:, None, None]
        grid = torch.stack([(2 * x + 1) / self.w - 1, (2 * y + 1) / self.h - 1], dim=-1)
        return idx, grid

    def crop(self, idx: torch.Tensor, grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(BGR float 0-255 crops (n, 3, S, S), level codes (n, S, S) long) at ``grid``."""
        img = F.grid_sample(self.images[idx].float(), grid, mode="bilinear", padding_mode="reflection",
                            align_corners=False)
        lv = F.grid_sample(self.levels[idx].float(), grid, mode="nearest", padding_mode="reflection",
                           align_corners=False)
        return img, lv[:, 0].round().long().clamp_(0, self.n_levels - 1)

    def photometric(self, img: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        """The CPU path's photometric changes, per crop, on BGR float 0-255 (n, 3, S, S)."""
        n, d = img.shape[0], img.device

        def draw(p: float) -> torch.Tensor:
            return (torch.rand(n, generator=g, device=d) < p).view(n, 1, 1, 1)

        def unif(lo: float, hi: float, *shape: int) -> torch.Tensor:
            return torch.empty(n, *shape, device=d).uniform_(lo, hi, generator=g)

        mean = img.mean(dim=(1, 2, 3), keepdim=True)
        contrast = (img - mean) * unif(0.6, 1.4).view(n, 1, 1, 1) + mean + unif(-40, 40).view(n, 1, 1, 1)
        img = torch.where(draw(0.8), contrast, img)
        img = torch.where(draw(0.5), img * unif(0.85, 1.15, 3).view(n, 3, 1, 1), img)
        img = img.clamp(0, 255)
        # Saturation and hue: the chroma plane (I, Q) scaled and turned (about +-24 degrees, the
        # CPU path's +-12 of OpenCV's 180 hue steps).
        yiq = torch.einsum("ij,njhw->nihw", self.rgb2yiq, img.flip(1))
        ang = unif(-24, 24) * math.pi / 180
        sat = unif(0.5, 1.5)
        c, sn = (torch.cos(ang) * sat).view(n, 1, 1), (torch.sin(ang) * sat).view(n, 1, 1)
        i, q = yiq[:, 1], yiq[:, 2]
        turned = torch.stack([yiq[:, 0], c * i - sn * q, sn * i + c * q], dim=1)
        hued = torch.einsum("ij,njhw->nihw", self.yiq2rgb, turned).flip(1).clamp(0, 255)
        img = torch.where(draw(0.3), hued, img)
        grey = (0.114 * img[:, 0:1] + 0.587 * img[:, 1:2] + 0.299 * img[:, 2:3]).expand_as(img)
        img = torch.where(draw(0.1), grey, img)
        img = torch.where(draw(0.2), self._blur(img, g), img)
        noise = torch.randn(img.shape, generator=g, device=d) * unif(2, 8).view(n, 1, 1, 1)
        img = torch.where(draw(0.3), (img + noise).clamp(0, 255), img)
        return img

    def _blur(self, img: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        """Each crop blurred by one of the :data:`BLUR_SIGMAS` kernels (separable, reflected)."""
        n, ch, hh, ww = img.shape
        k = self.kernels[torch.randint(0, len(BLUR_SIGMAS), (n,), generator=g, device=img.device)]  # n,K
        k = k.repeat_interleave(ch, dim=0)  # n*ch, K
        r = k.shape[1] // 2
        x = F.pad(img.reshape(1, n * ch, hh, ww), (r, r, r, r), mode="reflect")
        x = F.conv2d(x, k[:, None, None, :], groups=n * ch)
        x = F.conv2d(x, k[:, None, :, None], groups=n * ch)
        return x.reshape(n, ch, hh, ww)

    def soft_target(self, lv: torch.Tensor) -> torch.Tensor:
        """(n, L, S/stride, S/stride): the share of each cell's pixels in each level."""
        onehot = F.one_hot(lv, self.n_levels).permute(0, 3, 1, 2).float()
        return F.avg_pool2d(onehot, self.stride)

    def batch(self, n: int, size: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """One training batch on the device: normalised inputs (n, 3, S, S) and soft targets
        (n, L, S/stride, S/stride), as :func:`companion.training.landability.make_batch`."""
        if size % self.stride:
            raise ValueError(f"crop side {size} is not a multiple of the stride {self.stride}")
        with torch.no_grad():
            img, lv = self.crop(*self.grids(n, size, g))
            img = self.photometric(img, g)
            x = (img * M.SCALE - self.mean) / self.std
            return x, self.soft_target(lv)
