"""Pipeline stages in processes of their own, each streaming straight to the rollout.

An :class:`~infinirl.components.env_worker.EnvWorker` normally simulates its stages itself, or
relays them to simulator subprocesses (``env.num_workers >= 1``). With ``env.stage_processes``
it instead starts one *stage process* per stage. Each stage process:

* builds exactly the envs that stage would have in the env worker (same seeds, same sizes), as a
  one-stage :class:`~infinirl.components.env_worker.StagedEnv`;
* opens its own link to the rollout rank;
* serves its stage with the same loop the env worker uses (:func:`serve_stages`).

Why: with K stages the simulators of different stages then run at the same time, on different
cores, and every message crosses one process boundary instead of two (rollout -> env worker ->
simulator -> env worker -> rollout). On CPU that is what lets a cheap policy pipelined with a
simulator use every core. The env worker stays the component Ray sees: it starts, feeds and
supervises its stage processes, and reports their failures as its own, with the stage's traceback.

Failure reporting: a stage that raises sends its traceback to the env worker and closes its link;
the rollout then sees :class:`~infinirl.components.env_link.EnvLinkClosed`, a secondary symptom the
runner drops in favour of the env worker's error. A stage process that dies without a word
(segfault, OOM kill) is reported with its exit code or signal. Sub-env exceptions inside a stage
are recovered in place as everywhere (the sub-env is rebuilt, its episode marked truncated).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import traceback
from multiprocessing.connection import wait
from typing import Any

from infinirl.components.env_worker import EnvSpec, StagedEnv, serve_stages

__all__ = ["EnvStageError", "StageProcess", "serve_in_stage_processes"]

_CLOSE_TIMEOUT_S = 5.0
SYMPTOM_GRACE_S = 5.0
"""How long a stage's closed-link failure waits for another stage's report: the link closes when
the stage at the other end failed, and that failure, not the closed link, is the root cause."""


class EnvStageError(RuntimeError):
    """A stage process failed; the message names the stage, rank and pid and holds its traceback."""


class StageProcess:
    """One pipeline stage of one env rank, simulated and served in a child process."""

    def __init__(self, spec: EnvSpec, rank: int, stage: int, start_method: str = "spawn"):
        context = mp.get_context(start_method)  # spawn: forking a process holding Ray/torch threads is unsafe
        self.spec, self.rank, self.stage = spec, rank, stage
        self._control, child_end = context.Pipe()
        self._process = context.Process(target=_stage_main, args=(child_end, spec, rank, stage), daemon=True,
                                        name=f"infinirl-env{rank}-stage{stage}")
        self._process.start()
        child_end.close()
        self._ready = False

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def wait_ready(self) -> None:
        """Block until the stage's envs are built (a bad env option fails here, at launch)."""
        if not self._ready:
            self._expect("built")
            self._ready = True

    def open_link(self, family: str | None) -> dict:
        """The address the rollout connects to for this stage."""
        self.wait_ready()
        self._control.send(("listen", family))
        return self._expect("listening")

    def accept_link(self) -> None:
        """Start accepting the rollout's connection (returns at once); see :meth:`wait_accepted`."""
        self._control.send(("accept",))

    def wait_accepted(self) -> None:
        self._expect("accepted")

    def start_serving(self, seeds: list[int], num_steps: int) -> None:
        self._control.send(("serve", [int(s) for s in seeds], int(num_steps)))

    def finish_serving(self) -> dict:
        return self._expect("served")

    @property
    def control(self):
        return self._control

    def close(self) -> None:
        if self._process.is_alive():
            try:
                self._control.send(("close",))
            except (OSError, EOFError):
                pass
            self._process.join(_CLOSE_TIMEOUT_S)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(_CLOSE_TIMEOUT_S)
        self._control.close()

    def _expect(self, what: str) -> Any:
        try:
            kind, payload = self._control.recv()
        except (EOFError, OSError):
            raise EnvStageError(f"env stage {self.stage} of rank {self.rank} (pid {self.pid}) died while "
                                f"{_doing(what)}: {self._exit_reason()}") from None
        if kind == "error":
            raise EnvStageError(payload)
        if kind != what:
            raise EnvStageError(f"env stage {self.stage} of rank {self.rank} answered {kind!r}, expected {what!r}")
        return payload

    def _exit_reason(self) -> str:
        self._process.join(1.0)
        code = self._process.exitcode
        if code is None:
            return "its control pipe closed, the process is still running"
        if code < 0:
            try:
                return f"killed by signal {signal.Signals(-code).name}"
            except ValueError:
                return f"killed by signal {-code}"
        return f"exit code {code}"


def serve_in_stage_processes(stages: list[StageProcess], sizes: list[int], seeds: list[int],
                             num_steps: int) -> dict:
    """One iteration on every stage process at once; raises the first stage failure as it happens,
    except that a stage whose link was closed under it waits a moment for a root cause elsewhere.

    ``env/simulate_s`` is the simulation time of all stages together (CPU seconds, comparable with
    the in-process env worker's); ``env/simulate_max_stage_s`` the busiest stage's share, the
    time simulation takes on the critical path when the stages run in parallel."""
    if len(seeds) != sum(sizes):
        raise ValueError(f"expected {sum(sizes)} seeds (one per env of this rank), got {len(seeds)}")
    start = 0
    for stage, size in zip(stages, sizes):
        stage.start_serving(seeds[start:start + size], num_steps)
        start += size
    waiting = {stage.control: stage for stage in stages}
    busy, symptom = [], None
    while waiting:
        ready = wait(list(waiting), timeout=SYMPTOM_GRACE_S if symptom is not None else None)
        if not ready:
            raise symptom
        for control in ready:
            try:
                busy.append(waiting.pop(control).finish_serving()["busy_s"])
            except EnvStageError as exc:
                if "EnvLinkClosed" not in str(exc):
                    raise
                symptom = symptom or exc  # another stage's failure may have closed it: wait for that one
    if symptom is not None:
        raise symptom
    return {"env/simulate_s": sum(busy), "env/simulate_max_stage_s": max(busy)}


def _doing(what: str) -> str:
    return {"built": "building its envs", "listening": "opening its link", "accepted": "waiting for the rollout",
            "served": "serving an iteration"}.get(what, what)


def _stage_main(control, spec: EnvSpec, rank: int, stage: int) -> None:
    """The stage process: build the stage's envs, then obey the env worker's commands until told
    to close or until the env worker is gone; a failure goes back to it with its traceback."""
    server = None
    try:
        server = _StageServer(spec, rank, stage)
        control.send(("built", None))
        _obey(control, server)
    except BaseException:
        text = f"env stage {stage} of rank {rank} (pid {os.getpid()}) failed:\n{traceback.format_exc()}"
        if server is not None:
            server.close_link()  # the rollout stops waiting for this stage at once
        try:
            control.send(("error", text))
        except (OSError, EOFError):
            pass
    finally:
        if server is not None:
            server.close()


def _obey(control, server: _StageServer) -> None:
    """Answer the env worker's commands, one reply each, until ``close`` or a closed pipe."""
    while True:
        try:
            command, *args = control.recv()
        except (EOFError, OSError):  # the env worker is gone: nothing left to serve
            return
        if command == "close":
            return
        handler = _STAGE_COMMANDS.get(command)
        if handler is None:
            raise RuntimeError(f"unknown stage command {command!r}")
        control.send(handler(server, *args))


class _StageServer:
    """What a stage process holds: its one-stage :class:`StagedEnv`, the server it listens on,
    and its link to the rollout once accepted. Each command returns the reply to send."""

    def __init__(self, spec: EnvSpec, rank: int, stage: int):
        self.env = StagedEnv(spec, rank, stages=[stage])
        self.server = self.link = None

    def listen(self, family: str | None) -> tuple[str, Any]:
        from infinirl.components.env_link import open_server

        self.server, address = open_server("socket", family=family)
        return "listening", address

    def accept(self) -> tuple[str, None]:
        from infinirl.components.env_link import accept

        self.link = accept(self.server)
        return "accepted", None

    def serve(self, seeds: list[int], num_steps: int) -> tuple[str, dict]:
        if self.link is None:
            raise RuntimeError("serve before the rollout connected (open_link/accept_link first)")
        stats = serve_stages(self.env, self.link, seeds, num_steps)
        return "served", {"busy_s": stats["env/simulate_s"]}

    def close_link(self) -> None:
        if self.link is not None:
            self.link.close()

    def close(self) -> None:
        if self.server is not None:
            from infinirl.components.env_link import close_server

            close_server(self.server)
        self.close_link()
        self.env.close()


_STAGE_COMMANDS = {"listen": _StageServer.listen, "accept": _StageServer.accept, "serve": _StageServer.serve}
