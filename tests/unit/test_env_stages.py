"""Stage processes (``env.stage_processes``): each pipeline stage simulated and served by a process
of its own, streaming straight to the rollout.

* What the rollout receives is exactly what stepping the rank's stages one by one in a single
  process gives (where a stage runs never changes what it simulates).
* A stage that fails is reported with its own traceback (stage, rank, pid); the rollout's side sees
  ``EnvLinkClosed``, the symptom. A stage process that dies is reported with its signal.
* The runner shows the env's error, not the rollout's closed link, and the reverse.
"""

from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pytest

pytest.importorskip("gymnasium")

from infinirl.components.env_link import EnvLinkClosed, connect  # noqa: E402
from infinirl.components.env_stages import EnvStageError, StageProcess, serve_in_stage_processes  # noqa: E402
from infinirl.components.env_worker import EnvSpec, StagedEnv  # noqa: E402
from infinirl.runners.embodied import _raise_env_root_cause  # noqa: E402
from infinirl.runtime.errors import WorkerError  # noqa: E402

STAGES, ENVS, ROUNDS, RANK = 2, 4, 6, 1
SPEC = EnvSpec(name="gym:Pendulum-v1", num_envs=ENVS, stages=STAGES, num_workers=0, max_episode_steps=4, seed=3,
               stage_processes=True)
SEEDS = [11, 12, 13, 14]


def scripted_actions():
    rng = np.random.default_rng(0)
    return [[rng.uniform(-2, 2, (ENVS // STAGES, 1)).astype(np.float32) for _ in range(STAGES)]
            for _ in range(ROUNDS)]


def stepped_in_one_process() -> list[list[dict]]:
    """Per stage, the messages one process stepping the whole rank produces."""
    env = StagedEnv(EnvSpec(**{**SPEC.__dict__, "stage_processes": False}), RANK)
    try:
        per_stage = [[m] for m in env.reset(SEEDS)]
        for actions in scripted_actions():
            for stage in range(STAGES):
                per_stage[stage].append(env.step(stage, actions[stage]))
        return per_stage
    finally:
        env.close()


class Stages:
    """A rank's stage processes with the rollout's links connected (what EnvWorker + rollout do)."""

    def __init__(self, spec=SPEC):
        self.procs = [StageProcess(spec, RANK, s) for s in range(spec.stages)]
        for proc in self.procs:
            proc.wait_ready()
        addresses = [proc.open_link("AF_UNIX") for proc in self.procs]
        for proc in self.procs:
            proc.accept_link()
        self.links = [connect(a) for a in addresses]
        for proc in self.procs:
            proc.wait_accepted()

    def serve_in_background(self, num_steps=ROUNDS):
        outcome = {}

        def target():
            try:
                outcome["stats"] = serve_in_stage_processes(self.procs, SPEC.stage_sizes(), SEEDS, num_steps)
            except BaseException as exc:  # noqa: BLE001 - handed to the test thread
                outcome["error"] = exc

        thread = threading.Thread(target=target, daemon=True)
        thread.start()
        return thread, outcome

    def serve_past_reset(self):
        """Start serving and read every stage's first (reset) message; the thread and its outcome."""
        thread, outcome = self.serve_in_background()
        for link in self.links:
            link.recv()
        return thread, outcome

    def close(self):
        for link in self.links:
            link.close()
        for proc in self.procs:
            proc.close()


def test_stage_processes_send_what_one_process_gives():
    stages = Stages()
    try:
        thread, outcome = stages.serve_in_background()
        received = [[stages.links[s].recv()] for s in range(STAGES)]
        for actions in scripted_actions():
            for s in range(STAGES):
                stages.links[s].send((s, actions[s]))
                received[s].append(stages.links[s].recv())
        thread.join(30)
        assert "error" not in outcome, outcome.get("error")
        assert outcome["stats"]["env/simulate_s"] > 0
        assert outcome["stats"]["env/simulate_max_stage_s"] <= outcome["stats"]["env/simulate_s"]
    finally:
        stages.close()
    expected = stepped_in_one_process()
    for s in range(STAGES):
        assert len(received[s]) == len(expected[s]) == ROUNDS + 1
        for got, want in zip(received[s], expected[s]):
            np.testing.assert_array_equal(got["obs"]["state"], want["obs"]["state"])
            for key in ("reward", "terminated", "truncated", "ended"):
                if key in want:
                    np.testing.assert_array_equal(got[key], want[key])
    assert any(len(m.get("ended", [])) for m in received[0])  # episodes ended and auto-reset in a stage


def test_a_failing_stage_reports_its_own_traceback_and_the_rollout_sees_a_closed_link():
    stages = Stages()
    try:
        thread, outcome = stages.serve_past_reset()
        stages.links[0].send((0, np.zeros((ENVS // STAGES, 3), np.float32)))  # wrong action shape
        with pytest.raises(EnvLinkClosed):
            stages.links[0].recv()
        stages.links[1].close()  # the rollout gives up: stage 1 stops waiting for actions
        thread.join(30)
        error = outcome["error"]
        assert isinstance(error, EnvStageError)
        text = str(error)
        assert f"env stage 0 of rank {RANK}" in text and "pid" in text
        assert "expected actions of shape (2, 1)" in text  # the root cause, with its traceback
    finally:
        stages.close()


def test_a_stage_process_that_dies_is_reported_with_its_signal():
    stages = Stages()
    try:
        thread, outcome = stages.serve_past_reset()
        os.kill(stages.procs[1].pid, signal.SIGKILL)
        thread.join(30)
        error = outcome["error"]
        assert isinstance(error, EnvStageError)
        assert "env stage 1" in str(error) and "SIGKILL" in str(error)
        with pytest.raises(EnvLinkClosed):
            stages.links[1].recv()
    finally:
        stages.close()


def test_a_stage_that_cannot_build_fails_at_start_with_the_reason():
    bad = EnvSpec(**{**SPEC.__dict__, "kwargs": {"no_such_option": 1}})
    proc = StageProcess(bad, RANK, 0)
    try:
        with pytest.raises(EnvStageError, match="no_such_option"):
            proc.wait_ready()
    finally:
        proc.close()


class FakeServing:
    def __init__(self, error=None):
        self.error = error

    def wait(self, timeout=None):
        if self.error is not None:
            raise self.error
        return [{}]


def worker_error(component, last_line):
    return WorkerError(component, 0, "serve", "127.0.0.1", "host", 1, f"Traceback ...\n{last_line}\n")


def test_the_runner_shows_the_env_error_not_the_rollouts_closed_link():
    rollout = worker_error("rollout", "infinirl.components.env_link.EnvLinkClosed: the env link's other end closed it")
    env = worker_error("env", "ValueError: expected actions of shape (2, 1)")
    with pytest.raises(WorkerError) as raised:
        _raise_env_root_cause(FakeServing(env), rollout)
    assert raised.value is env


def test_the_runner_keeps_the_rollouts_own_error():
    rollout = worker_error("rollout", "RuntimeError: policy exploded")
    env = worker_error("env", "infinirl.components.env_link.EnvLinkClosed: the env link's other end closed it")
    _raise_env_root_cause(FakeServing(env), rollout)  # returns: the caller re-raises the rollout's error
    _raise_env_root_cause(None, rollout)
    # the rollout saw a closed link but the env finished or also saw one: nothing better to show
    _raise_env_root_cause(FakeServing(env), worker_error("rollout", "infinirl.components.env_link.EnvLinkClosed: x"))
    _raise_env_root_cause(FakeServing(), worker_error("rollout", "infinirl.components.env_link.EnvLinkClosed: x"))


def test_a_root_cause_reported_after_a_closed_link_still_wins():
    """Stage 1's link closes first (a symptom), stage 0 fails on its own a moment later: the error
    raised is stage 0's, not the closed link that happened to be reported first."""
    import time

    stages = Stages()
    try:
        thread, outcome = stages.serve_past_reset()
        stages.links[1].close()
        time.sleep(1.0)  # stage 1 reports its closed link before stage 0 fails
        stages.links[0].send((0, np.zeros((ENVS // STAGES, 3), np.float32)))  # wrong action shape
        thread.join(30)
        error = outcome["error"]
        assert isinstance(error, EnvStageError)
        assert "env stage 0 of rank" in str(error) and "expected actions of shape (2, 1)" in str(error)
    finally:
        stages.close()


BROKEN = EnvSpec(name="gym:Pendulum-v1", num_envs=ENVS, stages=STAGES, num_workers=0, max_episode_steps=4, seed=3,
                 kwargs={"g": "not a number"}, max_restarts=0)
"""Resets fine, raises on its first step (gravity must be a number); with max_restarts=0 the first
crash stops the env rank (EnvCrashError) instead of being rebuilt."""


def test_an_env_rank_without_stage_processes_that_fails_closes_its_link():
    """The env rank's own failure (an EnvCrashError here) closes its link, so the rollout waiting
    for the step fails at once with EnvLinkClosed instead of waiting forever, and the runner shows
    the env rank's error as the root cause."""
    from multiprocessing.connection import wait

    from infinirl.components.env_link import accept, open_server
    from infinirl.components.env_worker import EnvWorker
    from infinirl.envs.base import EnvCrashError
    from infinirl.runtime.worker import RankContext

    worker = EnvWorker.__new__(EnvWorker)
    worker.ctx = RankContext("env", 0, 1)
    worker.__init__(BROKEN)
    server, address = open_server("socket")
    worker._server = server
    connecting = threading.Thread(target=lambda: setattr(worker, "link", accept(server)), daemon=True)
    connecting.start()
    rollout = connect(address)
    connecting.join(10)
    outcome = {}

    def serve():
        try:
            outcome["stats"] = worker.serve(SEEDS, ROUNDS)
        except BaseException as exc:  # noqa: BLE001 - handed to the test thread
            outcome["error"] = exc

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        for _ in range(STAGES):
            rollout.recv()  # the reset
        rollout.send((0, np.zeros((ENVS // STAGES, 1), np.float32)))
        assert wait([rollout], timeout=30), "the rollout would wait forever for the failed step"
        with pytest.raises(EnvLinkClosed):
            rollout.recv()
        thread.join(30)
        assert not thread.is_alive()
        error = outcome["error"]
        assert isinstance(error, EnvCrashError) and "unsupported operand" in str(error)
        assert worker.link is None
        with pytest.raises(EnvCrashError):  # what the runner raises for the rollout's closed link
            _raise_env_root_cause(FakeServing(error), EnvLinkClosed("the env link's other end closed it"))
    finally:
        rollout.close()
        worker.close()


class FakeCollecting:
    """The rollout ranks' handle: still collecting for ``pending`` waits, then ``result``."""

    def __init__(self, pending, result=None):
        self.pending, self.result, self.waits = pending, result, []

    def wait(self, timeout=None):
        self.waits.append(timeout)
        if self.pending is None or (self.pending and timeout is not None):
            if self.pending:
                self.pending -= 1
            raise TimeoutError("still collecting")
        return self.result


class PendingServing(FakeServing):
    def __init__(self, error=None, pending=1):
        super().__init__(error)
        self.pending = pending

    def wait(self, timeout=None):
        if self.pending:
            self.pending -= 1
            raise TimeoutError("still serving")
        return super().wait(timeout)


def test_the_runner_raises_an_env_ranks_own_failure_while_the_rollout_still_waits():
    """Whatever keeps the rollout waiting (a link its failed env rank left open), the driver sees
    the env rank's own error within a watch period, not never."""
    from infinirl.runners.embodied import _wait_collecting

    env = worker_error("env", "infinirl.envs.base.EnvCrashError: 1 sub-env restarts exceed max_restarts=0")
    with pytest.raises(WorkerError) as raised:
        _wait_collecting(FakeCollecting(pending=None), PendingServing(env), watch_s=0.01)
    assert raised.value is env
    # a closed link on the env side is the rollout's failure: its own error is the one to wait for
    closed = worker_error("env", "infinirl.components.env_link.EnvLinkClosed: the env link's other end closed it")
    collecting = FakeCollecting(pending=2, result=["rollout"])
    assert _wait_collecting(collecting, PendingServing(closed), watch_s=0.01) == ["rollout"]
    assert collecting.waits[-1] is None  # no env left to watch: waits for the rollout alone
    # env ranks done, or collocated (no serving handle): only the rollout is waited for
    assert _wait_collecting(FakeCollecting(pending=1, result=["r"]), FakeServing(), watch_s=0.01) == ["r"]
    assert _wait_collecting(FakeCollecting(pending=0, result=["r"]), None) == ["r"]
