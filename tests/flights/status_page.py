"""The status page as a browser and a ground station's operator see it: headless Chromium's
rendered DOM and screenshot, ``/status.json``, and the text under each element id. Shared by the
flights that serve the page (``test_gcs_flight``, ``test_status_page_ground``)."""

from __future__ import annotations

import asyncio
import json
import shutil
import tempfile
import time
from collections.abc import Callable
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import pytest

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--virtual-time-budget=3000"]



def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")



async def dump_dom(port: int, *args: str) -> tuple[str | None, str | None]:
    """The page as headless Chromium renders it (``--dump-dom``, or ``args`` instead, e.g. a
    screenshot), or None and why not. A page whose live view never sends a frame never finishes
    loading: the 60 s timeout is what such a hang runs into."""
    exe = chromium()
    if exe is None:
        return None, "no chromium binary (apt-get install chromium; .ci/run installs it when it can)"
    with tempfile.TemporaryDirectory() as profile:
        proc = await asyncio.create_subprocess_exec(
            exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *(args or ("--dump-dom",)),
            f"http://127.0.0.1:{port}/", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        try:
            out, err = await asyncio.wait_for(proc.communicate(), 60.0)
        except (TimeoutError, asyncio.TimeoutError):  # one class from 3.11 on
            proc.kill()
            await proc.wait()
            return None, "chromium did not finish within 60 s"
    if proc.returncode != 0:
        return None, f"chromium exited {proc.returncode}: {err.decode(errors='replace')[-500:]}"
    return out.decode(errors="replace"), None



async def http_get(port: int, path: str, limit: int | None = None) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    await writer.drain()
    if limit is None:
        data = await asyncio.wait_for(reader.read(), 5.0)
    else:
        data = b""
        while len(data) < limit:
            chunk = await asyncio.wait_for(reader.read(limit - len(data)), 10.0)
            if not chunk:
                break
            data += chunk
    writer.close()
    return data



async def until_while_running(task: asyncio.Task[Any], done: Callable[[], bool], timeout_s: float) -> None:
    """Poll ``done`` every 0.1 s until it holds, the service's ``task`` ends or ``timeout_s``
    passes; the caller asserts what it needs (this only waits)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not task.done() and not done():
        await asyncio.sleep(0.1)


async def screenshot(port: int, path: Path) -> tuple[float, str | None]:
    """A 1280 x 900 screenshot of the page to ``path``: the seconds it took, and why none (None: taken)."""
    t0 = time.monotonic()
    _, err = await dump_dom(port, "--window-size=1280,900", f"--screenshot={path}")
    return time.monotonic() - t0, err


async def page_now(port: int) -> tuple[str | None, str | None, dict[str, Any]]:
    """The page now: its DOM as Chromium renders it (or None), why none, and /status.json."""
    dom, err = await dump_dom(port)
    body = (await http_get(port, "/status.json")).split(b"\r\n\r\n", 1)[1]
    return dom, err, json.loads(body)


def check_screenshot(when: str, shot: Path | None, took: float, err: str | None) -> None:
    """The screenshot at ``when`` finished, is a real picture, and took under 30 s (skip without
    a browser)."""
    if err is not None and err.startswith("no chromium"):
        pytest.skip(f"no headless browser: {err}")
    assert err is None and shot is not None and shot.stat().st_size > 10_000, (when, err)
    assert took < 30.0, (when, took)


class Ids(HTMLParser):
    """The text under each element with an id, and the zones table's rows."""

    def __init__(self) -> None:
        super().__init__()
        self.text: dict[str, str] = {}
        self.rows = 0
        self._open: list[str | None] = []
        self._in_zones = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        self._open.append(a.get("id"))
        if a.get("id") == "zones":
            self._in_zones = True
        if tag == "tr" and self._in_zones:
            self.rows += 1

    def handle_endtag(self, tag: str) -> None:
        if self._open:
            ident = self._open.pop()
            if ident == "zones":
                self._in_zones = False

    def handle_data(self, data: str) -> None:
        for ident in self._open:
            if ident:
                self.text[ident] = self.text.get(ident, "") + data



def page_text(dom: str) -> Ids:
    page = Ids()
    page.feed(dom)
    return page

