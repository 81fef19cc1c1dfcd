"""What the simulator's ground is (``sim.world.ground.SURFACES``), and touchdowns judged on it: a landing
on a tree or a bench is counted apart, whoever stood near."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.flights.flight import FOOTPRINT_M, FlightResult, FlightSpec, touchdown_surfaces
from sim.flights.results import summarise_baseline, summarise_rows, summary_text
from sim.world.ground import BLOCK, LANDABLE_SURFACES, SURFACE_LEVEL, SURFACES, FlatGround, ProceduralGround


def _shapes(ground: ProceduralGround, surface: str, blocks: int = 12):
    """(block, shape) pairs of ``surface`` over the first blocks of the ground."""
    for bi in range(blocks):
        for bj in range(blocks):
            for s in ground._blocks(bi, bj):
                if s.surface == surface:
                    yield (bi, bj), s


def _last_over(ground: ProceduralGround, block: tuple[int, int], point: np.ndarray, shape) -> bool:
    """Whether no later shape of the block with a surface covers ``point`` (then ``shape`` is what
    the ground is there)."""
    import cv2

    later = ground._blocks(*block)
    after = later[next(i for i, s in enumerate(later) if s is shape) + 1:]
    for s in after:
        if s.surface is None or s.line > 0:
            continue
        if cv2.pointPolygonTest(s.pts.astype(np.float32), (float(point[0]), float(point[1])), True) > -0.1:
            return False
    return True


@pytest.mark.parametrize("surface", ["tree", "bench", "car", "roof", "road", "path"])
def test_a_shape_says_what_the_ground_is_at_its_middle(surface: str) -> None:
    g = ProceduralGround(7)
    found = 0
    for block, shape in _shapes(g, surface):
        mid = shape.pts.mean(axis=0)
        if shape.line == 0 and not _last_over(g, block, mid, shape):
            continue  # something drawn over it there (a car on the road, a bench on a path)
        if shape.line > 0:  # a path: its first end, inside the lot
            mid = shape.pts[0] + 0.5 * (shape.pts[1] - shape.pts[0])
            if any(s.surface in ("tree", "bench") and math.dist(s.pts.mean(axis=0), mid) < 4
                   for s in g._blocks(*block)):
                continue
        assert g.surface_at(*mid) == surface, (block, surface, mid)
        found += 1
        if found == 3:
            break
    assert found, f"no {surface} in the first blocks of seed 7: the test tests nothing"


def test_a_trees_shade_is_grass_and_the_lawn_around_it_too() -> None:
    g = ProceduralGround(7)
    block, tree = next(_shapes(g, "tree"))
    centre = tree.pts.mean(axis=0)
    r = float(np.max(np.hypot(*(tree.pts - centre).T)))
    # The shade disc is the canopy moved 0.4 m north-east: its crescent beyond the canopy is
    # shadowed grass, not tree.
    crescent = centre + (r + 0.3) / math.sqrt(2) * np.array([1.0, 1.0])
    if _last_over(g, block, crescent, tree) and g.block_kind(*block) == "grass":
        assert g.surface_at(*crescent) in ("grass", "path")
    assert g.surface_at(*centre) == "tree"
    assert g.surfaces_within(*centre, radius=r + 1.5) >= {"tree"}
    assert len(g.surfaces_within(*centre, radius=r + 1.5)) >= 2  # the edge of the canopy and beyond


def test_the_vocabulary_maps_every_surface_to_a_landability_level() -> None:
    assert set(SURFACE_LEVEL) == set(SURFACES)
    assert LANDABLE_SURFACES == {"grass", "paving", "gravel", "path", "road"}
    assert {"tree", "bench", "car", "roof"}.isdisjoint(LANDABLE_SURFACES)


def test_surface_labels_cover_the_rectangle_and_refuse_bad_input() -> None:
    g = ProceduralGround(3)
    labels, A = g.surface_labels(0.0, 2 * BLOCK, 0.0, 2 * BLOCK, 0.25)
    assert labels.shape == (256, 256) and labels.dtype == np.uint8
    assert (labels > 0).all()  # every pixel is some ground: the blocks tile the plane
    # A maps (north, east) to (col, row) as ProceduralGround.view does.
    col, row, _ = A @ np.array([10.0, 30.0, 1.0])
    assert (col, row) == (120.0, 40.0)
    with pytest.raises(ValueError):
        g.surface_labels(0.0, 0.0, 0.0, 1.0, 0.1)
    with pytest.raises(ValueError):
        g.surface_labels(0.0, 1.0, 0.0, 1.0, 0.0)
    with pytest.raises(ValueError):
        g.surface_labels(0.0, 1e4, 0.0, 1e4, 0.1)  # 100,000 pixels a side


def test_the_picture_does_not_depend_on_the_truth() -> None:
    """The surfaces are the truth of the same shapes: the picture (what the model sees) is the
    same with every shape's surface taken away."""
    import dataclasses

    g, bare = ProceduralGround(5), ProceduralGround(5)
    bare._blocks = lambda bi, bj: tuple(dataclasses.replace(s, surface=None)  # type: ignore[method-assign]
                                        for s in g._blocks(bi, bj))
    assert np.array_equal(g.tile(0, 0, 0), bare._make_tile(0, 0, 0))
    assert np.array_equal(g.tile(2, 1, -1), bare._make_tile(2, 1, -1))


def test_a_touchdown_on_a_tree_is_judged_unlandable_and_on_a_lawn_landable() -> None:
    g = ProceduralGround(7)
    _block, tree = next(_shapes(g, "tree"))
    on_tree = touchdown_surfaces(g, tuple(tree.pts.mean(axis=0)))
    assert on_tree is not None and "tree" in on_tree
    spec = FlightSpec(seed=7)
    r = FlightResult(spec, "safe", touchdown=(0.0, 0.0), clearance_m=5.0, touchdown_surfaces=on_tree)
    assert r.unlandable_touchdown is True and r.as_dict()["unlandable_touchdown"] is True
    lawn = FlightResult(spec, "safe", touchdown=(0.0, 0.0), clearance_m=5.0, touchdown_surfaces=["grass"])
    assert lawn.unlandable_touchdown is False
    assert touchdown_surfaces(FlatGround(), (0.0, 0.0)) is None  # a flat colour says nothing
    assert FlightResult(spec, "safe").as_dict()["touchdown_surfaces"] is None
    assert 0.3 <= FOOTPRINT_M <= 1.0


def test_the_summary_counts_touchdowns_on_unlandable_ground_whoever_landed() -> None:
    spec = FlightSpec(seed=1)

    def row(outcome: str, surfaces: list[str] | None, starved: bool = False, baseline: bool = False) -> dict:
        r = FlightResult(spec if not baseline else FlightSpec(seed=1, companion=False), outcome,
                         touchdown=(0.0, 0.0), clearance_m=5.0, touchdown_surfaces=surfaces,
                         starved=starved).as_dict()
        return r

    rows = [row("safe", ["grass", "tree"]), row("safe", ["grass"]), row("handback", ["bench", "path"]),
            row("unsafe", ["car"], starved=True), row("safe", None)]
    s = summarise_rows(rows)
    # The starved flight is out of every clean count; the one without a ground is not judged.
    assert (s["touchdowns_judged_for_surface"], s["unlandable_touchdowns"], s["companion_landings_unlandable"]) == (3, 2, 1)
    assert "unlandable ground" in summary_text(s) and "2 of 3" in summary_text(s)
    base = summarise_baseline([row("handback", ["tree"], baseline=True), row("handback", ["grass"], baseline=True)])
    assert (base["unlandable_touchdowns"], base["touchdowns_judged_for_surface"]) == (1, 2)
    # Rows of older runs (no key) are never guessed.
    old = [{k: v for k, v in r.items() if k not in ("touchdown_surfaces", "unlandable_touchdown")} for r in rows]
    assert summarise_rows(old)["unlandable_touchdowns"] is None
    assert "unlandable ground" not in summary_text(summarise_rows(old))
