"""Run a robot control loop asynchronously in a test and collect what it sends."""

import threading
import time
from collections.abc import Callable
from typing import Any


def run_async(loop, episodes: int, timeout_s: float, meanwhile: Callable[[], Any] | None = None):
    """Start ``loop`` (episodes go to a list), wait until it has sent ``episodes`` (at most
    ``timeout_s``), call ``meanwhile()`` while it still runs, stop and close it. Returns the sent
    episodes, ``meanwhile``'s result and ``stop()``'s stats."""
    sent, lock = [], threading.Lock()

    def submit(episode):
        with lock:
            sent.append(episode)

    try:
        loop.start(submit)
        deadline = time.monotonic() + timeout_s
        while len(sent) < episodes and time.monotonic() < deadline:
            time.sleep(0.02)
        result = meanwhile() if meanwhile is not None else None
        stats = loop.stop()
    finally:
        loop.close()
    return sent, result, stats
