"""EnvWorker.serve (``serve_stages``): what the rollout receives does not depend on how the env side schedules stages.

With simulator subprocesses the env worker starts a stage and finishes the *next* one (so stages
simulate at once); with the sub-envs in its own process it simulates each stage as soon as its
actions arrive. Both must hand the rollout exactly the messages that stepping the stages one by one
gives, in the order it reads them (stage 0, 1, ..., per round). On the iteration's last round
episodes that end are not reset (the next iteration resets every env with its own seed).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gymnasium")

from infinirl.components.env_worker import EnvSpec, StagedEnv, serve_stages  # noqa: E402

STAGES, ENVS, ROUNDS = 2, 4, 6
EPISODE = 3  # episodes end at rounds 3 and 6: mid-iteration and on the last round


class ScriptedLink:
    """The rollout's side, scripted: hands out fixed actions per (round, stage), records messages."""

    def __init__(self, actions):
        self._actions = iter(actions)
        self.sent = []

    def recv(self):
        return next(self._actions)

    def send(self, message):
        self.sent.append(message)


def scripted_actions():
    rng = np.random.default_rng(0)
    return [(stage, rng.uniform(-2, 2, (ENVS // STAGES, 1)).astype(np.float32))
            for _ in range(ROUNDS) for stage in range(STAGES)]


def served(num_workers: int) -> tuple[list, bool]:
    env = StagedEnv(EnvSpec(name="gym:Pendulum-v1", num_envs=ENVS, stages=STAGES, num_workers=num_workers,
                            max_episode_steps=EPISODE))
    link = ScriptedLink(scripted_actions())
    try:
        stats = serve_stages(env, link, seeds=list(range(ENVS)), num_steps=ROUNDS)
        assert stats["env/simulate_s"] > 0
        return link.sent, env.simulates_in_background
    finally:
        env.close()


def stepped_one_by_one() -> list:
    env = StagedEnv(EnvSpec(name="gym:Pendulum-v1", num_envs=ENVS, stages=STAGES, num_workers=0,
                            max_episode_steps=EPISODE))
    try:
        messages = env.reset(list(range(ENVS)))
        last_round = (ROUNDS - 1) * STAGES
        messages += [env.step(stage, actions, autoreset=i < last_round)
                     for i, (stage, actions) in enumerate(scripted_actions())]
        return messages
    finally:
        env.close()


@pytest.mark.parametrize("num_workers", [0, 1])
def test_serve_sends_what_stepping_stage_by_stage_gives(num_workers):
    sent, background = served(num_workers)
    assert background == (num_workers > 0)
    expected = stepped_one_by_one()
    assert len(sent) == len(expected) == STAGES * (ROUNDS + 1)
    for got, want in zip(sent, expected):
        np.testing.assert_array_equal(got["obs"]["state"], want["obs"]["state"])
        for key in ("reward", "terminated", "truncated", "ended"):
            if key in want:
                np.testing.assert_array_equal(got[key], want[key])
    mid, last = sent[EPISODE * STAGES:(EPISODE + 1) * STAGES], sent[-STAGES:]
    for message in mid + last:
        assert len(message["ended"]) == ENVS // STAGES  # every episode ended here
    for message in mid:  # ... and mid-iteration a new one began at once
        assert not np.array_equal(message["obs"]["state"], message["final_obs"]["state"])
    for message in last:  # on the last round nothing was reset: the obs is the final one
        np.testing.assert_array_equal(message["obs"]["state"], message["final_obs"]["state"])


class _Plan:
    """The placement facts the embodied runner's env layout reads: env and rollout on disjoint slots."""

    def relation(self, a, b):
        return "disjoint"

    def world_size(self, component):
        return 1


@pytest.mark.parametrize("runner", ["embodied", "sac"])
def test_env_step_timeout_and_max_restarts_reach_every_vector_env(runner):
    """env.step_timeout_s (a hung simulator worker is replaced) and env.max_restarts go from the
    config to the VectorEnv the runner's workers build; by default a generous timeout is set."""
    from infinirl.config import to_dataclass
    from infinirl.envs.vector import VectorEnv

    env = {"name": "gym:Pendulum-v1", "num_envs": 2, "num_workers": 1}
    if runner == "embodied":
        from infinirl.runners.embodied import _layout
        from infinirl.runners.embodied_config import EmbodiedConfig

        def vector_envs(section):
            cfg = to_dataclass(EmbodiedConfig, {"env": section, "rollout_steps": 32,
                                                "placement": {"env": "0", "rollout": "1"}})
            _, spec = _layout(cfg, _Plan())
            staged = StagedEnv(spec)
            return staged.envs, staged.close
    else:
        from infinirl.runners.sac import collector_env_spec
        from infinirl.runners.sac_config import SACConfig

        def vector_envs(section):
            built = collector_env_spec(to_dataclass(SACConfig, {"env": section})).build(1)
            return [built], built.close

    envs, close = vector_envs({**env, "step_timeout_s": 7.5, "max_restarts": 3})
    try:
        assert envs and all(isinstance(e, VectorEnv) for e in envs)
        assert {(e._step_timeout_s, e._max_restarts) for e in envs} == {(7.5, 3)}
    finally:
        close()
    envs, close = vector_envs({**env, "num_workers": 0, "step_timeout_s": None})
    try:
        assert {(e._step_timeout_s, e._max_restarts) for e in envs} == {(None, 100)}
    finally:
        close()


def test_the_env_step_timeout_defaults_to_a_generous_bound_and_may_change_on_resume():
    """Neither key feeds a checkpoint's state, so a run resumes with new values (and from a
    checkpoint written before the keys existed)."""
    from infinirl.runners.embodied_config import EmbodiedConfig
    from infinirl.runners.sac_config import SACConfig
    from infinirl.runners.sim_config import SimEnvConfig

    assert SimEnvConfig().step_timeout_s == 300.0 and SimEnvConfig().max_restarts == 100
    for cfg in (EmbodiedConfig(), SACConfig()):
        assert cfg.resume_may_change("env.step_timeout_s") and cfg.resume_may_change("env.max_restarts")
