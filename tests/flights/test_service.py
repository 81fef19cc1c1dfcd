"""The service as integrators run it: ``companion run`` in a subprocess, against the simulator
over real MAVLink on loopback, a real MJPEG camera, the real ONNX model and a real NOTIFY_SOCKET.
"""

from __future__ import annotations

import asyncio
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from companion.geometry.camera import Intrinsics, Mount
from companion.recording import RecordingReader

REPO = Path(__file__).resolve().parents[2]
SHIPPED_MODEL = REPO / "companion" / "models" / "slz-density-v4.onnx"
PEER_MODEL = REPO.parent / "shared" / "peers" / "mcnn-shb.onnx"

pytestmark = pytest.mark.sitl


def _model() -> Path:
    """The shipped model (the one integrators run)."""
    if SHIPPED_MODEL.is_file():
        return SHIPPED_MODEL
    if PEER_MODEL.is_file():  # until the trained model is committed
        return PEER_MODEL
    pytest.fail(f"the shipped density model {SHIPPED_MODEL} is missing")


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class NotifySocket:
    """A Unix datagram socket standing in for systemd's notify socket, drained by the event
    loop as soon as a message arrives (as systemd does), each message stamped on arrival."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)
        self.messages: list[tuple[float, str]] = []
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.sock.fileno(), self.drain)

    def drain(self) -> list[tuple[float, str]]:
        while True:
            try:
                data = self.sock.recv(4096)
            except BlockingIOError:
                return self.messages
            self.messages.append((time.monotonic(), data.decode()))

    def lines(self, prefix: str) -> list[str]:
        """Every line received so far that starts with ``prefix`` (e.g. "STATUS="), in order."""
        return [line for _, m in self.drain() for line in m.split("\n") if line.startswith(prefix)]

    def has(self, prefix: str) -> bool:
        return bool(self.lines(prefix))

    def latest(self, prefix: str) -> str | None:
        """The last line that starts with ``prefix``, or None."""
        found = self.lines(prefix)
        return found[-1] if found else None

    def times(self, prefix: str) -> list[float]:
        return [t for t, m in self.drain() if any(line.startswith(prefix) for line in m.split("\n"))]

    def close(self) -> None:
        self._loop.remove_reader(self.sock.fileno())
        self.sock.close()


class Service:
    """``python -m companion run ...`` as a subprocess with its stderr collected."""

    def __init__(self, args: list[str], env: dict[str, str], log: Path) -> None:
        self.log_path = log
        self._log = open(log, "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "companion", "--log-level", "DEBUG", "run", *args],
                                     env=env, stdout=self._log, stderr=subprocess.STDOUT, cwd=str(REPO))

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        self._log.close()


async def _until(pred, timeout: float, what: str, svc: Service | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if svc is not None and svc.proc.poll() is not None:
            raise AssertionError(f"service exited with {svc.proc.returncode} while waiting for {what}:\n{svc.log()[-3000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}\n"
                                 + (svc.log()[-3000:] if svc else ""))
        await asyncio.sleep(0.05)


@asynccontextmanager
async def simulated_vehicle(port: int, *, altitude: float = 25.0, fps: float = 8.0,
                            flavour: str = "ardupilot", seed: int = 3,
                            free_radius: float = 5.0) -> AsyncIterator[tuple]:
    """Simulator (MAVLink udpout to ``port``) plus its MJPEG camera, the vehicle hovering over a
    crowd with one free circle of ``free_radius`` m, 12 m north-east of it, on a lawn of the
    seed's procedural ground (as the scenarios place theirs): elsewhere the circle may lie on
    ground the model marks (seed 3's first circle, on paving at (8.5, 8.5), was measured 3 m
    wide whether it was 5 or 7 m, 2026-11-26), and the only zones were gaps in the crowd."""
    from sim.vehicle.simulator import SimConfig, Simulator
    from sim.world.camera_server import CameraServer
    from sim.world.crowd import Circle, crowd_with_free_area
    from sim.world.ground import ProceduralGround

    cn, ce = ProceduralGround(seed).lawn_near(0.0, 0.0)
    start = (cn - 8.5, ce - 8.5)
    world = crowd_with_free_area(seed=seed, free=Circle(cn, ce, free_radius), centre=start)
    sim = Simulator(SimConfig(flavour=flavour, outputs=[f"udpout:127.0.0.1:{port}"],
                              start_position=(start[0], start[1], 0.0), seed=seed), world=world)
    intr = Intrinsics.from_fov(640, 480, 90.0)
    cam = CameraServer(sim.pose, world, intr, Mount.from_degrees(0, -90, 0), fps=fps)
    await sim.start()
    await cam.start()
    sim.take_off(altitude)
    try:
        yield sim, cam, world
    finally:
        await cam.stop()
        await sim.stop()


def _env(notify: NotifySocket | None, watchdog_usec: int | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")}
    if notify is not None:
        env["NOTIFY_SOCKET"] = str(notify.path)
    if watchdog_usec is not None:
        env["WATCHDOG_USEC"] = str(watchdog_usec)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _write_config(tmp_path: Path, port: int, cam_url: str, extra: str = "", model: Path | None = None,
                  link_extra: str = "") -> Path:
    cfg = tmp_path / "companion.toml"
    cfg.write_text(
        f'[link]\nurl = "udpin:127.0.0.1:{port}"\n{link_extra}'
        f'[camera]\nsource = "{cam_url}"\nwidth = 640\nheight = 480\nfps = 8.0\nhfov_deg = 90.0\n'
        f'stall_timeout_s = 1.0\nreopen_max_backoff_s = 1.0\n'
        f'[model]\npath = "{model or _model()}"\nthreads = 1\n'
        f'[log]\nhealth_interval_s = 2.0\n' + extra)
    return cfg


# ---- start-up errors --------------------------------------------------------------------------

def _run_quick(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", "run", *args], capture_output=True, text=True,
                          timeout=60, cwd=str(tmp_path), env=_env(None))


def test_bad_config_exits_non_zero_and_names_the_key(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[camera]\nfsp = 10\n")
    r = _run_quick(["--config", str(cfg)], tmp_path)
    assert r.returncode == 2
    assert "unknown key 'camera.fsp'" in r.stderr and "camera.fps" in r.stderr
    r = _run_quick(["--set", "pipeline.r0_m=-3"], tmp_path)
    assert r.returncode == 2 and "pipeline.r0_m must be >= 0.1" in r.stderr
    r = _run_quick(["--set", "camera.fps"], tmp_path)
    assert r.returncode == 2 and "key=value" in r.stderr
    # A key that was removed (issue 58) says so, and where its measurement is.
    cfg.write_text("[pipeline]\nfusion = \"map\"\n")
    r = _run_quick(["--config", str(cfg)], tmp_path)
    assert r.returncode == 2 and "pipeline.fusion was removed" in r.stderr
    assert "docs/measurements.md" in r.stderr and "unknown key" not in r.stderr


def test_missing_or_corrupt_model_exits_non_zero_and_names_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere" / "model.onnx"
    r = _run_quick(["--model", str(missing), "--camera", str(tmp_path)], tmp_path)
    assert r.returncode == 2
    assert str(missing) in r.stderr and "does not exist" in r.stderr
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x01garbage" * 50)
    r = _run_quick(["--model", str(corrupt), "--camera", str(tmp_path)], tmp_path)
    assert r.returncode == 2 and str(corrupt) in r.stderr


def test_bad_camera_source_exits_non_zero(tmp_path: Path) -> None:
    r = _run_quick(["--camera", str(tmp_path / "missing.mp4"), "--model", str(_model())], tmp_path)
    assert r.returncode == 2 and "missing.mp4" in r.stderr


def test_bad_link_urls_and_an_empty_frames_folder_exit_2_with_a_message(tmp_path: Path) -> None:
    for url, words in (("udp:127.0.0.1:14550", "must start with udpin:"),
                       ("udpin:127.0.0.1:70000", "port 70000 out of range")):
        r = _run_quick(["--link", url], tmp_path)
        assert r.returncode == 2 and "link.url" in r.stderr and words in r.stderr, r.stderr
        assert "Traceback" not in r.stderr
    empty = tmp_path / "frames"
    empty.mkdir()
    r = _run_quick(["--camera", str(empty), "--model", str(_model())], tmp_path)
    assert r.returncode == 2 and "folder holds no image files" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


# ---- running against the simulator -------------------------------------------------------------

#: Runs in the service process (``sitecustomize``): the pipeline call after the file named by
#: $COMPANION_TEST_STUCK_FLAG appears hangs for 7 s (a stuck pipeline, an internal fault).
STUCK_PIPELINE = '''\
import os
import time

import companion.pipeline.slz as slz

_process = slz.SLZPipeline.process
_flag = os.environ["COMPANION_TEST_STUCK_FLAG"]


def _maybe_stuck(self, *args, **kwargs):
    try:
        os.unlink(_flag)
    except FileNotFoundError:
        pass
    else:
        time.sleep(7.0)
    return _process(self, *args, **kwargs)


slz.SLZPipeline.process = _maybe_stuck
'''


async def test_ready_watchdog_status_on_faults_and_clean_sigterm(tmp_path: Path) -> None:
    """READY after the first heartbeat; external faults (camera stopped, autopilot silent) are
    told as STATUS=degraded while WATCHDOG=1 goes on (a restart cannot fix them; the service
    reconnects), and STATUS is back to normal when they end; an internal fault (a pipeline call
    stuck beyond 5 s) stops the pings until it ends. SIGTERM -> STOPPING and exit 0 within 2 s;
    the recording it made reads back frame by frame with poses."""
    from tests.patched_service import patched_env

    port = _free_udp_port()
    notify = NotifySocket(tmp_path / "notify.sock")
    rec_dir = tmp_path / "rec"
    stuck_flag = tmp_path / "stuck"
    env = {**_env(notify, 1_000_000), **dict(patched_env(tmp_path / "site", STUCK_PIPELINE)),
           "COMPANION_TEST_STUCK_FLAG": str(stuck_flag)}

    def statuses_since(t: float) -> list[str]:
        return [line for when, m in notify.drain() if when > t for line in m.split("\n")
                if line.startswith("STATUS=")]

    def pings_between(t0: float, t1: float) -> int:
        return sum(t0 < t < t1 for t in notify.times("WATCHDOG=1"))

    async def external_fault(what: str, start, end) -> None:
        t0 = time.monotonic()
        await start()
        await _until(lambda: f"STATUS=degraded: {what}; MONITOR" in "\n".join(statuses_since(t0)), 10,
                     f"STATUS=degraded: {what}", svc)
        t_degraded = time.monotonic()
        await asyncio.sleep(2.5)
        pings = pings_between(t_degraded, time.monotonic())
        assert pings >= 3, f"only {pings} WATCHDOG=1 in 2.5 s while {what} (an external fault)"
        assert t_degraded - t0 < 6
        t_back = time.monotonic()
        await end()
        await _until(lambda: any(s.startswith("STATUS=MONITOR") for s in statuses_since(t_back)), 15,
                     f"STATUS back to normal after {what}", svc)

    async with simulated_vehicle(port) as (sim, cam, _world):
        cfg = _write_config(tmp_path, port, cam.url)
        svc = Service(["--config", str(cfg), "--record", str(rec_dir)],
                      env, tmp_path / "svc.log")
        try:
            await _until(lambda: notify.has("READY=1"), 60, "READY=1", svc)
            await _until(lambda: len(notify.times("WATCHDOG=1")) >= 3, 10, "WATCHDOG=1 pings", svc)
            await sim.wait_for(lambda t: t.position[2] < -20.0, 30)
            await _until(lambda: "frames camera=" in svc.log() and "processed=0 " not in svc.log().splitlines()[-1]
                         or svc.log().count("processed=") >= 2, 20, "health log", svc)

            # The camera stops (an external fault): reported, pings go on; back (same port): the
            # source reopens and STATUS is normal again.
            await external_fault("camera not delivering", cam.stop, cam.start)
            assert "reopened" in svc.log()
            assert "health: camera not delivering (external fault" in svc.log()
            assert "health: camera ok again" in svc.log()

            # The autopilot goes silent (every datagram from the vehicle lost): the same.
            silence: list[float] = []

            async def silent() -> None:
                silence.append(time.monotonic())
                sim.set_link_faults(loss_tx=1.0)

            async def heard() -> None:
                sim.set_link_faults()
                silence.append(time.monotonic() + 1.0)  # the first poses to arrive again
            await external_fault("no autopilot heartbeat", silent, heard)
            assert "health: link ok again" in svc.log()

            # A pipeline call stuck for 7 s (an internal fault): the pings stop once it has been
            # stuck 5 s, and resume when it returns.
            t_stuck = time.monotonic()
            stuck_flag.touch()
            await _until(lambda: any(s.startswith("STATUS=unhealthy: pipeline stuck") for s in statuses_since(t_stuck)),
                         10, "STATUS=unhealthy: pipeline stuck", svc)
            t_unhealthy = time.monotonic()
            assert t_unhealthy - t_stuck > 4.5
            await _until(lambda: not stuck_flag.exists() and "health: pipeline ok again" in svc.log(), 10,
                         "the stuck pipeline call to return", svc)
            t_ok = time.monotonic()
            late = pings_between(t_unhealthy + 0.3, t_ok - 0.3)
            assert late == 0, f"{late} WATCHDOG=1 sent while the pipeline was stuck"
            await _until(lambda: pings_between(t_ok, math.inf) >= 1, 5, "WATCHDOG=1 after the pipeline recovered", svc)
            assert "pipeline stuck for" in svc.log() and "internal fault: watchdog no longer fed" in svc.log()

            # SIGTERM: STOPPING=1, exit 0, within 2 s.
            t0 = time.monotonic()
            svc.proc.send_signal(signal.SIGTERM)
            rc = await asyncio.to_thread(svc.proc.wait, 5)
            elapsed = time.monotonic() - t0
            assert rc == 0, svc.log()[-3000:]
            assert elapsed < 2.0, f"shutdown took {elapsed:.2f} s"
            assert notify.has("STOPPING=1")
        finally:
            svc.stop()
            notify.close()

    runs = [p for p in rec_dir.iterdir() if (p / "meta.json").is_file()]
    assert len(runs) == 1
    reader = RecordingReader(runs[0])
    assert reader.intrinsics == Intrinsics.from_fov(640, 480, 90.0)
    assert reader.meta["model"]["path"] == str(_model())
    frames = list(reader.frames())
    assert len(frames) >= 10, svc.log()[-2000:]
    with_pose = [f for f in frames if f.pose is not None]
    heard = [f for f in frames if not silence[0] < f.t < silence[1]]  # not while the autopilot was silent
    assert len(with_pose) >= 0.8 * len(heard)
    ts = [f.t for f in frames]
    assert ts == sorted(ts) and len({f.index for f in frames}) == len(frames)
    for f in with_pose:
        assert f.frame_bgr.shape == (480, 640, 3)
        # The pose is the one at the frame's capture time, or a held one that says its true age
        # (never older than pipeline.max_pose_age_s, 0.25 s).
        assert f.t - 0.25 - 1e-6 <= f.pose.t <= f.t + 1e-6
        assert -40 < f.pose.down < 0  # airborne, above home
    # The hover altitude the recorded poses show is the simulator's (25 m).
    assert abs(with_pose[-1].pose.down + 25.0) < 2.0
    assert list(reader.events("zones")), "no pipeline decisions recorded"
    telemetry = list(reader.events("telemetry"))
    kinds = {e["msg"] for e in telemetry}
    assert {"HEARTBEAT", "ATTITUDE", "GLOBAL_POSITION_INT"} <= kinds, kinds
    att = [e for e in telemetry if e["msg"] == "ATTITUDE"]
    assert all(isinstance(e["roll"], float) and e["t"] > 0 for e in att)


async def _fly_once(tmp_path: Path) -> tuple[str, Any, list[str], Any]:
    """One hover-failsafe-landing flight: (service log, truth at the end, STATUSTEXTs, world)."""
    port = _free_udp_port()
    notify = NotifySocket(tmp_path / "notify.sock")
    async with simulated_vehicle(port, altitude=20.0, free_radius=7.0) as (sim, cam, world):  # see _take_over's callers
        heard: list[str] = []
        handle = sim.autopilot.handle_message

        def spy(msg, link):  # the ground-station side of the real packets the service sent
            if msg.get_type() == "STATUSTEXT":
                heard.append(msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace"))
            return handle(msg, link)

        sim.autopilot.handle_message = spy  # type: ignore[method-assign]
        # A 45 s takeover budget (90 s by default) keeps a flight that cannot land short (CI's time).
        cfg = _write_config(tmp_path, port, cam.url, "[controller]\nselect_timeout_s = 30.0\nmax_takeover_s = 45.0\n")
        svc = Service(["--config", str(cfg)], _env(notify, 5_000_000), tmp_path / "svc.log")
        try:
            await _until(lambda: notify.has("READY=1"), 60, "READY=1", svc)
            await sim.wait_for(lambda t: t.position[2] < -18.0, 40)
            await _until(lambda: notify.has("STATUS=MONITOR: oldest stable zone"), 40,
                         "a stable zone before the failsafe", svc)
            sim.inject_failsafe("battery_critical")
            await _until(lambda: "-> APPROACH" in svc.log(), 30, "the controller to take over", svc)
            truth = await sim.wait_for(lambda t: t.landed or (t.on_ground and not t.armed), 150)
        finally:
            log = svc.log()
            if svc.proc.poll() is None:
                svc.proc.send_signal(signal.SIGTERM)
                assert await asyncio.to_thread(svc.proc.wait, 5) == 0
            svc.stop()
            notify.close()
        return log, truth, heard, world


async def test_service_lands_the_vehicle_away_from_people(tmp_path: Path) -> None:
    """The whole loop: hover over a crowd, the autopilot's battery failsafe fires, the service
    takes over and the vehicle lands, either in the zone the service flew to (LANDED, nobody
    within r_0) or, when zones kept being lost, after a clean handback to the autopilot's own LAND
    (HANDBACK; see the README's known limitation); the ground station hears STATUSTEXTs."""
    if not SHIPPED_MODEL.is_file():
        # The stand-in peer model (MCNN, ShanghaiTech B) sees the simulator's people poorly: zones
        # keep shrinking and the controller (rightly) holds instead of landing.
        pytest.skip(f"needs the shipped model {SHIPPED_MODEL} (not committed yet)")
    log, truth, heard, world = await _fly_once(tmp_path)
    where = (float(truth.position[0]), float(truth.position[1]))
    clearance = world.nearest_person_distance(where)
    assert truth.landed or (truth.on_ground and not truth.armed)
    story = "\n".join(line for line in log.splitlines() if "SLZ:" in line)
    after = log.split("-> APPROACH", 1)[1]
    assert "-> LAND" in after or "-> HANDBACK" in after, log[-3000:]
    if "-> HANDBACK" in after:
        # Handed back: the autopilot's own LAND touched down wherever the vehicle was, which the
        # companion does not choose (the README's known limitation; issue 11 is the fix). Such a
        # touchdown is a strike to count over many flights (companion sim-scenarios), not a
        # guarantee one flight can check; the handback itself must have been clean.
        assert "handing back to the autopilot (LAND)" in story, story
        print(f"handed back; the autopilot landed {clearance:.1f} m from the nearest person")
    else:
        # The companion chose the touchdown: nobody within r_0 (2 m), ever.
        assert clearance >= 2.0, f"landed {clearance:.2f} m from a person at {where}:\n{story}"
    assert any(h.startswith("SLZ") or "zone" in h for h in heard), heard
    print(f"landed at {where}, {clearance:.1f} m from the nearest person; STATUSTEXT: {heard}")


def _health(log: str) -> list[dict[str, int]]:
    """The counters of each periodic health line in the service log."""
    out = []
    for line in log.splitlines():
        if " health " in line and "frames camera=" in line:
            fields = dict(kv.split("=", 1) for kv in line.split("frames ", 1)[1].split(" | ")[0].split())
            out.append({k: int(v) for k, v in fields.items()})
    return out


async def test_frames_without_a_fresh_pose_are_not_used(tmp_path: Path) -> None:
    """Telemetry stops (every datagram from the vehicle lost) while the camera keeps delivering:
    no pose is fresh at a frame's capture time, frames are counted as no_pose and none reaches
    the pipeline or the controller; processing resumes when telemetry does."""
    port = _free_udp_port()
    async with simulated_vehicle(port) as (sim, cam, _world):
        cfg = _write_config(tmp_path, port, cam.url)
        svc = Service(["--config", str(cfg), "--set", "log.health_interval_s=1.0"], _env(None),
                      tmp_path / "svc.log")
        try:
            await _until(lambda: any(h["processed"] > 3 for h in _health(svc.log())), 60, "frames processed", svc)
            sim.set_link_faults(loss_tx=1.0)
            await asyncio.sleep(1.5)  # the health line after the last pose went stale
            before = _health(svc.log())[-1]
            await asyncio.sleep(4.0)
            after = _health(svc.log())[-1]
            assert after["no_pose"] - before["no_pose"] >= 5, (before, after)
            assert after["processed"] == before["processed"], (before, after)
            sim.set_link_faults()
            await _until(lambda: _health(svc.log())[-1]["processed"] > after["processed"], 20,
                         "processing to resume with fresh poses", svc)
            svc.proc.send_signal(signal.SIGTERM)
            assert await asyncio.to_thread(svc.proc.wait, 5) == 0
        finally:
            svc.stop()


async def _take_over(sim: Any, svc: Service, notify: NotifySocket, external: str) -> None:
    """Ready, the vehicle up and a stable zone seen; then the battery failsafe, until the
    companion has switched the autopilot to its ``external`` mode (GUIDED / OFFBOARD)."""
    await _until(lambda: notify.has("READY=1"), 60, "READY=1", svc)
    await sim.wait_for(lambda t: t.position[2] < -18.0, 40)
    # 60 s, not 40: on a loaded 2-core run (the whole suite) the first stable zone over the walking
    # crowd once took longer than 40 s with the shipped model (2026-11-26); alone it takes 5-15 s.
    # The latest status, not any earlier one: a zone seen stable once may be gone by now, and the
    # trigger must find one (CI, 2026-11-26: no takeover in 20 s, the vehicle in PX4's own LAND).
    await _until(lambda: (notify.latest("STATUS=") or "").startswith("STATUS=MONITOR: oldest stable zone"),
                 60, "a stable zone", svc)
    sim.inject_failsafe("battery_critical")
    try:
        await sim.wait_for(lambda t: t.mode == external, 20)  # the companion took over
    except (TimeoutError, asyncio.TimeoutError) as e:
        said = "\n".join(line for line in svc.log().splitlines() if " DEBUG " not in line)
        raise AssertionError(f"{e}\n--- service log (no DEBUG), tail ---\n{said[-6000:]}") from None


@pytest.mark.parametrize("flavour, external, land", [("ardupilot", "GUIDED", "LAND"),
                                                      ("px4", "OFFBOARD", "AUTO.LAND")])
async def test_sigterm_during_a_takeover_hands_back_to_the_autopilot(
        tmp_path: Path, flavour: str, external: str, land: str) -> None:
    """Stopping while the companion flies the vehicle gives it back to the autopilot's LAND
    (never leaves it in GUIDED/OFFBOARD with nobody in charge), and still exits 0 within 2 s.
    The flavour is picked from the heartbeat (link.flavour = auto)."""
    port = _free_udp_port()
    notify = NotifySocket(tmp_path / "notify.sock")
    # A 7 m free circle on a lawn: these tests are about what a shutdown does during a takeover,
    # and the takeover must happen. Over the old 5 m circle on paving, a zone the status line
    # called stable (a gap in the crowd) was gone when the failsafe came on a loaded CI run
    # (2026-11-26): no takeover in 20 s while PX4's own LAND came down. On the lawn a 5 m circle
    # is measured about 4 m, the least a zone needs to be chosen; a 7 m one 5.5-7 m.
    async with simulated_vehicle(port, altitude=20.0, flavour=flavour, free_radius=7.0) as (sim, cam, _world):
        cfg = _write_config(tmp_path, port, cam.url, "[controller]\nselect_timeout_s = 30.0\nhold_timeout_s = 60.0\n")
        svc = Service(["--config", str(cfg)], _env(notify), tmp_path / "svc.log")
        try:
            await _take_over(sim, svc, notify, external)
            await asyncio.sleep(1.0)
            assert sim.truth.mode == external
            assert f"autopilot flavour: {flavour}" in svc.log()
            t0 = time.monotonic()
            svc.proc.send_signal(signal.SIGTERM)
            rc = await asyncio.to_thread(svc.proc.wait, 5)
            assert rc == 0 and time.monotonic() - t0 < 2.0, svc.log()[-3000:]
            truth = await sim.wait_for(lambda t: t.mode == land, 2.0)
            assert truth.mode == land
            assert "handing back to the autopilot (LAND)" in svc.log()
            assert notify.has("STOPPING=1")
        finally:
            svc.stop()
            notify.close()


async def test_sigterm_with_an_autopilot_that_never_acks_insists_on_land_and_exits_0(tmp_path: Path) -> None:
    """Shutdown during a takeover with nothing coming back from the autopilot (no ACK): LAND is
    sent again and again within the 2 s, not once, and the service still exits 0 in time."""
    port = _free_udp_port()
    notify = NotifySocket(tmp_path / "notify.sock")
    # A 7 m free circle: the takeover must happen (see the test above).
    async with simulated_vehicle(port, altitude=20.0, flavour="ardupilot", free_radius=7.0) as (sim, cam, _world):
        cfg = _write_config(tmp_path, port, cam.url, "[controller]\nselect_timeout_s = 30.0\nhold_timeout_s = 60.0\n")
        svc = Service(["--config", str(cfg)], _env(notify), tmp_path / "svc.log")
        try:
            await _take_over(sim, svc, notify, "GUIDED")
            await asyncio.sleep(0.5)
            modes: list[float] = []
            ap = sim.autopilot
            real = ap._cmd_set_mode

            def counting(p, channel, msg, is_int):  # the simulator still obeys; its ACKs are lost
                modes.append(float(p[1]))
                return real(p, channel, msg, is_int)
            ap._cmd_set_mode = counting  # type: ignore[method-assign]
            sim.set_link_faults(loss_tx=1.0, loss_rx=0.0)  # nothing from the vehicle arrives
            t0 = time.monotonic()
            svc.proc.send_signal(signal.SIGTERM)
            rc = await asyncio.to_thread(svc.proc.wait, 5)
            assert rc == 0 and time.monotonic() - t0 < 2.0, svc.log()[-3000:]
            land = 9.0  # COPTER_MODE_LAND
            assert modes.count(land) >= 3, (modes, svc.log()[-3000:])
            assert sim.truth.mode == "LAND"
        finally:
            svc.stop()
            notify.close()


async def test_configured_ground_station_ids_and_the_local_trigger_socket(tmp_path: Path) -> None:
    """failsafe.gcs_system_ids and failsafe.local_socket are settings the service uses: the trigger
    from a configured ground station is accepted, from another system refused; the socket answers."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    from companion.mavlink.failsafe import send_local_trigger

    port = _free_udp_port()
    notify = NotifySocket(tmp_path / "notify.sock")
    sock_path = tmp_path / "trigger.sock"
    async with simulated_vehicle(port, altitude=20.0) as (sim, cam, _world):
        # The ground station shares the companion's port here (in the field its commands come
        # through the autopilot): it must be in link.peers, or it is dropped by address.
        cfg = _write_config(tmp_path, port, cam.url,
                            f'[failsafe]\ngcs_system_ids = [42]\nlocal_socket = "{sock_path}"\n',
                            link_extra='peers = ["127.0.0.1"]\n')
        svc = Service(["--config", str(cfg)], _env(notify), tmp_path / "svc.log")
        gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        gcs.bind(("127.0.0.1", 0))
        gcs.setblocking(False)
        loop = asyncio.get_running_loop()

        async def trigger_from(sysid: int) -> int:
            out = mav.MAVLink(None, srcSystem=sysid, srcComponent=190)
            rx = mav.MAVLink(None)
            rx.robust_parsing = True
            end = time.monotonic() + 5.0
            while time.monotonic() < end:
                gcs.sendto(out.command_long_encode(1, 191, 31010, 0, 0, 0, 0, 0, 0, 0, 0).pack(out),
                           ("127.0.0.1", port))
                try:
                    data = await asyncio.wait_for(loop.sock_recv(gcs, 4096), 0.5)
                except (TimeoutError, asyncio.TimeoutError):
                    continue
                for msg in rx.parse_buffer(data) or []:
                    if msg.get_type() == "COMMAND_ACK" and msg.command == 31010 and msg.target_system == sysid:
                        return int(msg.result)
            raise AssertionError(f"no COMMAND_ACK for system {sysid}")
        try:
            await _until(lambda: notify.has("READY=1"), 60, "READY=1", svc)
            assert sock_path.is_socket()
            assert await trigger_from(255) == mav.MAV_RESULT_DENIED  # the default id, not configured
            assert "not in gcs_system_ids (42,)" in svc.log()
            assert await send_local_trigger(str(sock_path), "bench check") == "ok"
            assert await trigger_from(42) == mav.MAV_RESULT_ACCEPTED
            svc.proc.send_signal(signal.SIGTERM)
            assert await asyncio.to_thread(svc.proc.wait, 5) == 0
            assert not sock_path.exists()  # removed at shutdown
        finally:
            gcs.close()
            svc.stop()
            notify.close()


# ---- a full disk at shutdown ---------------------------------------------------------------------

#: Runs in the service process (``sitecustomize``): every file the recorder opens for writing
#: besides meta.json is ``/dev/full`` (each write fails with ENOSPC, as on a disk that filled up
#: mid-flight), and every part that shutdown stops raises after doing its work (the worst a part
#: could do on the way out).
FULL_DISK = '''\
import builtins
import errno
import inspect
import io
import os

_open = builtins.open


def _full(file, mode="r", *args, **kwargs):
    name = os.fspath(file) if isinstance(file, (str, bytes, os.PathLike)) else ""
    if isinstance(name, str) and ("w" in mode or "a" in mode) and "/rec/" in name and not name.endswith("meta.json"):
        return _open("/dev/full", mode, *args, **kwargs)
    return _open(file, mode, *args, **kwargs)


builtins.open = io.open = _full


def _then_enospc(cls, name):
    real = getattr(cls, name)
    error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), f"patched {cls.__name__}.{name}")

    def wrapper(self, *args, **kwargs):
        real(self, *args, **kwargs)
        raise error

    async def async_wrapper(self, *args, **kwargs):
        await real(self, *args, **kwargs)
        raise error

    setattr(cls, name, async_wrapper if inspect.iscoroutinefunction(real) else wrapper)


import companion.mavlink.link as _link  # noqa: E402
import companion.recording as _recording  # noqa: E402
import companion.service.camera as _camera  # noqa: E402

_then_enospc(_recording.FlightRecorder, "close")
_then_enospc(_camera.CameraSource, "stop")
_then_enospc(_link.MavLink, "close")
'''


async def test_sigterm_with_a_full_disk_exits_0_within_2_s_without_a_traceback(tmp_path: Path) -> None:
    """The recording's writes fail with ENOSPC and every part shutdown stops raises OSError on the
    way out: each failure is logged, the remaining steps still run, and SIGTERM still means
    STOPPING=1 and exit 0 within 2 s, with no traceback."""
    from tests.patched_service import patched_env

    port = _free_udp_port()
    notify = NotifySocket(tmp_path / "notify.sock")
    rec_dir = tmp_path / "rec"
    async with simulated_vehicle(port) as (sim, cam, _world):
        cfg = _write_config(tmp_path, port, cam.url)
        env = {**_env(notify), **dict(patched_env(tmp_path / "site", FULL_DISK))}
        svc = Service(["--config", str(cfg), "--record", str(rec_dir)], env, tmp_path / "svc.log")
        try:
            await _until(lambda: notify.has("READY=1"), 60, "READY=1", svc)
            await _until(lambda: "No space left on device" in svc.log(), 20, "a write to fail with ENOSPC", svc)
            await asyncio.sleep(1.0)  # frames and events keep failing to be written meanwhile
            t0 = time.monotonic()
            svc.proc.send_signal(signal.SIGTERM)
            rc = await asyncio.to_thread(svc.proc.wait, 5)
            elapsed = time.monotonic() - t0
            log = svc.log()
            assert rc == 0, log[-3000:]
            assert "Traceback" not in log, log[-3000:]
            assert elapsed < 2.0, f"shutdown took {elapsed:.2f} s"
            print(f"shutdown with a full disk: {elapsed:.2f} s")
            for part in ("recorder", "camera", "link"):
                assert f"shutdown: {part} failed" in log, (part, log[-3000:])
            assert "companion.service: stopped" in log, log[-2000:]  # the last step ran
            assert notify.has("STOPPING=1")
        finally:
            svc.stop()
            notify.close()
