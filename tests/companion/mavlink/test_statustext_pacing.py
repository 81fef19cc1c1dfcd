"""Texts a pilot can read (issue 62): at most 150 characters, chunks cut at a space with the
prefix on each, and one paced queue per link: at most 4 texts in any 10 s, none repeated within
5 s, most severe first, chunks apart so that PX4's forwarding buffer is never asked to hold a
burst. The pacing on a fake clock, then the real outbox over MAVLink on loopback."""

from __future__ import annotations

import asyncio

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from companion.mavlink.link import LinkConfig, MavLink
from companion.mavlink.statustext import (
    MAX_TEXT,
    STATUSTEXT_LEN,
    TextOutbox,
    TextPacer,
    attach_outbox,
    fit_text,
    join_chunks,
    send_statustext,
    statustext_chunks,
)
from tests.mavpeer import MavPeer

MOVED = "SLZ: zone 17: landing point moved {:.1f} m, 1.9 m from where people were seen in the last 30 s (was 0.0 m)"


def test_a_long_text_is_cut_at_spaces_each_chunk_marked_and_nothing_over_150_characters():
    text = MOVED.format(2.0)
    chunks = [c.decode() for c in statustext_chunks(text)]
    assert all(len(c.encode()) <= STATUSTEXT_LEN for c in chunks)
    # Every chunk but the last fills its 50 bytes (a shorter one would end the text for a
    # ground station that joins them), is cut between words, and each begins "SLZ: ".
    assert all(len(c.encode()) == STATUSTEXT_LEN for c in chunks[:-1])
    assert all(c.startswith("SLZ: ") for c in chunks)
    words = set(text.split())
    assert all(w in words for c in chunks for w in c.removeprefix("SLZ: ").split())
    assert join_chunks(chunks) == text
    huge = "SLZ: " + " ".join(f"word{k}" for k in range(60))
    fitted = fit_text(huge)
    assert len(fitted) <= MAX_TEXT and fitted.endswith("...") and huge.startswith(fitted[:-3])
    assert len(statustext_chunks(fitted)) <= 4


def _fly_texts(pacer: TextPacer, offers: list[tuple[float, str, int]], until: float) -> list[tuple[float, int, str]]:
    """Offer each (time, text, severity) on a 10 ms fake clock and take whatever is due (the
    model's speed with its condition's key, as ``GroundStation`` says it)."""
    sent: list[tuple[float, int, str]] = []
    offers = sorted(offers)
    t, i = 0.0, 0
    while t <= until:
        while i < len(offers) and offers[i][0] <= t:
            pacer.offer(offers[i][1], offers[i][2], t, key="slow" if "model s" in offers[i][1] else "")
            i += 1
        item = pacer.take(t)
        if item is not None:
            sent.append((t, *item))
        t = round(t + 0.01, 2)
    return sent


def _assert_targets(sent: list[tuple[float, int, str]]) -> None:
    for t0, _, _ in sent:
        window = [s for s in sent if t0 <= s[0] < t0 + 10.0]
        assert len(window) <= 4, window
        assert sum("model s" in s[2] for s in window) <= 2, window
    for k, (t0, _, text) in enumerate(sent):
        assert not any(text == s[2] and s[0] - t0 < 5.0 for s in sent[k + 1:]), text


def test_the_flood_of_a_ground_station_flight_is_paced_to_the_targets():
    # What issue 62 saw: the landing point told 19 times in 12 s (flip-flopping between two
    # places), the model speed flapping around its threshold, and the trigger's burst.
    offers = [(0.0, "SLZ: trigger: battery critical; looking for a landing zone", m.MAV_SEVERITY_WARNING),
              (0.0, "SLZ: landing at zone 3, 12.4 m away, radius 4.1 m", m.MAV_SEVERITY_NOTICE)]
    offers += [(0.5 + 0.63 * k, MOVED.format(2.0 if k % 2 else 2.6), m.MAV_SEVERITY_INFO) for k in range(19)]
    offers += [(1.0 + 6.0 * k, "SLZ: model slow: 104 ms/frame > 100 ms" if k % 2 == 0 else
                "SLZ: model speed ok: 96 ms/frame", m.MAV_SEVERITY_WARNING if k % 2 == 0 else m.MAV_SEVERITY_NOTICE)
               for k in range(7)]
    offers.append((12.0, "SLZ: LAND over zone 3 at 4.4 m, radius 4.1 m", m.MAV_SEVERITY_NOTICE))
    offers.append((12.5, "SLZ: zone 3 lost (no longer tracked); holding", m.MAV_SEVERITY_WARNING))
    pacer = TextPacer()
    sent = _fly_texts(pacer, offers, until=60.0)
    _assert_targets(sent)
    texts = [s[2] for s in sent]
    # The trigger first, at once; what matters is told, the repeats and stale news are not.
    assert sent[0] == (0.0, m.MAV_SEVERITY_WARNING, offers[0][1])
    assert "SLZ: zone 3 lost (no longer tracked); holding" in texts
    assert "SLZ: landing at zone 3, 12.4 m away, radius 4.1 m" in texts
    assert pacer.repeats + pacer.dropped + len(sent) == len(offers)
    # 19 offered, 4 told in a minute (the controller itself now offers one per 5 s at most:
    # companion.control.aim.MoveNews).
    assert texts.count(MOVED.format(2.0)) + texts.count(MOVED.format(2.6)) <= 4


def test_the_most_severe_text_waiting_goes_first_and_stale_news_is_dropped():
    pacer = TextPacer()
    for k in range(4):  # four told: the window is full for 10 s
        pacer.offer(f"SLZ: note {k}", m.MAV_SEVERITY_INFO, 0.0)
    sent = [pacer.take(t / 10) for t in range(40)]
    assert [s for s in sent if s] == [(m.MAV_SEVERITY_INFO, f"SLZ: note {k}") for k in range(4)]
    pacer.offer("SLZ: zone 4 is nice", m.MAV_SEVERITY_INFO, 4.0)
    pacer.offer("SLZ: handing back to the autopilot (LAND)", m.MAV_SEVERITY_CRITICAL, 5.0)
    assert pacer.take(9.9) is None and pacer.next_at(9.9) == pytest.approx(10.0)
    assert pacer.take(10.0) == (m.MAV_SEVERITY_CRITICAL, "SLZ: handing back to the autopilot (LAND)")
    assert pacer.take(11.0) == (m.MAV_SEVERITY_INFO, "SLZ: zone 4 is nice")
    for k in range(4):  # the window full again from 12 s to 22 s
        pacer.offer(f"SLZ: urgent {k}", m.MAV_SEVERITY_ERROR, 6.0)
    pacer.offer("SLZ: old news", m.MAV_SEVERITY_NOTICE, 6.0)
    pacer.offer("SLZ: still true", m.MAV_SEVERITY_WARNING, 6.0)
    taken = [pacer.take(t / 10) for t in range(120, 400)]
    told = [s[1] for s in taken if s]
    # A NOTICE that would go out 16 s late is dropped; a WARNING is told however late.
    assert told == [f"SLZ: urgent {k}" for k in range(4)] + ["SLZ: still true"], told
    assert pacer.dropped == 1
    # The same text again within 5 s is not told twice.
    p2 = TextPacer()
    assert p2.offer("SLZ: camera lost: no landing zones", m.MAV_SEVERITY_ERROR, 0.0)
    assert p2.take(0.0) is not None
    assert not p2.offer("SLZ: camera lost: no landing zones", m.MAV_SEVERITY_ERROR, 4.9)
    assert p2.offer("SLZ: camera lost: no landing zones", m.MAV_SEVERITY_ERROR, 5.1)
    assert p2.repeats == 1


def test_a_full_queue_drops_the_least_severe_oldest_text():
    pacer = TextPacer(max_queue=3)
    pacer.offer("SLZ: a", m.MAV_SEVERITY_INFO, 0.0)
    pacer.offer("SLZ: b", m.MAV_SEVERITY_WARNING, 0.0)
    pacer.offer("SLZ: c", m.MAV_SEVERITY_INFO, 0.0)
    pacer.offer("SLZ: d", m.MAV_SEVERITY_CRITICAL, 0.0)
    assert pacer.dropped == 1
    told = [pacer.take(float(k)) for k in range(3)]
    assert [t[1] for t in told if t] == ["SLZ: d", "SLZ: b", "SLZ: c"]


def test_drain_empties_the_queue_giving_what_the_window_has_room_for_most_severe_first():
    pacer = TextPacer()
    pacer.told("SLZ: told 0", 0.0)
    pacer.told("SLZ: told 1", 0.5)
    for k, sev in enumerate([m.MAV_SEVERITY_INFO, m.MAV_SEVERITY_WARNING, m.MAV_SEVERITY_INFO]):
        pacer.offer(f"SLZ: queued {k}", sev, 1.0)
    assert pacer.drain(2.0) == [(m.MAV_SEVERITY_WARNING, "SLZ: queued 1"), (m.MAV_SEVERITY_INFO, "SLZ: queued 0")]
    assert pacer.dropped == 1 and pacer.next_at(2.0) is None and pacer.drain(2.0) == []

async def test_a_burst_arrives_whole_over_mavlink_paced_and_in_severity_order():
    """The real outbox on a real link, a pymavlink ground station on loopback: every text of a
    burst arrives, whole (its chunks joined), most severe first, at the pace set (here scaled 10
    times faster so the test takes seconds), chunks apart."""
    link = MavLink(LinkConfig("udpin:127.0.0.1:0", message_rates_hz={}, heartbeat_period_s=0.05,
                              heartbeat_timeout_s=0.5))
    pacer = TextPacer(max_per_window=4, window_s=1.0, min_gap_s=0.1, repeat_s=0.5, stale_s=1.5)
    box = attach_outbox(link, TextOutbox(link, pacer, chunk_gap_s=0.02))
    await link.start()
    peer = MavPeer()
    await peer.connect_udp(link.local_address)
    peer.start_heartbeats(0.05)
    try:
        await link.wait_connected(2.0)
        burst = [("SLZ: trigger: battery critical; looking for a landing zone, the long way round",
                  m.MAV_SEVERITY_WARNING),
                 ("SLZ: landing at zone 3, 12.4 m away, radius 4.1 m", m.MAV_SEVERITY_NOTICE),
                 (MOVED.format(2.0), m.MAV_SEVERITY_INFO),
                 (MOVED.format(2.0), m.MAV_SEVERITY_INFO),  # a repeat: not told
                 ("SLZ: handing back to the autopilot (LAND)", m.MAV_SEVERITY_CRITICAL),
                 ("SLZ: zone 3 lost (no longer tracked); holding", m.MAV_SEVERITY_WARNING)]
        for text, severity in burst:
            send_statustext(link, text, severity)
        await peer.wait_for_text("(was 0.0 m)", timeout=5.0)
        await asyncio.sleep(0.05)
        got = peer.statustexts()
        assert got == [(m.MAV_SEVERITY_CRITICAL, "SLZ: handing back to the autopilot (LAND)"),
                       (m.MAV_SEVERITY_WARNING, burst[0][0]),
                       (m.MAV_SEVERITY_WARNING, "SLZ: zone 3 lost (no longer tracked); holding"),
                       (m.MAV_SEVERITY_NOTICE, "SLZ: landing at zone 3, 12.4 m away, radius 4.1 m"),
                       (m.MAV_SEVERITY_INFO, MOVED.format(2.0))], got
        assert pacer.repeats == 1 and [t for _, _, t in box.sent] == [t for _, t in got]
        # The pace: at most 4 texts in any window, MIN_GAP apart; chunks of one text 20 ms apart.
        starts = [t for t, _, _ in box.sent]
        assert all(b - a >= 0.1 - 1e-3 for a, b in zip(starts, starts[1:]))
        assert starts[4] - starts[0] >= 1.0 - 1e-3
        times = [t for msg, t in peer.received if msg.get_type() == "STATUSTEXT" and msg.id and msg.chunk_seq > 0]
        assert times, "no chunked text arrived"
        # The service's last words (stopping, handing back) go at once, past a full window.
        send_statustext(link, "SLZ: companion stopping; handing back (LAND)", m.MAV_SEVERITY_WARNING, last=True)
        await peer.wait_for_text("companion stopping", timeout=0.3)
    finally:
        await peer.close()
        await link.close()
    await asyncio.sleep(0)


def test_a_stop_sends_what_waits_only_as_far_as_the_pace_allows():
    """At stop the texts still queued go at once (nothing could send them later), most severe
    first, but no more than the window has room for: a stop must not burst past 4 texts in 10 s
    (a shadow landing's last texts and the stop's did so in a ground-station flight). The stop's
    own text (``last``) goes whatever the pace, and counts in it."""
    now = [0.0]

    class Wire:
        def __init__(self) -> None:
            from pymavlink.dialects.v20 import ardupilotmega as dialect
            self.mav = dialect.MAVLink(None, 1, 191)
            self.sent: list[object] = []

        def send(self, msg: object) -> None:
            self.sent.append(msg)

    wire = Wire()
    box = TextOutbox(wire, TextPacer(), clock=lambda: now[0])  # type: ignore[arg-type]
    box.told("SLZ: landing at zone 1, 0.0 m away, radius 6.1 m", m.MAV_SEVERITY_NOTICE)
    now[0] = 1.0
    box.told("SLZ: over zone 1, descending from 13.3 m", m.MAV_SEVERITY_NOTICE)
    for k, sev in enumerate([m.MAV_SEVERITY_INFO, m.MAV_SEVERITY_NOTICE, m.MAV_SEVERITY_WARNING, m.MAV_SEVERITY_INFO]):
        box.pacer.offer(f"SLZ: queued text {k}", sev, now[0])
    now[0] = 2.0
    assert box.flush_all() == 2  # 2 told in the last 10 s: room for 2 more
    assert [t for _, _, t in box.sent[2:]] == ["SLZ: queued text 2", "SLZ: queued text 1"]  # most severe first
    assert box.pacer.dropped == 2 and box.pacer.allowance(now[0]) == 0
    attach_outbox(wire, box)  # type: ignore[arg-type]
    send_statustext(wire, "SLZ: companion stopping; handing back (LAND)", m.MAV_SEVERITY_WARNING,  # type: ignore[arg-type]
                    last=True)
    assert box.sent[-1][2] == "SLZ: companion stopping; handing back (LAND)"
    now[0] = 12.5
    assert box.pacer.allowance(now[0]) == 4  # the window has moved on
