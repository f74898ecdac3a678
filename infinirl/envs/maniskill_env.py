"""ManiSkill3 (SAPIEN physics) tasks on CPU as a :class:`SubEnv`: ``make_env("maniskill:PickCube-v1", 8)``.

Each sub-env is one ManiSkill scene on SAPIEN's CPU PhysX backend (``sim_backend="physx_cpu"``,
which simulates one scene per instance), batched by :class:`VectorEnv` like every CPU simulator.
ManiSkill returns torch tensors with a batch dimension of 1; this adapter hands out plain numpy
rows so nothing downstream depends on the simulator's tensor type. (On a CUDA machine ManiSkill
can instead batch hundreds of scenes on the GPU in one process; that path is not this adapter.)

SAPIEN needs a Vulkan driver even for state observations (it builds render materials when a scene
loads). Without a GPU that is Mesa's software ``lavapipe``, and it must be Mesa >= 23: on Debian 12
install ``mesa-vulkan-drivers libvulkan1`` from ``bookworm-backports`` (see docs/envs.md).

``obs_mode="state"``: ``state`` is ManiSkill's flattened state vector. ``obs_mode="rgb"``: ``rgb``
from the task's default camera plus ``proprio`` (joint positions and velocities).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from infinirl.envs.base import ActionSpace, ArraySpec, Obs, SubStep
from infinirl.envs.options import EnvOptions, keyword_names

__all__ = ["ManiSkillFactory", "ManiSkillSubEnv", "maniskill_factory", "maniskill_options"]

MANISKILL_OBS_MODES = ("state", "rgb")
ADAPTER_OPTIONS = ("obs_mode", "image_size")
"""The options this adapter takes itself; every other one goes to ``gymnasium.make``."""
ADAPTER_SETS = {
    "sim_backend": "the adapter simulates on SAPIEN's CPU backend, physx_cpu",
    "render_backend": "the adapter sets it from obs_mode and render_mode",
}
_CAMERA = "base_camera"


def task_instruction(task: str) -> str:
    """``"PickCube-v1"`` -> ``"pick cube"`` (ManiSkill tasks carry no language annotation)."""
    words = re.findall(r"[A-Z][a-z]*|[a-z]+|\d+", task.rsplit("-v", 1)[0])
    return " ".join(word.lower() for word in words)


def _numpy_row(value: Any) -> np.ndarray:
    """ManiSkill's ``[1, ...]`` torch tensor -> its numpy row."""
    return value[0].detach().cpu().numpy()


class ManiSkillSubEnv:
    """One ManiSkill task instance on the CPU simulator."""

    def __init__(
        self,
        task: str,
        *,
        obs_mode: str = "state",
        image_size: int = 128,
        make_kwargs: dict[str, Any] | None = None,
    ) -> None:
        import gymnasium as gym
        import mani_skill.envs  # noqa: F401  (registers the ManiSkill tasks with gymnasium)

        kwargs = dict(make_kwargs or {})
        if obs_mode == "rgb":
            kwargs.setdefault("sensor_configs", {"width": image_size, "height": image_size})
        self._env = gym.make(
            task,
            obs_mode=obs_mode,
            sim_backend="physx_cpu",
            # a renderer only when frames are wanted: observations, or videos (render_mode="rgb_array")
            render_backend="cpu" if obs_mode == "rgb" or kwargs.get("render_mode") else "none",
            num_envs=1,
            **kwargs,
        )
        self._obs_mode = obs_mode
        self._instruction = task_instruction(task)
        space = self._env.action_space
        self.action_space = ActionSpace.box(space.low.reshape(-1), space.high.reshape(-1))
        first = self._observe(self._env.reset(seed=0)[0])
        self.observation_spec = {
            key: ArraySpec((), "str") if isinstance(value, str) else ArraySpec(value.shape, str(value.dtype))
            for key, value in first.items()
        }

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs:
        """A seeded episode; a ``state_id`` is used as the seed (ManiSkill has no fixed states)."""
        raw, _ = self._env.reset(seed=state_id if state_id is not None else seed)
        return self._observe(raw)

    def step(self, action: np.ndarray) -> SubStep:
        action = np.clip(np.asarray(action, np.float32), self.action_space.low, self.action_space.high)
        raw, reward, terminated, truncated, info = self._env.step(action[None])
        return SubStep(
            self._observe(raw),
            float(reward[0]),
            bool(terminated[0]),
            bool(truncated[0]),
            bool(info["success"][0]) if "success" in info else False,
        )

    def render(self) -> np.ndarray:
        frame = self._env.render()
        if frame is None:
            raise RuntimeError("this ManiSkill env was built without a renderer (obs_mode='state'); build it "
                               "with render_mode='rgb_array' (e.g. eval.video_env_kwargs={render_mode: rgb_array})")
        return np.asarray(_numpy_row(frame), dtype=np.uint8)

    def close(self) -> None:
        self._env.close()

    def _observe(self, raw: Any) -> Obs:
        if self._obs_mode == "state":
            return {"state": _numpy_row(raw).astype(np.float32), "instruction": self._instruction}
        agent = raw["agent"]
        proprio = np.concatenate([_numpy_row(agent["qpos"]), _numpy_row(agent["qvel"])])
        return {
            "rgb": _numpy_row(raw["sensor_data"][_CAMERA]["rgb"]).astype(np.uint8),
            "proprio": proprio.astype(np.float32),
            "instruction": self._instruction,
        }


@dataclass(frozen=True)
class ManiSkillFactory:
    """Picklable ``index -> ManiSkillSubEnv`` (every index gets the same task)."""

    task: str
    obs_mode: str = "state"
    image_size: int = 128
    make_kwargs: dict[str, Any] = field(default_factory=dict)

    def __call__(self, index: int) -> ManiSkillSubEnv:
        return ManiSkillSubEnv(
            self.task, obs_mode=self.obs_mode, image_size=self.image_size, make_kwargs=self.make_kwargs
        )


def maniskill_factory(task: str | None, **kwargs: Any) -> ManiSkillFactory:
    """Registry entry: ``maniskill:<task id>``; unknown keyword arguments go to ``gymnasium.make``
    (e.g. ``control_mode="pd_ee_delta_pos"``, ``reward_mode="dense"``)."""
    check_task(task)
    own = {key: kwargs.pop(key) for key in ADAPTER_OPTIONS if key in kwargs}
    if own.get("obs_mode", "state") not in MANISKILL_OBS_MODES:
        raise ValueError(f"ManiSkill obs_mode must be one of {MANISKILL_OBS_MODES}, got {own['obs_mode']!r}")
    return ManiSkillFactory(task, make_kwargs=kwargs, **own)


def maniskill_options(task: str | None) -> EnvOptions:
    """What ``maniskill:<task>`` takes: this adapter's options, ``gymnasium.make``'s own, and the
    task class's constructor options (ManiSkill's ``BaseEnv`` ones included), read off signatures:
    importing ManiSkill registers its tasks, no scene is built."""
    import gymnasium as gym

    check_task(task)
    from mani_skill.utils.registration import REGISTERED_ENVS

    constructor, passes_others = keyword_names(REGISTERED_ENVS[task].cls)
    make_options, _ = keyword_names(gym.make, skip=("id",))
    return EnvOptions(
        names=frozenset(ADAPTER_OPTIONS) | make_options | (constructor - set(ADAPTER_SETS)),
        passes_others=passes_others,
        reserved=ADAPTER_SETS,
        choices={"obs_mode": MANISKILL_OBS_MODES},
    )


def check_task(task: str | None) -> None:
    """Fail in the caller's process if ManiSkill is missing or does not know ``task``."""
    try:
        import mani_skill.envs  # noqa: F401  (registers the ManiSkill tasks)
    except ImportError as exc:
        raise ModuleNotFoundError(
            "ManiSkill is not installed: pip install mani-skill (and Mesa >= 23 Vulkan drivers, "
            "see docs/envs.md)"
        ) from exc
    from mani_skill.utils.registration import REGISTERED_ENVS

    if task not in REGISTERED_ENVS:
        raise ValueError(f"unknown ManiSkill task {task!r}; tasks: {', '.join(sorted(REGISTERED_ENVS))}")
