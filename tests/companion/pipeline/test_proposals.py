"""Largest-free-circle proposals (pipeline step 4) against a brute-force oracle."""

import math

import numpy as np
import pytest

from companion.pipeline.headplane import GridSpec
from companion.pipeline.proposals import distance_cells, propose


def _random_map(seed, shape=(60, 80), n_blobs=25):
    rng = np.random.default_rng(seed)
    free = np.full(shape, 255, np.uint8)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    for _ in range(n_blobs):
        cy, cx, r = rng.uniform(0, shape[0]), rng.uniform(0, shape[1]), rng.uniform(0.5, 4)
        free[(yy - cy) ** 2 + (xx - cx) ** 2 <= r * r] = 0
    # Unknown margin, as outside a camera footprint.
    free[:, : rng.integers(0, 6)] = 0
    return free


def _oracle_radius_cells(free):
    """Largest distance from a free cell centre to the nearest non-free cell centre (or the
    outside of the grid), brute force."""
    rows, cols = free.shape
    occ = np.argwhere(free == 0).astype(float)
    border = [(i, -1) for i in range(-1, rows + 1)] + [(i, cols) for i in range(-1, rows + 1)]
    border += [(-1, j) for j in range(cols)] + [(rows, j) for j in range(cols)]
    occ = np.vstack([occ, np.array(border, float)])
    best = 0.0
    for i, j in np.argwhere(free > 0):
        best = max(best, float(np.min(np.hypot(occ[:, 0] - i, occ[:, 1] - j))))
    return best


def _touches(circle, free, grid):
    """True if the circle overlaps any non-free cell square or leaves the grid."""
    ci = (circle.y - grid.y0) / grid.cell
    cj = (circle.x - grid.x0) / grid.cell
    r = circle.r / grid.cell
    rows, cols = free.shape
    if ci - r < -0.5 or cj - r < -0.5 or ci + r > rows - 0.5 or cj + r > cols - 0.5:
        return True
    occ = np.argwhere(free == 0)
    dy = np.maximum(np.abs(occ[:, 0] - ci) - 0.5, 0)
    dx = np.maximum(np.abs(occ[:, 1] - cj) - 0.5, 0)
    return bool((np.hypot(dx, dy) < r - 1e-9).any())


@pytest.mark.parametrize("seed", range(15))
def test_against_brute_force_oracle(seed):
    free = _random_map(seed)
    grid = GridSpec(x0=3.0, y0=-2.0, cell=0.25, rows=free.shape[0], cols=free.shape[1])
    circles = propose(free, grid, n_max=6, r_min=0.3)
    assert circles, "a map with free space must give a proposal"
    oracle = _oracle_radius_cells(free) * grid.cell
    assert abs(circles[0].r - oracle) <= grid.cell
    for c in circles:
        assert not _touches(c, free, grid)
        assert c.r >= 0.3
    radii = [c.r for c in circles]
    assert radii == sorted(radii, reverse=True)
    for a in range(len(circles)):
        for b in range(a + 1, len(circles)):
            ca, cb = circles[a], circles[b]
            assert math.hypot(ca.x - cb.x, ca.y - cb.y) >= ca.r + cb.r - 1e-9


def test_stops_at_r_min_and_n_max():
    free = np.full((100, 100), 255, np.uint8)
    grid = GridSpec(0.0, 0.0, 0.1, 100, 100)
    assert len(propose(free, grid, n_max=2, r_min=0.1)) == 2
    big = propose(free, grid, n_max=10, r_min=4.0)
    assert len(big) == 1 and big[0].r == pytest.approx(5.0 - math.sqrt(2) / 2 * 0.1, abs=1e-3)
    assert propose(free, grid, n_max=10, r_min=6.0) == []


def test_empty_and_all_occupied_maps_give_no_proposals():
    assert propose(np.zeros((40, 50), np.uint8), GridSpec(0, 0, 0.1, 40, 50), 5, 0.1) == []
    assert propose(np.zeros((0, 0), np.uint8), GridSpec(0, 0, 0.1, 0, 0), 5, 0.1) == []


def test_clearance_at_a_point_never_reaches_a_non_free_cell():
    from companion.pipeline.proposals import clearance_at, distance_cells

    free = _random_map(3)
    grid = GridSpec(x0=1.0, y0=2.0, cell=0.2, rows=free.shape[0], cols=free.shape[1])
    dist = distance_cells(free)
    rng = np.random.default_rng(0)
    from companion.pipeline.circles import Circle

    for _ in range(200):
        x = rng.uniform(grid.x0 - 1, grid.x0 + grid.cols * grid.cell + 1)
        y = rng.uniform(grid.y0 - 1, grid.y0 + grid.rows * grid.cell + 1)
        r = clearance_at(dist, grid, x, y)
        if r > 0:
            assert not _touches(Circle(x, y, r), free, grid)
    assert clearance_at(dist, grid, -100.0, -100.0) == 0.0


@pytest.mark.parametrize("seed", range(15))
def test_a_preferred_point_keeps_every_guarantee_of_the_oracle(seed):
    # Near-ties go to the preferred point, but every circle is still free, disjoint, at least
    # r_min, and the first within tie_m (plus a cell of sampling) of the largest one.
    free = _random_map(seed)
    grid = GridSpec(x0=3.0, y0=-2.0, cell=0.25, rows=free.shape[0], cols=free.shape[1])
    rng = np.random.default_rng(seed)
    prefer = (float(rng.uniform(3.0, 23.0)), float(rng.uniform(-2.0, 13.0)))
    circles = propose(free, grid, n_max=6, r_min=0.3, prefer=prefer, tie_m=0.5)
    assert circles
    assert circles[0].r >= _oracle_radius_cells(free) * grid.cell - 0.5 - grid.cell
    for c in circles:
        assert not _touches(c, free, grid) and c.r >= 0.3
    for a in range(len(circles)):
        for b in range(a + 1, len(circles)):
            ca, cb = circles[a], circles[b]
            assert math.hypot(ca.x - cb.x, ca.y - cb.y) >= ca.r + cb.r - 1e-9


def _view(shift_cells):
    # Empty ground seen through a 4:3 footprint: the largest free circles form a ridge along
    # the footprint's long axis, 2 m long here.
    free = np.zeros((120, 160), np.uint8)
    free[20:100, 20 + shift_cells:140 + shift_cells] = 255
    return free


def test_over_empty_ground_the_proposal_stays_under_the_camera_as_the_view_moves():
    # The uniform-ground flake (issue 11): a plain argmax takes the first cell of the ridge, so
    # the proposal jumps to the footprint's far end as the view sways, and the tracker loses it.
    grid = GridSpec(0.0, 0.0, 0.1, 120, 160)
    under = (9.0, 6.0)  # the camera over the ridge's east part
    centres = []
    for shift in (-8, -4, 0, 4, 8):  # the footprint swaying 0.8 m either way
        c = propose(_view(shift), grid, n_max=1, r_min=2.0, prefer=under)[0]
        assert c.r >= 3.9 - 0.3 - 0.1
        centres.append((c.x, c.y))
        assert abs(c.y - 6.0) < 0.1 and abs(c.x - 9.0) < 0.1  # right under the camera
    # Without the preference, the first cell of the ridge: its west end, moving with the view.
    plain = [propose(_view(s), grid, n_max=1, r_min=2.0)[0].x for s in (-8, 8)]
    assert plain[1] - plain[0] == pytest.approx(1.6, abs=0.11)
    assert plain[0] < 7.0


def test_a_preference_never_drops_a_circle_to_below_r_min():
    # The largest circle is just over r_min; a nearer centre within tie_m would be under it.
    free = np.zeros((60, 60), np.uint8)
    free[10:50, 10:50] = 255  # 4 m square: largest radius ~2 m
    grid = GridSpec(0.0, 0.0, 0.1, 60, 60)
    best = propose(free, grid, n_max=1, r_min=0.1)[0]
    c = propose(free, grid, n_max=1, r_min=best.r - 0.01, prefer=(0.0, 0.0), tie_m=1.0)
    assert len(c) == 1 and c[0].r >= best.r - 0.01


@pytest.mark.parametrize("seed", range(30))
def test_the_distance_read_at_points_equals_the_whole_transform(seed):
    """``PointDistance`` (how far the view reaches, read at the zones' centres) gives exactly what
    ``distance_cells`` gives, on random grids and on convex footprints, with the grid's edge
    counted as non-free."""
    import cv2

    from companion.pipeline.proposals import PointDistance

    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(1, 50, 2))
    if seed % 3 == 0:
        grid = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(grid, rng.uniform(-5, 55, (4, 2)).astype(np.int32), 255)
    else:
        grid = ((rng.random((h, w)) < rng.uniform(0.3, 1.0)) * 255).astype(np.uint8)
    full, points = distance_cells(grid), PointDistance(grid)
    assert points.shape == full.shape
    for i in range(h):
        for j in range(w):
            assert points[i, j] == pytest.approx(float(full[i, j]), abs=1e-5)


# ---- centres on landable ground (pipeline.unlandable_scope = "landing_point") -------------------

def _centre_cell(circle, grid):
    return int(round((circle.y - grid.y0) / grid.cell)), int(round((circle.x - grid.x0) / grid.cell))


@pytest.mark.parametrize("seed", range(8))
def test_allowed_centres_keep_every_guarantee_and_sit_on_allowed_cells(seed):
    """Random people and a random patch of unlandable cells: each circle is centred on an allowed
    cell, keeps off people (not off the unlandable cells: its radius is people's), the circles are
    disjoint, largest first, and the first is the largest circle any allowed centre has."""
    free = _random_map(seed)
    rng = np.random.default_rng(100 + seed)
    centres = np.ones(free.shape, bool)
    i0, j0 = rng.integers(0, 40), rng.integers(0, 50)
    centres[i0:i0 + 25, j0:j0 + 35] = False  # a roof
    grid = GridSpec(x0=3.0, y0=-2.0, cell=0.25, rows=free.shape[0], cols=free.shape[1])
    for prefer in (None, (10.0, 5.0)):
        circles = propose(free, grid, n_max=6, r_min=0.3, prefer=prefer, centres=centres)
        assert circles
        dist = distance_cells(free)
        best_allowed = float(np.max(np.where(centres, dist, 0))) - math.sqrt(2) / 2
        tie = 0.3 if prefer is not None else 0.0
        assert circles[0].r * (1 / grid.cell) >= best_allowed - tie / grid.cell - 0.01
        for c in circles:
            assert centres[_centre_cell(c, grid)], f"{c} is centred on unlandable ground"
            assert not _touches(c, free, grid) and c.r >= 0.3
        for a in range(len(circles)):
            for b in range(a + 1, len(circles)):
                ca, cb = circles[a], circles[b]
                assert math.hypot(ca.x - cb.x, ca.y - cb.y) >= ca.r + cb.r - 1e-9
    # All centres allowed: exactly the unmasked proposals.
    everywhere = np.ones(free.shape, bool)
    assert propose(free, grid, 6, 0.3, centres=everywhere) == propose(free, grid, 6, 0.3)


def test_no_allowed_centre_gives_no_proposal_and_a_wrong_mask_is_refused():
    free = np.full((40, 40), 255, np.uint8)
    grid = GridSpec(0.0, 0.0, 0.1, 40, 40)
    assert propose(free, grid, 3, 0.2, centres=np.zeros((40, 40), bool)) == []
    with pytest.raises(ValueError, match="centres shape"):
        propose(free, grid, 3, 0.2, centres=np.ones((40, 41), bool))


def test_landing_points_keep_the_footprint_off_unlandable_ground():
    from companion.pipeline.proposals import landing_points

    surface = np.full((50, 50), 255, np.uint8)
    surface[:, :20] = 0  # unlandable west of column 20
    pts = landing_points(surface, 0.1, 0.5)
    cols = np.flatnonzero(pts[25])
    # The last unlandable square ends at column 19.5: column 25 is the first whose disc of 0.5 m
    # (5 cells) stays off it, with the half diagonal of a cell paid as a zone's radius pays it.
    assert cols.min() == 25 and not pts[:, :25].any()
    assert not pts[:5].any() and not pts[-5:].any()  # off the grid counts as unlandable too
    assert np.array_equal(landing_points(surface, 0.1, 0.0), surface > 0)
    with pytest.raises(ValueError):
        landing_points(surface, 0.0, 0.5)
    with pytest.raises(ValueError):
        landing_points(surface, 0.1, -1.0)
