"""The photo world made cheaper (session 30) renders the same frames and builds the same ground,
bit for bit. The references here are the session-29 code, kept verbatim: the walkers' Lab
statistics by numpy's ``mean`` and ``std``, the painter that tests every person one by one, and
the labelling of whole class maps. Needs ``../shared`` (the held-out photos); skips without it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from companion.evaluation.compositor import Compositor, _lab_stats, cutouts_from
from companion.geometry.camera import Intrinsics, Mount, Pose
from sim.flights.flight import build_world, photo_ground
from sim.flights.scenarios import FlightJob
from sim.world.photo_ground import CAR, PERSON, _components, class_window
from sim.world.photo_people import BODY_Z, COLOUR_MATCH, PhotoPeople
from sim.world.render import SUN_SHADOW, project_points, render_ground


def _numpy_lab_stats(bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lab = cv2.cvtColor(bgr.astype(np.float32) / 255.0, cv2.COLOR_BGR2Lab).reshape(-1, 3)
    return lab.mean(axis=0), np.maximum(lab.std(axis=0), 1e-3)


def _reference_paint(painter: PhotoPeople, img: np.ndarray, pos: np.ndarray, hd: np.ndarray, pose: Pose,
                     intrinsics: Intrinsics, mount: Mount, ids: np.ndarray) -> None:
    """``PhotoPeople.paint`` as session 29 drew it."""
    h, w = img.shape[:2]
    n = len(pos)
    who = np.asarray(ids, np.int64).ravel()[:n]
    centre = np.column_stack([pos, np.full(n, BODY_Z)])
    fwd = centre + np.column_stack([np.cos(hd), np.sin(hd), np.zeros(n)]) * 0.5
    sun = np.column_stack([pos + SUN_SHADOW, np.zeros(n)])
    foot = np.column_stack([pos, np.zeros(n)])
    (uv, z), (fuv, _), (suv, _), (puv, _) = (project_points(p, intrinsics, mount, pose)
                                             for p in (centre, fwd, sun, foot))
    f = max(intrinsics.fx, intrinsics.fy)
    order = np.argsort(-z)
    canvas = None
    for k in order:
        if not z[k] > 0.3:
            continue
        sil = painter.silhouettes[int(who[k] * 2654435761 % (1 << 32)) % len(painter.silhouettes)]
        size = sil.size_m * f / z[k]
        if size < 2.0:
            continue
        u, v = uv[k]
        half = 1.5 * size + 4
        if u < -half or u > w + half or v < -half or v > h + half:
            continue
        if canvas is None:
            canvas = img.astype(np.float32)
        x0, y0 = int(max(0, u - 2 * half)), int(max(0, v - 2 * half))
        x1, y1 = int(min(w, u + 2 * half)), int(min(h, v + 2 * half))
        if x1 - x0 < 2 or y1 - y0 < 2:
            continue
        mean, std = _numpy_lab_stats(np.clip(canvas[y0:y1, x0:x1] + 0.5, 0, 255).astype(np.uint8))
        dx, dy = fuv[k] - uv[k]
        angle = -math.degrees(math.atan2(dx, -dy))
        bgr, alpha = Compositor._render(sil.cutout, size, angle, 0.6, mean, std, COLOUR_MATCH)
        ph, pw = alpha.shape
        px0, py0 = int(round(u - pw / 2)), int(round(v - ph / 2))
        sdx, sdy = suv[k] - puv[k]
        length = math.hypot(sdx, sdy) / max(size, 1e-6)
        dark = float(np.clip(0.15 + 0.004 * mean[0], 0.2, 0.5))
        Compositor._shadow(canvas, alpha, px0, py0, size, math.atan2(sdy, sdx), min(length, 1.5), dark)
        ix0, iy0, ix1, iy1 = max(px0, 0), max(py0, 0), min(px0 + pw, w), min(py0 + ph, h)
        if ix0 >= ix1 or iy0 >= iy1:
            continue
        a = alpha[iy0 - py0:iy1 - py0, ix0 - px0:ix1 - px0, None]
        canvas[iy0:iy1, ix0:ix1] = (a * bgr[iy0 - py0:iy1 - py0, ix0 - px0:ix1 - px0]
                                    + (1 - a) * canvas[iy0:iy1, ix0:ix1])
    if canvas is not None:
        img[:] = np.clip(canvas + 0.5, 0, 255).astype(np.uint8)


def test_lab_statistics_are_numpys_mean_and_std_bit_for_bit(photos: str) -> None:
    rng = np.random.default_rng(30)
    images: list[np.ndarray] = [rng.integers(0, 256, (int(h), int(w), 3)).astype(np.uint8)
              for h, w in rng.integers(1, 160, (40, 2))]
    images += [cv2.GaussianBlur(im, (0, 0), 2.0) for im in images[:20]]
    photo = photo_ground(photos).patches[0].bgr
    for h, w in rng.integers(2, 400, (40, 2)):
        y, x = int(rng.integers(0, photo.shape[0] - h)), int(rng.integers(0, photo.shape[1] - w))
        images.append(photo[y:y + h, x:x + w])
    images.append(photo)
    for im in images:
        mean, std = _lab_stats(im)
        ref_mean, ref_std = _numpy_lab_stats(im)
        assert mean.dtype == ref_mean.dtype and std.dtype == ref_std.dtype
        assert np.array_equal(mean, ref_mean) and np.array_equal(std, ref_std), im.shape


@pytest.mark.parametrize("seed", [1, 2])  # a dense crowd (dense_beyond) and a crossing world
def test_walkers_are_painted_as_before_bit_for_bit(photos: str, seed: int) -> None:
    spec = FlightJob(seed, "px4", ground="photo", photos=photos).spec()
    world, free, start = build_world(spec)
    world.step(2.0)
    ground = photo_ground(photos)
    painter = ground.people_painter
    K = Intrinsics.from_fov(640, 480, spec.hfov_deg)
    pos, hd, ids = world.positions(), world.headings(), world.ids()
    assert len(pos) > 100
    # From the failsafe's height down to the last metres, tilted and turned, near the walker
    # nearest the vehicle's start.
    near = pos[int(np.argmin(np.hypot(pos[:, 0] - start[0], pos[:, 1] - start[1])))]
    painted = 0
    for alt, tilt, yaw, dn, de in [(spec.altitude_m, 0.0, 0.0, 0.0, 0.0), (12.0, 0.05, 0.7, 2.0, -3.0),
                                   (6.0, -0.04, 2.1, -1.0, 1.5), (2.5, 0.02, -1.2, 0.5, 0.5)]:
        pose = Pose(0.0, near[0] + dn / alt, near[1] + de / alt, -alt, tilt, -tilt, yaw)
        base = render_ground(pose, K, Mount(), ground)
        new, ref = base.copy(), base.copy()
        painter.paint(new, pos, hd, None, pose, K, Mount(), ids)  # type: ignore[arg-type]
        _reference_paint(painter, ref, pos, hd, pose, K, Mount(), ids)
        assert np.array_equal(new, ref), (seed, alt)
        painted += int(not np.array_equal(new, base))
    assert painted == 4  # the walkers were in view, not an empty comparison


def test_components_in_the_class_window_are_the_whole_maps(photos: str) -> None:
    ground = photo_ground(photos)
    compared = 0
    for p in ground.patches[::4]:
        for cls in (PERSON, CAR):
            found = _components(p.classes, cls)
            mask = (p.classes == cls).astype(np.uint8)
            n, cc, stats, cent = cv2.connectedComponentsWithStats(mask, connectivity=8)
            if found is None:
                assert n == 1 and class_window(p.classes, cls) is None
                continue
            rows, cols = class_window(p.classes, cls)  # type: ignore[misc]
            assert found.count == n
            shifted = found.stats.copy()
            shifted[:, 0] += cols.start
            shifted[:, 1] += rows.start
            assert np.array_equal(shifted[1:], stats[1:])
            assert np.array_equal(found.centroids[1:], cent[1:])  # bit for bit, float64
            assert np.array_equal(found.labels, cc[rows, cols])
            compared += 1
        window = class_window(p.classes, PERSON)
        if window is not None:
            whole = cutouts_from(p.bgr, p.classes, p.name, stats=(np.zeros(3), np.ones(3)))
            cut = cutouts_from(p.bgr[window], p.classes[window], p.name, stats=(np.zeros(3), np.ones(3)))
            assert [c.source for c in cut] == [c.source for c in whole]
            for a, b in zip(cut, whole, strict=True):
                assert np.array_equal(a.bgr, b.bgr) and np.array_equal(a.alpha, b.alpha)
    assert compared >= 15
