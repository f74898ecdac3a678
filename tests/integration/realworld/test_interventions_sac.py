"""Interventions in the real-world SAC runner: a simulated human takes over the simulated Sawyer
while SAC learns; the intervened steps reach the replay store with their flag, their stretches also
go into the RLPD demonstrations store, the human's success marks are the reward, and marked episodes
are saved as success-classifier labels."""

import importlib.util
import json

import numpy as np
import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None, reason="needs metaworld")

from infinirl.config import ConfigError  # noqa: E402
from infinirl.realworld.intervention.metrics import intervention_stats  # noqa: E402
from infinirl.realworld.intervention.segments import intervened_runs  # noqa: E402
from infinirl.realworld.replay import ReplayStore  # noqa: E402
from infinirl.runners.realworld_sac import run  # noqa: E402
from tests.integration.realworld.test_realworld_sac import make_cfg  # noqa: E402

HUMAN = {"device": "simulated_human", "reward": "human", "labels": True, "as_demos": True,
         "options": {"expert": "sawyer_goal", "threshold": 0.5, "reaction_steps": 1, "correct_steps": 12, "seed": 3}}
# 20 Hz: the hand moves up to 2 cm per control period, so the human's corrections reach the goal.
ROBOT = {"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 20.0, "image_size": None}}


def episodes_in(path):
    store = ReplayStore(str(path), writable=False)
    try:
        return [store.episode(i) for i in range(store.num_episodes)]
    finally:
        store.close()


def test_simulated_human_feeds_the_store_the_demos_and_the_reward(ray_cluster, tmp_path):
    out = tmp_path / "run"
    run(make_cfg(out, 1, interventions=HUMAN, robot=ROBOT, task={"max_episode_steps": 30},
                 pipeline={"mode": "sync", "iteration_s": 4.0, "durable": False},
                 algorithm={"batch_size": 32, "learning_starts": 40, "utd_ratio": 0.25}))
    row = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()][-1]
    assert row["intervention/rate"] > 0  # warm-up actions are uniform: the human takes over

    online = episodes_in(out / "replay")
    flags = np.concatenate([e["intervened"] for e in online])
    assert row["intervention/steps"] == flags.sum() > 0
    assert row["intervention/takeovers_per_episode"] == pytest.approx(
        np.mean([intervention_stats(e["intervened"]).takeovers for e in online]))
    # Human reward: 0 everywhere but the step a success mark followed, which ends its episode.
    for episode in online:
        assert set(np.unique(episode["reward"])) <= {0.0, 1.0}
        np.testing.assert_array_equal(episode["reward"], episode["terminated"])
        assert episode["terminated"][:-1].sum() == 0
    # RLPD: each intervened stretch is an episode of the demonstrations store, step for step.
    demos = episodes_in(out / "demos")
    stretches = [(e, a, b) for e in online for a, b in intervened_runs(e["intervened"])]
    assert len(demos) == len(stretches)
    for demo, (episode, start, stop) in zip(demos, stretches):
        np.testing.assert_array_equal(demo["action"], episode["action"][start:stop])
        np.testing.assert_array_equal(demo["state"], episode["state"][start:stop + 1])
    assert row["replay/intervention_demo_steps"] == flags.sum()
    # Success labels: one file per marked episode, the marked observation last.
    successes = [e for e in online if e["reward"].sum() == 1]
    labels = sorted((out / "success_labels").glob("rank0-*.npz"))
    assert len(labels) == len(successes) >= 1
    with np.load(labels[0]) as first:
        assert first["label"][-1] == 1 and first["label"][:-1].sum() == 0
        np.testing.assert_array_equal(first["state"], successes[0]["state"])


def test_intervention_config_errors_name_the_key(tmp_path):
    for extra, key in (({"interventions": {"device": "joystick"}}, "interventions.device"),
                       ({"interventions": {"reward": "human"}}, "interventions.reward")):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            make_cfg(tmp_path / "bad", 1, **extra).validate()
