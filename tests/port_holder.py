"""The body of a process that reserves ports and holds them (tests/flights/test_sim_scale.py).

Its own module, so that the fork server the processes running it come from preloads
``sim.flights.flight`` and no more than that (not the test module and all it imports).
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

from sim.flights.flight import reserve_port


def reserve_and_hold(folder: str, count: int, barrier: Any, queue: Any) -> None:
    claims = [reserve_port(socket.SOCK_DGRAM if i % 2 else socket.SOCK_STREAM, Path(folder))
              for i in range(count)]
    queue.put((os.getpid(), [c.port for c in claims]))
    barrier.wait(timeout=60)  # every process holds its claims until all have reserved
    for c in claims:
        c.release()
