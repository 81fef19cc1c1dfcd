"""``companion demo --live`` (issue 62 item 3): the demo serves the service's status page and live
view on loopback and prints its URL; the page answers while the demo flies. The demo runs as a
user runs it, a subprocess of the real command, with the real service, simulator and model."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(420)]


def _get(url: str, timeout: float = 2.0) -> tuple[int, bytes]:
    with urllib.request.urlopen(url, timeout=timeout) as r:  # noqa: S310 (loopback, our own server)
        return r.status, r.read()


def test_demo_live_prints_the_page_url_and_serves_it_during_the_flight(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "companion", "demo", "--live", "--no-video",
                             "--out", str(tmp_path / "out")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    url: list[str] = []
    got_url = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            found = re.search(r"http://127\.0\.0\.1:\d+/", line)
            if found and not url:
                url.append(found.group(0))
                got_url.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert got_url.wait(60), "".join(lines)
        page = status = None
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                code, body = _get(url[0] + "status.json")
                status = json.loads(body)
                if code == 200 and status.get("frames_processed", 0) > 0:
                    page = _get(url[0])
                    break
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                pass  # the service is not up yet
            time.sleep(0.5)
        assert page is not None, ("the page never answered with frames processed", status, "".join(lines))
        assert page[0] == 200 and b"/status.json" in page[1] and b"/stream.mjpg" in page[1]
        assert status is not None and {"phase", "health", "zones"} <= set(status)
        assert proc.wait(300) in (0, 1), "".join(lines)  # 0 safe, 1 another outcome: it flew to the end
    finally:
        if proc.poll() is None:
            proc.kill()
        reader.join(5)
    text = "".join(lines)
    assert "demo: outcome" in text, text
    assert text.index(url[0]) < text.index("demo: outcome")  # told before the flight, not after
