"""Turn-taking between benchmark rows that run side by side, one iteration at a time, in rotation.

Why: a shared VM's speed drifts by tens of percent over minutes (this project's 2-core machine:
the same PPO row measured 1,300 and 2,000 env-steps/s ten minutes apart). Rows run one after the
other then compare different spells of the machine, and a ratio of two such rows says more about
the spell than about the code. Here every row's process starts at once and the rows take turns:
one row runs one iteration while the others wait, then the next row, and so on. The i-th
iteration of every row runs within a few seconds of the others', so a slow spell lands on all of
them alike, and each cycle's ratio compares measurements taken under the same conditions. A row
never runs while another does, so they never compete for the cores.

A waiting row is frozen: every process of its session (its runner, and the Ray instance, workers
and simulators it started) is stopped with SIGSTOP until its turn. Blocking on a pipe alone is not
enough: a waiting row's Ray processes keep waking up (each Ray worker's main thread every 10 ms),
~10% of a core per idle Ray instance on this project's 2-core machine, and that load fell on the
row whose turn it was, the more so the more of the cores that row needs (a pipelined row uses
both; a sequential one leaves one mostly free). Frozen, the other rows take no CPU, as if the row
ran alone. A row is frozen only once it is blocked waiting for its next turn, after its work
between turns (logging, progress), so that work never overlaps another row's turn either.

The protocol, over two pipes per row (stdlib only; the child finds its ends in ``$INFINIRL_BENCH_TURNS``):

* child -> conductor ``r``: ready for a turn (then blocks until it is granted);
* conductor -> child ``g``: go;
* child -> conductor ``d``: the turn's work is done.

A row takes one turn per measured unit of work (a PPO iteration) and then one last turn for what
it does after its loop (final evaluation, checkpoint, shutdown), which the conductor grants to all
rows at once when every cycle is over, so that work never overlaps a measured iteration. A row that
exits or crashes closes its pipe; the conductor then stops every row and reports the failing row's
stderr.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import tempfile
from collections.abc import Sequence

ENV_VAR = "INFINIRL_BENCH_TURNS"
_STOP_TIMEOUT_S = 30.0


def _session_pids(session: int) -> list[int]:
    """Every live process of ``session``, read from Linux's ``/proc`` (empty where there is none:
    :func:`_signal_session` then signals the leader's process group only)."""
    pids = []
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as stat:
                fields = stat.read().rpartition(")")[2].split()
        except OSError:
            continue  # it exited meanwhile
        if int(fields[3]) == session:  # fields after the command: state, ppid, pgrp, session
            pids.append(int(entry))
    return pids


def _signal_session(session: int, sig: int) -> None:
    """``sig`` to every process of the session a row leads (Ray's workers each lead a process
    group of their own inside it, so the row's process group alone would miss them)."""
    pids = _session_pids(session)
    if not pids:
        try:
            os.killpg(session, sig)
        except ProcessLookupError:
            pass
        return
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass


class RowFailed(RuntimeError):
    """A row's process ended (or broke the protocol) before its turns were over; ``row`` names it."""

    def __init__(self, message: str, row: str | None = None):
        super().__init__(message)
        self.row = row


class Turn:
    """The child's side: ``with turn: <one iteration>``; :meth:`take` alone for the last turn."""

    def __init__(self, read_fd: int, write_fd: int):
        self._read, self._write = read_fd, write_fd

    @classmethod
    def from_env(cls) -> Turn | None:
        """The turn of this process if a conductor started it, else None (the row runs freely)."""
        value = os.environ.get(ENV_VAR)
        if not value:
            return None
        read_fd, write_fd = (int(part) for part in value.split(","))
        return cls(read_fd, write_fd)

    def take(self) -> None:
        """Say we are ready and block until the conductor grants the turn."""
        os.write(self._write, b"r")
        if os.read(self._read, 1) != b"g":
            raise RowFailed("the benchmark's conductor went away")

    def __enter__(self) -> Turn:
        self.take()
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            os.write(self._write, b"d")


#: The embodied flow's method that runs one iteration (the run loop calls it once per iteration).
EMBODIED_STEP = "step"


def gate_embodied_runner() -> None:
    """In a row's process started by a :class:`Conductor`: each ``EmbodiedFlow.step`` (one
    iteration) in a turn of its own, and what follows the last iteration in one more. The runner's
    own timing (``time/iteration_s``) is inside the turn, so waiting for a turn is never measured."""
    turn = Turn.from_env()
    if turn is None:
        return
    from infinirl.runners.embodied import EmbodiedFlow

    original = getattr(EmbodiedFlow, EMBODIED_STEP, None)
    if not callable(original):
        raise RuntimeError(f"infinirl.runners.embodied.EmbodiedFlow has no method {EMBODIED_STEP!r} to run in turns; "
                        "point _bench_turns.EMBODIED_STEP at the method the run loop calls once per iteration")

    @functools.wraps(original)
    def step(self, index: int) -> dict:
        with turn:
            metrics = original(self, index)
        if index + 1 == self.cfg.iterations:
            turn.take()  # the last turn: the final evaluation, checkpoint and shutdown
        return metrics

    setattr(EmbodiedFlow, EMBODIED_STEP, step)


class _Row:
    def __init__(self, name: str, cmd: Sequence[str], env: dict):
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()
        self.name = name
        self.stdout = tempfile.TemporaryFile(mode="w+")
        self.stderr = tempfile.TemporaryFile(mode="w+")
        # A session of its own, so that stopping the row reaches what it started (Ray, simulators).
        # SIGINT back to its default in the row: a benchmark started in the background (nohup, &)
        # inherits it ignored, and the row would then not hear the stop.
        self.process = subprocess.Popen(list(cmd), env={**env, ENV_VAR: f"{to_child_r},{from_child_w}"},
                                        stdout=self.stdout, stderr=self.stderr,
                                        pass_fds=(to_child_r, from_child_w), start_new_session=True,
                                        preexec_fn=_default_sigint)
        os.close(to_child_r)
        os.close(from_child_w)  # the child's exit is then EOF here
        self.ready = False

    def expect(self, token: bytes, doing: str) -> None:
        got = os.read(self._from_child, 1)
        if got != token:
            if not got:
                self.process.wait()  # it closed its pipe: it is exiting
            what = "exited" if not got else f"sent {got!r}"
            raise RowFailed(f"row {self.name} {what} while {doing} (exit code {self.process.returncode}):\n"
                            f"{self.stderr_tail()}", row=self.name)

    def await_ready(self) -> None:
        if not self.ready:
            self.expect(b"r", "starting or waiting for its turn")
            self.ready = True

    def grant(self) -> None:
        self.await_ready()
        os.write(self._to_child, b"g")
        self.ready = False

    def freeze(self) -> None:
        """Stop every process of this row's session (it is waiting for a turn)."""
        _signal_session(self.process.pid, signal.SIGSTOP)

    def thaw(self) -> None:
        _signal_session(self.process.pid, signal.SIGCONT)

    def stderr_tail(self, chars: int = 4000) -> str:
        self.stderr.seek(0)
        return self.stderr.read()[-chars:]

    def output(self) -> str:
        self.stdout.seek(0)
        return self.stdout.read()

    def stop(self) -> None:
        """Interrupt the row (its runner cleans up, Ray shuts down), then kill what is left."""
        if self.process.poll() is None:
            self.thaw()  # a frozen row would not act on SIGINT
            try:
                os.killpg(self.process.pid, signal.SIGINT)
                self.process.wait(_STOP_TIMEOUT_S)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.process.wait()

    def close(self) -> None:
        for fd in (self._to_child, self._from_child):
            try:
                os.close(fd)
            except OSError:
                pass
        self.stdout.close()
        self.stderr.close()


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Conductor:
    """Start rows at once and let them run their turns in rotation.

    ``run(turns)`` waits until every row is ready (start-up never overlaps a turn), then runs
    ``turns`` cycles. Cycle ``i`` gives each row one turn, in the row order rotated by ``i``, so no
    row always follows the same neighbour. Then every row gets its last turn at once and the
    conductor waits for all of them to exit. Returns each row's stdout."""

    def __init__(self, rows: dict[str, Sequence[str]], env: dict | None = None,
                 row_env: dict[str, dict] | None = None):
        """``rows``: name -> command; ``env``: their environment (default: this one's);
        ``row_env``: per row, variables to set on top (e.g. another checkout's PYTHONPATH)."""
        self.rows: list[_Row] = []
        base = dict(os.environ if env is None else env)
        try:
            for name, cmd in rows.items():
                self.rows.append(_Row(name, cmd, {**base, **(row_env or {}).get(name, {})}))
        except BaseException:
            self._stop_all()
            raise

    def run(self, turns: int, on_cycle=None) -> dict[str, str]:
        try:
            for row in self.rows:
                row.await_ready()
                row.freeze()
            for cycle in range(turns):
                shift = cycle % len(self.rows)
                for row in self.rows[shift:] + self.rows[:shift]:
                    row.thaw()
                    row.grant()
                    row.expect(b"d", f"running turn {cycle + 1} of {turns}")
                    row.await_ready()  # its work between turns is done: it waits for the next one
                    row.freeze()
                if on_cycle is not None:
                    on_cycle(cycle)
            for row in self.rows:
                row.thaw()
                row.grant()  # the last turn: whatever the row does after its loop, then exit
            outputs = {}
            for row in self.rows:
                code = row.process.wait()
                if code:
                    raise RowFailed(f"row {row.name} failed after its turns (exit code {code}):\n{row.stderr_tail()}",
                                    row=row.name)
                outputs[row.name] = row.output()
            return outputs
        except BaseException:
            self._stop_all()
            raise
        finally:
            for row in self.rows:
                row.close()

    def _stop_all(self) -> None:
        for row in self.rows:
            row.stop()
