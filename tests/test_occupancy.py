"""Occupancy map (pipeline step 2)."""

import numpy as np
import pytest

from companion.pipeline.occupancy import (
    FREE,
    OCCUPIED,
    OccupancyParams,
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


@pytest.mark.parametrize("kw", [dict(threshold=-1.0), dict(threshold=float("nan")),
                                dict(kernel=4), dict(kernel=0), dict(iterations=-1)])
def test_bad_parameters_are_clear_errors(kw):
    with pytest.raises(ValueError, match="occupancy"):
        OccupancyParams(**kw)


def test_density_must_be_2d():
    with pytest.raises(ValueError, match="2-D"):
        occupied_mask(np.zeros((2, 3, 4)))
