"""Closed-form circle IoU against Monte Carlo."""

import numpy as np
import pytest

from companion.pipeline.circles import Circle, circle_iou, iou_matrix


def _monte_carlo_iou(a, b, n=400_000, seed=0):
    rng = np.random.default_rng(seed)
    lo = np.minimum([a.x - a.r, a.y - a.r], [b.x - b.r, b.y - b.r])
    hi = np.maximum([a.x + a.r, a.y + a.r], [b.x + b.r, b.y + b.r])
    p = rng.uniform(lo, hi, size=(n, 2))
    ina = np.hypot(p[:, 0] - a.x, p[:, 1] - a.y) <= a.r
    inb = np.hypot(p[:, 0] - b.x, p[:, 1] - b.y) <= b.r
    return (ina & inb).sum() / (ina | inb).sum()


@pytest.mark.parametrize("seed", range(12))
def test_iou_matches_monte_carlo_within_one_percent(seed):
    rng = np.random.default_rng(100 + seed)
    a = Circle(*rng.uniform(-3, 3, 2), rng.uniform(0.5, 4))
    while True:
        b = Circle(*rng.uniform(-3, 3, 2), rng.uniform(0.5, 4))
        if circle_iou(a, b) > 0.05:
            break
    assert circle_iou(a, b) == pytest.approx(_monte_carlo_iou(a, b, seed=seed), abs=0.01)


def test_special_cases():
    a = Circle(1.0, 2.0, 3.0)
    assert circle_iou(a, a) == pytest.approx(1.0)
    assert circle_iou(a, Circle(10.0, 2.0, 3.0)) == 0.0
    assert circle_iou(a, Circle(7.0, 2.0, 3.0)) == 0.0  # touching
    inner = Circle(1.5, 2.0, 1.0)
    assert circle_iou(a, inner) == pytest.approx(1.0 / 9.0)
    assert circle_iou(a, Circle(1.0, 2.0, 0.0)) == 0.0


def test_matrix_shape_and_symmetry():
    a = np.array([[0, 0, 1], [1, 0, 1], [5, 5, 2]], float)
    m = iou_matrix(a, a)
    assert m.shape == (3, 3)
    assert np.allclose(m, m.T) and np.allclose(np.diag(m), 1)
    assert iou_matrix(np.zeros((0, 3)), a).shape == (0, 3)
