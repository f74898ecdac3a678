"""A vectoriser worker process, and the parent's handle on a worker, in-process or not.

:func:`worker_main` is what runs in a child process: it builds a :class:`SlotGroup` and serves the
parent's commands over a pipe. :class:`ProcessWorker` is the parent's side of that pipe; it turns a
dead or silent child into :class:`WorkerLost`, which :class:`~infinirl.envs.vector.VectorEnv`
answers by starting a replacement. :class:`LocalWorker` runs the same group in the calling process
behind the same interface (``num_workers=0``).
"""

from __future__ import annotations

import logging
import signal
import traceback
from collections.abc import Callable
from typing import Any

from infinirl.envs.base import EnvCrashError
from infinirl.envs.episode_slots import SlotGroup

__all__ = ["COMMANDS", "LocalWorker", "ProcessWorker", "WorkerLost", "close_workers", "worker_main"]

logger = logging.getLogger(__name__)

_CLOSE_TIMEOUT_S = 5.0


COMMANDS: dict[str, Callable[..., Any]] = {
    "reset": SlotGroup.reset,
    "step": SlotGroup.step,
    "render": SlotGroup.render,
    "close": SlotGroup.close,
}


def worker_main(conn, factory, indices, base_seed, generation, max_episode_steps) -> None:
    """Entry point of a worker process: build the slots, then serve commands until told to close
    or until the parent disappears (its end of the pipe closes)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    try:
        group = SlotGroup(factory, indices, base_seed, generation, max_episode_steps)
        conn.send(("ok", group.specs()))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
        conn.close()
        return
    while True:
        try:
            command, args = conn.recv()
        except (EOFError, OSError):
            break
        try:
            reply = ("ok", COMMANDS[command](group, *args))
        except Exception:
            reply = ("error", traceback.format_exc())
        conn.send(reply)
        if command == "close":
            break
    conn.close()



class WorkerLost(Exception):
    """The worker process died or stopped answering; the parent replaces it."""


class LocalWorker:
    """Runs a :class:`SlotGroup` in the calling process (``num_workers=0``)."""

    def __init__(self, factory, indices, base_seed, max_episode_steps) -> None:
        self.indices = list(indices)
        self._group = SlotGroup(factory, indices, base_seed, 0, max_episode_steps)
        self.specs = self._group.specs()
        self._pending: tuple[str, tuple] | None = None

    def send(self, command: str, *args: Any) -> None:
        self._pending = (command, args)

    def receive(self, timeout_s: float | None = None) -> Any:
        command, args = self._pending
        self._pending = None
        return COMMANDS[command](self._group, *args)

    def restart(self) -> None:  # a local worker cannot die without taking the parent with it
        raise AssertionError("in-process workers are never restarted")

    def close(self) -> None:
        self._group.close()


class ProcessWorker:
    """A child process owning ``indices``; ``receive`` turns death or silence into
    :class:`WorkerLost` and a Python error inside it into :class:`EnvCrashError`."""

    def __init__(self, context, factory, indices, base_seed, max_episode_steps) -> None:
        self.indices = list(indices)
        self._context = context
        self._args = (factory, self.indices, base_seed)
        self._max_episode_steps = max_episode_steps
        self.generation = 0
        self.process = None
        self._conn = None
        self.specs = None

    def start(self) -> None:
        parent_conn, child_conn = self._context.Pipe()
        factory, indices, base_seed = self._args
        self.process = self._context.Process(
            target=worker_main,
            args=(child_conn, factory, indices, base_seed, self.generation, self._max_episode_steps),
            name=f"infinirl-env-worker-{indices[0]}-{indices[-1]}",
            daemon=True,
        )
        self.process.start()
        child_conn.close()  # so that the child's death reads as EOF here
        self._conn = parent_conn

    def wait_ready(self) -> None:
        self.specs = self.receive()

    def send(self, command: str, *args: Any) -> None:
        try:
            self._conn.send((command, args))
        except (BrokenPipeError, OSError):
            pass  # the death is reported by the following receive

    def receive(self, timeout_s: float | None = None) -> Any:
        try:
            if not self._conn.poll(timeout_s):
                raise WorkerLost(f"no answer within {timeout_s} s")
            status, payload = self._conn.recv()
        except (EOFError, OSError, ConnectionError) as exc:
            self.process.join(_CLOSE_TIMEOUT_S)  # reap it, so the exit code is known
            raise WorkerLost(f"process died (exit code {self.process.exitcode})") from exc
        if status == "error":
            raise EnvCrashError(f"sub-envs {self.indices} failed in their worker process:\n{payload}")
        return payload

    def restart(self) -> None:
        self._stop(graceful=False)
        self.generation += 1
        self.start()
        self.wait_ready()

    def close(self) -> None:
        self._stop(graceful=True)

    def _stop(self, graceful: bool) -> None:
        if self.process is None:
            return
        if graceful and self.process.is_alive():
            self.send("close")
            try:
                self.receive(_CLOSE_TIMEOUT_S)
            except (WorkerLost, EnvCrashError):
                pass
            self.process.join(_CLOSE_TIMEOUT_S)
        if self.process.is_alive():
            self.process.kill()
        self.process.join()  # reaps the child: no zombie left behind
        self._conn.close()
        self.process = None


def close_workers(workers: list) -> None:
    for worker in workers:
        try:
            worker.close()
        except Exception:  # closing is best effort; one broken worker must not keep others open
            logger.exception("closing env worker %s failed", worker.indices)

