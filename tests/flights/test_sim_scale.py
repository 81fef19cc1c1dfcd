"""`companion sim-scenarios` at scale (docs/scale.md): node-wide port claims, resumable results
files, starvation flagged rather than counted, exact binomial bounds, and the same verdicts
whether flights run one after another, in worker processes or as Ray tasks.

The unmarked tests fly nothing (fast lane); the `sitl` ones fly the simulator.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from scipy.stats import binomtest

from sim.flights import scenarios
from sim.flights.flight import (
    STARVED_SHARE,
    FlightResult,
    FlightSpec,
    claim_port,
    fly,
    reserve_port,
    starved,
    summarise,
)
from sim.flights.results import (
    ResultsFile,
    binomial_interval,
    further_clean_flights,
    read_rows,
    summarise_rows,
    summary_text,
)
from sim.flights.scenarios import FlightJob, plan, run_jobs
from tests.patched_service import patched_env
from tests.port_holder import reserve_and_hold

# ---- ports -----------------------------------------------------------------------------------


def test_concurrent_reservations_never_get_the_same_port(tmp_path: Path) -> None:
    folder = tmp_path / "ports"
    # Threads of one process (the same pid: O_EXCL alone must tell them apart) ...
    held: list[int] = []
    lock = threading.Lock()
    start = threading.Barrier(16)

    def grab() -> None:
        start.wait()
        ports = [reserve_port(folder=folder).port for _ in range(15)]
        with lock:
            held.extend(ports)

    threads = [threading.Thread(target=grab) for _ in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(held) == 16 * 15 and len(set(held)) == len(held)

    # ... and processes reserving at once, while this one still holds all of the threads' claims.
    # Forked by a fork server that has imported sim.flights.flight once: spawned, each imported it
    # itself (a second each, one after another on two cores) before it could reserve anything.
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["tests.port_holder"])
    barrier, queue = ctx.Barrier(4), ctx.Queue()
    procs = [ctx.Process(target=reserve_and_hold, args=(str(folder), 25, barrier, queue)) for _ in range(4)]
    for p in procs:
        p.start()
    got = [queue.get(timeout=60) for _ in procs]
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    ports = [port for _, ps in got for port in ps]
    assert len(set(ports)) == len(ports) == 100
    assert not set(ports) & set(held)


def test_a_dead_processs_claim_is_taken_over_and_a_live_ones_is_not(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    (tmp_path / "20001").write_text(dead.stdout)
    claim = claim_port(20001, tmp_path)
    assert claim is not None and (tmp_path / "20001").read_text().strip() == str(os.getpid())
    (tmp_path / "20002").write_text(f"{os.getppid()}\n")  # alive
    assert claim_port(20002, tmp_path) is None
    assert claim_port(20001, tmp_path) is None  # ours, held
    claim.release()
    assert not (tmp_path / "20001").exists()
    assert claim_port(20001, tmp_path) is not None


def test_reserved_ports_lie_outside_the_kernels_ephemeral_range(tmp_path: Path) -> None:
    lo = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    with reserve_port(folder=tmp_path) as claim:
        assert claim.port < lo and (tmp_path / str(claim.port)).exists()
    assert not (tmp_path / str(claim.port)).exists()


# ---- bounds and the summary -----------------------------------------------------------------


@pytest.mark.parametrize("k,n", [(0, 300), (3, 100), (0, 1), (5, 5), (1, 1000), (17, 40)])
def test_binomial_bounds_match_scipys_exact_interval(k: int, n: int) -> None:
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
    lo, hi = binomial_interval(k, n)
    assert lo == pytest.approx(ci.low, abs=1e-9) and hi == pytest.approx(ci.high, abs=1e-9)


def test_known_bounds_and_the_flights_still_needed() -> None:
    assert binomial_interval(0, 300)[1] == pytest.approx(0.0122, abs=1e-4)
    assert binomial_interval(0, 0) == (0.0, 1.0)
    # With nothing unsafe, 368 clean flights bring the upper bound under 1 % (1 - 0.025**(1/n)).
    assert further_clean_flights(0, 0) == 368
    assert further_clean_flights(0, 300) == 68 and further_clean_flights(0, 400) == 0
    m = further_clean_flights(3, 100)
    assert binomial_interval(3, 100 + m)[1] < 0.01 <= binomial_interval(3, 100 + m - 1)[1]


def _row(seed: int, outcome: str, *, starved: bool = False, strike: bool = False,
         clearance: float | None = 4.0, flavour: str = "ardupilot") -> dict[str, Any]:
    return {"seed": seed, "flavour": flavour, "world": "free_area", "outcome": outcome, "starved": starved,
            "strike": strike, "clearance_m": clearance, "time_to_touchdown_s": 30.0 + seed,
            "max_climb_m": 0.1 * seed, "processed_fps": 4.0 if starved else 9.5, "altitude_m": 20.0,
            "phases": [], "messages": []}


def test_starved_flights_are_not_clean_results_and_nothing_is_hidden() -> None:
    rows = [_row(1, "safe"), _row(2, "handback", strike=True, clearance=1.5), _row(3, "unsafe", clearance=1.0,
            strike=True), _row(4, "safe", starved=True), _row(5, "unsafe", starved=True, clearance=0.5),
            _row(6, "timeout", clearance=None)]
    s = summarise_rows(rows)
    for key in ("total", "safe", "handbacks", "unsafe", "timeouts", "min_clearance_m",
                "median_time_to_touchdown_s", "max_climb_m", "unsafe_rate_upper95", "strike_rate_upper95",
                "starved"):
        assert key in s
    assert (s["total"], s["safe"], s["handbacks"], s["unsafe"], s["timeouts"], s["starved"]) == (6, 1, 1, 1, 1, 2)
    assert s["total"] == s["safe"] + s["handbacks"] + s["unsafe"] + s["timeouts"] + s["starved"]
    assert s["starved_outcomes"] == {"safe": 1, "unsafe": 1}
    assert s["clean_flights"] == 4 and s["strikes"] == 2 and s["companion_landings"] == 2
    assert s["unsafe_rate_upper95"] == pytest.approx(binomial_interval(1, 4)[1], abs=1e-6)
    assert s["strike_rate_upper95"] == pytest.approx(binomial_interval(2, 4)[1], abs=1e-6)
    assert s["min_clearance_m"] == 0.5  # the starved unsafe landing's clearance is not hidden
    assert s["max_climb_m"] == 0.6
    text = summary_text(s)
    assert "STARVED" in text and "2 flight(s)" in text
    assert "starved" in scenarios.flight_line(rows[3]).lower()


def test_starvation_is_a_rate_below_70_percent_or_frames_over_half_a_period() -> None:
    # Measured (docs/scale.md): alone, 8.8-9.8 Hz at 33-38 ms per frame; two at once on 2 cores,
    # 8.5-9.7 Hz at 82-100 ms; a service slowed to under 4 Hz.
    assert not starved(9.2, 35.0, 10.0) and not starved(8.8, 38.1, 10.0) and not starved(None, None, 10.0)
    assert starved(3.6, 35.0, 10.0) and starved(6.9, None, 10.0)
    assert starved(9.5, 82.0, 10.0) and not starved(9.5, 82.0, 5.0)  # 82 ms is 41 % of a 5 Hz period


def test_summarise_keeps_its_figures_for_flight_results() -> None:
    from sim.flights.flight import FlightResult

    r = FlightResult(FlightSpec(), "safe", touchdown=(0.0, 0.0), clearance_m=1.0, time_to_touchdown_s=20.0,
                     processed_fps=3.0, starved=True)
    assert r.struck and r.as_dict()["strike"] and r.as_dict()["starved"]
    s = summarise([r])
    assert s["starved"] == 1 and s["safe"] == 0 and s["total"] == 1


def test_landings_on_ground_nobody_walks_into_are_counted_apart_from_gaps_in_the_crowd() -> None:
    from sim.flights.flight import FlightResult
    from sim.world.crowd import crowd_with_free_area, dense_crowd
    from sim.world.walkers import Circle as WCircle

    world = crowd_with_free_area(seed=3, free=WCircle(10.0, 20.0, 6.0), half_size=40.0)
    assert world.nobody_walks_at((14.0, 23.0)) is True  # on the lawn
    assert world.nobody_walks_at((17.0, 20.5)) is False  # 7 m from its centre: in the crowd
    assert world.nobody_walks_at((60.0, 0.0)) is True  # beyond the crowd's square
    beyond = dense_crowd(seed=1)
    assert beyond.nobody_walks_at((0.0, 0.0)) is False and beyond.nobody_walks_at((0.0, 45.0)) is True

    def flight(seed: int, outcome: str, on_free: bool | None, world: str = "free_area") -> dict:
        return FlightResult(FlightSpec(seed=seed, world=world), outcome, touchdown=(0.0, 0.0), clearance_m=4.0,
                            in_free_area=on_free).as_dict()

    rows = [flight(1, "safe", True), flight(2, "safe", False), flight(3, "handback", False),
            flight(4, "safe", None, "dronecrowd")]
    assert [r["in_free_area"] for r in rows] == [True, False, False, None]
    s = summarise_rows(rows)
    # Of the three companion landings, two can be judged (the real DroneCrowd motion cannot say),
    # one of them on the lawn; the handback is not a companion landing.
    assert (s["companion_landings"], s["companion_landings_judged_for_area"], s["companion_landings_in_free_area"]) == (3, 2, 1)
    assert "nobody walks into" in summary_text(s) and "1 of 2" in summary_text(s)
    # Rows of older runs (no in_free_area) are left out of both figures, never guessed.
    old = [{k: v for k, v in r.items() if k != "in_free_area"} for r in rows]
    assert summarise_rows(old)["companion_landings_judged_for_area"] == 0
    assert "nobody walks into" not in summary_text(summarise_rows(old))


def test_a_flights_model_threads_follow_the_cpus_it_is_given() -> None:
    # N flights at once never run more onnxruntime threads than the CPUs they were given.
    assert [scenarios.model_threads(c) for c in (0.5, 1.0, 1.9, 2.0, 4.0)] == [1, 1, 1, 2, 4]
    spec = FlightJob(3, "ardupilot", threads=1).spec()
    assert spec.service_set[-1] == "model.threads=1"
    assert FlightJob(3, "ardupilot").spec().service_set == scenarios.scenario(3, "ardupilot").service_set
    # A flight's own model.threads (a test's or a user's override) wins.
    own = FlightJob(3, "ardupilot", (("service_set", ("model.threads=2",)),), threads=1)
    assert own.spec().service_set == ("model.threads=2",)
    # The row says the threads the service flew with, not the ones the job offered.
    assert own.model_threads() == 2 and FlightJob(3, "ardupilot", threads=1).model_threads() == 1
    assert FlightJob(3, "ardupilot", threads=2, service_set=("model.threads=1",)).model_threads() == 1
    assert FlightJob(3, "ardupilot").model_threads() is None


# ---- results files and resuming -------------------------------------------------------------


def test_a_killed_run_resumes_without_flying_its_finished_seeds(tmp_path: Path, monkeypatch, capsys) -> None:
    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append(_row(1, "safe"))
        f.append(_row(2, "handback"))
        f.append(_row(3, "safe", flavour="px4"))  # another autopilot's flight of seed 3: not ours
    with open(out, "a") as f:
        f.write('{"seed": 4, "flavour": "ardu')  # the row being written when the run was killed
    flown: list[int] = []

    def fake(job: FlightJob) -> dict[str, Any]:
        flown.append(job.seed)
        return _row(job.seed, "safe")

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    jobs = [FlightJob(s, "ardupilot") for s in (1, 2, 3, 4)]
    todo, kept = plan(jobs, read_rows(out)[0])
    assert [j.seed for j in todo] == [3, 4] and set(kept) == {(1, "ardupilot"), (2, "ardupilot")}

    rc = run_jobs(jobs, workers=1, out=out, as_json=True)
    assert flown == [3, 4] and rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert [r["seed"] for r in summary["flights"]] == [1, 2, 3, 4]
    assert (summary["total"], summary["safe"], summary["handbacks"]) == (4, 3, 1)
    rows, bad = read_rows(out)
    assert bad == 1 and len(rows) == 5  # the torn line stays unreadable; the new rows are whole

    # Once more: nothing left to fly, the same figures from the file.
    flown.clear()
    assert run_jobs(jobs, workers=1, out=out, as_json=True) == 0 and flown == []
    assert json.loads(capsys.readouterr().out)["total"] == 4


def test_a_flight_that_cannot_fly_is_reported_and_left_to_retry(tmp_path: Path, monkeypatch, capsys) -> None:
    out = tmp_path / "results.jsonl"

    def fake(job: FlightJob) -> dict[str, Any]:
        if job.seed == 2:
            raise RuntimeError("the service did not become ready")
        return _row(job.seed, "safe")

    monkeypatch.setattr(scenarios, "fly_seed", fake)
    rc = run_jobs([FlightJob(1, "ardupilot"), FlightJob(2, "ardupilot")], out=out, as_json=True)
    captured = capsys.readouterr()
    assert rc == 3 and "seed 2: could not fly" in captured.err
    summary = json.loads(captured.out)
    assert summary["could_not_fly"] == [2] and summary["total"] == 1
    assert [r["seed"] for r in read_rows(out)[0]] == [1]


def test_the_machine_check_times_the_flights_own_pipeline_at_the_camera_rate(model_path) -> None:
    # The real model and the flight's settings: a job with one model thread is timed on one.
    check = scenarios.machine_check(FlightJob(3, "ardupilot", threads=1), frames=3)
    assert check.threads == 1 and check.fps == 10.0
    assert check.limit_ms == pytest.approx(50.0)  # sim.flights.flight.starved's limit at 10 Hz
    assert 0 < check.frame_ms_p50 <= check.frame_ms_p95
    assert check.as_dict()["starves"] == (check.frame_ms_p95 > 50.0)
    slow = scenarios.MachineCheck(70.0, 95.0, 50.0, 10.0, 2)
    assert slow.starves and "expect every flight starved" in slow.text(1) and "2 flights at once" in slow.text(2)
    assert "expect" not in scenarios.MachineCheck(25.0, 30.0, 50.0, 10.0, 2).text(1)
    tight = scenarios.MachineCheck(33.0, 45.0, 50.0, 10.0, 2)  # under the limit, by less than flights add
    assert tight.tight and not tight.starves and "expect starved flights" in tight.text(1)
    assert not slow.tight and tight.as_dict()["tight"] is True


def test_a_run_says_before_flying_when_its_machine_would_starve_the_flights(tmp_path: Path, monkeypatch,
                                                                           capsys) -> None:
    checked: list[FlightJob] = []

    def slow_machine(job: FlightJob) -> scenarios.MachineCheck:
        checked.append(job)
        return scenarios.MachineCheck(70.0, 95.0, 50.0, 10.0, 2)

    monkeypatch.setattr(scenarios, "machine_check", slow_machine)
    monkeypatch.setattr(scenarios, "fly_seed", lambda job: _row(job.seed, "safe"))
    jobs = [FlightJob(1, "ardupilot"), FlightJob(2, "ardupilot")]
    assert run_jobs(jobs, out=tmp_path / "r.jsonl", as_json=True, check_machine=True) == 0
    captured = capsys.readouterr()
    assert "expect every flight starved" in captured.err and len(checked) == 1  # once a run, then it flies
    summary = json.loads(captured.out)
    assert summary["machine_check"]["starves"] is True and summary["total"] == 2
    # Nothing left to fly (resumed), or only baselines (no service): no check.
    assert run_jobs(jobs, out=tmp_path / "r.jsonl", as_json=True, check_machine=True) == 0
    assert run_jobs([FlightJob(1, "ardupilot", baseline=True)], as_json=True, check_machine=True) == 0
    assert len(checked) == 1 and "machine_check" not in json.loads(capsys.readouterr().out.splitlines()[-1])


def test_a_model_that_does_not_load_stops_the_run_before_anything_flies(tmp_path: Path, monkeypatch,
                                                                       capsys) -> None:
    bad = tmp_path / "corrupt.onnx"
    bad.write_bytes(b"not an onnx file")
    monkeypatch.setattr(scenarios, "fly_seed", lambda job: pytest.fail("nothing may fly"))
    job = FlightJob(1, "ardupilot", service_set=scenarios.service_settings([f"model.path={bad}"]))
    assert run_jobs([job], as_json=True, check_machine=True) == 2
    assert str(bad) in capsys.readouterr().err


# ---- flights ---------------------------------------------------------------------------------

SLOW = '''\
import time

import companion.pipeline.slz as slz

_process = slz.SLZPipeline.process


def _slow(self, *args, **kwargs):
    time.sleep(0.25)  # a service that cannot keep 10 Hz: at most 4 frames a second
    return _process(self, *args, **kwargs)


slz.SLZPipeline.process = _slow
'''


def _uniform(seed: int) -> FlightJob:
    # Nobody on one-colour ground: a landing under the companion every time (tests/flights/test_sitl.py).
    return FlightJob(seed, "ardupilot", (("world", "uniform"), ("altitude_m", 18.0)))


@pytest.mark.sitl
@pytest.mark.timeout(300)
def test_a_starved_flight_is_flagged(tmp_path: Path, model_path) -> None:
    spec = FlightSpec(flavour="ardupilot", world="uniform", seed=6, altitude_m=18.0,
                      service_set=("controller.max_takeover_s=45",),
                      service_env=patched_env(tmp_path / "site", SLOW))
    r = asyncio.run(fly(spec))
    assert r.processed_fps is not None and r.processed_fps < 4.0, (r.processed_fps, r.log_tail)
    assert r.starved and r.as_dict()["starved"]
    s = summarise([r])
    assert s["starved"] == 1 and s["clean_flights"] == 0 and s["safe"] == 0
    assert STARVED_SHARE * spec.fps > r.processed_fps


@pytest.mark.sitl
@pytest.mark.timeout(300)
def test_a_real_run_resumes_flying_only_what_is_missing(tmp_path: Path, model_path, capsys) -> None:
    out = tmp_path / "results.jsonl"
    with ResultsFile(out) as f:
        f.append({**_row(6, "safe"), "note": "flown before the crash"})
    rc = run_jobs([_uniform(6), _uniform(7)], workers=1, out=out, as_json=True)
    summary = json.loads(capsys.readouterr().out)
    rows = {r["seed"]: r for r in summary["flights"]}
    assert set(rows) == {6, 7} and rows[6]["note"] == "flown before the crash"
    assert summary["run"]["flown"] == 1 and "wall_s" in rows[7] and "note" not in rows[7]
    assert rows[7]["outcome"] == "safe", rows[7]
    # A flight this host starved is an incomplete run (exit 3), not a failed resume: the suite
    # also runs on slow shared machines (test_a_starved_flight_is_flagged is the starvation test).
    assert rc == (3 if rows[7]["starved"] else 0) and len(read_rows(out)[0]) == 2


@pytest.mark.sitl
@pytest.mark.timeout(600)
def test_two_workers_give_the_sequential_verdicts(tmp_path: Path, model_path, capsys) -> None:
    # A landing under the companion (uniform ground: "safe" when flown alone, as in
    # test_sitl.py and test_a_real_run_resumes_flying_only_what_is_missing) and a dense crowd with
    # no free ground anywhere (the companion searches briefly, then hands back to the autopilot's
    # own LAND), flown at once. The sequential verdicts are those two; flying them alone again
    # here would only add two minutes to CI.
    dense = FlightJob(1, "ardupilot", (("world", "dense"), ("service_set", ("controller.search_s=8",))))
    jobs = [_uniform(6), dense]
    out = tmp_path / "w2.jsonl"
    run_jobs(jobs, workers=2, out=out, as_json=True)
    capsys.readouterr()
    rows = read_rows(out)[0]
    assert sorted(r["seed"] for r in rows) == [1, 6]
    verdicts = {r["seed"]: (r["outcome"], r["starved"], r["processed_fps"]) for r in rows}
    assert verdicts[6][0] == "safe" and verdicts[1][0] == "handback", verdicts
    # Both met their world at the same world time (its clock starts when the service is ready),
    # however long each service took to start beside the other.
    assert all(abs(r["world_t_trigger"] - 4.0) <= 0.2 for r in rows), [r["world_t_trigger"] for r in rows]


@pytest.mark.sitl
@pytest.mark.timeout(600)
def test_ray_auto_flies_seeds_as_ray_tasks(tmp_path: Path, model_path) -> None:
    pytest.importorskip("ray", reason="--ray needs the 'scale' extra: pip install '.[scale]'")
    out = tmp_path / "results.jsonl"
    proc = subprocess.run([sys.executable, "-m", "companion", "sim-scenarios", "--seeds", "1,2",
                           "--flavour", "ardupilot", "--ray", "auto", "--out", str(out), "--json",
                           "--no-progress"], capture_output=True, text=True, timeout=560)
    assert proc.returncode in (0, 1, 3), proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert sorted(r["seed"] for r in summary["flights"]) == [1, 2], proc.stderr[-3000:]
    assert summary["run"]["ray"] == "auto" and summary["could_not_fly"] == []
    assert all(r["outcome"] in ("safe", "unsafe", "handback", "timeout") for r in summary["flights"])
    assert len(read_rows(out)[0]) == 2


def _exited(pid: int) -> bool:
    """Whether process ``pid`` has ended: gone, or a zombie (exited, its status not yet collected).
    A killed runner's children become init's, which collects them when it gets round to it (1.4
    to 1.9 s after they exited, on a 2-core CI machine); ``kill(pid, 0)`` succeeds on a zombie,
    so /proc tells."""
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:  # gone since, or no /proc: the next look decides
        return False
    return stat[stat.rindex(")") + 2] in "ZX"


def test_a_killed_runner_leaves_no_service_running(tmp_path):
    # sim-scenarios killed mid-flight used to leave the flight's service running on, its camera
    # gone, eating the CPU of the flights after it. The service now dies with its parent.
    import os
    import signal
    import subprocess
    import sys
    import time

    import companion.parallel
    import sim.flights.flight

    # The flight's service is started with sim.flights.flight's die_with_parent, which is this one:
    # imported from companion.parallel, the parent does not spend a second importing sim.flights.flight.
    assert sim.flights.flight.die_with_parent is companion.parallel.die_with_parent
    code = ("import subprocess, sys, time\n"
            "from companion.parallel import die_with_parent\n"
            "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], preexec_fn=die_with_parent)\n"
            "print(p.pid, flush=True)\n"
            "time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    os.kill(child, 0)  # running
    parent.send_signal(signal.SIGKILL)  # no clean-up can run in the parent
    parent.wait(timeout=10)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        if _exited(child):  # it was the parent's, not ours: the init process reaps it
            break
        time.sleep(0.01)
    else:
        os.kill(child, signal.SIGKILL)
        raise AssertionError("the child outlived its parent")


def test_a_killed_runner_leaves_no_worker_flying(tmp_path):
    # A --workers N run killed outright used to leave its pool's workers flying the seeds they
    # held to the end (services and all). They now die with the runner.
    import os
    import signal
    import subprocess
    import sys
    import time

    code = ("import multiprocessing, threading, time\n"
            "from companion.parallel import fan_out\n"
            "threading.Thread(target=lambda: list(fan_out(time.sleep, [60, 60], workers=2)), daemon=True).start()\n"
            "while len(multiprocessing.active_children()) < 2: time.sleep(0.01)\n"
            "print(' '.join(str(p.pid) for p in multiprocessing.active_children()), flush=True)\n"
            "time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    workers = [int(p) for p in parent.stdout.readline().split()]
    assert len(workers) == 2

    def in_task(pid: int) -> bool:  # in time.sleep, its task: its initializer has run
        try:
            return "nanosleep" in Path(f"/proc/{pid}/wchan").read_text()
        except OSError:
            return False

    # Until both workers are in their task (where the kernel does not tell, 10 s: more than the
    # second that was once waited blindly for the initializers).
    started = time.monotonic()
    while not all(in_task(pid) for pid in workers) and time.monotonic() - started < 10:
        time.sleep(0.01)
    for pid in workers:
        os.kill(pid, 0)  # running
    parent.send_signal(signal.SIGKILL)
    parent.wait(timeout=10)
    deadline = time.monotonic() + 10
    alive = set(workers)
    while alive and time.monotonic() < deadline:
        alive = {pid for pid in alive if not _exited(pid)}
        time.sleep(0.01)
    for pid in alive:
        os.kill(pid, signal.SIGKILL)
    assert not alive, "a worker outlived the runner"


def test_zones_given_up_over_them_are_judged_on_the_truth_under_the_vehicle() -> None:
    from sim.flights.flight import FlightResult, zone_losses

    truth = [(9.9, 5.0), (10.0, 1.5), (10.1, 4.0), (20.0, 3.5)]  # (monotonic s, nearest person m)
    events = [
        {"t": 5.0, "event": "hold", "old": "APPROACH", "lost_zone_id": 1, "reason": "no longer tracked"},
        {"t": 9.0, "event": "hold", "old": "DESCEND", "lost_zone_id": 2, "reason": "early"},
        {"t": 10.05, "event": "hold", "old": "DESCEND", "lost_zone_id": 3,
         "reason": "1.9 m free around the vehicle < r0 2 m"},
        {"t": 12.0, "event": "phase", "old": "HOLD", "phase": "APPROACH", "zone_id": 4},
        {"t": 20.5, "event": "target", "old": "LAND", "phase": "APPROACH", "lost_zone_id": 4, "zone_id": 5,
         "text": "SLZ: zone 4 lost (shrank to r 1.9 m < r0 2 m); re-targeting zone 5, 3.0 m away, radius 4.1 m"},
    ]
    losses = zone_losses(events, truth)
    # Lost on the approach (not over the zone) is left out; before any truth sample, nobody is
    # known to be near (inf, never a guess); otherwise the latest sample at or before the loss.
    assert [(z.zone_id, z.nearest_m) for z in losses] == [(2, float("inf")), (3, 1.5), (4, 3.5)]
    assert losses[2].reason == "shrank to r 1.9 m < r0 2 m"
    row = FlightResult(FlightSpec(seed=1), "safe", touchdown=(0.0, 0.0), clearance_m=4.0,
                       zone_losses=losses).as_dict()
    assert (row["zone_losses"], row["zone_losses_r0_free"], row["zone_loss_nearest_m"]) == (3, 2, [None, 1.5, 3.5])
    assert "zones lost over them 3 (2 with r0 free)" in scenarios.flight_line({**row, "altitude_m": 20.0})
    s = summarise_rows([row, {**row, "seed": 2, "starved": True}])
    assert (s["zone_losses"], s["zone_losses_r0_free"]) == (3, 2)  # the starved flight is not counted
    assert "zones given up while over them: 3, of which 2 with nobody within r_0" in summary_text(s)
    # Rows of older runs say nothing about losses: None, and no line, never a zero.
    old = {k: v for k, v in row.items() if not k.startswith("zone_loss")}
    assert summarise_rows([old])["zone_losses"] is None
    assert "given up" not in summary_text(summarise_rows([old]))


def test_the_last_metres_are_measured_on_the_truth_and_summarised_over_clean_companion_landings():
    row = FlightResult(FlightSpec(seed=1), "safe", touchdown=(0.0, 0.0), clearance_m=4.0,
                       last_metres_s=2.345).as_dict()
    assert row["last_metres_s"] == 2.35
    rows = [row, {**row, "seed": 2, "last_metres_s": 3.1}, {**row, "seed": 3, "last_metres_s": 9.0, "starved": True},
            {**row, "seed": 4, "outcome": "handback", "last_metres_s": 7.0}]
    s = summarise_rows(rows)
    # The starved flight and the autopilot's landing after a handback are not the companion's.
    assert s["median_last_metres_s"] == round((2.35 + 3.1) / 2, 2)
    assert "a median 2.73 s over their last 3.5 m" in summary_text(s)
    old = {k: v for k, v in row.items() if k != "last_metres_s"}
    assert summarise_rows([old])["median_last_metres_s"] is None
    assert "last 3.5 m" not in summary_text(summarise_rows([old]))
    assert FlightResult(FlightSpec(seed=1), "timeout").as_dict()["last_metres_s"] is None
