"""Forged telemetry on an unsigned link (issue 61, items 1 and 3): one packet, or a flood of
replayed ones, must not take the pose away. Real MAVLink bytes on loopback: a genuine autopilot
streams the pose at 20 Hz, a forger sends from the autopilot's own address, and the vehicle
state is asked for the pose of a frame every 0.1 s, as the service does.
"""

from __future__ import annotations

import asyncio
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.state import VehicleState
from tests.mavpeer import MavPeer

FAST = dict(heartbeat_period_s=0.1, heartbeat_timeout_s=0.4, command_timeout_s=0.15, command_retries=2)
LAT, LON = 47.397742, 8.545594


class Autopilot:
    """A MavPeer streaming ATTITUDE and GLOBAL_POSITION_INT at 20 Hz on its own boot clock."""

    def __init__(self, peer: MavPeer) -> None:
        self.peer = peer
        self.boot_at = time.monotonic() - 600.0  # up for ten minutes
        self.task: asyncio.Task[None] | None = None

    def boot_ms(self) -> int:
        return int((time.monotonic() - self.boot_at) * 1000)

    async def stream(self) -> None:
        mav = self.peer.mav
        mav.home_position_send(int(LAT * 1e7), int(LON * 1e7), 400_000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
        while True:
            ms = self.boot_ms()
            mav.attitude_send(ms, 0.01, 0.02, 0.3, 0, 0, 0)
            mav.global_position_int_send(ms, int(LAT * 1e7), int(LON * 1e7), 420_000, 20_000, 0, 0, 0, 0)
            await asyncio.sleep(0.05)

    def forged(self, msg: m.MAVLink_message, seq: int = 77) -> bytes:
        """A packet with the autopilot's ids, not sent through its own sequence counter."""
        sender = m.MAVLink(None, 1, 1)
        sender.seq = seq
        return bytes(msg.pack(sender))


async def _frames_without_pose(state: VehicleState, seconds: float) -> tuple[int, int, int]:
    """(frames, frames without a pose, longest run without one) for a frame every 0.1 s whose
    capture was 50 ms ago (the telemetry after it has arrived)."""
    frames = missing = run = longest = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        await asyncio.sleep(0.1)
        frames += 1
        pose = state.pose_at(time.monotonic() - 0.05)
        if pose is None:
            missing += 1
            run += 1
            longest = max(longest, run)
        else:
            run = 0
    return frames, missing, longest


async def _link_state_peer() -> tuple[MavLink, VehicleState, MavPeer]:
    """The link started with the vehicle state on it, and the autopilot's peer sending heartbeats."""
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, **FAST))
    state = VehicleState(max_extrapolation_s=0.25)
    state.attach(link)
    await link.start()
    peer = MavPeer()
    await peer.connect_udp(link.local_address)
    peer.start_heartbeats(0.1)
    return link, state, peer


async def _setup() -> tuple[MavLink, VehicleState, Autopilot]:
    link, state, peer = await _link_state_peer()
    await link.wait_connected(2.0)
    ap = Autopilot(peer)
    ap.task = asyncio.create_task(ap.stream())
    # Until a frame has its pose (the home and the stream's first samples), not a fixed 0.6 s:
    # each test's first window then shows the pose steady before anything is forged.
    deadline = time.monotonic() + 2.0
    while state.pose_at(time.monotonic() - 0.05) is None:
        assert time.monotonic() < deadline, "the autopilot's stream gave no pose"
        await asyncio.sleep(0.01)
    return link, state, ap


async def _teardown(link: MavLink, ap: Autopilot) -> None:
    assert ap.task is not None
    ap.task.cancel()
    await ap.peer.close()
    await link.close()


@pytest.mark.parametrize("lead_s", [0.6, 5.0, 3600.0])
@pytest.mark.parametrize("kind", ["ATTITUDE", "GLOBAL_POSITION_INT"])
async def test_one_forged_pose_packet_ahead_of_the_clock_costs_at_most_one_frame(lead_s: float, kind: str):
    """The audit: one unsigned ATTITUDE from the autopilot's address with time_boot_ms an hour
    ahead left the service without a pose for the hour (0 of 83 frames in 20 s)."""
    link, state, ap = await _setup()
    try:
        frames, missing, _ = await _frames_without_pose(state, 0.5)
        assert frames >= 3 and missing == 0
        ms = ap.boot_ms() + int(lead_s * 1000)
        msg = (m.MAVLink_attitude_message(ms, 1.0, 0.5, -2.0, 0, 0, 0) if kind == "ATTITUDE" else
               m.MAVLink_global_position_int_message(ms, int((LAT + 0.001) * 1e7), int(LON * 1e7),
                                                     470_000, 70_000, 0, 0, 0, 0))
        ap.peer.send_raw(ap.forged(msg))
        frames, missing, longest = await _frames_without_pose(state, 1.5)
        assert frames >= 10 and longest <= 1, (missing, longest)
        assert state.clock.stats.ahead == 1 and state.rejected == 1
        pose = state.pose_at(time.monotonic() - 0.05)
        assert pose is not None and pose.yaw == pytest.approx(0.3) and pose.down == pytest.approx(-20.0)
    finally:
        await _teardown(link, ap)


async def test_a_flood_of_replayed_old_attitudes_is_no_reboot_and_the_genuine_pose_stays():
    """The audit: ATTITUDEs more than 5 s old counted as 195 reboots in 10 s; each cleared the
    history and made the replayed pose current, with an unlimited warning line each."""
    link, state, ap = await _setup()
    try:
        old_ms = ap.boot_ms() - 60_000

        async def flood() -> None:
            for k in range(400):  # 200 a second for 2 s, from the autopilot's address
                msg = m.MAVLink_attitude_message(old_ms + 10 * k, 1.5, 0.0, 1.5, 0, 0, 0)
                ap.peer.send_raw(ap.forged(msg, seq=k % 256))
                await asyncio.sleep(0.005)

        task = asyncio.create_task(flood())
        frames, missing, longest = await _frames_without_pose(state, 2.0)
        await task
        assert state.clock.stats.reboots == 0
        assert frames >= 12 and longest <= 1, (missing, longest)
        pose = state.pose_at(time.monotonic() - 0.05)
        assert pose is not None and pose.yaw == pytest.approx(0.3) and pose.roll == pytest.approx(0.01)
    finally:
        await _teardown(link, ap)


async def test_a_forged_pose_packet_before_the_autopilots_first_costs_a_few_frames_not_an_hour():
    """The forger speaks before the autopilot's first pose sample: its clock is the first
    estimate. The genuine streams, all late against it, replace it within 0.25 s."""
    link, state, peer = await _link_state_peer()
    ap = Autopilot(peer)
    try:
        await link.wait_connected(2.0)
        ap.peer.send_raw(ap.forged(m.MAVLink_attitude_message(ap.boot_ms() + 3_600_000, 1.0, 0.5, -2.0, 0, 0, 0)))
        await asyncio.sleep(0.05)
        ap.task = asyncio.create_task(ap.stream())
        await asyncio.sleep(0.5)
        frames, missing, longest = await _frames_without_pose(state, 1.0)
        assert frames >= 7 and missing == 0, (missing, longest)
        pose = state.pose_at(time.monotonic() - 0.05)
        assert pose is not None and pose.yaw == pytest.approx(0.3)
    finally:
        await _teardown(link, ap)
