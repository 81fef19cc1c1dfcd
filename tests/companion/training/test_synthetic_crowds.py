"""Synthetic top-down crowds and hard negatives: the labels agree with the pixels, splits are disjoint.

The first tests build a small bank in memory (drawn people on a flat ground with a class map), so
they run on a plain clone; the others use the real semantic-drone photos and DroneCrowd layouts
in ``../shared`` and skip without them.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.evaluation import compositor as C
from companion.evaluation.datasets import semantic_drone

GRASS, ROOF, TREE, CAR = 3, 9, 19, 17
CLASSES = {"paved-area": 1, "grass": 3, "roof": 9, "wall": 10, "window": 11, "fence": 13, "fence-pole": 14,
           "car": 17, "tree": 19, "bald-tree": 20, "obstacle": 22, "person": 15}


def drawn_bank(ground_value: int = 120) -> tuple[list[C.Cutout], list[C.Background], C.Layouts]:
    """People: filled ellipses of distinct colours; ground: flat grey grass with a roof, a tree, a car."""
    rng = np.random.default_rng(5)
    cutouts = []
    for k in range(12):
        h, w = int(rng.integers(10, 40)), int(rng.integers(8, 24))
        alpha = np.zeros((h, w), np.float32)
        cv2.ellipse(alpha, (w // 2, h // 2), (max(1, w // 2 - 1), max(1, h // 2 - 1)), 0, 0, 360, 1.0, -1)
        bgr = np.zeros((h, w, 3), np.uint8)
        bgr[:] = (20 + 15 * k, 200 - 10 * k, 60)
        mean, std = np.array([50.0, 0.0, 0.0]), np.array([20.0, 5.0, 5.0])
        cutouts.append(C.Cutout(bgr, alpha, mean, std, f"drawn#{k}"))
    classes = np.full((300, 400), GRASS, np.uint8)
    classes[20:120, 20:160] = ROOF
    cv2.circle(classes, (300, 200), 45, TREE, -1)
    classes[240:270, 60:110] = CAR
    ground = np.full((300, 400, 3), ground_value, np.uint8)
    grounds = [C.Background("flat", ground, classes, 20.0)]
    # A dense, regular crowd layout (DroneCrowd pixels): a 40 x 20 grid spaced 24 px.
    gx, gy = np.meshgrid(np.arange(40) * 24.0 + 400, np.arange(20) * 24.0 + 300)
    anno = np.stack([np.zeros(gx.size), np.arange(gx.size), gx.ravel() - 10, gy.ravel() - 10,
                     gx.ravel() + 10, gy.ravel() + 10], axis=1).astype(np.float32)
    return cutouts, grounds, C.Layouts({"00001": anno})


def assert_labels_agree(comp: C.Composite) -> None:
    """Every pasted person has exactly one head point, inside its own visible silhouette; nothing else."""
    n = len(comp.points)
    assert comp.boxes.shape == (n, 4) and comp.sizes.shape == (n,)
    ids = np.unique(comp.instances)
    assert set(ids.tolist()) == set(range(n + 1)) or (n == 0 and ids.tolist() == [0])
    rows = np.floor(comp.points[:, 1]).astype(int)
    cols = np.floor(comp.points[:, 0]).astype(int)
    # The point of person k lies on person k's visible pixels: one point per mask, none outside masks.
    np.testing.assert_array_equal(comp.instances[rows, cols], np.arange(1, n + 1))
    for k, (x1, y1, x2, y2) in enumerate(comp.boxes, start=1):
        ys, xs = np.nonzero(comp.instances == k)
        assert xs.min() >= x1 and xs.max() < x2 and ys.min() >= y1 and ys.max() < y2
        assert comp.sizes[k - 1] == max(x2 - x1, y2 - y1)


def test_drawn_composite_labels_agree_with_its_pixels() -> None:
    cutouts, grounds, layouts = drawn_bank()
    params = C.CompositorParams(person_px=(8.0, 20.0), shadow=0.0)
    comp = C.Compositor(cutouts, grounds, layouts, params)
    rng = np.random.default_rng(1)
    total = 0
    for i in range(12):
        c = comp.sample(rng, (160, 192), name=f"t{i}")
        assert c.image.shape == (160, 192, 3) and c.image.dtype == np.uint8
        assert_labels_agree(c)
        total += len(c.points)
        # Nothing but the pasted people changes the flat ground: every changed pixel lies within a
        # few pixels (the camera blur) of a pasted person's box.
        changed = np.abs(c.image.astype(int) - 120).max(axis=2) > 2
        near = np.zeros(changed.shape, bool)
        for x1, y1, x2, y2 in c.boxes.astype(int):
            near[max(0, y1 - 4):y2 + 4, max(0, x1 - 4):x2 + 4] = True
        assert not (changed & ~near).any()
        # Each pasted person is visible: its visible pixels differ from the ground.
        for k in range(1, len(c.points) + 1):
            assert changed[c.instances == k].mean() > 0.5
        assert 0.5 * params.person_px[0] <= c.sizes.min() if len(c.sizes) else True
        assert (c.sizes <= params.person_px[1] + 1).all()
    assert total > 50  # the dense layout really places people


def test_people_avoid_roofs_and_cars_and_trees_cover_them() -> None:
    cutouts, grounds, layouts = drawn_bank()
    comp = C.Compositor(cutouts, grounds, layouts, C.CompositorParams(person_px=(10.0, 20.0), shadow=0.0))
    rng = np.random.default_rng(2)
    on_tree_ground = 0
    for _ in range(15):
        c = comp.sample(rng, (128, 128))
        assert not ((c.instances > 0) & (c.classes == TREE)).any()  # trees are drawn over people
        deep = cv2.erode(np.isin(c.classes, (ROOF, CAR)).astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        for x1, y1, x2, y2 in c.boxes:  # the box centre is the paste point, give or take a pixel
            assert not deep[min(int((y1 + y2) / 2), 127), min(int((x1 + x2) / 2), 127)]
        on_tree_ground += int(((c.classes == TREE) & (cv2.dilate((c.instances > 0).astype(np.uint8),
                                                                  np.ones((3, 3), np.uint8)) > 0)).sum())
    assert on_tree_ground > 0  # some people do stand at or under the tree's edge, partly covered


def test_same_seed_same_sample_and_a_new_seed_a_new_one() -> None:
    comp = C.Compositor(*drawn_bank())
    a = comp.sample(np.random.default_rng(7), (96, 96))
    b = comp.sample(np.random.default_rng(7), (96, 96))
    c = comp.sample(np.random.default_rng(8), (96, 96))
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.array_equal(a.image, c.image)


def test_compositor_needs_its_ingredients() -> None:
    cutouts, grounds, layouts = drawn_bank()
    with pytest.raises(ValueError, match="at least one cutout"):
        C.Compositor([], grounds, layouts)


def test_hard_negatives_have_zero_targets_and_cover_the_kinds() -> None:
    from companion.training.negatives import EMPTY, HardNegatives

    _, grounds, _ = drawn_bank()
    empty = C.Background("nobody", np.full((200, 200, 3), 90, np.uint8), np.full((200, 200), GRASS, np.uint8), 30.0)
    neg = HardNegatives.build([*grounds, empty], CLASSES)
    assert set(neg.kinds) == {"roof", "tree", "car", EMPTY}
    rng = np.random.default_rng(0)
    seen = set()
    for _ in range(40):
        img, tgt, kind = neg.crop(64, rng)
        assert img.shape == (64, 64, 3) and tgt.shape == (64, 64) and not tgt.any()
        seen.add(kind)
    assert seen == set(neg.kinds)


# --- on the real data ------------------------------------------------------------------------


def test_real_composites_agree_with_their_labels(shared_dir: Path) -> None:
    comp = C.load_compositor(shared_dir, "val", max_images=10)
    assert comp.cutouts and comp.grounds and comp.layouts.sequences
    rng = np.random.default_rng(0)
    people, times = 0, []
    for _ in range(6):
        t0 = time.perf_counter()
        c = comp.sample(rng, (512, 512))
        times.append(time.perf_counter() - t0)
        assert_labels_agree(c)
        people += len(c.points)
    assert people > 20
    assert np.median(times) < 2.0  # generous: a shared 2-core machine; tens of ms when quiet


def test_splits_are_disjoint_and_fixed(shared_dir: Path) -> None:
    root = shared_dir / "data" / "semantic_drone"
    train, val = C._semantic_names(root, "train"), C._semantic_names(root, "val")
    assert not set(train) & set(val) and len(train) + len(val) == 400
    # The same held-out fifth as the evaluation's semantic-drone set.
    assert {f"{s.name}.jpg" for s in semantic_drone(shared_dir, "val")} == set(val)
    lt, lv = C.load_layouts(shared_dir, "train"), C.load_layouts(shared_dir, "val")
    assert not set(lt.sequences) & set(lv.sequences)
    assert "00017" in lv.sequences and "00112" in lt.sequences and "00010" in lv.sequences
    # People cut for training come only from training photos.
    cut, grounds = C.load_semantic(shared_dir, "train", max_images=5)
    assert {c.source.split("#")[0] for c in cut} <= {Path(n).stem for n in train}
    assert {g.name for g in grounds} <= {Path(n).stem for n in train}


def test_grounds_are_person_free(shared_dir: Path) -> None:
    _, grounds = C.load_semantic(shared_dir, "val", max_images=5)
    root = shared_dir / "data" / "semantic_drone"
    for g in grounds:
        if not (g.classes == C.PERSON).any():
            continue
        orig = cv2.imread(str(root / "images" / f"{g.name}.jpg"))
        person = g.classes == C.PERSON
        assert np.abs(orig[person].astype(int) - g.bgr[person].astype(int)).mean() > 5  # painted over
        np.testing.assert_array_equal(orig[~cv2.dilate(person.astype(np.uint8), np.ones((15, 15))).astype(bool)],
                                      g.bgr[~cv2.dilate(person.astype(np.uint8), np.ones((15, 15))).astype(bool)])


def test_real_hard_negatives(shared_dir: Path) -> None:
    from companion.training.negatives import KINDS, HardNegatives, class_indices

    classes = class_indices(shared_dir)
    assert classes["person"] == C.PERSON and classes["tree"] == 19 and classes["car"] == 17
    _, grounds = C.load_semantic(shared_dir, "train", max_images=20)
    neg = HardNegatives.build(grounds, classes)
    assert {"roof", "car", "tree", "road-marking"} <= set(neg.kinds) <= {*KINDS, "no-person-photo"}
    rng = np.random.default_rng(1)
    for _ in range(10):
        img, tgt, _kind = neg.crop(96, rng)
        assert img.shape == (96, 96, 3) and not tgt.any()


def test_compositor_command_times_and_writes_samples(few_photos_shared: Path, tmp_path: Path, capsys) -> None:
    import json

    # The command loads every photo of the split (seconds on the full set): five held-out ones here.
    shared_dir = few_photos_shared
    assert C.main(["--shared", str(shared_dir), "--split", "val", "--n", "2", "--size", "64", "--out", str(tmp_path)]) == 0
    assert "2 samples of 64x64: median" in capsys.readouterr().out
    labels = json.loads((tmp_path / "labels.json").read_text())
    assert sorted(labels) == ["val_0000", "val_0001"] and (tmp_path / "val_0000.png").is_file()


def test_compositor_command_without_the_data(tmp_path: Path, capsys) -> None:
    assert C.main(["--shared", str(tmp_path), "--n", "1"]) == 2
    assert "missing" in capsys.readouterr().err


def test_path_edge_negatives_are_the_band_where_paving_meets_grass() -> None:
    """A paved strip across grass: the ``path-edge`` kind is the band EDGE_PX pixels either side
    of both its edges, never the middle of the strip or of the lawn; a photo without paving next
    to grass has none."""
    from companion.training.negatives import EDGE_PX, HardNegatives, kind_mask

    classes = np.full((100, 120), GRASS, np.uint8)
    classes[:, 50:70] = CLASSES["paved-area"]  # a path 20 px wide, edges at columns 50 and 70
    ground = C.Background("park", np.full((100, 120, 3), 100, np.uint8), classes, 30.0)
    band = kind_mask("path-edge", ground, CLASSES)
    cols = np.nonzero(band.any(axis=0))[0]
    assert set(cols) == set(range(50 - EDGE_PX, 50 + EDGE_PX)) | set(range(70 - EDGE_PX, 70 + EDGE_PX))
    assert band[:, 50 - EDGE_PX].all() and not band[:, 60].any() and not band[:, 10].any()
    lawn = C.Background("lawn", ground.bgr, np.full((100, 120), GRASS, np.uint8), 30.0)
    assert not kind_mask("path-edge", lawn, CLASSES).any()
    neg = HardNegatives.build([ground], CLASSES)
    assert "path-edge" in neg.kinds


def test_landable_negatives_are_bare_landable_ground_away_from_people() -> None:
    """The opt-in ``landable`` kind: paving, dirt, grass or gravel farther than
    ``LANDABLE_CLEAR_PX`` from every person pixel; never a roof, never beside a person. It is drawn
    only when named: "all kinds" (None), what every shipped model was trained with, leaves it out."""
    from companion.training.negatives import LANDABLE_CLEAR_PX, HardNegatives, check_kinds, kind_mask

    classes = np.full((400, 500), GRASS, np.uint8)
    classes[:, 250:] = CLASSES["paved-area"]
    classes[:100, :100] = ROOF
    classes[300:310, 400:405] = C.PERSON  # one person on the paving
    classes[0, 0] = C.PERSON  # and one on the roof's corner
    ground = C.Background("yard", np.full((400, 500, 3), 110, np.uint8), classes, 20.0)
    mask = kind_mask("landable", ground, {**CLASSES, "dirt": 2, "gravel": 4})
    assert not mask[classes == ROOF].any() and not mask[classes == C.PERSON].any()
    ys, xs = np.nonzero(mask)
    d_person = np.min([np.hypot(ys - 305, xs - 402), np.hypot(ys, xs)], axis=0)
    assert d_person.min() > LANDABLE_CLEAR_PX - 8  # the nearest person pixel, not the person's centre
    assert mask[200, 200] and mask[100, 300] and not mask[305, 402 - LANDABLE_CLEAR_PX // 2]
    assert "landable" not in check_kinds(None) and check_kinds(["landable"]) == ("landable",)
    assert "landable" not in HardNegatives.build([ground], {**CLASSES, "dirt": 2, "gravel": 4}).kinds
    neg = HardNegatives.build([ground], {**CLASSES, "dirt": 2, "gravel": 4}, kinds=["landable"])
    rng = np.random.default_rng(3)
    assert all(neg.crop(64, rng)[2] == "landable" for _ in range(5))


def test_hard_negatives_refuse_a_class_list_without_a_class_a_kind_needs() -> None:
    from companion.evaluation.datasets import DatasetError
    from companion.training.negatives import HardNegatives

    _, grounds, _ = drawn_bank()
    no_grass = {k: v for k, v in CLASSES.items() if k != "grass"}  # path-edge is made from grass
    with pytest.raises(DatasetError, match="no class named grass"):
        HardNegatives.build(grounds, no_grass)


def test_hard_negatives_of_chosen_kinds_only() -> None:
    """``kinds`` keeps only the named kinds (to train on one alone); an unknown or repeated name,
    or kinds none of the photos hold, are refused naming them."""
    from companion.evaluation.datasets import DatasetError
    from companion.training.negatives import EMPTY, HardNegatives, check_kinds

    _, grounds, _ = drawn_bank()
    empty = C.Background("nobody", np.full((200, 200, 3), 90, np.uint8), np.full((200, 200), GRASS, np.uint8), 30.0)
    neg = HardNegatives.build([*grounds, empty], CLASSES, kinds=["roof", EMPTY])
    assert neg.kinds == sorted(["roof", EMPTY])
    rng = np.random.default_rng(0)
    assert {neg.crop(32, rng)[2] for _ in range(30)} == {"roof", EMPTY}
    assert HardNegatives.build(grounds, CLASSES, kinds=["car"]).kinds == ["car"]
    with pytest.raises(ValueError, match="unknown hard-negative kind 'puddle'"):
        check_kinds(["roof", "puddle"])
    with pytest.raises(ValueError, match="without repeats"):
        check_kinds(["roof", "roof"])
    with pytest.raises(ValueError, match="non-empty"):
        check_kinds([])
    with pytest.raises(DatasetError, match="no hard negative of the kinds path-edge"):
        HardNegatives.build(grounds, CLASSES, kinds=["path-edge"])  # the drawn ground has no paving
