"""companion.parallel: the same results in one process and in worker processes; an item whose call
raises is reported with its item and does not stop the others."""

from __future__ import annotations

import pytest

from companion.parallel import ParallelError, default_workers, fan_out


def square_or_fail(x: int) -> int:
    if x == 3:
        raise ValueError("three is bad")
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_every_item_comes_back_once_with_its_result_or_its_error(workers: int) -> None:
    out = dict(fan_out(square_or_fail, [1, 2, 3, 4], workers=workers))
    assert set(out) == {1, 2, 3, 4}
    assert (out[1], out[2], out[4]) == (1, 4, 16)
    assert isinstance(out[3], ValueError) and "three" in str(out[3])


def test_bad_worker_counts_are_refused_and_the_default_fits_the_machine() -> None:
    with pytest.raises(ParallelError):
        list(fan_out(square_or_fail, [1], workers=0))
    assert default_workers(1.0) >= 1 and default_workers(1000.0) == 1
