"""Occupancy map (pipeline step 2)."""

import cv2
import numpy as np
import pytest

from companion.pipeline.occupancy import (
    FREE,
    OCCUPIED,
    OccupancyParams,
    drop_specks,
    free_from_occupied,
    occupancy_map,
    occupied_mask,
    resize_keep_occupied,
)


def test_paper_rule_marks_above_minimum():
    d = np.full((4, 4), 0.2, np.float32)
    d[1, 2] = 0.2001
    occ = occupied_mask(d, 0.0)
    assert occ.sum() == 1 and occ[1, 2]
    assert not occupied_mask(d, 0.01).any()


def test_one_person_grows_by_two_5x5_dilations():
    d = np.zeros((120, 160), np.float32)
    d[60, 80] = 1.0  # stride 4: covers pixels 240..243 x 320..323
    free = occupancy_map(d, (480, 640))
    occ = np.argwhere(free == OCCUPIED)
    assert occ[:, 0].min() == 240 - 4 and occ[:, 0].max() == 243 + 4
    assert occ[:, 1].min() == 320 - 4 and occ[:, 1].max() == 323 + 4
    assert set(np.unique(free)) == {FREE, OCCUPIED}


def test_parameters_change_the_growth():
    d = np.zeros((120, 160), np.float32)
    d[60, 80] = 1.0
    free = occupancy_map(d, (480, 640), OccupancyParams(threshold=0.0, kernel=3, iterations=1))
    assert (free == OCCUPIED).sum() == 6 * 6
    assert (occupancy_map(d, (480, 640), OccupancyParams(threshold=2.0)) == FREE).all()


def _free_the_long_way(occ: np.ndarray, image_hw: tuple[int, int], params: OccupancyParams) -> np.ndarray:
    """The paper's order, literally: up to the image size, then each 5x5 dilation in turn."""
    img = resize_keep_occupied(occ, image_hw).astype(np.uint8) * 255
    if params.iterations > 0 and params.kernel > 1:
        img = cv2.dilate(img, np.ones((params.kernel, params.kernel), np.uint8), iterations=params.iterations)
    return cv2.bitwise_not(img)


@pytest.mark.parametrize("mask_hw,image_hw", [((120, 160), (480, 640)), ((180, 320), (720, 1280)),
                                              ((119, 160), (474, 638)), ((60, 80), (480, 640)),
                                              ((120, 160), (120, 160)), ((120, 160), (240, 480)),
                                              ((240, 320), (120, 160)), ((7, 5), (21, 35)), ((120, 160), (240, 320))])
@pytest.mark.parametrize("kernel,iterations", [(5, 2), (3, 1), (5, 0), (1, 3), (7, 3), (3, 4)])
def test_the_cheap_growth_is_the_papers_pixel_for_pixel(mask_hw, image_hw, kernel, iterations):
    # Dilating on the mask before bringing it up (whole multiples) must give the same map as the
    # literal order, borders included: random people, some touching the edges.
    rng = np.random.default_rng(kernel * 10 + iterations)
    occ = rng.random(mask_hw) < 0.03
    occ[0, 0] = occ[-1, -1] = True
    params = OccupancyParams(threshold=0.0, kernel=kernel, iterations=iterations)
    got = free_from_occupied(occ, image_hw, params)
    assert got.dtype == np.uint8 and got.shape == image_hw
    assert np.array_equal(got, _free_the_long_way(occ, image_hw, params))


def test_downscaling_never_loses_an_occupied_pixel():
    m = np.zeros((480, 640), bool)
    m[101, 333] = True
    small = resize_keep_occupied(m, (120, 160))
    assert small.sum() >= 1 and small[101 // 4, 333 // 4]
    odd = resize_keep_occupied(m, (97, 131))
    assert odd.any()


def test_non_finite_density_is_occupied_and_empty_density_is_all_occupied():
    d = np.zeros((10, 10), np.float32)
    d[3, 3] = np.nan
    assert occupied_mask(d)[3, 3]
    assert occupied_mask(np.full((5, 5), np.nan)).all()
    assert (occupancy_map(np.zeros((0, 0)), (48, 64)) == OCCUPIED).all()


def _person(d: np.ndarray, row: int, col: int, people: float = 1.0, sigma: float = 1.5) -> None:
    """Add a Gaussian blob holding ``people`` (its sum) centred on cell (row, col)."""
    yy, xx = np.mgrid[: d.shape[0], : d.shape[1]]
    g = np.exp(-((yy - row) ** 2 + (xx - col) ** 2) / (2 * sigma**2))
    d += (people * g / g.sum()).astype(np.float32)


def test_specks_below_min_mass_are_free_and_people_stay_occupied():
    d = np.zeros((60, 80), np.float32)
    _person(d, 20, 20)                     # a person: sum 1
    _person(d, 40, 60, people=0.3)         # a third of a person (the frame's edge, a faint one)
    d[50, 10] += 0.02                      # a speck: one cell just over the threshold
    d[10, 70] += 0.02
    d[11, 71] += 0.02                      # two cells touching diagonally: one patch of 0.04
    thr = 0.01
    occ = occupied_mask(d, thr)
    assert occ[50, 10] and occ[10, 70] and occ[11, 71]
    kept = drop_specks(occ, d, min_mass=0.05)
    assert kept[20, 20] and kept[40, 60]
    assert not kept[50, 10] and not kept[10, 70] and not kept[11, 71]
    # Only whole patches go: every cell of the person's patch is kept, nothing else changes.
    assert (kept == (occ & ~np.isin(np.arange(occ.size).reshape(occ.shape),
                                   [50 * 80 + 10, 10 * 80 + 70, 11 * 80 + 71]))).all()
    # The same through the whole occupancy step: the speck's pixels are free at image size.
    free = occupancy_map(d, (240, 320), OccupancyParams(threshold=thr, min_mass=0.05))
    assert free[50 * 4, 10 * 4] == FREE and free[20 * 4, 20 * 4] == OCCUPIED and free[40 * 4, 60 * 4] == OCCUPIED
    paper = occupancy_map(d, (240, 320), OccupancyParams(threshold=thr))
    assert paper[50 * 4, 10 * 4] == OCCUPIED
    # A patch weighs the density above the frame's minimum: a raised floor adds nothing.
    assert not drop_specks(occupied_mask(d + 5.0, thr), d + 5.0, 0.05)[50, 10]


def test_min_mass_zero_keeps_every_patch_and_non_finite_patches_are_never_specks():
    d = np.zeros((20, 20), np.float32)
    d[5, 5] = 0.02
    occ = occupied_mask(d, 0.01)
    assert drop_specks(occ, d, 0.0) is occ
    d[15, 15] = np.nan
    kept = drop_specks(occupied_mask(d, 0.01), d, 10.0)
    assert kept[15, 15] and not kept[5, 5]
    assert drop_specks(occupied_mask(np.full((4, 4), np.nan)), np.full((4, 4), np.nan), 10.0).all()


@pytest.mark.parametrize("kw", [dict(threshold=-1.0), dict(threshold=float("nan")),
                                dict(kernel=4), dict(kernel=0), dict(iterations=-1),
                                dict(min_mass=-0.1), dict(min_mass=float("inf"))])
def test_bad_parameters_are_clear_errors(kw):
    with pytest.raises(ValueError, match="occupancy"):
        OccupancyParams(**kw)


def test_density_must_be_2d():
    with pytest.raises(ValueError, match="2-D"):
        occupied_mask(np.zeros((2, 3, 4)))
