"""`companion sim-compare`: two results files paired seed by seed, with exact tests (sim/evidence/compare.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from scipy.stats import binomtest, wilcoxon

from sim.evidence.compare import MIN_DISCORDANT, CompareError, compare, comparison_text, main, mcnemar_p


def _row(seed: int, outcome: str, *, flavour: str = "px4", t: float = 30.0, phases: int = 5,
         starved: bool = False, strike: bool = False, free: bool | None = True, losses: int | None = None,
         settings: list[str] | None = None, baseline: bool = False) -> dict[str, Any]:
    row: dict[str, Any] = {"seed": seed, "flavour": flavour, "world": "free_area", "outcome": outcome,
                           "clearance_m": 1.0 if outcome == "unsafe" else 4.0, "time_to_touchdown_s": t,
                           "phases": ["SELECT"] * phases, "starved": starved, "strike": strike,
                           "in_free_area": free, "settings": settings or [], "baseline": baseline,
                           "frame_ms_p95": 55.0 if starved else 40.0 + seed % 3}
    if losses is not None:
        row["zone_losses"] = losses
    return row


def test_the_mcnemar_test_is_scipys_exact_binomial_test_of_the_discordant_pairs() -> None:
    for b, c in ((0, 6), (1, 9), (3, 3), (7, 2)):
        assert mcnemar_p(b, c) == pytest.approx(binomtest(min(b, c), b + c, 0.5).pvalue)
    assert mcnemar_p(0, 0) == 1.0
    # 0 against 5 is still chance at 0.05 (p = 0.0625); 0 against 6 is not.
    assert MIN_DISCORDANT == 6 and mcnemar_p(0, 5) > 0.05 > mcnemar_p(0, 6)


def test_pairs_are_compared_seed_by_seed_and_starved_or_unpaired_flights_are_left_out() -> None:
    before = [_row(s, "handback", t=100.0, phases=20, free=None) for s in range(1, 9)]
    before += [_row(20, "safe"), _row(21, "safe", flavour="ardupilot"), _row(30, "safe"),
               _row(1, "handback", baseline=True)]  # a baseline row never pairs
    after = [_row(s, "safe", t=40.0 + s, phases=9, settings=["controller.x=1"]) for s in range(1, 8)]
    after += [_row(8, "unsafe", t=50.0, phases=9, strike=True, free=False, settings=["controller.x=1"]),
              _row(20, "safe", starved=True), _row(21, "safe", flavour="ardupilot"), _row(40, "safe")]
    c = compare(before, after)
    # Seeds 1-8 and 21 pair; 20 is starved on one side; 30 and 40 were flown in one file only.
    assert c.pairs == 9 and c.starved_left_out == 1
    assert c.only_before == [(30, "px4")] and c.only_after == [(40, "px4")]
    assert c.settings_after == [[], ["controller.x=1"]]
    got = {b.name: b for b in c.binary}
    hb = got["handback"]
    assert (hb.before, hb.after, hb.only_before, hb.only_after) == (8, 0, 8, 0)
    assert hb.p == pytest.approx(binomtest(0, 8, 0.5).pvalue, abs=1e-4) and hb.p < 0.05
    unsafe = got["unsafe landing"]
    assert (unsafe.only_before, unsafe.only_after, unsafe.p) == (0, 1, 1.0)
    # Ground nobody walks into: asked only of the landings that say (a handback is not one).
    free = got["companion landing on ground nobody walks into"]
    assert (free.before, free.after, free.pairs) == (1, 8, 9)
    assert [(p.seed, p.before, p.after) for p in c.changed][-1] == (8, "handback 4.0 m", "unsafe 1.0 m")
    # Touchdowns on unlandable ground: rows without the judge's surfaces (older runs) say nothing.
    assert got["touchdown on a tree, bench, car or roof (whoever landed)"].pairs == 0
    on = compare([{**_row(1, "safe"), "unlandable_touchdown": False}, {**_row(2, "safe"), "unlandable_touchdown": True}],
                 [{**_row(1, "safe"), "unlandable_touchdown": True}, {**_row(2, "safe"), "unlandable_touchdown": True}])
    tree = next(b for b in on.binary if b.name.startswith("touchdown on a tree"))
    assert (tree.pairs, tree.before, tree.after, tree.only_before, tree.only_after) == (2, 1, 2, 0, 1)
    phases = next(n for n in c.numeric if n.name == "phase changes")
    xs, ys = [20.0] * 8 + [5.0], [9.0] * 8 + [5.0]
    assert (phases.pairs, phases.before_median, phases.after_median, phases.median_difference) == (9, 20.0, 9.0, -11.0)
    assert phases.p == pytest.approx(wilcoxon(xs, ys).pvalue, abs=1e-4)
    # Time to touchdown only where both landed: the handbacks leave one pair (seed 21).
    time = next(n for n in c.numeric if n.name.startswith("time"))
    assert time.pairs == 1 and time.p is None
    assert next(n for n in c.numeric if n.name.startswith("zones")).pairs == 0
    # The share of pairs whose verdict changed, with scipy's exact interval: 8 of 9 here.
    assert c.verdicts_changed_rate == round(8 / 9, 4)
    assert c.verdicts_changed_ci95 == [round(v, 4) for v in binomtest(8, 9).proportion_ci(method="exact")]
    text = comparison_text(c)
    assert "verdicts changed in 8 of 9 pairs" in text
    assert "9 pairs" in text and "handback" in text and "beyond chance at the 0.05 level (*)" in text
    # --starved takes the starved pair too, and then says which were starved.
    loaded = compare(before, after, include_starved=True)
    assert loaded.pairs == 10
    assert next(b for b in loaded.binary if b.name.startswith("starved")).only_after == 1
    assert next(b for b in c.binary if b.name.startswith("starved")).after == 0
    p95 = next(n for n in loaded.numeric if n.name.startswith("service frame time"))
    assert p95.pairs == 10 and p95.median_difference == 0.0
    # Nothing clean: said so, not a table of zeros.
    starved = compare([_row(1, "safe", starved=True)], [_row(1, "safe")])
    assert starved.pairs == 0 and "no pair is clean" in comparison_text(starved)


def test_no_difference_is_called_chance_and_never_sameness() -> None:
    rows = [_row(s, "safe") for s in range(1, 6)]
    c = compare(rows, [{**r, "outcome": "unsafe" if r["seed"] == 1 else "safe"} for r in rows])
    assert c.beyond_chance == []
    assert "does not make them the same" in comparison_text(c) and f"at least {MIN_DISCORDANT}" in comparison_text(c)


def test_files_that_cannot_be_paired_are_refused() -> None:
    with pytest.raises(CompareError, match="two rows of seed 1"):
        compare([_row(1, "safe"), _row(1, "safe", settings=["a=1"])], [_row(1, "safe")])
    with pytest.raises(CompareError, match="no seed"):
        compare([_row(1, "safe")], [_row(2, "safe")])


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", "sim-compare", *args],
                          capture_output=True, text=True, timeout=60)


def test_the_command_compares_two_results_files_and_refuses_bad_ones(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    a, b, dup = tmp_path / "a.jsonl", tmp_path / "b.jsonl", tmp_path / "dup.jsonl"
    a.write_text("".join(json.dumps(_row(s, "handback", free=None)) + "\n" for s in range(1, 7)) + "{torn\n")
    b.write_text("".join(json.dumps(_row(s, "safe")) + "\n" for s in range(1, 7)))
    dup.write_text(json.dumps(_row(1, "safe")) + "\n" + json.dumps(_row(1, "safe", settings=["x=1"])) + "\n")
    done = _cli(str(a), str(b))
    assert done.returncode == 0, done.stderr
    assert "6 pairs" in done.stdout and "1 unreadable line" in done.stderr
    # The rest in this process (the entry point is proven above; each interpreter costs a second).
    assert main([str(a), str(b), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["pairs"] == 6 and "handback" in data["beyond_chance"]
    assert main([str(a), str(tmp_path / "missing.jsonl")]) == 2
    assert main([str(dup), str(b)]) == 2 and "two rows of seed 1" in capsys.readouterr().err


def test_the_settings_line_names_a_land_speed_other_than_the_scenarios() -> None:
    # `sim-scenarios --land-speed` rows pair with the scenarios' own by seed, and say what differs.
    before = [{**_row(s, "safe"), "land_speed": 1.0} for s in (1, 2)]
    after = [{**_row(1, "safe"), "land_speed": 0.5}, {**_row(2, "safe", settings=["controller.x=1"]), "land_speed": 0.5}]
    c = compare(before, after)
    assert c.pairs == 2 and c.settings_before == [[]]
    assert c.settings_after == [["controller.x=1", "land_speed=0.5"], ["land_speed=0.5"]]
    assert "AFTER [['controller.x=1', 'land_speed=0.5'], ['land_speed=0.5']]" in comparison_text(c)
    # `--crossing-window` likewise: named when it is not the world's own 4-24 s.
    wide = [{**_row(s, "safe"), "land_speed": 0.5, "crossing_window": [4.0, 84.0]} for s in (1, 2)]
    own = [{**_row(s, "safe"), "crossing_window": [4.0, 24.0]} for s in (1, 2)]
    c = compare(own, wide)
    assert c.settings_before == [[]] and c.settings_after == [["land_speed=0.5", "crossing_window=4-84"]]
    # A longer watch before the failsafe (--watch-s) is named; the scenarios' own is not.
    watched = [{**_row(s, "safe"), "watch_s": 30.0} for s in (1, 2)]
    c = compare(before, watched)
    assert c.pairs == 2 and c.settings_after == [["watch_s=30"]]
    assert compare(before, [{**_row(s, "safe"), "watch_s": 4.0} for s in (1, 2)]).settings_after == [[]]
    # Link latency added each way (--link-latency) is named: the same seeds with and without it pair.
    lagged = [{**_row(s, "safe"), "link_latency_s": 0.2} for s in (1, 2)]
    c = compare(before, lagged)
    assert c.pairs == 2 and c.settings_after == [["link_latency_s=0.2"]]


def test_the_last_metres_are_paired_where_both_rows_carry_them() -> None:
    """``last_metres_s`` (the truth's time over the last 3.5 m, whoever landed) is compared pair by
    pair, like the time to touchdown; rows of older runs, which lack it, pair nothing."""
    before = [{**_row(s, "safe"), "last_metres_s": 4.4 + 0.1 * s} for s in range(1, 8)]
    after = [{**_row(s, "safe"), "last_metres_s": 2.2 + 0.1 * s} for s in range(1, 8)]
    last = next(n for n in compare(before, after).numeric if n.name.startswith("time over the last 3.5 m"))
    assert (last.pairs, last.before_median, last.after_median) == (7, pytest.approx(4.8), pytest.approx(2.6))
    assert last.median_difference == pytest.approx(-2.2)
    assert last.p == pytest.approx(wilcoxon([4.4 + 0.1 * s for s in range(1, 8)],
                                            [2.2 + 0.1 * s for s in range(1, 8)]).pvalue, abs=1e-4)
    old = [_row(s, "safe") for s in range(1, 8)]
    assert next(n for n in compare(old, after).numeric if n.name.startswith("time over the last")).pairs == 0


def test_lockstep_files_are_named_and_need_the_clock_start_yardstick() -> None:
    # `sim-scenarios --lockstep` rows pair with real-time ones by seed; the settings line says
    # which side flew on the simulated clock and from where its clock started. Two lockstep sides
    # still need a yardstick: a change also changes how a flight's times round.
    real = [_row(s, "safe") for s in (1, 2, 3)]
    lock = [{**_row(s, "safe" if s != 2 else "handback"), "lockstep": True, "clock_start_s": 1000.0}
            for s in (1, 2, 3)]
    c = compare(real, lock)
    assert c.pairs == 3 and not c.lockstep and not c.clock_only and c.settings_after == [["lockstep"]]
    assert "compare with theirs" in comparison_text(c)
    setting = [{**r, "outcome": "safe", "settings": ["controller.min_calm_s=3"]} for r in lock]
    c = compare(lock, setting)
    assert c.lockstep and not c.clock_only and len(c.changed) == 1 and c.settings_before == [["lockstep"]]
    text = comparison_text(c)
    assert "both flown in lockstep" in text and "--clock-start" in text and "yardstick" not in text
    # The same settings from another clock start: the comparison is the yardstick, and says so.
    moved = [{**r, "outcome": "safe", "clock_start_s": 2000.0} for r in lock]
    c = compare(lock, moved)
    assert c.lockstep and c.clock_only and c.settings_after == [["clock_start_s=2000", "lockstep"]]
    assert "this is the yardstick" in comparison_text(c)
    # Lockstep rows written before the start was fixed started on the machine's uptime.
    old = [{k: v for k, v in r.items() if k != "clock_start_s"} for r in lock]
    c = compare(old, lock)
    assert c.clock_only and c.settings_before == [["clock_start_s=unknown", "lockstep"]]


def test_the_software_that_flew_each_side_is_named_where_it_differs() -> None:
    # Another numpy or onnxruntime rounds differently, which changes verdicts as another clock
    # start does: a comparison says when its two sides were not flown by the same software.
    sw = {"python": "3.11.7", "numpy": "2.4.6", "onnxruntime": "1.32.0", "git": "abc"}
    before = [{**_row(s, "safe"), "software": sw} for s in (1, 2)]
    same = compare(before, [{**r} for r in before])
    assert same.software_before == same.software_after == [sw]
    assert "software differs" not in comparison_text(same)
    after = [{**_row(s, "safe"), "software": {**sw, "onnxruntime": "1.33.0", "git": "def"}} for s in (1, 2)]
    text = comparison_text(compare(before, after))
    assert "software differs" in text and "onnxruntime 1.32.0 -> 1.33.0" in text and "git abc -> def" in text
    assert "numpy" not in text.split("software differs")[1].split("\n")[0]
    # Rows written before they said which software flew them: nothing to say.
    assert "software differs" not in comparison_text(compare([_row(s, "safe") for s in (1, 2)], after))


def test_rows_are_compared_whole_but_for_what_the_host_sets(tmp_path: Path) -> None:
    """A restructuring is proven by rows equal in every field but the host's: frame times, wall
    time and software may differ, a message may not, and baseline rows count too."""
    def row(seed: int, baseline: bool = False, **extra: Any) -> dict[str, Any]:
        base = {"seed": seed, "flavour": "px4", "world": "crossing", "outcome": "safe", "clearance_m": 5.0,
                "baseline": baseline, "lockstep": True, "messages": ["SLZ: a"], "wall_s": 40.0,
                "frame_ms_p95": 50.0, "software": {"git": "a"}}
        return {**base, **extra}
    before = [row(1), row(2), row(1, baseline=True)]
    after = [row(1, wall_s=90.0, frame_ms_p95=110.0, software={"git": "b"}), row(2, messages=["SLZ: b"]),
             row(1, baseline=True, host="other")]
    same = compare(before, after).identity
    assert (same.pairs, same.identical, same.fields) == (3, 2, {"messages": 1})
    assert "2 of 3" in comparison_text(compare(before, after)) and "messages in 1" in comparison_text(
        compare(before, after))
    # Files of baseline rows alone: no companion pair, still whether the flights are the same.
    b, a = tmp_path / "b.jsonl", tmp_path / "a.jsonl"
    b.write_text(json.dumps(row(1, baseline=True)) + "\n")
    a.write_text(json.dumps(row(1, baseline=True, clearance_m=4.0)) + "\n")
    assert main([str(b), str(a)]) == 0
    a.write_text(json.dumps(row(3, baseline=True)) + "\n")
    assert main([str(b), str(a)]) == 2  # nothing in common: refused as before
