"""The noise-steering env (``vla_noise:<family>:<task>``, :mod:`infinirl.envs.noise_steering`): the frozen
VLA folded into the env. A step decodes the given initial noise with the VLA's deterministic sampler
(checked against the plain ``pi0_smollm2`` policy drawing that noise itself) and runs the chunk's
actions in the wrapped env, stopping where its episode ends; its observation is the steered policy's
features. Bad options are one-line errors before anything is built."""

import numpy as np
import pytest
import torch

pytest.importorskip("metaworld")

from infinirl.envs import check_env_kwargs, make_env  # noqa: E402
from infinirl.envs.metaworld_env import MetaWorldSubEnv  # noqa: E402
from infinirl.envs.noise_steering import FEATURES, noise_steering_factory  # noqa: E402
from infinirl.models.policies.base import build_policy  # noqa: E402
from infinirl.models.vla import save_vla  # noqa: E402
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla  # noqa: E402

TASK = "button-press-topdown-v3"
SIM = {"obs_mode": "state+rgb", "image_size": 16, "camera": "corner"}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return str(save_vla(tiny_vla(), tmp_path_factory.mktemp("vla") / "policy"))


def vla_options(checkpoint, chunk=2):
    return {"checkpoint": checkpoint, "chunk": chunk, "cameras": {"rgb": CAMERA}, "state_key": "proprio"}


def batch_of(obs):
    return {key: [value] if isinstance(value, str) else torch.as_tensor(np.asarray(value)[None])
            for key, value in obs.items()}


def test_a_step_runs_the_chunk_the_vla_decodes_from_the_given_noise(checkpoint):
    env = noise_steering_factory(f"metaworld:{TASK}", vla=vla_options(checkpoint), noise_bound=2.0,
                                 reward_offset=-1.0, **SIM)(0)
    reference = MetaWorldSubEnv(TASK, **SIM)
    plain = build_policy("pi0_smollm2", checkpoint=checkpoint, action_dim=4, chunk=2, cameras={"rgb": CAMERA},
                         state_key="proprio", value_head=False)
    try:
        assert env.action_space.shape == (int(np.prod(env.policy.noise_shape)),)
        assert np.all(env.action_space.high == 2.0) and np.all(env.action_space.low == -2.0)
        obs = env.reset(seed=3)
        inner_obs = reference.reset(seed=3)
        expected = env.policy.features(batch_of(inner_obs))[0][0].numpy()
        np.testing.assert_array_equal(obs[FEATURES], expected)
        for draw in range(2):
            torch.manual_seed(draw)
            drawn = plain.act(batch_of(inner_obs), deterministic=True)  # the VLA's own noise-free sampler
            noise, actions = drawn.extras["chain"][0, 0], drawn.actions[0].numpy()
            step = env.step(noise.reshape(-1).numpy())
            rewards = []
            for action in actions:
                inner = reference.step(action)
                rewards.append(inner.reward)
            inner_obs = inner.obs
            assert step.reward == pytest.approx(sum(rewards) - 1.0, rel=1e-6)  # the offset, once a decision
            assert not step.terminated and not step.truncated
            np.testing.assert_allclose(step.obs[FEATURES], env.policy.features(batch_of(inner_obs))[0][0].numpy(),
                                       rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(env.inner._sim.data.qpos, reference._sim.data.qpos, atol=1e-6)
    finally:
        env.close()
        reference.close()


def test_an_episode_that_ends_inside_a_chunk_stops_there(checkpoint):
    """MetaWorld's limit of 3 steps with chunks of 2: the second decision runs one action and is
    truncated; through the vectoriser an episode's length counts decisions."""
    env = noise_steering_factory(f"metaworld:{TASK}", vla=vla_options(checkpoint), max_episode_steps=3, **SIM)(0)
    try:
        env.reset(seed=0)
        noise = np.zeros(env.action_space.shape, np.float32)
        first, second = env.step(noise), env.step(noise)
        assert not (first.terminated or first.truncated) and second.truncated
        assert env.inner._sim.curr_path_length == 3
    finally:
        env.close()
    vector = make_env(f"vla_noise:metaworld:{TASK}", 1, seed=0, num_workers=0, max_episode_steps=2,
                      vla=vla_options(checkpoint), **SIM)
    try:
        vector.reset(seeds=[0])
        noise = np.zeros((1, *vector.action_space.shape), np.float32)
        vector.step(noise)
        ended = vector.step(noise)
        assert ended.truncated[0] and ended.info["episode_length"][0] == 2
    finally:
        vector.close()


def test_task_names_are_the_wrapped_envs(checkpoint):
    factory = noise_steering_factory("metaworld:door-open-v3,window-open-v3", vla=vla_options(checkpoint), **SIM)
    assert factory.task_names(3) == ["door-open-v3", "window-open-v3", "door-open-v3"]


@pytest.mark.parametrize("options, message", [
    ({"vla": {"chunk": 2}}, "vla_noise needs the option vla.checkpoint"),
    ({"vla": {"checkpoint": "x", "action_dim": 4}}, "vla.action_dim is the wrapped env's"),
    ({"vla": {"checkpoint": "x"}, "noise_bound": 0}, "noise_bound must be > 0"),
    ({"vla": {"checkpoint": "x"}, "reward_offset": float("nan")}, "reward_offset must be a finite number"),
])
def test_bad_options_are_one_line_before_anything_is_built(options, message):
    with pytest.raises(ValueError, match=message) as error:
        noise_steering_factory(f"metaworld:{TASK}", **options)
    assert "\n" not in str(error.value)


def test_a_policy_that_cannot_be_steered_is_named(checkpoint):
    factory = noise_steering_factory(f"metaworld:{TASK}", vla={**vla_options(checkpoint), "policy": "mlp_gaussian"},
                                     **SIM)
    with pytest.raises(ValueError, match=r"^vla.policy='mlp_gaussian' is not a VLA that can be steered; one of "
                                         r"pi0, pi05, pi0_smollm2$"):
        factory(0)


def test_options_are_the_wrapped_familys_and_its_own():
    check_env_kwargs(f"vla_noise:metaworld:{TASK}", {"vla": {}, "noise_bound": 1.0, "obs_mode": "state+rgb"}, "env")
    with pytest.raises(ValueError, match=r"^env\.kwargs: vla_noise env 'metaworld:button-press-topdown-v3' does not "
                                         r"take 'colour'"):
        check_env_kwargs(f"vla_noise:metaworld:{TASK}", {"colour": 1}, "env.kwargs")
    with pytest.raises(ValueError, match="write vla_noise:<family>:<task>"):
        noise_steering_factory(None, vla={"checkpoint": "x"})
