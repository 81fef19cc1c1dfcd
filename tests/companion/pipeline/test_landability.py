"""The landability model (issue 15): its runner and metadata checks, the pipeline with people AND
unlandable ground, the zones' edges, start-up errors, the drawing, and training a few steps."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx import TensorProto, helper, numpy_helper

from companion import config
from companion.geometry.camera import PlaneProjection
from companion.pipeline.density import DensityModel, DensityModelError
from companion.pipeline.edges import PEOPLE, SURFACE, VIEW, edge_reason
from companion.pipeline.headplane import GridSpec
from companion.pipeline.landability import LandabilityModel, LandabilityModelError
from companion.pipeline.occupancy import FREE, OCCUPIED, surface_free_map
from companion.pipeline.proposals import distance_cells
from companion.pipeline.slz import PipelineConfig, SLZPipeline
from tests import early
from tests.companion.evaluation.test_density_runner import _save

REPO = Path(__file__).resolve().parents[3]
LANDABILITY = REPO / "companion" / "models" / "slz-landability.onnx"
LEVELS = [{"name": "landable", "classes": ["grass", "paved-area"]},
          {"name": "water", "classes": ["water", "pool"]},
          {"name": "obstacles", "classes": ["roof"]}]


def _meta(**changes: str | None) -> dict[str, str]:
    meta = {"companion.output": "risk-level-probabilities", "companion.levels": json.dumps(LEVELS),
            "companion.landable_level": "landable", "companion.unlandable_threshold": "0.4",
            "companion.stride": "8", "companion.scale": "1"}
    for k, v in changes.items():
        key = "companion." + k
        if v is None:
            meta.pop(key, None)
        else:
            meta[key] = v
    return meta


def level_model(tmp_path: Path, meta: dict[str, str], levels: int = 3, name: str = "l.onnx") -> Path:
    """(N, 3, H, W) -> 8x8 average pool -> 1x1 conv -> softmax: (N, levels, H/8, W/8). Channel 0
    (landable) follows the green channel, channel 1 (water) the blue one, the rest nothing."""
    w = np.zeros((levels, 3, 1, 1), np.float32)
    w[0, 1] = 0.05
    w[1, 0] = 0.05
    graph = helper.make_graph(
        [helper.make_node("AveragePool", ["x"], ["p"], kernel_shape=[8, 8], strides=[8, 8]),
         helper.make_node("Conv", ["p", "w"], ["c"]),
         helper.make_node("Softmax", ["c"], ["y"], axis=1)],
        "levels",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", 3, "h", "w"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", levels, "h8", "w8"])],
        [numpy_helper.from_array(w, "w")],
    )
    return _save(tmp_path, graph, meta, name)


# ---- the runner and the metadata ------------------------------------------------------------

def test_a_small_level_model_loads_and_gives_probabilities(tmp_path: Path) -> None:
    m = LandabilityModel(level_model(tmp_path, _meta()), threads=1)
    assert m.landability.names == ("landable", "water", "obstacles")
    assert m.landability.threshold == pytest.approx(0.4) and m.spec.stride == 8
    frame = np.zeros((64, 96, 3), np.uint8)
    frame[:, :48] = (255, 0, 0)   # blue: water on the left
    frame[:, 48:] = (0, 255, 0)   # green: lawn on the right
    p = m(frame)
    assert p.shape == (3, 8, 12) and np.allclose(p.sum(axis=0), 1.0, atol=1e-5)
    unl = m.unlandable()
    assert unl.names == ("water", "obstacles") and unl.threshold == pytest.approx(0.4)
    u = unl(frame)
    assert u.shape == (8, 12) and (u[:, :6] > 0.9).all() and (u[:, 6:] < 0.1).all()
    assert m.unlandable(["obstacles"])(frame).max() < 0.1  # water not in the set: landable
    with pytest.raises(LandabilityModelError, match="no risk level named 'lava'"):
        m.unlandable(["lava"])


@pytest.mark.parametrize("change, message", [
    ({"levels": "not json"}, "companion.levels is not valid JSON"),
    ({"levels": json.dumps([{"name": "landable", "classes": ["grass"]}])}, "at least two"),
    ({"levels": json.dumps([{"name": "landable", "classes": ["grass"]}, {"name": "landable", "classes": []},
                            {"name": "x", "classes": []}])}, "appears twice"),
    ({"levels": json.dumps([{"name": "landable", "classes": ["grass"]}, {"name": "water", "classes": ["grass"]},
                            {"name": "x", "classes": []}])}, "class 'grass' is in two levels"),
    ({"levels": json.dumps([{"name": "Landable!", "classes": []}, {"name": "w", "classes": []},
                            {"name": "x", "classes": []}])}, "lower-case name"),
    ({"levels": json.dumps([{"name": "landable", "classes": "grass"}, {"name": "w", "classes": []},
                            {"name": "x", "classes": []}])}, "must be a list of class names"),
    ({"levels": json.dumps([{"name": "landable"}, {"name": "w", "classes": []}, {"name": "x", "classes": []}])},
     "exactly the keys name and classes"),
    ({"levels": None}, "companion.levels is missing"),
    ({"landable_level": "lawn"}, "companion.landable_level must name one of the levels"),
    ({"unlandable_threshold": "1.5"}, "unlandable_threshold must be a number in"),
    ({"unlandable_threshold": "nan"}, "unlandable_threshold must be a number in"),
    ({"output": "occupancy-probability"}, "companion.output must be 'risk-level-probabilities'"),
    ({"levels": json.dumps(LEVELS[:2])}, "gives 3 channels but companion.levels names 2 levels"),
])
def test_a_malformed_grouping_is_a_clear_error_at_load(tmp_path: Path, change: dict, message: str) -> None:
    path = level_model(tmp_path, _meta(**change))
    with pytest.raises(LandabilityModelError, match=message) as e:
        LandabilityModel(path, threads=1)
    assert str(path) in str(e.value)
    assert isinstance(e.value, DensityModelError)  # start-up paths stop on it (exit 2)


def test_missing_corrupt_or_one_channel_files_are_clear_errors(tmp_path: Path, model_path: Path) -> None:
    with pytest.raises(LandabilityModelError, match="landability model file .* does not exist"):
        LandabilityModel(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx model")
    with pytest.raises(LandabilityModelError, match="not a loadable ONNX model"):
        LandabilityModel(bad)
    # The density model (one channel, no levels) is no landability model.
    with pytest.raises(LandabilityModelError):
        LandabilityModel(model_path)


@pytest.mark.parametrize("path", [LANDABILITY, LANDABILITY.with_name("slz-landability-v1.onnx")],
                         ids=["shipped", "first"])
def test_the_shipped_landability_model_is_small_and_well_formed(path: Path) -> None:
    """The default file and the first model, kept beside it for recordings flown with it."""
    assert path.is_file(), f"the landability model {path.name} is missing"
    assert path.stat().st_size < 1_000_000
    m = LandabilityModel(path, threads=1)
    assert m.landability.landable == "landable" and len(m.landability.levels) == 7
    assert m.spec.stride == 8 and 0 < m.landability.threshold < 1
    classes = {c for lv in m.landability.levels for c in lv.classes}
    assert len(classes) == 24  # every semantic-drone class has a level
    p = m(np.random.default_rng(0).integers(0, 256, (480, 640, 3), np.uint8))
    assert p.shape == (7, 60, 80) and np.allclose(p.sum(axis=0), 1.0, atol=1e-4)


# ---- the occupancy step and the zones' edges ----------------------------------------------------

def test_surface_free_map_thresholds_absolute_probability_and_fails_safe() -> None:
    p = np.full((4, 4), 0.2, np.float32)
    p[0, 0] = 0.9
    p[3, 3] = np.nan
    free = surface_free_map(p, (32, 32), 0.5, PipelineConfig().occupancy)
    assert free.shape == (32, 32)
    assert free[0, 0] == OCCUPIED and free[31, 31] == OCCUPIED and free[16, 16] == FREE
    assert (free[:12, :12] == OCCUPIED).all()  # the cell (8 px) plus the dilation (2 x 2 px)
    assert (surface_free_map(np.zeros((0, 0)), (8, 8), 0.5) == OCCUPIED).all()


def test_edge_reason_names_people_surface_and_view() -> None:
    grid = GridSpec(0.0, 0.0, 1.0, 40, 40)
    seen = np.full((40, 40), 255, np.uint8)
    people = np.full((40, 40), 255, np.uint8)
    surface = np.full((40, 40), 255, np.uint8)
    people[:, :5] = 0        # people along the west...
    surface[:, 30:] = 0      # ...water along the east
    free = np.minimum(people, surface)
    dist = distance_cells(free)
    assert edge_reason(12, 20, grid, dist, free, seen, people, surface) == PEOPLE
    assert edge_reason(24, 20, grid, dist, free, seen, people, surface) == SURFACE
    assert edge_reason(2, 20, grid, dist, free, seen, people, surface) == PEOPLE   # inside the people
    # A zone whose nearest edge is the end of the grid / the view.
    assert edge_reason(17, 1, grid, dist, free, seen, people, surface) == VIEW
    assert edge_reason(50, 20, grid, dist, free, seen, people, surface) == VIEW   # off the grid
    unseen = seen.copy()
    unseen[:, 30:] = 0
    assert edge_reason(24, 20, grid, dist, free, unseen, people, surface) == VIEW
    # Without a landability model every seen non-free cell is people.
    assert edge_reason(24, 20, grid, distance_cells(surface), surface, seen) == PEOPLE
    # A large zone: the ring is all that is looked at, and it still finds the water.
    big = np.full((400, 400), 255, np.uint8)
    big[:, 390:] = 0
    bgrid = GridSpec(0.0, 0.0, 0.1, 400, 400)
    assert edge_reason(20.0, 20.0, bgrid, distance_cells(big), big, np.full_like(big, 255), np.full_like(big, 255),
                       big) == SURFACE


# ---- the pipeline: people OR unlandable ground ----------------------------------------------------

def _crowd_frames(n: int = 6) -> list[np.ndarray]:
    from companion import synthetic

    scene = synthetic.crowd_scene(640, 480, n_people=60, free=((200, 240, 90),), seed=3)
    return [synthetic.render(scene, seed=k) for k in range(n)]


def test_without_a_landability_model_the_zones_are_exactly_the_people_only_ones(model_path: Path) -> None:
    """No surface model, or one that calls all ground landable: identical zones frame by frame
    (the combined path adds nothing of its own), and the records only gain the ``edge`` key."""
    density = DensityModel(model_path, threads=1)
    proj = PlaneProjection.nadir(0.05)

    def all_landable(frame: np.ndarray) -> np.ndarray:
        return np.zeros((frame.shape[0] // 8, frame.shape[1] // 8), np.float32)

    alone = SLZPipeline(density, projection=proj)
    both = SLZPipeline(density, projection=proj, surface=all_landable)
    zones = 0
    for k, frame in enumerate(_crowd_frames()):
        a, b = alone.process(frame, k / 10), both.process(frame, k / 10)
        assert a.surface is None and a.people_free is None and "landability" not in a.timings_ms
        assert np.array_equal(a.occupancy, b.occupancy) and np.array_equal(a.free_grid, b.free_grid)
        assert a.proposals == b.proposals
        assert [(t.id, t.x, t.y, t.r, t.age) for t in a.tracks] == [(t.id, t.x, t.y, t.r, t.age) for t in b.tracks]
        assert a.proposal_edges == [] and all(t.edge == "" for t in a.tracks)  # not judged without it
        assert len(b.proposal_edges) == len(b.proposals) and set(b.proposal_edges) <= {PEOPLE, VIEW}
        zones += len(a.proposals)
    assert zones > 0


def test_service_settings_switch_the_landability_model(tmp_path: Path) -> None:
    from companion.service.parts import build_pipeline, load_landability, load_model

    off = config.load(None, {"model.landability": False, "model.threads": 1})
    assert load_landability(off) is None
    assert build_pipeline(off, load_model(off)).surface is None
    on = config.load(None, {"model.threads": 1, "pipeline.unlandable_levels": ["water", "vehicles"]})
    assert on.model.landability is config.LANDABILITY_DEFAULT
    if on.model.landability:
        surface = load_landability(on)
        assert surface is not None and surface.names == ("water", "vehicles")
    bad = config.load(None, {"model.landability": True, "pipeline.unlandable_levels": ["lava"]})
    with pytest.raises(LandabilityModelError, match="pipeline.unlandable_levels: .*no risk level named 'lava'"):
        load_landability(bad)


@pytest.mark.parametrize("value, message", [
    (["water", "water"], "pipeline.unlandable_levels must list distinct level names"),
    (["Water"], "pipeline.unlandable_levels must list distinct level names"),
])
def test_config_validates_the_unlandable_levels(value: list[str], message: str) -> None:
    with pytest.raises(config.ConfigError, match=message):
        config.load(None, {"pipeline.unlandable_levels": value})
    with pytest.raises(config.ConfigError, match="pipeline.unlandable_threshold"):
        config.load(None, {"pipeline.unlandable_threshold": -0.5})
    with pytest.raises(config.ConfigError, match="pipeline.unlandable_threshold"):
        config.load(None, {"pipeline.unlandable_threshold": 1.0})


@early.batch("landability-exit-2")
def _landability_exit_2(folder: Path) -> list[early.Run]:
    """``companion run`` and ``check-config`` with a missing and a corrupt landability model, and
    ``check-config`` with an unknown unlandable level: each starts a Python and loads onnxruntime,
    so they start side by side once the session knows it runs the test (tests/early.py)."""
    (folder / "bad.onnx").write_bytes(b"garbage, not onnx")
    runs: list[early.Run] = []
    for k, (path, _) in enumerate(LANDABILITY_CASES):
        f = folder / f"c{k}.toml"
        f.write_text(f'[model]\nthreads = 1\nlandability = true\nlandability_path = "{path}"\n')
        runs += [early.Run([sys.executable, "-m", "companion", *args], folder)
                 for args in (("run", "--config", str(f)), ("check-config", str(f)))]
    lava = folder / "lava.toml"
    lava.write_text('[model]\nthreads = 1\nlandability = true\n[pipeline]\nunlandable_levels = ["lava"]\n')
    runs.append(early.Run([sys.executable, "-m", "companion", "check-config", str(lava)], folder))
    return runs


LANDABILITY_CASES = (("missing.onnx", "does not exist"), ("bad.onnx", "not a loadable ONNX model"))


@pytest.mark.started_early("landability-exit-2")
def test_a_missing_or_corrupt_landability_model_stops_the_start_with_exit_2() -> None:
    cases = LANDABILITY_CASES
    results = early.result("landability-exit-2")[1]
    for k, (path, words) in enumerate(cases):
        r, c = results[2 * k], results[2 * k + 1]
        assert r.returncode == 2, (r.stdout, r.stderr)
        assert "model error" in r.stderr and path in r.stderr and words in r.stderr and "Traceback" not in r.stderr
        assert c.returncode == 2 and "model.landability_path" in c.stderr and "Traceback" not in c.stderr
    r = results[-1]
    assert r.returncode == 2 and "pipeline.unlandable_levels" in r.stderr and "lava" in r.stderr


# ---- a synthetic frame of real water beside a real lawn ------------------------------------------

def _largest_patch(shared: Path, stem: str, cls: str) -> np.ndarray:
    """The largest square of the held-out photo ``stem`` whose pixels are all of class ``cls``."""
    from companion.evaluation import datasets as D

    sample = next(s for s in D.semantic_drone(shared, "val") if s.name == stem)
    mask = (D.semantic_labels(sample) == D.semantic_classes(shared)[cls]).astype(np.uint8)
    # The border counts as another class, so the square stays inside the photo.
    dist = cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_C, 3)[1:-1, 1:-1]
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    half = int(dist[i, j]) - 1
    assert half >= 40, f"{stem} has no {cls} patch large enough"
    return sample.image()[i - half:i + half, j - half:j + half]


def _fill(patch: np.ndarray, h: int, w: int) -> np.ndarray:
    """``patch`` mirrored (no seams) to fill h x w."""
    ph, pw = patch.shape[:2]
    row = np.concatenate([patch, patch[:, ::-1]], axis=1)
    tile = np.concatenate([row, row[::-1]], axis=0)
    return np.tile(tile, (h // (2 * ph) + 1, w // (2 * pw) + 1, 1))[:h, :w]


def test_water_beside_a_lawn_gives_circles_only_on_the_lawn(shared_dir: Path, model_path: Path) -> None:
    """Built at test time from held-out semantic-drone pixels (never saved): water (photo 321)
    on the left half, a lawn (photo 414) on the right; the shipped models, default settings."""
    water = _largest_patch(shared_dir, "321", "water")
    grass = _largest_patch(shared_dir, "414", "grass")
    h, w = 480, 640
    frame = np.concatenate([_fill(water, h, w // 2), _fill(grass, h, w // 2)], axis=1)
    gsd = 0.04
    surface = LandabilityModel(LANDABILITY, threads=1).unlandable()
    pipe = SLZPipeline(DensityModel(model_path, threads=1), projection=PlaneProjection.nadir(gsd), surface=surface)
    res = pipe.process(frame, 0.0)
    assert res.surface is not None
    assert (res.surface[:, : w // 2 - 16] == OCCUPIED).mean() > 0.95, "the water is not seen as unlandable"
    assert (res.surface[:, w // 2 + 16:] == FREE).mean() > 0.5, "the lawn is not seen as landable"
    assert res.proposals, "no landing circle on the lawn"
    boundary = (w // 2) * gsd
    for c in res.proposals:
        assert c.x - c.r >= boundary - 1e-6, f"circle {c} reaches into the water"
    assert SURFACE in res.proposal_edges  # the largest circle on the lawn is bounded by the water
    assert set(res.proposal_edges) <= {SURFACE, VIEW, PEOPLE}
    # The replay's JSON Lines carry it per proposal (tracks get theirs once born).
    from companion.control.planner import PlannerConfig, ZonePlanner
    from companion.replay.records import frame_record

    rec = frame_record(0, res, ZonePlanner(PlannerConfig()))
    assert [p["edge"] for p in rec["proposals"]] == res.proposal_edges


# ---- drawing ----------------------------------------------------------------------------------

def test_unlandable_ground_is_drawn_apart_from_people() -> None:
    from companion.replay.draw import MAGENTA, RED, overlay_people

    frame = np.full((10, 20, 3), 100, np.uint8)
    people = np.full((10, 20), FREE, np.uint8)
    surface = np.full((10, 20), FREE, np.uint8)
    people[:, :5] = OCCUPIED
    surface[:, 10:] = OCCUPIED
    surface[:, 3] = OCCUPIED  # a person on the water stays red
    out = overlay_people(frame, np.minimum(people, surface), surface_free=surface, people_free=people)
    assert out[0, 1, 2] > out[0, 1, 0] and out[0, 3, 2] > out[0, 3, 0]       # red
    assert out[0, 15, 0] > 100 and out[0, 15, 2] > 100 and out[0, 15, 1] < 100  # magenta
    assert (out[:, 6:10] == 100).all()                                        # free: untouched
    assert RED != MAGENTA
    # Without the landability model: people red, as before.
    plain = overlay_people(frame, people)
    assert np.array_equal(plain[:, :5], out[:, :5]) and (plain[:, 5:] == 100).all()


# ---- training ---------------------------------------------------------------------------------

def test_training_runs_a_few_steps_and_exports_a_loadable_model(tmp_path: Path, shared_dir: Path) -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    out = tmp_path / "l.onnx"
    rc = T.main(["--shared", str(shared_dir), "--out", str(out), "--steps", "3", "--batch", "2",
                 "--crop", "64", "--max-images", "9", "--level-weight", "obstacles=3"])
    assert rc == 0 and out.is_file() and out.stat().st_size < 1_000_000
    import onnx
    note = {p.key: p.value for p in onnx.load(str(out)).metadata_props}["companion.training"]
    assert "level_weights=1,3,3,3,1.5,3,1 " in note  # the change is recorded with the model
    m = LandabilityModel(out, threads=1)
    assert m.landability.names == tuple(lv.name for lv in T.LEVELS)
    assert m.landability.threshold in T.THRESHOLDS
    assert m(np.zeros((64, 64, 3), np.uint8)).shape == (7, 8, 8)
    assert T.main(["--shared", str(shared_dir), "--out", str(out), "--crop", "60"]) == 2
    assert T.main(["--shared", str(shared_dir), "--out", str(out), "--device", "cuda:99"]) == 2
    for bad in (["--width", "0"], ["--workers", "-1"], ["--seconds", "-1"], ["--seconds", "nan"],
                ["--level-weight", "roofs=3"], ["--level-weight", "obstacles=0"]):
        assert T.main(["--shared", str(shared_dir), "--out", str(out), *bad]) == 2, bad


def test_level_weights_take_changes_by_name_and_refuse_bad_ones() -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    assert T.weights_with([]) == T.LEVEL_WEIGHTS
    changed = T.weights_with(["obstacles=4", "water=5.5"])
    names = [lv.name for lv in T.LEVELS]
    assert changed[names.index("obstacles")] == 4.0 and changed[names.index("water")] == 5.5
    assert [w for n, w in zip(names, changed) if n not in ("obstacles", "water")] == \
        [w for n, w in zip(names, T.LEVEL_WEIGHTS) if n not in ("obstacles", "water")]
    for bad, words in (("roof=2", "LEVEL one of"), ("obstacles", "LEVEL one of"), ("obstacles=-1", "positive"),
                       ("obstacles=inf", "positive"), ("obstacles=x", "positive")):
        with pytest.raises(ValueError, match=words):
            T.weights_with([bad])


def test_false_landable_cells_are_the_unlandable_cells_the_network_leaves_landable() -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    names = [lv.name for lv in T.LEVELS]
    land, roof = names.index("landable"), names.index("obstacles")
    levels = np.full((20, 24), land, np.uint8)  # 3 x 3 cells of 8 px (the last row padded)
    levels[0:8, 8:16] = roof  # cell (0, 1): a roof
    levels[8:16, 16:24] = roof  # cell (1, 2): a roof
    levels[8:12, 0:8] = roof  # cell (1, 0): half roof, half grass: not mostly unlandable
    probs = np.zeros((len(names), 3, 3), np.float32)
    probs[land] = 1.0  # called landable everywhere...
    probs[land, 1, 2], probs[roof, 1, 2] = 0.2, 0.8  # ...but the second roof, seen for what it is
    cells = T.mistaken_cells(probs, levels, threshold=0.3)
    assert cells.tolist() == [[12.0, 4.0]]  # the centre (x, y) of the one roof called landable
    # The other way: grass called unlandable (cell (2, 0)), and none of the roofs.
    probs[land, 2, 0], probs[roof, 2, 0] = 0.5, 0.5
    assert T.mistaken_cells(probs, levels, threshold=0.3, kind=1).tolist() == [[4.0, 20.0]]
    # Mixed kinds are drawn half and half, however many of each there are.
    mixed = T.HardCells(np.zeros(10, np.int64), np.zeros((10, 2)), np.array([0] * 9 + [1]))
    draws = [mixed.draw(np.random.default_rng(k)) for k in range(200)]
    assert 60 < sum(d == 9 for d in draws) < 140
    # A larger photo with one 16 x 16 px roof the network calls landable: crops centred on its
    # cells see it in their middle far more often than random crops do.
    big = np.full((96, 96), land, np.uint8)
    big[0:16, 16:32] = roof
    p_big = np.zeros((len(names), 12, 12), np.float32)
    p_big[land] = 1.0
    hard = T.HardCells(np.zeros(4, np.int64), T.mistaken_cells(p_big, big, threshold=0.3))
    assert len(hard) == 4
    photos = T.Photos(["a"], [np.zeros((96, 96, 3), np.uint8)], [big])
    _, y_hard = T.make_batch(photos, 32, 32, np.random.default_rng(0), hard, hard_share=1.0)
    _, y_rand = T.make_batch(photos, 32, 32, np.random.default_rng(0))
    mid_hard, mid_rand = float(y_hard[:, roof, 1:3, 1:3].mean()), float(y_rand[:, roof, 1:3, 1:3].mean())
    assert mid_hard > 0.3 and mid_hard > 5 * mid_rand, (mid_hard, mid_rand)
    # Without hard mining the batches are the shipped recipe's, draw for draw.
    a = T.make_batch(photos, 3, 32, np.random.default_rng(5))
    b = T.make_batch(photos, 3, 32, np.random.default_rng(5), hard, hard_share=0.0)
    assert all(torch_equal(u, v) for u, v in zip(a, b))


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))


def test_training_with_hard_mining_runs_records_it_and_refuses_bad_settings(tmp_path: Path, shared_dir: Path) -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    out = tmp_path / "h.onnx"
    rc = T.main(["--shared", str(shared_dir), "--out", str(out), "--steps", "4", "--batch", "2", "--crop", "64",
                 "--max-images", "9", "--hard-share", "0.5", "--mine-every", "2"])
    assert rc == 0
    import onnxruntime as ort
    meta = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    assert "hard_share=0.5 mine=false-landable mine_every=2 mine_threshold=0.3 " in meta["companion.training"]
    assert T.main(["--shared", str(shared_dir), "--out", str(out), "--steps", "3", "--batch", "2", "--crop", "64",
                   "--max-images", "9", "--hard-share", "0.5", "--mine-every", "2", "--mine", "both"]) == 0
    for bad in (["--hard-share", "1.5"], ["--hard-share", "0.5", "--workers", "1"], ["--mine-every", "0"],
                ["--mine-threshold", "0"], ["--mine-threshold", "1"]):
        assert T.main(["--shared", str(shared_dir), "--out", str(out), *bad]) == 2, bad


def test_training_by_time_with_worker_processes_and_another_width(tmp_path: Path, shared_dir: Path) -> None:
    """The GPU form of the command (``--seconds``, ``--workers``, ``--width``) on the CPU: crops
    made in a worker process, stopped by the clock, the width and the run written into the file."""
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    out = tmp_path / "w.onnx"
    rc = T.main(["--shared", str(shared_dir), "--out", str(out), "--seconds", "2", "--workers", "1",
                 "--width", "8", "--batch", "2", "--crop", "64", "--max-images", "9"])
    assert rc == 0
    m = LandabilityModel(out, threads=1)
    assert m(np.zeros((64, 64, 3), np.uint8)).shape == (7, 8, 8)
    import onnxruntime as ort
    meta = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    assert "width=8 workers=1 seconds=2" in meta["companion.training"]
    assert int(meta["companion.parameters"]) < 39015  # narrower than the default width 32


def test_the_grouping_covers_every_class_once(shared_dir: Path) -> None:
    from companion.evaluation import datasets as D
    from companion.evaluation.landability import level_lut
    from companion.pipeline.landability import RiskLevel

    pytest.importorskip("torch", reason="the grouping lives in the training module (the 'train' extra)")
    from companion.training.landability import LEVELS as SHIPPED

    classes = D.semantic_classes(shared_dir)
    lut = level_lut(SHIPPED, classes)
    assert sorted(set(lut[list(classes.values())])) == list(range(len(SHIPPED)))
    with pytest.raises(ValueError, match="in no level"):
        level_lut(SHIPPED[:-1], classes)
    with pytest.raises(ValueError, match="'lava'"):
        level_lut((*SHIPPED, RiskLevel("lava", ("lava",))), classes)


def test_replay_with_the_landability_model_records_edges_in_the_zone_scope_and_the_model(tmp_path: Path, model_path: Path) -> None:
    from companion.cli import main

    frames = tmp_path / "frames"
    frames.mkdir()
    for k, frame in enumerate(_crowd_frames(3)):
        cv2.imwrite(str(frames / f"{k:03d}.png"), frame)
    out = tmp_path / "r.jsonl"
    summary = tmp_path / "s.json"
    args = ["replay", str(frames), "--fps", "5", "--nadir", "--gsd", "0.05", "--threads", "1",
            "--jsonl", str(out), "--summary-json", str(summary)]
    assert main([*args, "--set", "pipeline.unlandable_scope=zone"]) == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    edges = [p["edge"] for r in recs for p in r["proposals"]]
    assert len(recs) == 3 and edges and set(edges) <= {PEOPLE, SURFACE, VIEW}
    assert json.loads(summary.read_text())["landability_model"] == str(LANDABILITY)
    # The default: the model on, in the landing-point scope: people and the view bound a zone,
    # so no edge is judged.
    assert main(args) == 0
    assert json.loads(summary.read_text())["landability_model"] == str(LANDABILITY)
    assert all(p["edge"] is None for line in out.read_text().splitlines() for p in json.loads(line)["proposals"])
    # Off: no model, and no edges judged.
    assert main([*args, "--set", "model.landability=false"]) == 0
    assert json.loads(summary.read_text())["landability_model"] is None
    assert all(p["edge"] is None for line in out.read_text().splitlines() for p in json.loads(line)["proposals"])
    bad = ["--set", f"model.landability_path={tmp_path / 'nope.onnx'}"]
    assert main([*args, *bad]) == 2


def test_a_second_context_branch_trains_exports_and_runs(tmp_path: Path, shared_dir: Path) -> None:
    """``--context 2`` (a second context branch at stride 32) trains a few steps, exports a model
    the runner loads at any frame size a multiple of 8, and says so in its training note; the
    default network is the shipped one, parameter for parameter; anything but 1 or 2 is refused."""
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    assert T.M.count_parameters(T.LandabilityNet()) == 39015  # the default width 32 (the first shipped file)
    assert T.M.count_parameters(T.LandabilityNet(context=2)) > 39015
    with pytest.raises(ValueError, match="context"):
        T.LandabilityNet(context=3)
    out = tmp_path / "c2.onnx"
    rc = T.main(["--shared", str(shared_dir), "--out", str(out), "--steps", "2", "--batch", "2",
                 "--crop", "64", "--max-images", "9", "--context", "2"])
    assert rc == 0
    m = LandabilityModel(out, threads=1)
    for h, w in ((64, 64), (480, 640), (72, 200)):  # not multiples of 32: the branches meet anyway
        probs = m(np.zeros((h, w, 3), np.uint8))
        assert probs.shape == (7, h // 8, w // 8)
        assert np.allclose(probs.sum(axis=0), 1.0, atol=1e-4)
    import onnxruntime as ort
    meta = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    assert "context=2 " in meta["companion.training"]
    with pytest.raises(SystemExit):
        T.main(["--shared", str(shared_dir), "--out", str(out), "--context", "3"])


def test_the_threshold_rule_caps_the_obstacle_pixels_left_landable() -> None:
    """A model that is precise enough at a high threshold but leaves part of a roof landable
    there: the precision alone takes the high threshold; the cap on obstacle pixels (the rule
    since 2026-11-28) takes the one below it, where the roof is unlandable."""
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    names = [lv.name for lv in T.LEVELS]
    land, obst = names.index("landable"), names.index("obstacles")
    h = w = 400
    levels = np.full((h, w), land, np.uint8)
    levels[100:140, 100:140] = obst  # a 40x40 roof, 1 % of the pixels
    unl = np.full((h, w), 0.02, np.float32)
    unl[100:140, 100:140] = 0.9
    unl[100:140, 120:140] = 0.12  # half the roof only weakly unlandable: left landable above 0.12
    probs = np.zeros((len(names), h, w), np.float32)
    probs[land], probs[obst] = 1.0 - unl, unl
    t_prec, curve = T.choose_threshold([probs], [levels], max_left={})
    t_capped, capped = T.choose_threshold([probs], [levels])
    assert t_prec > 0.12 >= t_capped, (t_prec, t_capped)
    at = {round(c["threshold"], 3): c for c in capped}
    assert at[round(t_prec, 3)]["precision"] >= T.LANDABLE_PRECISION
    assert at[round(t_prec, 3)]["left_obstacles"] >= T.MAX_LEFT_LANDABLE["obstacles"]
    assert at[round(t_capped, 3)]["left_obstacles"] == 0.0
    assert "obstacles pixels left landable < 0.43 %" in T.threshold_rule()
    for bad in ({"landable": 0.1}, {"roofs": 0.1}):
        with pytest.raises(ValueError, match="unlandable level"):
            T.choose_threshold([probs], [levels], max_left=bad)


def test_rethreshold_keeps_the_shipped_threshold_and_refuses_other_models(tmp_path: Path, shared_dir: Path,
                                                                          model_path: Path) -> None:
    """``--rethreshold`` applies the current rule to an exported model on the validation photos:
    the shipped file was chosen by that rule, so its threshold stays and the note says so; a
    model of other levels (or not a landability model) is a clear error, exit 2."""
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import landability as T

    out = tmp_path / "re.onnx"
    assert T.main(["--shared", str(shared_dir), "--rethreshold", str(LANDABILITY), "--out", str(out),
                   "--threads", "2"]) == 0
    shipped, again = LandabilityModel(LANDABILITY, threads=1), LandabilityModel(out, threads=1)
    assert again.landability.threshold == shipped.landability.threshold
    import onnxruntime as ort
    meta = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    assert "threshold re-chosen" in meta["companion.training"]
    assert T.main(["--shared", str(shared_dir), "--rethreshold", str(model_path), "--out", str(out)]) == 2
    assert T.main(["--shared", str(shared_dir), "--rethreshold", str(tmp_path / "none.onnx"), "--out", str(out)]) == 2


# ---- the landing-point scope (pipeline.unlandable_scope) ---------------------------------------

def test_in_the_landing_point_scope_unlandable_ground_keeps_the_centre_off_not_the_zone(model_path: Path) -> None:
    """Nobody in view, the west half unlandable (a roof): in the ``zone`` scope every circle keeps
    off the roof; in the ``landing_point`` scope circles may span it but each is centred on the
    landable half, its footprint clear of the roof, and the largest is larger; the roof is drawn."""
    density = DensityModel(model_path, threads=1)
    gsd = 0.05
    proj = PlaneProjection.nadir(gsd)
    frame = np.full((480, 640, 3), 120, np.uint8)

    def roof_west(f: np.ndarray) -> np.ndarray:
        p = np.zeros((f.shape[0] // 8, f.shape[1] // 8), np.float32)
        p[:, : p.shape[1] // 2] = 0.9
        return p

    cfg = PipelineConfig(surface_threshold=0.5)
    zone = SLZPipeline(density, cfg, projection=proj, surface=roof_west).process(frame, 0.0)
    point = SLZPipeline(density, replace(cfg, surface_scope="landing_point"), projection=proj,
                        surface=roof_west).process(frame, 0.0)
    edge = 320 * gsd  # the roof's edge (m east of the frame's west side, as x grows)
    x0 = zone.grid.x0 - zone.grid.cell / 2
    assert zone.proposals and point.proposals
    assert all(c.x - c.r >= x0 + edge - 0.05 - 1e-6 for c in zone.proposals)  # grown marks: a cell's slack
    for c in point.proposals:
        assert c.x - x0 >= edge + 0.5 - 0.1, f"{c} is centred within the footprint of the roof"
    assert point.proposals[0].r > zone.proposals[0].r + 1.0
    assert point.proposal_edges == []  # people and view only bound a zone here: not judged
    # The zones' occupancy is people's alone; the roof is still in the surface map (drawn).
    assert (point.occupancy == FREE).all() and np.array_equal(point.surface, zone.surface)
    assert (point.surface[:, :300] == OCCUPIED).all()
    with pytest.raises(ValueError, match="surface_scope"):
        PipelineConfig(surface_scope="roof")
    with pytest.raises(ValueError, match="footprint_m"):
        PipelineConfig(footprint_m=-0.1)


def test_the_landing_point_is_not_moved_onto_unlandable_ground() -> None:
    """The frame's ground view offers the spot farthest from walkers only where the vehicle may
    touch down (``GroundView.landable``)."""
    from companion.pipeline.riskmap import GroundRiskMap, RiskMapConfig, SpotRequest
    from companion.pipeline.slz import GroundView

    risk = GroundRiskMap(RiskMapConfig())
    cell = risk.config.cell_m
    grid = GridSpec(x0=-10.0, y0=-10.0, cell=cell, rows=int(20 / cell) + 1, cols=int(20 / cell) + 1)
    free = np.full(grid.shape, 255, np.uint8)
    free[:, : grid.shape[1] // 2 - int(3 / cell)] = 0  # people west of x = -3 m
    risk.update(grid, free, np.full(grid.shape, 255, np.uint8), 1.0, (0.0, 0.0))
    request = SpotRequest(0.0, 0.0, 3.0, 30.0, aim=(0.0, 0.0))
    anywhere = GroundView(1.0, risk, risk.stats.updates)
    spot = anywhere.spot(request)
    assert spot is not None and spot.x > 1.0  # away from the people, east
    east_is_water = GroundView(1.0, risk, risk.stats.updates, landable=lambda x, y: x < 0.5)
    assert east_is_water.spot(request) is None  # it stays where it is
    assert GroundView(1.0, risk, risk.stats.updates, landable=lambda x, y: True).spot(request) == spot
