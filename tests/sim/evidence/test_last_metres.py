"""The per-camera physics of the last metres (``python -m sim.evidence.last_metres``)."""

from __future__ import annotations

import pytest

from sim.evidence import last_metres


def _row(rows: list[dict[str, object]], cam: str, speed: float, starts: str) -> list[float]:
    (r,) = [r for r in rows if r["camera"] == cam and r["walk_mps"] == speed and str(r["descent"]).startswith(starts)]
    return list(r["guaranteed_m"])  # type: ignore[call-overload]


def test_only_the_fisheye_guarantees_r0_at_the_simulators_descent() -> None:
    rows = last_metres.table()
    sim_rf = "the simulator's, rangefinder"
    # The 70-degree pinhole sees 0.524 m per metre: however high the landing starts, a walker
    # heading in from beyond the view may be at the point at touchdown.
    assert all(v < 0 for v in _row(rows, "pinhole:70", 1.5, sim_rf))
    assert all(v < 0 for v in _row(rows, "pinhole:110", 1.5, sim_rf))
    # The fisheye's 1.724 outruns a walker from the judging height down (r0 = 2 m and more) ...
    assert all(v > 2.0 for v in _row(rows, "fisheye:160", 1.5, sim_rf))
    # ... but not a runner: the commit rule reads the walking speed (docs/design.md).
    assert all(v < 0 for v in _row(rows, "fisheye:160", 2.4, sim_rf))
    # Guarantees never shrink with a higher start (the best over the heights passed).
    for r in rows:
        g = list(r["guaranteed_m"])  # type: ignore[call-overload]
        assert g == sorted(g)


def test_the_command_prints_a_table_per_speed_and_refuses_a_bad_camera(capsys: pytest.CaptureFixture[str]) -> None:
    assert last_metres.main(["--camera", "pinhole:70", "--camera", "fisheye:160"]) == 0
    out = capsys.readouterr().out
    assert out.count("| descent | pinhole:70 (0.524) | fisheye:160 (1.724) |") == 2
    assert "People at 2.4 m/s" in out
    with pytest.raises(SystemExit) as exc:
        last_metres.main(["--camera", "wide:90"])
    assert exc.value.code == 2
