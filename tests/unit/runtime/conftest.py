"""Runtime tests kill worker processes on purpose; keep Ray's report of those deaths out of the output.

How the report gets there: when a worker process exits unexpectedly, its raylet publishes "A
worker died or was killed while executing a task by an unexpected system error ... Worker PID:
<pid> ... (1) the process was killed by the OOM killer ..." to the driver. Every Ray driver runs
a thread (``ray._private.worker.listen_error_messages``) that prints such messages to stdout
through ``ray._private.worker.print_to_stdstream``, whatever ``log_to_driver`` says, at whatever
moment they arrive (also between tests, or after pytest stopped capturing).

A test that kills a rank on purpose declares the process with the ``deliberate_deaths`` fixture
(``deliberate_deaths(pid, ...)``); raylet messages that name one of those pids are dropped, every
other message (an unexpected death, any other error) is printed as before.
"""

import re

import pytest

_expected_pids: set[int] = set()
_WORKER_PID = re.compile(r"Worker PID: (\d+)")


def about_a_deliberate_death(line: str) -> bool:
    """Whether a raylet message reports the death of a process a test killed on purpose."""
    match = _WORKER_PID.search(line)
    return bool(match) and int(match[1]) in _expected_pids


def _install_filter() -> None:
    import ray._private.worker as ray_worker

    original = ray_worker.print_to_stdstream
    if getattr(original, "drops_deliberate_deaths", False):
        return

    def print_to_stdstream(data, ignore_prefix: bool):
        if data.get("pid") == "raylet":
            lines = [line for line in data.get("lines", []) if not about_a_deliberate_death(line)]
            if not lines:
                return
            data = {**data, "lines": lines}
        return original(data, ignore_prefix)

    print_to_stdstream.drops_deliberate_deaths = True
    ray_worker.print_to_stdstream = print_to_stdstream


@pytest.fixture
def deliberate_deaths():
    """Call with the pids of worker processes the test is about to kill or crash."""
    _install_filter()

    def expect(*pids: int) -> None:
        _expected_pids.update(int(pid) for pid in pids if pid)

    return expect
