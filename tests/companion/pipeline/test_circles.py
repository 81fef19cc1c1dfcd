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


def test_the_pair_by_pair_form_equals_the_array_form():
    """A few circles go pair by pair (SMALL_PAIRS); the values are the array form's, on every
    case the formulas branch on: apart, touching, overlapping, nested, equal, zero and negative
    radii, and a non-finite input (the array form decides it)."""
    from companion.pipeline import circles as C

    rng = np.random.default_rng(7)
    a = np.column_stack([rng.uniform(-5, 5, 6), rng.uniform(-5, 5, 6), rng.uniform(-1, 4, 6)])
    b = np.vstack([np.column_stack([rng.uniform(-5, 5, 4), rng.uniform(-5, 5, 4), rng.uniform(0, 4, 4)]),
                   [a[0, 0], a[0, 1], a[0, 2]],            # the same circle
                   [a[1, 0] + 0.1, a[1, 1], a[1, 2] + 3],  # containing one
                   [a[2, 0] + abs(a[2, 2]) + 1.0, a[2, 1], 1.0],  # touching from outside
                   [0.0, 0.0, 0.0]])
    assert len(a) * len(b) <= C.SMALL_PAIRS
    small = iou_matrix(a, b)
    inter = C.intersection_area(a, b)
    area_a = np.pi * np.maximum(a[:, 2], 0)[:, None] ** 2
    area_b = np.pi * np.maximum(b[:, 2], 0)[None, :] ** 2
    union = area_a + area_b - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        array_form = np.clip(np.where(union > 0, inter / union, 0.0), 0.0, 1.0)
    np.testing.assert_allclose(small, array_form, rtol=1e-12, atol=1e-12)
    assert small[0, 4] == pytest.approx(1.0) and small.shape == (6, 8)
    bad = iou_matrix(np.array([[np.nan, 0.0, 1.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert bad.shape == (1, 1) and bad[0, 0] == 0.0
