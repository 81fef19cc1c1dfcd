"""Issue 59's first target on the photo world: no touchdown on unlandable ground. The people-only
pipeline proposes an empty roof as a landing zone (the companion landed on three in session 33's
yardstick); with the defaults (the landability model in the landing-point scope) no zone is
centred on it. Real parts: the photo world's ground, the shipped models, the service's settings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from companion import config as settings
from companion.geometry.camera import Intrinsics, Mount, Pose
from companion.service.parts import build_pipeline, load_landability, load_model
from sim.evidence.false_positives import _landable_at
from sim.flights.flight import photo_ground
from sim.world.crowd import World
from sim.world.render import render_world

YARDSTICK = Path(__file__).resolve().parents[3] / "docs" / "yardstick"


def _roof_touchdowns() -> list[tuple[int, float, float]]:
    """(seed, north, east) of session 33's PX4 companion touchdowns on roofs (its photo rows)."""
    rows = map(json.loads, (YARDSTICK / "photo-px4-defaults-1000-13-75.jsonl").read_text().splitlines())
    return [(r["seed"], *r["touchdown"]) for r in rows
            if not r["baseline"] and r["outcome"] == "safe" and r["touchdown_surfaces"] == ["roof"]]


def test_an_empty_roof_is_a_zone_for_people_alone_and_none_by_default(photos) -> None:
    roofs = _roof_touchdowns()
    assert [seed for seed, *_ in roofs] == [22, 27, 39]
    ground = photo_ground(photos)
    K = Intrinsics.from_fov(640, 480, 70.0)
    camera = {"camera.width": 640, "camera.height": 480, "camera.hfov_deg": 70.0}
    for seed, north, east in roofs[:2]:
        centres = {}
        for name, extra in (("people alone", {"model.landability": False}), ("defaults", {})):
            cfg = settings.load(None, {**camera, **extra})
            pipe = build_pipeline(cfg, load_model(cfg), load_landability(cfg))
            result = None
            for k in range(3):  # straight down over the roof from 15 m, nobody walking
                pose = Pose(0.1 * k, north, east, -15.0, 0.0, 0.0, 0.0)
                result = pipe.process(render_world(World(seed=seed), pose, K, Mount(), ground), pose.t, pose)
            assert result is not None
            xy = np.array([[c.x, c.y] for c in result.proposals]).reshape(-1, 2)
            centres[name] = _landable_at(ground, xy) if len(xy) else np.zeros(0, bool)
        assert (~centres["people alone"]).any(), f"seed {seed}: the empty roof is no zone even for people alone"
        assert centres["defaults"].all(), f"seed {seed}: a zone is centred on unlandable ground by default"
