"""A mark the person gives while the robot resets, after the episode they judged ended and before
the next one's first step, goes to the episode that ended: the asynchronous control loop holds each
episode back until the next one's first poll. Without that it would have no step to reward and
would only be counted (on a real arm the reset takes seconds: the moment people click)."""

import threading
import time

import numpy as np
import pytest

pytest.importorskip("metaworld")

from infinirl.config import to_dataclass  # noqa: E402
from infinirl.realworld.control_loop import _OUTBOX_EPISODES, RobotControlLoop  # noqa: E402
from infinirl.realworld.driver import RobotError  # noqa: E402
from infinirl.realworld.intervention.device import HumanInput, InterventionDevice  # noqa: E402
from infinirl.realworld.intervention.human_reward import MARK_REWARD  # noqa: E402
from infinirl.realworld.intervention.spec import InterventionSpec  # noqa: E402
from infinirl.runners.realworld_sac import env_spec_of, net_spec_of, robot_setup_of  # noqa: E402
from infinirl.runners.realworld_sac_config import RealWorldSACConfig  # noqa: E402
from tests.unit.realworld.running_loop import run_async  # noqa: E402

STEPS = 5


class MarksDuringTheReset(InterventionDevice):
    """A person who marks every episode a success once it has ended, while the robot resets: the
    mark reaches the device after the loop's last poll of that episode (here: when the loop calls
    ``reset`` for the next one), so the next episode's first poll delivers it."""

    def __init__(self, *, action_dim: int) -> None:
        super().__init__(action_dim=action_dim)
        self.resets, self.pending = 0, []

    def reset(self) -> None:
        self.resets += 1
        if self.resets > 1:
            self.pending.append("success")

    def poll(self, *, observation=None, policy_action=None) -> HumanInput:
        marks, self.pending = tuple(self.pending), []
        return HumanInput(active=False, marks=marks)


class MarksEachEpisodeAsTheRobotResets(InterventionDevice):
    """A person who marks every episode they watched a success while the robot resets for the next
    one, whatever kind that is: the mark waits in the device for the next episode's first poll."""

    def __init__(self, *, action_dim: int) -> None:
        super().__init__(action_dim=action_dim)
        self.env, self.previous_steps, self.given = None, None, 0

    def bind(self, env) -> None:
        self.env = env

    def poll(self, *, observation=None, policy_action=None) -> HumanInput:
        steps, previous, self.previous_steps = self.env.steps, self.previous_steps, self.env.steps
        if steps == 0 and previous not in (None, 0):  # a new episode: the last one was watched to its end
            self.given += 1
            return HumanInput(active=False, marks=("success",))
        return HumanInput(active=False)


def a_loop(tmp_path, device=MarksDuringTheReset) -> RobotControlLoop:
    cfg = to_dataclass(RealWorldSACConfig, {
        "output_dir": str(tmp_path / "run"),
        "robot": {"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 100.0}},
        "task": {"max_episode_steps": STEPS}, "network": {"actor_hidden": [16], "critic_hidden": [16]}})
    loop = RobotControlLoop(robot_setup_of(cfg), env_spec_of(cfg), net_spec_of(cfg), seed=0)
    loop.intervention = InterventionSpec(device="simulated_human", reward="human")
    loop.intervention_device = device(action_dim=loop.action_dim)
    loop.intervention_device.bind(loop.env)
    return loop


def test_a_mark_given_while_the_robot_resets_rewards_the_episode_that_ended(tmp_path):
    loop = a_loop(tmp_path)
    sent, _, stats = run_async(loop, 3, 60)
    marked = loop.intervention_device.resets - 1  # every reset after the first brought a mark
    assert len(sent) >= 3 and marked >= len(sent) - 1
    for episode in sent[:-1]:  # each held back until the next one's first poll brought its mark
        assert len(episode["action"]) == STEPS
        assert episode["reward"][-1] == MARK_REWARD["success"] and np.all(episode["reward"][:-1] == 0.0)
        assert episode["terminated"][-1]
    assert stats["counts"]["marks_success"] == marked
    assert stats["counts"]["successes"] >= len(sent) - 1
    assert stats["counts"]["episodes"] == len(sent)  # the last one, held when the loop stopped, is sent too


def test_a_mark_given_while_the_robot_resets_for_an_evaluation_goes_to_the_training_episode_that_ended(tmp_path):
    """An evaluation requested between two training episodes starts with a reset too: the mark given
    then judges the training episode that ended, not the evaluation episode nor the next training one."""
    loop = a_loop(tmp_path, MarksEachEpisodeAsTheRobotResets)
    sent, lock = [], threading.Lock()

    def submit(episode):
        with lock:
            sent.append(episode)

    def wait_for(count):
        deadline = time.monotonic() + 60
        while len(sent) < count and time.monotonic() < deadline:
            time.sleep(0.02)
        assert len(sent) >= count

    try:
        loop.start(submit)
        wait_for(2)
        evaluation = loop.evaluate(1)
        with lock:
            before_the_evaluation = len(sent)
        wait_for(before_the_evaluation + 3)  # training goes on after the evaluation
        stats = loop.stop()
    finally:
        loop.close()
    assert evaluation["eval/episodes"] == 1 and evaluation["eval/length_mean"] == STEPS  # no mark ended it
    # Every training episode but the one held when the loop stopped was marked, the one that ended just
    # before the evaluation (sent while it ran, or just after) included.
    for index, episode in enumerate(sent[:-1]):
        assert episode["reward"][-1] == MARK_REWARD["success"], f"training episode {index} lost its mark"
        assert len(episode["action"]) == STEPS and episode["terminated"][-1]
    assert stats["counts"]["marks_success"] == loop.intervention_device.given


def test_a_failed_sender_stops_the_control_loop(tmp_path):
    """Episodes that can no longer be delivered must not pile up while the robot keeps moving."""
    loop = a_loop(tmp_path)

    def submit(episode):
        raise ConnectionError("the learner's channel is gone")

    try:
        loop.start(submit)
        thread = loop._thread
        thread.join(30)
        assert not thread.is_alive()  # the control loop ended by itself
        assert loop._outbox.qsize() <= 1  # at most the episode the sender never took
        with pytest.raises(RobotError, match="the learner's channel is gone"):
            loop.stats()
    finally:
        with pytest.raises(RobotError):
            loop.close()


def test_a_slow_sender_pauses_the_robot_at_a_bounded_outbox(tmp_path):
    loop = a_loop(tmp_path)
    proceed, sent = threading.Event(), []

    def submit(episode):
        proceed.wait(30)
        sent.append(episode)

    try:
        loop.start(submit)
        deadline = time.monotonic() + 60
        while loop.counts["outbox_full_waits"] == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert loop.counts["outbox_full_waits"] == 1 and loop._outbox.qsize() == _OUTBOX_EPISODES
        episodes = loop.counts["episodes"]
        time.sleep(0.5)
        assert loop.counts["episodes"] == episodes  # paused: no episode finished meanwhile
        proceed.set()
        stats = loop.stop()
        assert stats["counts"]["episodes_sent"] == len(sent) == stats["counts"]["episodes"]
    finally:
        proceed.set()
        loop.close()
