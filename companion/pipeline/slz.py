"""The per-frame safe-landing-zone pipeline: frame (+ pose or fixed projection) in, zones out.

density -> occupancy -> head-plane grid -> proposals -> tracks (docs/design.md, steps 1-5). The density
model is injected (any callable returning a 2-D map), so the pipeline runs with the shipped ONNX
model, another model, or a synthetic stand-in.

A second callable, ``surface`` (optional), maps the frame to the per-cell probability that the ground
is unlandable (``companion.pipeline.landability``: water, vehicles, trees, roofs, ...). What it keeps
off is ``PipelineConfig.surface_scope``. ``"landing_point"``: the zones are people's alone, and a
proposal is centred (and the landing point moved) only where the vehicle's footprint is on landable
ground (``proposals.landing_points``). ``"zone"``: the occupancy step marks a pixel not-free where
people are OR the ground is unlandable, and that one combined map feeds the grid, the risk map, the
proposals and the tracks; each zone says which of the two (or the end of the view) bounds it
(``companion.pipeline.edges``). Without it the pipeline is exactly the people-only one.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from companion.geometry.camera import GeometryError, Intrinsics, Mount, PlaneProjection, Pose
from companion.invariant import require
from companion.pipeline.circles import Circle, GroundBelow
from companion.pipeline.density import resolve_threshold
from companion.pipeline.edges import edge_reason
from companion.pipeline.headplane import (
    GridParams,
    GridSpec,
    grid_for_view,
    lens_crop_box,
    sample_to_grid,
    sample_with_view,
)
from companion.pipeline.input_scale import density_scale, shrunk
from companion.pipeline.occupancy import OccupancyParams, occupancy_map, surface_free_map
from companion.pipeline.people import PeopleParams, PeopleTracker, Person, density_peaks, place_people
from companion.pipeline.proposals import TIE_M, PointDistance, clearance_at, distance_cells, landing_points, propose
from companion.pipeline.riskmap import GroundRiskMap, RiskMapConfig, RiskMapError, Spot, SpotRequest
from companion.pipeline.tracker import Track, TrackerParams, ZoneTracker

log = logging.getLogger(__name__)

DensityFn = Callable[[np.ndarray], np.ndarray]
#: frame -> 2-D per-cell probability that the ground is unlandable (``landability.UnlandableMap``).
SurfaceFn = Callable[[np.ndarray], np.ndarray]

#: What unlandable ground keeps off (``PipelineConfig.surface_scope``).
SURFACE_SCOPES = ("zone", "landing_point")
STAGES = ("density", "occupancy", "projection", "fusion", "proposals", "tracking", "people")

#: ``GroundView.spot``: the risk map's cells are coarsened this many times (0.3 m at the default 0.1 m).
SPOT_FACTOR = 3
#: ``GroundView.spot``: distances to where people were seen are measured up to this (m). Farther
#: makes no difference to where the point goes inside a zone of a few metres, and costs more.
PLACE_REACH_M = 8.0


@dataclass(frozen=True)
class PipelineConfig:
    """head_height_m: h_h, metres of the head plane above the ground. r0_m: smallest landing
    radius in metres (proposals below it are not made). Which zone is the target is not the
    pipeline's to say: ``companion.control.planner`` decides that, in flight and in replay.
    Proposals come from each frame alone, as in the paper; the ground risk map (``risk``: its
    settings, its cell the grid's) measures what frames remember (calm, unwalked ground, where
    people walked).
    surface_threshold: a cell is unlandable where the surface model's probability exceeds this;
    None = the model's own (``threshold`` of the callable), else 0.5. Unused without one.
    surface_scope: what unlandable ground keeps off: ``"zone"``, the whole circle (a zone's radius
    is the free ground's of people and ground together), or ``"landing_point"``, only the centre
    and ``footprint_m`` (m) around it (the radius is people's alone; the landing point moves only
    onto such centres). Unused without a surface model."""

    occupancy: OccupancyParams = field(default_factory=OccupancyParams)
    grid: GridParams = field(default_factory=GridParams)
    tracker: TrackerParams = field(default_factory=TrackerParams)
    head_height_m: float = 1.7
    r0_m: float = 2.0
    #: Near-ties of the largest circle go to the ground under the camera (``proposals.propose``).
    proposal_tie_m: float = TIE_M
    risk: RiskMapConfig = field(default_factory=RiskMapConfig)
    #: People followed on the ground over posed frames (the people stage: the bench and the
    #: walkers' analysis; the service's settings no longer ask for it); None: not followed, and
    #: not paid for.
    people: PeopleParams | None = None
    surface_threshold: float | None = None
    surface_scope: str = "zone"
    footprint_m: float = 0.5
    #: Measure each posed frame's zones' and ground-below's ``calm_s`` over ``r0_m`` plus
    #: ``calm_margin_m`` (m) around their centre (``riskmap.GroundRiskMap.calm_s``); off, they
    #: stay NaN and, without ``unwalked`` either, the map is not run at all (its update is the
    #: bench's ``fusion`` stage, about 0.3 ms a frame at 640x480, nobody would read it).
    calm: bool = False
    calm_margin_m: float = 1.0
    #: Measure each posed frame's confirmed zones' ``unwalked_s`` over the calm disc
    #: (``riskmap.GroundRiskMap.unwalked_s``), for the planner's ``prefer_unwalked``; off, it stays NaN.
    unwalked: bool = False
    #: Measure each zone's ``Track.steady_s`` against ``r0_m`` plus this free radius (m), for the
    #: planner's steady zones (``controller.steady_s``); None: not measured, it stays NaN.
    steady_margin_m: float | None = None
    #: Through a pinhole, shrink the frame before the density model runs so that the smallest
    #: person (``input_scale.PERSON_M``) still spans this many pixels where the view reaches
    #: farthest (``input_scale.density_scale``): low over real ground the full frame shows the
    #: model the ground's grain, which it takes for people. The landability model (``surface``)
    #: is given the same shrunk frame. 0: always the full frame.
    person_px: float = 0.0

    def __post_init__(self) -> None:
        # The one place these rules live (the settings name the key of a field refused here).
        steady = self.steady_margin_m
        require(steady is None or (math.isfinite(steady) and steady >= 0), "pipeline", "steady_margin_m",
                "must be >= 0 m or None", steady)
        require(math.isfinite(self.calm_margin_m) and self.calm_margin_m >= 0, "pipeline", "calm_margin_m",
                "must be >= 0", self.calm_margin_m)
        surface = self.surface_threshold
        require(surface is None or (math.isfinite(surface) and 0.0 <= surface < 1.0), "pipeline",
                "surface_threshold", "must be in [0, 1)", surface)
        require(self.surface_scope in SURFACE_SCOPES, "pipeline", "surface_scope",
                f"must be one of {', '.join(SURFACE_SCOPES)}", self.surface_scope)
        require(math.isfinite(self.footprint_m) and 0 <= self.footprint_m <= 10, "pipeline", "footprint_m",
                "must be >= 0 and <= 10 m", self.footprint_m)
        if abs(self.risk.cell_m - self.grid.cell) > 1e-9:
            raise ValueError(f"the risk map's cell ({self.risk.cell_m} m) must be the grid's ({self.grid.cell} m)")
        require(math.isfinite(self.head_height_m) and 0 <= self.head_height_m < 5, "pipeline", "head_height_m",
                "must be >= 0 and < 5", self.head_height_m)
        require(math.isfinite(self.proposal_tie_m) and self.proposal_tie_m >= 0, "pipeline", "proposal_tie_m",
                "must be >= 0", self.proposal_tie_m)
        require(math.isfinite(self.r0_m) and self.r0_m > 0, "pipeline", "r0_m", "must be > 0", self.r0_m)
        require(math.isfinite(self.person_px) and 0 <= self.person_px <= 1000, "pipeline", "person_px",
                "must be >= 0 and <= 1000 px", self.person_px)

    @property
    def n_proposals(self) -> int:
        return self.tracker.max_tracks


@dataclass(frozen=True)
class FrameClearance:
    """How far the ground is free and seen around plane points on one frame, for the tracker
    (``tracker.Clearance``): ``free`` the distances (cells) to the nearest cell not free and
    ``view`` those to the end of the view, on ``grid``."""

    free: np.ndarray
    view: PointDistance
    grid: GridSpec

    def at(self, x: float, y: float) -> tuple[float, float]:
        """(free radius, view radius) in metres around plane point (x, y)."""
        return clearance_at(self.free, self.grid, x, y), clearance_at(self.view, self.grid, x, y)


@dataclass(frozen=True)
class GroundView:
    """What the decision may ask of the risk map about the frame captured at ``t``: where the
    landing point may go (``spot``, the controller's ``place_lookback_s``). It reads the map as
    that frame left it (``revision``: the map's updates then); once the pipeline has taken another
    frame it answers None. The service decides on each frame before it processes the next.
    ``landable``: whether the vehicle may touch down at a plane point on this frame (the
    landability model's ``landing_point`` scope); a spot elsewhere is not offered."""

    t: float
    risk: GroundRiskMap | None
    revision: int
    landable: Callable[[float, float], bool] | None = None

    def spot(self, request: SpotRequest) -> Spot | None:
        """The point within ``request.radius_m`` of its centre farthest from the ground people were
        seen on within ``request.lookback_s`` (``GroundRiskMap.farthest_from_walkers``, distances up
        to ``PLACE_REACH_M``), with that distance at the present landing point. None without a map
        (no posed frame yet, or a pipeline that keeps none), where the zone reaches past it, or
        once the map has moved on (0.1-0.5 ms)."""
        risk = self.risk
        if risk is None or risk.stats.updates != self.revision:
            return None
        try:
            spot = risk.farthest_from_walkers(request.x, request.y, request.radius_m, self.t, request.lookback_s,
                                              PLACE_REACH_M, aim=request.aim, factor=SPOT_FACTOR)
        except ValueError as exc:  # a bug, not the vehicle's fault: the point stays where it is
            log.warning("landing point not placed: %s", exc)
            return None
        if spot is not None and self.landable is not None and not self.landable(spot.x, spot.y):
            return None  # farther from people, but not ground to land on: the point stays
        return spot


@dataclass(frozen=True)
class _CellMask:
    """Plane point (m) -> whether its cell of ``grid`` is set in ``mask``; False off the grid."""

    grid: GridSpec
    mask: np.ndarray

    def __call__(self, x: float, y: float) -> bool:
        i, j = self.grid.cell_of(x, y)
        return 0 <= i < self.mask.shape[0] and 0 <= j < self.mask.shape[1] and bool(self.mask[i, j])


@dataclass
class FrameResult:
    """What one frame produced. Circles and tracks are in head-plane metres; ``occupancy`` is the
    image-sized free map (255 free, 0 occupied); ``free_grid`` the head-plane grid described by
    ``grid``; ``timings_ms`` per stage plus ``post_density`` and ``total`` (and ``landability`` when a
    surface model runs; it is counted in ``total``, not in ``post_density``).

    With a surface model: ``people_free`` and ``surface`` are the image-sized free maps of each alone
    (``occupancy``, what the zones are measured on, is their minimum in the ``zone`` scope and
    people's alone in the ``landing_point`` scope), ``unlandable`` the model's map. ``proposal_edges`` says, per
    proposal, what bounds it (``edges.EDGES``); each track's ``edge`` does the same. Without a
    surface model neither is judged (an empty list, empty strings)."""

    t: float
    proposals: list[Circle]
    tracks: list[Track]
    timings_ms: dict[str, float]
    projection: PlaneProjection
    occupancy: np.ndarray
    grid: GridSpec
    free_grid: np.ndarray
    density: np.ndarray
    #: The ground under the camera (posed frames and fixed projections that know where the
    #: camera is), measured like a track's radius: what the controller checks under the vehicle.
    below: GroundBelow | None = None
    #: The people followed on the ground after this frame (posed frames; empty otherwise).
    people: list[Person] = field(default_factory=list)
    proposal_edges: list[str] = field(default_factory=list)
    people_free: np.ndarray | None = None
    surface: np.ndarray | None = None
    unlandable: np.ndarray | None = None
    #: What the decision may ask of the risk map about this frame (the landing spot).
    ground: GroundView | None = None
    #: Through a fisheye, the pixel box (x0, y0, x1, y1) the density model looked at
    #: (``headplane.lens_crop_box``): outside it ``occupancy`` is 0 because unseen, not occupied;
    #: None: the whole frame.
    looked_at: tuple[int, int, int, int] | None = None


def _with_calm(track: Track, calm_s: float, unwalked_s: float) -> Track:
    return replace(track, calm_s=calm_s, unwalked_s=unwalked_s)


class SLZPipeline:
    """Runs steps 1-5 on each frame and keeps the tracker's state between frames.

    With ``intrinsics`` and ``mount``, frames are projected with the vehicle ``pose`` given to
    ``process``; a fixed ``projection`` (nadir or homography) may be given instead. The
    intrinsics describe the frames as passed in (use ``Intrinsics.scaled_to`` after a resize).
    """

    def __init__(self, density: DensityFn, config: PipelineConfig = PipelineConfig(),
                 intrinsics: Intrinsics | None = None, mount: Mount | None = None,
                 projection: PlaneProjection | None = None, surface: SurfaceFn | None = None):
        self.density = density
        self.surface = surface
        if config.occupancy.threshold is None:
            config = replace(config, occupancy=replace(
                config.occupancy, threshold=resolve_threshold(None, getattr(density, "spec", None))))
        if surface is not None and config.surface_threshold is None:
            thr = getattr(surface, "threshold", None)
            config = replace(config, surface_threshold=float(thr) if isinstance(thr, (int, float)) else 0.5)
        self.config = config
        self.intrinsics = intrinsics
        self.mount = mount or Mount()
        self.fixed_projection = projection
        self.tracker = ZoneTracker(config.tracker)
        # The map runs only to measure calm (``calm_s``) or unwalked ground; the zones are
        # measured on the frame alone.
        needed = config.calm or config.unwalked
        self.risk = GroundRiskMap(config.risk) if needed else None
        self.people = PeopleTracker(config.people) if config.people is not None else None
        # Through a fisheye the density model runs on the part of the frame the rules can use
        # (``headplane.lens_crop_box``) when it takes frames of any size: its stride, else None.
        spec = getattr(density, "spec", None)
        self._crop_multiple: int | None = (int(spec.stride) if spec is not None
                                           and getattr(density, "any_size", False) else None)
        # A pinhole's distortion is undone on the image, then the homography holds; a fisheye's
        # projection goes through the lens cell by cell (``PlaneProjection.lens``).
        self._undistort = (intrinsics.undistort_maps()
                           if intrinsics is not None and intrinsics.has_distortion and not intrinsics.is_fisheye
                           else None)

    def projection_for(self, pose: Pose | None) -> PlaneProjection:
        if pose is not None:
            if self.intrinsics is None:
                raise GeometryError("a pose was given but the pipeline has no camera intrinsics")
            return PlaneProjection.from_pose(self.intrinsics, self.mount, pose,
                                             self.config.head_height_m)
        if self.fixed_projection is None:
            raise GeometryError("no pose and no fixed projection: cannot place the frame on the "
                                "head plane")
        return self.fixed_projection

    def _density(self, frame: np.ndarray, box: tuple[int, int, int, int] | None) -> np.ndarray:
        """The density map of the whole ``frame``, or of ``box`` only: outside it the map holds the
        box's least value (no people, and ``min(D)``, which the occupancy step subtracts, is the
        least over the pixels looked at; the occupancy outside is then cleared by the caller)."""
        if box is None:
            return np.asarray(self.density(frame))
        x0, y0, x1, y1 = box
        part = np.asarray(self.density(np.ascontiguousarray(frame[y0:y1, x0:x1])))
        s = self._crop_multiple
        assert s is not None  # a box is made only for a model with a stride
        h, w = frame.shape[:2]
        fill = float(np.nanmin(part)) if np.isfinite(part).any() else 0.0
        full = np.full((*part.shape[:-2], math.ceil(h / s), math.ceil(w / s)), fill, part.dtype)
        r0, c0 = y0 // s, x0 // s
        full[..., r0:r0 + part.shape[-2], c0:c0 + part.shape[-1]] = part
        return full

    def process(self, frame: np.ndarray, t: float, pose: Pose | None = None) -> FrameResult:
        """One frame: BGR uint8 (H, W, 3) captured at ``t`` seconds, seen from ``pose``."""
        if not isinstance(frame, np.ndarray) or frame.ndim not in (2, 3) or frame.size == 0:
            raise ValueError(f"frame must be a non-empty image array, got {getattr(frame, 'shape', frame)!r}")
        h, w = frame.shape[:2]
        if self.intrinsics is not None and pose is not None and \
                (self.intrinsics.width, self.intrinsics.height) != (w, h):
            raise GeometryError(f"frame is {w}x{h} but the intrinsics are for "
                                f"{self.intrinsics.width}x{self.intrinsics.height}")
        # Geometry first: a bad pose is rejected before paying for the network.
        proj = self.projection_for(pose)
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        box = None
        if self._crop_multiple is not None and pose is not None:
            box = lens_crop_box(proj, (h, w), self._crop_multiple, self.config.grid.max_extent)
        scale = 1.0
        if box is None and pose is not None and self.config.person_px > 0 and proj.lens is None \
                and self._crop_multiple is not None:
            scale = density_scale(proj, (h, w), self.config.person_px)
        small = None
        if scale < 1.0:
            # The map of the shrunk frame is brought back to the frame's size by the occupancy
            # step, which never shrinks an occupied cell (``resize_keep_occupied``).
            small = shrunk(frame, scale, self._crop_multiple or 1)
            density = np.asarray(self.density(small))
        else:
            density = self._density(frame, box)
        t1 = time.perf_counter()
        unlandable = None
        if self.surface is not None:
            # The landability model sees the same shrunk frame: close up, the full frame shows it
            # the paving's grain too, which it calls roof and wall (sim.evidence.landability_threshold
            # --person-px); its map is brought back to the frame's size the same way.
            unlandable = np.asarray(self.surface(frame if small is None else small))
        t_surface = time.perf_counter()
        free = occupancy_map(density, (h, w), self.config.occupancy)
        if box is not None:
            # Not looked at is not free (the view says unseen there too).
            x0, y0, x1, y1 = box
            looked = np.zeros_like(free)
            looked[y0:y1, x0:x1] = free[y0:y1, x0:x1]
            free = looked
        people_free = surface = centres = None
        if unlandable is not None:
            thr = self.config.surface_threshold
            surface = surface_free_map(unlandable, (h, w), 0.5 if thr is None else thr, self.config.occupancy)
            people_free = free
        t2 = time.perf_counter()
        if self._undistort is not None and pose is not None:
            free = cv2.remap(free, *self._undistort, cv2.INTER_NEAREST,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            if surface is not None:
                people_free = free
                surface = cv2.remap(surface, *self._undistort, cv2.INTER_NEAREST,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        grid = grid_for_view(proj, (h, w), self.config.grid)
        free_grid, seen = sample_with_view(free, proj, grid, box)
        people_grid = surface_grid = None
        if surface is not None and self.config.surface_scope == "landing_point":
            # Unlandable ground keeps the landing point off, not the zone: the zone's radius is
            # people's alone (a roof beside a square does not shrink the square's zones), and
            # proposals are centred only where the vehicle's footprint is on landable ground.
            centres = landing_points(sample_to_grid(surface, proj, grid), grid.cell, self.config.footprint_m)
        elif surface is not None:
            # Sampling keeps a cell free only when all its pixels are (erosion, then nearest):
            # that commutes with the pixel-wise minimum, so the grid of the combined map is the
            # minimum of the two grids, and both are at hand for the zones' edges.
            people_grid = free_grid
            surface_grid = sample_to_grid(surface, proj, grid)
            free_grid = np.minimum(people_grid, surface_grid)
            free = np.minimum(free, surface)
        t3 = time.perf_counter()
        # Only posed frames are in the world frame: under a fixed projection (a video without
        # poses) plane coordinates move with the camera, and a map would smear people across it.
        calm_map = self.risk if pose is not None else None
        if calm_map is not None:
            try:
                calm_map.update(grid, free_grid, seen, t, proj.camera_xy)
            except RiskMapError:
                calm_map = None  # counted by the map; this frame's zones are not calm (0 s)
        t4 = time.perf_counter()
        dist = distance_cells(free_grid)
        # Near-ties go to the ground under the camera: proposals stay put as the view moves.
        proposals = propose(free_grid, grid, self.config.n_proposals, self.config.r0_m, dist,
                            prefer=proj.camera_xy, tie_m=self.config.proposal_tie_m, centres=centres)
        t5 = time.perf_counter()
        # How far the view reaches is asked at a few points only (the zones' centres).
        clearance = FrameClearance(dist, PointDistance(seen), grid)

        steady_r = None if self.config.steady_margin_m is None else self.config.r0_m + self.config.steady_margin_m
        tracks = self.tracker.update(proposals, t, clearance, r_min=self.config.r0_m, steady_r=steady_r)
        calm_r = self.config.r0_m + self.config.calm_margin_m

        def calm(x: float, y: float) -> float:
            return 0.0 if calm_map is None else calm_map.calm_s(x, y, calm_r, t)

        def unwalked(x: float, y: float) -> float:
            return 0.0 if calm_map is None else calm_map.unwalked_s(x, y, calm_r, t)

        measure = pose is not None and self.config.calm
        walked = pose is not None and self.config.unwalked
        if measure and walked and calm_map is not None:
            # Confirmed zones only, both measures from one read of the map.
            both = calm_map.calm_and_unwalked_s
            tracks = [_with_calm(tr, *both(tr.x, tr.y, calm_r, t)) if tr.misses == 0 else tr for tr in tracks]
        elif measure or walked:
            # Confirmed zones only, in one pass; what is not asked for keeps the track's NaN.
            tracks = [replace(tr, calm_s=calm(tr.x, tr.y) if measure else tr.calm_s,
                              unwalked_s=unwalked(tr.x, tr.y) if walked else tr.unwalked_s)
                      if tr.misses == 0 else tr for tr in tracks]

        edges: list[str] = []
        if surface_grid is not None:
            # Only with a surface model: without one every edge is people or the view, and the
            # people-only pipeline keeps its cost to the microsecond.
            def edge(x: float, y: float) -> str:
                return edge_reason(x, y, grid, dist, free_grid, seen, people_grid, surface_grid)

            edges = [edge(c.x, c.y) for c in proposals]
            tracks = [replace(tr, edge=edge(tr.x, tr.y)) for tr in tracks]
        below = None
        if proj.camera_xy is not None:
            bx, by = (float(v) for v in proj.camera_xy)
            if math.isfinite(bx) and math.isfinite(by):
                below = GroundBelow(bx, by, *clearance.at(bx, by),
                                    calm_s=calm(bx, by) if measure else math.nan)
        t6 = time.perf_counter()
        followed: list[Person] = []
        if self.people is not None and pose is not None:
            # World-frame people only: under a fixed projection the plane moves with the camera.
            params = self.people.params
            uv, strength = density_peaks(density, float(self.config.occupancy.threshold or 0.0), (h, w),
                                         params.window, params.edge_px)
            if self._undistort is not None and len(uv) and self.intrinsics is not None:
                K = self.intrinsics.K
                uv = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, np.asarray(self.intrinsics.dist, np.float64),
                                         P=K).reshape(-1, 2)
            found = place_people(uv, strength, proj, params.merge_m)
            followed = self.people.update(found, t, view=proj, image_hw=(h, w))
        t7 = time.perf_counter()
        starts = (t0, t_surface, t2, t3, t4, t5, t6)
        for name, a, b in zip(STAGES, starts, (t1, t2, t3, t4, t5, t6, t7), strict=True):
            timings[name] = (b - a) * 1e3
        if unlandable is not None:
            timings["landability"] = (t_surface - t1) * 1e3
        timings["post_density"] = (t7 - t_surface) * 1e3
        timings["total"] = (t7 - t0) * 1e3
        ground = GroundView(t, self.risk, self.risk.stats.updates if self.risk is not None else 0,
                            None if centres is None else _CellMask(grid, centres))
        return FrameResult(t, proposals, tracks, timings, proj, free, grid, free_grid,
                           density, below, followed, edges, people_free,
                           surface, unlandable, ground, box)
