"""The post-density stages' cheaper code gives the same output, bit for bit, as the code it replaced.

Session 28 made a fisheye frame's head-plane stages cheaper (issue 60's cost target): the lens's
seen-edge rays and the crop box's view are cached, a fully seen projection skips its mask's gathers
and takes its ray angles from ``seen_to_image``, ``lens_maps`` tests finiteness per coordinate and
``distance_cells`` takes a uint8 grid as it is. None of that may move a cell, a zone or a track.
This module keeps the code as it was (``_ref_*``, verbatim but for names; of the input tensor's,
only the step that changed, the normalisation) and checks the new code against it: function by function on random input, and the whole configured pipeline (the shipped
model on the bench's frame, through fisheye:160 and pinhole:70) with the old functions put back,
every ``FrameResult`` field and the risk map compared.

Session 29 (the same target) made the density step's input cheaper with the same map: the
model's input tensor is looked up per pixel value (``DensityModel._lut``) instead of computed; the
pipeline comparison puts the old ``preprocess`` back too, and it is checked alone on every pixel
value and colour order besides.

OpenCV's exact distance transform runs its own code on 2 threads or more and IPP's on one thread
or below 16384 cells, whose last bit varies from call to call; the comparisons run on 2 threads
and grids above that size, where the transform gives the same bits every time.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion import bench
from companion import config as settings
from companion.geometry import camera, lens
from companion.geometry.camera import Intrinsics, LensView, Mount, PlaneProjection, Pose
from companion.pipeline import headplane, proposals, slz
from companion.pipeline.density import DensityModel
from companion.pipeline.headplane import GridParams, GridSpec, grid_for_view, lens_crop_box
from companion.pipeline.slz import FrameResult, SLZPipeline

FISHEYE = Intrinsics.from_fov(640, 480, 160.0, "fisheye")
#: A calibrated-looking fisheye (k1..k4 not zero), so the polynomial's every term is used.
CALIBRATED = Intrinsics(205.0, 204.0, 321.5, 238.0, 640, 480, (0.02, -0.004, 0.0008, -0.0001), "fisheye")


# -- the code as it was before session 28 (reference) ------------------------------------------

def _ref_project(model: str, K: np.ndarray, dist: tuple[float, ...], xc: np.ndarray,
                 theta: np.ndarray | None = None) -> np.ndarray:
    p = np.asarray(xc, dtype=np.float64).reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    out = np.full((len(p), 2), np.nan)
    if model == "fisheye":
        r = np.hypot(x, y)
        th = np.arctan2(r, z)
        ok = np.isfinite(th) & (th <= lens.fisheye_theta_max(tuple(dist)))
        td = lens._theta_d(th[ok], dist)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(r[ok] > 1e-12, td / r[ok], 0.0)
        a, b = x[ok] * s, y[ok] * s
        out[ok, 0] = fx * a + skew * b + cx
        out[ok, 1] = fy * b + cy
        return out
    ok = np.isfinite(z) & (z > 1e-9)
    if not ok.any():
        return out
    if any(abs(d) > 0 for d in dist):
        uv, _ = cv2.projectPoints(p[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                  np.asarray(dist, np.float64))
        out[ok] = uv.reshape(-1, 2)
    else:
        out[ok, 0] = fx * x[ok] / z[ok] + skew * y[ok] / z[ok] + cx
        out[ok, 1] = fy * y[ok] / z[ok] + cy
    return out


def _ref_seen_to_image(self: LensView, xy: np.ndarray) -> np.ndarray:
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    d = np.column_stack([p[:, 0] - self.position[0], p[:, 1] - self.position[1],
                         np.full(len(p), self.plane_z - self.position[2])])
    xc = d @ self.R_cv_from_world.T
    uv = _ref_project(self.intrinsics.model, self.intrinsics.K, self.intrinsics.dist, xc)
    with np.errstate(invalid="ignore"):
        wide = np.arctan2(np.hypot(xc[:, 0], xc[:, 1]), xc[:, 2]) > lens.TRUSTED_THETA
    uv[wide] = np.nan
    return uv


def _ref_seen_boundary(self: LensView, n: int = 32) -> np.ndarray:
    w, h = self.intrinsics.width, self.intrinsics.height
    s = np.linspace(0.0, 1.0, n, endpoint=False)
    border = np.concatenate([np.column_stack([s * (w - 1), np.zeros(n)]),
                             np.column_stack([np.full(n, w - 1.0), s * (h - 1)]),
                             np.column_stack([(1 - s) * (w - 1), np.full(n, h - 1.0)]),
                             np.column_stack([np.zeros(n), (1 - s) * (h - 1)])])
    rays = self.intrinsics.unproject(border)
    with np.errstate(invalid="ignore"):
        rays = rays[rays[:, 2] >= math.cos(lens.TRUSTED_THETA) - 1e-12]
    phi = np.linspace(0.0, 2 * math.pi, 4 * n, endpoint=False)
    st, ct = math.sin(lens.TRUSTED_THETA), math.cos(lens.TRUSTED_THETA)
    cone = np.column_stack([st * np.cos(phi), st * np.sin(phi), np.full(len(phi), ct)])
    uv = _ref_project(self.intrinsics.model, self.intrinsics.K, self.intrinsics.dist, cone)
    with np.errstate(invalid="ignore"):
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    d = np.concatenate([rays, cone[inside]]) @ self.R_cv_from_world
    drop = self.plane_z - self.position[2]
    out = np.full((len(d), 2), np.nan)
    down = d[:, 2] > 1e-9
    out[down, 0] = self.position[0] + drop / d[down, 2] * d[down, 0]
    out[down, 1] = self.position[1] + drop / d[down, 2] * d[down, 1]
    return out


def _ref_lens_maps(proj: PlaneProjection, grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    s = headplane.LENS_STEP
    rows = np.arange(0, grid.rows + s, s, dtype=float)
    cols = np.arange(0, grid.cols + s, s, dtype=float)
    cc, rr = np.meshgrid(cols, rows)
    x, y = grid.to_plane(rr.ravel(), cc.ravel())
    assert proj.lens is not None
    uv = _ref_seen_to_image(proj.lens, np.column_stack([x, y])).reshape(len(rows), len(cols), 2)
    ok = np.isfinite(uv).all(axis=2).astype(np.uint8)
    ok = cv2.erode(ok, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    uv = np.where(np.isfinite(uv), uv, -1e4).astype(np.float32)
    size = ((len(cols) - 1) * s + 1, (len(rows) - 1) * s + 1)
    A = np.array([[1.0 / s, 0.0, 0.0], [0.0, 1.0 / s, 0.0]])
    mx = cv2.warpAffine(uv[..., 0], A, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_REPLICATE)[:grid.rows, :grid.cols]
    my = cv2.warpAffine(uv[..., 1], A, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_REPLICATE)[:grid.rows, :grid.cols]
    seen = cv2.warpAffine(ok, A, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)[:grid.rows, :grid.cols]
    mx[seen == 0] = -1.0
    my[seen == 0] = -1.0
    return mx, my


def _ref_box_view(h: int, w: int, k: int, box: tuple[int, int, int, int]) -> np.ndarray:
    x0, y0, x1, y1 = box
    view: np.ndarray = np.zeros((h, w), np.uint8)
    view[y0:y1, x0:x1] = 255
    if k > 1:
        view = cv2.erode(view, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return view


def _ref_distance_cells(free_grid: np.ndarray) -> np.ndarray:
    padded = cv2.copyMakeBorder((free_grid > 0).astype(np.uint8), 1, 1, 1, 1,
                                cv2.BORDER_CONSTANT, value=0)
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return dist[1:-1, 1:-1]


def _ref_preprocess(self: DensityModel, frame: np.ndarray) -> np.ndarray:
    # The image before normalisation is the same code as before (``model_image``); what changed,
    # and is kept here as it was, is the float32 multiply and add per channel plane.
    img = self.model_image(frame)
    planes = [img] if img.ndim == 2 else [img[..., c] for c in range(img.shape[2])]
    x = np.empty((1, len(planes), *img.shape[:2]), np.float32)
    for c, plane in enumerate(planes):
        np.multiply(plane, self._gain[c], out=x[0, c])
        x[0, c] += self._offset[c]
    return x


# -- helpers ----------------------------------------------------------------------------------

@pytest.fixture(autouse=True)
def opencv_threads() -> Iterator[None]:
    """OpenCV's own exact distance transform (2 threads or more; see the module docstring)."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(max(2, before))
    yield
    cv2.setNumThreads(before)


def _same(a: object, b: object, path: str = "") -> list[str]:
    """Where ``a`` and ``b`` differ (arrays by dtype, shape and bits, NaN equal to NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        x, y = np.asarray(a), np.asarray(b)
        ok = (x.dtype == y.dtype and x.shape == y.shape
              and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc"))
        return [] if ok else [path]
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        if type(a) is not type(b):
            return [path]
        return [d for f in dataclasses.fields(a) for d in _same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")]
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [path]
        return [d for k in a for d in _same(a[k], b[k], f"{path}[{k!r}]")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if type(a) is not type(b) or len(a) != len(b):
            return [path]
        return [d for i, (u, v) in enumerate(zip(a, b)) for d in _same(u, v, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if type(a) is type(b) and a == b else [path]


def _poses() -> list[Pose]:
    """The bench's drifting pose, and lower, tilted and turning ones (other grids, part unseen)."""
    out = [bench.drifting_pose(t) for t in (0.0, 0.7, 2.1)]
    out += [Pose(0.0, 1.0, -2.0, -6.0, 0.2, -0.15, 0.4), Pose(0.0, 0.0, 0.0, -35.0, -0.3, 0.25, 2.0),
            Pose(0.0, 5.0, 3.0, -12.0, 0.0, 0.6, -1.0)]
    return out


# -- function by function ---------------------------------------------------------------------

@pytest.mark.parametrize("K", [FISHEYE, CALIBRATED, Intrinsics.from_fov(640, 480, 110.0)], ids=["fe160", "calibrated", "p110"])
def test_projection_is_the_same_seen_or_not(K: Intrinsics) -> None:
    rng = np.random.default_rng(3)
    rays = rng.normal(size=(5000, 3))
    rays[:, 2] = np.abs(rays[:, 2]) + 0.2  # in front: every ray seen (the fast path)
    mixed = rng.normal(size=(5000, 3))  # behind and beyond the widest ray too
    mixed[:7] = np.array([[0, 0, 1], [0, 0, -1], [np.nan, 0, 1], [np.inf, 0, 1], [0, 0, 0], [1e-13, 0, 1], [3, 4, 0]])
    for xc in (rays, mixed, rays[:1], rays[:0]):
        with np.errstate(invalid="ignore"):  # the infinite ray
            want = _ref_project(K.model, K.K, K.dist, xc)
            assert not _same(K.project(xc), want)
            assert not _same(K.project(xc, lens.ray_theta(xc)), want)
    assert np.isfinite(K.project(rays)).all() or K.model == "pinhole"


@pytest.mark.parametrize("K", [FISHEYE, CALIBRATED], ids=["fe160", "calibrated"])
def test_lens_geometry_is_the_same(K: Intrinsics) -> None:
    rng = np.random.default_rng(5)
    for pose in _poses():
        proj = PlaneProjection.from_pose(K, Mount(), pose, 1.7)
        view = proj.lens
        assert view is not None
        cx, cy = proj.camera_xy or (0.0, 0.0)
        xy = np.column_stack([cx + rng.uniform(-80, 80, 4000), cy + rng.uniform(-80, 80, 4000)])
        assert not _same(view.seen_to_image(xy), _ref_seen_to_image(view, xy))
        for n in (8, 32):
            assert not _same(view.seen_boundary(n), _ref_seen_boundary(view, n))
        grid = grid_for_view(proj, (480, 640), GridParams())
        assert not _same(headplane.lens_maps(proj, grid), _ref_lens_maps(proj, grid))


def test_box_view_is_the_same_and_read_only() -> None:
    for box in ((64, 0, 576, 480), (0, 4, 640, 476), (12, 8, 100, 90)):
        for k in (1, 5, 7):
            got = headplane._box_view(480, 640, k, box)
            assert not _same(got, _ref_box_view(480, 640, k, box))
            assert headplane._box_view(480, 640, k, box) is got and not got.flags.writeable
    # The pipeline's call takes a box however its numbers come (the cache's key is a tuple).
    proj = PlaneProjection.from_pose(FISHEYE, Mount(), bench.drifting_pose(0.5), 1.7)
    grid = grid_for_view(proj, (480, 640), GridParams())
    crop = lens_crop_box(proj, (480, 640), 4, 40.0)
    assert crop is not None
    free = np.full((480, 640), 255, np.uint8)
    want = headplane.sample_with_view(free, proj, grid, crop)
    assert not _same(headplane.sample_with_view(free, proj, grid, list(np.asarray(crop))), want)  # type: ignore[arg-type]


def test_distance_cells_is_the_same_for_any_uint8_free_value() -> None:
    rng = np.random.default_rng(7)
    for _ in range(6):
        h, w = (int(v) for v in rng.integers(140, 400, 2))  # above 16384 cells
        free = rng.integers(1, 256, (h, w)).astype(np.uint8)
        for _ in range(40):
            cv2.circle(free, (int(rng.integers(0, w)), int(rng.integers(0, h))), int(rng.integers(1, 20)), 0, -1)
        free[rng.random((h, w)) < 0.01] = 0
        want = _ref_distance_cells(free)
        assert not _same(proposals.distance_cells(free), want)
        assert not _same(proposals.distance_cells(free > 0), want)  # a bool grid as before
        assert not _same(proposals.distance_cells((free > 0).astype(np.float32)), want)


def test_preprocess_is_the_same_for_every_pixel_value(shared_dir: Path) -> None:
    rng = np.random.default_rng(11)
    every = np.stack([rng.permutation(np.tile(np.arange(256, dtype=np.uint8), 64)).reshape(128, 128)
                      for _ in range(3)], axis=2)  # each value in each channel, 64 times
    frame = bench.bench_frame(640, 480, 0)[0]
    frames = [every, frame, np.ascontiguousarray(frame[:, 44:596]), frame[1:, 3:], every[..., 1], frame[..., :1]]
    peer = shared_dir / "peers" / "mcnn-shb.onnx"
    models = [DensityModel(settings.X86_MODEL), DensityModel(settings.PLAIN_MODEL, overrides={"color": "rgb"}),
              DensityModel(settings.PLAIN_MODEL, overrides={"mean": "0.1,0.5,0.9", "std": "0.3,0.2,0.1", "border_px": 0}),
              DensityModel(peer, overrides={"color": "gray", "scale": 1, "stride": 4})]
    for model in models:
        for f in frames:
            got, want = model.preprocess(f), _ref_preprocess(model, f)
            assert got.dtype == want.dtype == np.float32
            assert not _same(got.view(np.uint32), want.view(np.uint32))  # bits, -0.0 and +0.0 apart


# -- the whole configured pipeline ------------------------------------------------------------

def _pipeline(sets: list[str]) -> SLZPipeline:
    cfg = settings.load(None, dict(settings.parse_assignment(s) for s in sets))
    model = DensityModel(cfg.model.path, threads=cfg.model.threads, overrides=cfg.model.overrides)
    return SLZPipeline(model, settings.pipeline_config(cfg, model.spec), intrinsics=settings.intrinsics(cfg),
                       mount=settings.mount(cfg))


def _fly(sets: list[str], frames: list[np.ndarray]) -> tuple[list[FrameResult], dict[str, object]]:
    pipe = _pipeline(sets)
    out = []
    for k, frame in enumerate(frames):
        t = k / 5.0
        out.append(pipe.process(frame, t, bench.drifting_pose(t)))
    assert pipe.risk is not None
    return out, {k: v for k, v in vars(pipe.risk).items()}


@pytest.mark.parametrize("sets", [["camera.model=fisheye", "camera.hfov_deg=160"], []], ids=["fisheye160", "pinhole70"])
def test_the_configured_pipeline_gives_the_same_frames(sets: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    frames = [bench.bench_frame(640, 480, s)[0] for s in (0, 0, 0, 1, 1, 1)]
    new, new_risk = _fly(sets, frames)
    with monkeypatch.context() as m:  # the code as it was
        m.setattr(DensityModel, "preprocess", _ref_preprocess)
        m.setattr(lens, "project", _ref_project)
        m.setattr(camera.LensView, "seen_to_image", _ref_seen_to_image)
        m.setattr(camera.LensView, "seen_boundary", _ref_seen_boundary)
        m.setattr(headplane, "lens_maps", _ref_lens_maps)
        m.setattr(headplane, "_box_view", _ref_box_view)
        m.setattr(slz, "distance_cells", _ref_distance_cells)
        old, old_risk = _fly(sets, frames)
    assert sum(len(r.proposals) for r in new) >= len(frames) and sum(len(r.tracks) for r in new) >= 3
    fisheye = bool(sets)
    assert all((r.projection.lens is not None) == fisheye for r in new)
    if fisheye:  # the crop box's path: the density model saw part of the frame
        assert lens_crop_box(new[0].projection, (480, 640), 4, 40.0) is not None
    for a, b in zip(new, old, strict=True):
        assert a.grid.rows * a.grid.cols > 16384
        fields = [f.name for f in dataclasses.fields(FrameResult) if f.name not in ("timings_ms", "projection", "ground")]
        diffs = [d for name in fields for d in _same(getattr(a, name), getattr(b, name), name)]
        pa, pb = a.projection, b.projection
        diffs += _same((pa.H, pa.H_inv, pa.camera_xy, pa.w_sign), (pb.H, pb.H_inv, pb.camera_xy, pb.w_sign), "projection")
        assert a.ground is not None and b.ground is not None
        diffs += _same((a.ground.t, a.ground.revision), (b.ground.t, b.ground.revision), "ground")
        assert not diffs, (a.t, diffs)
    assert not _same(new_risk, old_risk, "risk")
