"""Evaluation episodes measure the policy alone: the control loop holds the intervention device off
for them (and for scripted demonstrations), so the web page refuses a take-over and says why, and a
device that reports a human action anyway is not obeyed; its marks judge nothing. Training episodes
open to the human again."""

import logging

import numpy as np
import pytest

pytest.importorskip("metaworld")

from infinirl.config import to_dataclass  # noqa: E402
from infinirl.realworld.control_loop import RobotControlLoop  # noqa: E402
from infinirl.realworld.intervention.device import INTERVENTION_DEVICES, HumanInput, InterventionDevice  # noqa: E402
from infinirl.realworld.intervention.spec import InterventionSpec  # noqa: E402
from infinirl.runners.realworld_sac import env_spec_of, net_spec_of, robot_setup_of  # noqa: E402
from infinirl.runners.realworld_sac_config import RealWorldSACConfig  # noqa: E402
from tests.unit.realworld.test_intervention_web import TOKEN, call  # noqa: E402

STEPS = 5


class SteersAlways(InterventionDevice):
    """A device that knows nothing of ``hold_off`` (as one registered by another package may): at
    every poll the human holds control, steering every entry to +1, and marks success."""

    def poll(self, *, observation=None, policy_action=None) -> HumanInput:
        return HumanInput(active=True, action=np.ones(self.action_dim, np.float32), marks=("success",))


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(INTERVENTION_DEVICES._entries, "test_steers_always", SteersAlways)


def a_loop(tmp_path, intervention: InterventionSpec) -> RobotControlLoop:
    cfg = to_dataclass(RealWorldSACConfig, {
        "output_dir": str(tmp_path / "run"),
        "robot": {"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 100.0}},
        "task": {"max_episode_steps": STEPS}, "network": {"actor_hidden": [16], "critic_hidden": [16]}})
    return RobotControlLoop(robot_setup_of(cfg), env_spec_of(cfg), net_spec_of(cfg), seed=0, intervention=intervention)


def test_the_page_refuses_a_take_over_while_the_robot_evaluates_and_opens_again_for_training(tmp_path):
    loop = a_loop(tmp_path, InterventionSpec(device="web", options={"token": TOKEN, "heartbeat_timeout_s": None}))
    device = loop.intervention_device
    try:
        ones = [1.0] * loop.action_dim
        assert call(device, "/api/takeover", {"action": ones})[0] == 200
        [episode] = loop.collect(1)
        assert episode["intervened"].all() and np.allclose(episode["action"], 1.0)  # the human steered

        assert loop.evaluate(1)["eval/episodes"] == 1
        status, state = call(device, "/api/state")
        assert state["held_off"] == "evaluation" and state["released_by"] == "evaluation" and not state["active"]
        status, answer = call(device, "/api/takeover", {"action": ones})
        assert status == 409 and answer["held_off"] == "evaluation"
        assert "evaluation episode is running" in answer["error"] and "next training episode" in answer["error"]

        [episode] = loop.collect(1)  # a training episode: the page opens again, the refused take-over stays refused
        assert call(device, "/api/state")[1]["held_off"] is None and not episode["intervened"].any()
        assert call(device, "/api/takeover", {"action": ones})[0] == 200
        [episode] = loop.collect(1)
        assert episode["intervened"].all()
        assert device.stats.refused_takeovers == 1 and loop.counts["refused_human_steps"] == 0
    finally:
        loop.close()


def test_a_device_that_reports_a_human_during_an_evaluation_is_not_obeyed(tmp_path, caplog, registered):
    loop = a_loop(tmp_path, InterventionSpec(device="test_steers_always"))
    try:
        with caplog.at_level(logging.WARNING, logger="infinirl.realworld.control_loop"):
            metrics = loop.evaluate(2)
        assert metrics["eval/episodes"] == 2 and metrics["eval/length_mean"] == STEPS  # no mark ended one
        assert loop.intervention_device.held_off == "evaluation"
        assert loop.counts["refused_human_steps"] == 2 * STEPS and loop.counts["marks_ignored"] == 2 * STEPS
        assert loop.counts["marks_success"] == 0 and loop.counts["episodes"] == 0  # nothing labelled or counted
        assert caplog.text.count("reports a take-over; not executed") == 2  # once per episode

        # Every executed action of an evaluation episode is the deterministic policy's for its state.
        episode, _ = loop._episode(deterministic=True, training=False)
        assert not episode["intervened"].any() and len(episode["action"]) == STEPS
        for state, action in zip(episode["state"][:-1], episode["action"], strict=True):
            np.testing.assert_allclose(action, loop.act({"state": state}, deterministic=True)[0], atol=1e-6)
        assert not np.allclose(episode["action"], 1.0)

        [episode] = loop.collect(1)  # training: the device's human is obeyed again
        assert loop.intervention_device.held_off is None
        assert episode["intervened"].all() and np.allclose(episode["action"], 1.0)
    finally:
        loop.close()
