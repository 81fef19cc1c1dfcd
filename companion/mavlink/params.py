"""Reading an autopilot's parameters by name (MAVLink parameter protocol).

``read_params`` sends ``PARAM_REQUEST_READ`` with ``param_index = -1`` for each name and waits for
the ``PARAM_VALUE`` that carries that name, resending up to ``retries`` times. Parameters that never
arrive are simply absent from the result: every caller has a configured fallback. Values that are
not finite are dropped and logged (a forged or garbled packet must not become a speed).

ArduPilot sends every value as a float in ``param_value`` whatever its type; PX4 packs integer
parameters bytewise into it. The parameters read here (speeds) are floats on both, so the value
is taken as it is.
"""

from __future__ import annotations

import asyncio
import logging
import math
import sys
from collections.abc import Iterable
from typing import Any

from companion.mavlink.link import MavLink

if sys.version_info >= (3, 11):
    from asyncio import timeout as _timeout
else:  # Python 3.10 (JetPack 6): the package asyncio.timeout was taken from
    from async_timeout import timeout as _timeout

log = logging.getLogger(__name__)

#: MAVLink's ``param_id`` holds at most 16 characters.
MAX_NAME = 16


def _name(raw: Any) -> str:
    if isinstance(raw, (bytes, bytearray)):
        raw = bytes(raw).decode("ascii", errors="replace")
    return str(raw).split("\x00", 1)[0]


async def read_params(link: MavLink, names: Iterable[str], *, timeout_s: float = 1.0, retries: int = 2,
                      target_component: int | None = None) -> dict[str, float]:
    """The values of ``names`` the autopilot answered, by name (absent: not answered in time).

    Each round requests every name still missing, then waits ``timeout_s`` for answers; at most
    ``1 + retries`` rounds. Raises ``ValueError`` for a name MAVLink cannot carry."""
    wanted = list(dict.fromkeys(names))
    for name in wanted:
        if not name or len(name) > MAX_NAME or not name.isascii():
            raise ValueError(f"parameter name {name!r} is not a MAVLink param_id (1-16 ASCII characters)")
    got: dict[str, float] = {}
    arrived = asyncio.Event()

    def on_value(msg: Any, _t: float) -> None:
        name = _name(msg.param_id)
        if name not in wanted or name in got:
            return
        value = float(msg.param_value)
        if not math.isfinite(value):
            log.warning("parameter %s arrived as %r: ignored", name, value)
            return
        got[name] = value
        if len(got) == len(wanted):
            arrived.set()

    unsubscribe = link.subscribe("PARAM_VALUE", on_value)
    try:
        component = link.config.target_component if target_component is None else target_component
        for _ in range(retries + 1):
            for name in wanted:
                if name not in got:
                    link.send(link.mav.param_request_read_encode(link.target_system, component,
                                                                 name.encode("ascii"), -1))
            try:
                async with _timeout(timeout_s):
                    await arrived.wait()
            except (TimeoutError, asyncio.TimeoutError):  # one class from 3.11 on
                continue
            break
    finally:
        unsubscribe()
    missing = [n for n in wanted if n not in got]
    if missing:
        log.info("autopilot did not answer for parameter(s) %s", ", ".join(missing))
    return got
