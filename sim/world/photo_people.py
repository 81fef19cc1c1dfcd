"""People who look real on the photo ground: walkers drawn as real person silhouettes, and walkers
who cross open ground.

**Silhouettes** (:class:`PhotoPeople`): every whole person of the held-out photos
(``sim.world.photo_ground``; never used for training), cut from its photo by its class map as
``companion.evaluation.compositor.cutouts_from`` cuts them, with its size in metres from its
photo's GSD. A walker (any person of the world's motion sources) keeps one silhouette (chosen by
its id), drawn at its ground position through the same camera model as everything else
(``sim.world.render.project_points``: its size from the depth of its mid-body), turned with its
heading, its colours moved toward the ground under it (the compositor's Lab transfer, half way),
blurred like the frame, with a soft shadow cast away from the simulator's sun
(``sim.world.render.SUN_SHADOW``), darker on bright ground than on dark. They do not swing their
limbs: a photo is one moment of one pose.

**Open ground** (:func:`open_ground_walkers`): walkers of the photo worlds who go from goal to goal
straight across everything, the free circle included (today's walkers walk round it, which
flatters every landing). Like the scripted crossers, they are the test: the world's ``free_areas``
still says where nobody stands at the start.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.evaluation.compositor import Compositor, Cutout, _lab_stats, cutouts_from
from companion.geometry.camera import Intrinsics, Mount, Pose
from sim.world.photo_ground import PERSON, PhotoGround, class_window
from sim.world.render import SUN_SHADOW, Looks, project_points
from sim.world.walkers import Bounds, Circle, CrowdParams, GeneratedCrowd, Walkable

#: Height (m above ground, NED z) at which a silhouette is centred: a standing person's middle.
BODY_Z = -0.85
#: Share of the way a walker's colours move toward the ground's (0 = its own photo's, 1 = the ground's).
COLOUR_MATCH = 0.5
#: Walkers crossing open ground per photo world.
OPEN_GROUND_WALKERS = 4


@dataclass(frozen=True)
class Silhouette:
    """A real person cut from a photo: its cutout and its longer side in metres."""

    cutout: Cutout
    size_m: float


@functools.lru_cache(maxsize=2)
def silhouettes(folder: str) -> tuple[Silhouette, ...]:
    """Every whole person of the photos of ``folder`` (cached per process), in photo order."""
    ground = PhotoGround(folder)
    out = []
    for p in sorted(ground.patches, key=lambda p: p.name):
        if len(p.people_px) == 0:
            continue
        # The photo's colour statistics from a quarter-size copy: the same figures, 16 times faster.
        small = cv2.resize(p.bgr, (p.bgr.shape[1] // 4, p.bgr.shape[0] // 4), interpolation=cv2.INTER_AREA)
        mean, std = _lab_stats(small)
        # Cut within the window of the photo's person pixels: the same cutouts (class_window),
        # labelled over a fifth of the pixels.
        window = class_window(p.classes, PERSON)
        if window is None:
            continue
        for c in cutouts_from(p.bgr[window], p.classes[window], p.name, stats=(mean, std)):
            size = c.size * p.gsd
            if 0.3 <= size <= 2.0:  # a whole person, not a fragment or two merged
                out.append(Silhouette(c, size))
    return tuple(out)


class PhotoPeople:
    """Draws the world's people as real silhouettes (see the module docstring); the renderer
    calls :meth:`paint` in place of its drawn people when the ground carries one
    (``ground.people_painter``)."""

    def __init__(self, folder: str) -> None:
        self.silhouettes = silhouettes(folder)
        if not self.silhouettes:
            raise ValueError(f"no whole person in the photos of {folder}")
        self._sizes_m = np.array([s.size_m for s in self.silhouettes], float)

    def paint(self, img: np.ndarray, pos: np.ndarray, hd: np.ndarray, lk: Looks, pose: Pose,
              intrinsics: Intrinsics, mount: Mount, ids: np.ndarray | None) -> None:
        """Draw people at ground positions ``pos`` (N, 2, north/east m) with headings ``hd``
        (rad from north toward east) into ``img`` (BGR uint8, in place); ``ids`` pick each one's
        silhouette (their index when None)."""
        h, w = img.shape[:2]
        n = len(pos)
        who = np.arange(n) if ids is None else np.asarray(ids, np.int64).ravel()[:n]
        centre = np.column_stack([pos, np.full(n, BODY_Z)])
        fwd = centre + np.column_stack([np.cos(hd), np.sin(hd), np.zeros(n)]) * 0.5
        sun = np.column_stack([pos + SUN_SHADOW, np.zeros(n)])
        foot = np.column_stack([pos, np.zeros(n)])
        (uv, z), (fuv, _), (suv, _), (puv, _) = (project_points(p, intrinsics, mount, pose)
                                                 for p in (centre, fwd, sun, foot))
        f = max(intrinsics.fx, intrinsics.fy)
        order = np.argsort(-z)  # far people first
        # Who is drawn, for everyone at once (a dense world holds some 2000 people, a few dozen
        # in view): the per-person tests of the loop below, in the same float64 operations.
        pick = who * 2654435761 % (1 << 32) % len(self.silhouettes)
        with np.errstate(divide="ignore", invalid="ignore"):
            sizes = self._sizes_m[pick] * f / z
            halves = 1.5 * sizes + 4
            shown = ((z > 0.3) & ~(sizes < 2.0)
                     & ~((uv[:, 0] < -halves) | (uv[:, 0] > w + halves) | (uv[:, 1] < -halves) | (uv[:, 1] > h + halves)))
        canvas = None
        for k in order[shown[order]]:
            sil = self.silhouettes[int(pick[k])]
            size, half = sizes[k], halves[k]
            u, v = uv[k]
            if canvas is None:
                canvas = img.astype(np.float32)
            x0, y0 = int(max(0, u - 2 * half)), int(max(0, v - 2 * half))
            x1, y1 = int(min(w, u + 2 * half)), int(min(h, v + 2 * half))
            if x1 - x0 < 2 or y1 - y0 < 2:
                continue
            mean, std = _lab_stats(np.clip(canvas[y0:y1, x0:x1] + 0.5, 0, 255).astype(np.uint8))
            dx, dy = fuv[k] - uv[k]
            angle = -math.degrees(math.atan2(dx, -dy))  # cv2 angles turn anticlockwise
            bgr, alpha = Compositor._render(sil.cutout, size, angle, 0.6, mean, std, COLOUR_MATCH)
            ph, pw = alpha.shape
            px0, py0 = int(round(u - pw / 2)), int(round(v - ph / 2))
            # The shadow: away from the sun, as long as the drawn people's, darker on bright ground.
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


class PhotoGroundWithPeople(PhotoGround):
    """The photo ground, carrying the painter of real-looking people the renderer uses."""

    def __init__(self, folder: str, origin: tuple[float, float] = (0.0, 0.0)) -> None:
        super().__init__(folder, origin)
        self.people_painter = PhotoPeople(self.folder)


def open_ground_walkers(bounds: Bounds, free: Circle | None, seed: int,
                        count: int = OPEN_GROUND_WALKERS, walkable: Walkable | None = None) -> GeneratedCrowd:
    """``count`` walkers who walk from goal to goal straight across open ground (no keep-out:
    the free circle too), starting outside ``free`` (nobody stands in it at the start); drawn
    from their own stream of ``seed``. ``walkable``: the ground they keep to (roofs, water and
    trees turn them, as any walker; None: anywhere)."""
    params = CrowdParams(n_walkers=count, n_groups=0, n_standing=0, keep_out=[], walkable=walkable)
    crowd = GeneratedCrowd(bounds, params, seed=int(np.random.SeedSequence([int(seed), 0x09E4]).generate_state(1)[0]))
    if free is not None:
        # Start them outside the free circle (they may walk into it at once, as people do).
        d = free.distance(crowd.lead_pos)
        inside = d < free.radius + 1.0
        if inside.any():
            v = crowd.lead_pos[inside] - free.centre
            nv = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-9)[:, None]
            v = np.where(nv > 1e-6, v / nv, np.array([1.0, 0.0]))
            crowd.lead_pos[inside] = free.centre + v * (free.radius + 1.5)
    crowd.crosses_open_ground = True  # type: ignore[attr-defined]  # World.nobody_walks_at: the test
    return crowd
