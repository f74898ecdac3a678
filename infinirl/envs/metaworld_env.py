"""MetaWorld (Sawyer arm manipulation, MuJoCo) as a :class:`SubEnv`.

``make_env("metaworld:reach-v3", 8)``; any of the 50 v3 task names, or ``MT10`` / ``MT25`` /
``MT50``, which give env ``i`` task ``i mod T`` of that benchmark (multi-task training with one
vector env), or a comma-separated list of any of these (``reach-v3,push-v3``). Requires
``metaworld`` and ``mujoco==3.3.0`` (MuJoCo 4 breaks metaworld).

What this adapter fixes on top of the raw MetaWorld class:

* **Seeded tasks.** MetaWorld's own MT1 API draws 50 goals once and picks among them with the
  global numpy RNG. Here every reset draws the object/goal layout from the sub-env's generator,
  seeded per episode, so the same seed gives the same first observation, and a fixed
  ``state_id`` (= that seed) gives a group of envs one identical task, as embodied GRPO needs.
  The goal is observable (MT1 convention), in the last three ``state`` entries.
* **Episode length.** 200 steps (truncation), not the class default of 500.
* **Upright camera images.** Several MetaWorld cameras (``corner``, ``corner2``..``corner4``) are
  mounted rolled by 180°, so their frames come out upside down. :func:`camera_is_upside_down`
  detects that from the camera's pose (its image-up axis points below the horizon) and frames are
  rotated back by 180° (a rotation, not a vertical flip, which would mirror the scene).
* **Cheaper steps.** The object quaternion in the observation is computed by
  :mod:`~infinirl.envs.fast_rotation` (scipy's numbers bit for bit, without scipy's per-call
  overhead, which is a sizeable share of a cheap task's step).
* **Affordable pixels on CPU.** ``fast_render`` (default) turns off shadows, reflections and
  multisample anti-aliasing in the model's visual settings (physics untouched): software GL then
  renders a small frame in a fraction of the time (see :func:`_fast_visuals`).
* **Sparse reward.** ``reward_mode="sparse"`` pays 1 on a step where the task is solved and 0
  elsewhere (the success signal πRL and RLinf train VLAs on), instead of MetaWorld's shaped
  ``"dense"`` reward, whose return can rise while success does not move. With
  ``terminate_on_success`` that is one reward at the step the task is first solved.
* **Success bonus.** ``success_bonus=B`` adds ``B`` to the reward of every solved step, so a dense
  return also ranks solved episodes above near misses (the shaped reward alone is continuous across
  the success threshold: PPO can raise it by getting closer without solving more).

Observations: ``state`` (39 floats: hand xyz, gripper opening, object poses, the previous frame of
those, goal xyz; when ``obs_mode`` asks, as it is privileged next to a camera), ``proprio`` (hand
xyz + gripper opening, always), ``rgb`` (uint8 HxWx3, when ``obs_mode`` asks), ``instruction``
(the task in words, e.g. ``"pick place"``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from infinirl.envs.base import ActionSpace, ArraySpec, Obs, SubStep
from infinirl.envs.fast_rotation import use_fast_rotation
from infinirl.envs.gymnasium_env import OBS_MODES, check_obs_mode, use_headless_gl
from infinirl.envs.options import EnvOptions

__all__ = [
    "DEFAULT_MAX_EPISODE_STEPS",
    "REWARD_MODES",
    "MetaWorldFactory",
    "MetaWorldSubEnv",
    "camera_is_upside_down",
    "metaworld_factory",
    "metaworld_options",
    "metaworld_task_names",
]

DEFAULT_MAX_EPISODE_STEPS = 200
REWARD_MODES = ("dense", "sparse")
_PROPRIO_DIMS = 4  # hand xyz + normalised gripper opening: the first entries of the state


def metaworld_task_names() -> dict[str, list[str]]:
    """Every accepted ``task``: each v3 task maps to itself, each benchmark to its task list."""
    from metaworld import env_dict

    names = {name: [name] for name in env_dict.ALL_V3_ENVIRONMENTS}
    names["MT10"] = list(env_dict.MT10_V3)
    names["MT25"] = list(env_dict.MT25_V3)
    names["MT50"] = list(env_dict.MT50_V3)
    return names


def task_instruction(task: str) -> str:
    """``"pick-place-v3"`` -> ``"pick place"``: MetaWorld has no language annotations, but
    language-conditioned policies need a string, and the task name is the honest one."""
    return task.rsplit("-v", 1)[0].replace("-", " ")


def camera_is_upside_down(model: Any, data: Any, camera: str) -> bool:
    """True if the named MuJoCo camera is rolled so that image-up points downwards in the world.

    A MuJoCo camera looks along its -z axis with image-up along +y; ``cam_xmat`` holds those axes
    in world coordinates. A +y axis with a negative world-z component means the picture's top
    shows what lies below: the frame must be rotated 180° to look natural.
    """
    import mujoco

    camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if camera_id < 0:
        names = [model.camera(i).name for i in range(model.ncam)]
        raise ValueError(f"unknown MetaWorld camera {camera!r}; cameras: {names}")
    image_up_in_world = np.asarray(data.cam_xmat[camera_id]).reshape(3, 3)[:, 1]
    return bool(image_up_in_world[2] < 0.0)


class MetaWorldSubEnv:
    """One MetaWorld task instance; see the module docstring for what it adds."""

    def __init__(
        self,
        task: str,
        *,
        obs_mode: str = "state",
        camera: str = "corner",
        image_size: int | tuple[int, int] = 128,
        max_episode_steps: int = DEFAULT_MAX_EPISODE_STEPS,
        terminate_on_success: bool = False,
        reward_function_version: str = "v2",
        reward_mode: str = "dense",
        success_bonus: float = 0.0,
        fast_render: bool = True,
    ) -> None:
        check_obs_mode(obs_mode)
        if reward_mode not in REWARD_MODES:
            raise ValueError(f"unknown MetaWorld reward_mode {reward_mode!r}; choices: {', '.join(REWARD_MODES)}")
        _check_success_bonus(success_bonus)
        if "rgb" in obs_mode:
            use_headless_gl()  # before MuJoCo is imported, so it loads the same GL library
        from metaworld import env_dict

        height, width = (image_size, image_size) if isinstance(image_size, int) else image_size
        self.task = task
        self._sim = env_dict.ALL_V3_ENVIRONMENTS[task](
            render_mode="rgb_array",  # the renderer itself is created lazily, on first render
            camera_name=camera,
            width=width,
            height=height,
            reward_function_version=reward_function_version,
        )
        use_fast_rotation(type(self._sim))
        _make_goal_observable_and_seedable(self._sim, env_dict.ML1_ARGS_KWARGS[task]["kwargs"])
        self._sim.max_path_length = max_episode_steps
        if fast_render:
            _fast_visuals(self._sim.model)
        self._camera = camera
        self._obs_mode = obs_mode
        self._terminate_on_success = terminate_on_success
        self._sparse_reward = reward_mode == "sparse"
        self._success_bonus = float(success_bonus)
        self._instruction = task_instruction(task)
        self._rotate_frames: bool | None = None  # decided on the first render
        self._last_frame: np.ndarray | None = None  # repeated by steps nobody observes
        self.action_space = ActionSpace.box(self._sim.action_space.low, self._sim.action_space.high)
        self.observation_spec = self._observation_spec((height, width))

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs:
        """A new episode whose object and goal placement is drawn with ``seed`` (a ``state_id``
        is used as that seed: the fixed states are the seeded layouts)."""
        seed = state_id if state_id is not None else seed
        if seed is not None:
            self._sim.seed(int(seed))
        state, _ = self._sim.reset()
        return self._observe(state)

    def step(self, action: np.ndarray, observe: bool = True) -> SubStep:
        """``observe=False``: nobody reads this step's observation (an inner step of an action
        chunk), so unless the episode ends here its ``rgb`` repeats the last frame instead of
        rendering a new one (physics, reward and state are the same either way)."""
        state, reward, terminated, truncated, info = self._sim.step(np.asarray(action, np.float32))
        success = bool(info["success"])
        terminated = bool(terminated) or (self._terminate_on_success and success)
        fresh_frame = observe or terminated or bool(truncated)
        reward = float(success) if self._sparse_reward else float(reward)
        if success:
            reward += self._success_bonus
        return SubStep(self._observe(state, fresh_frame), reward, terminated, bool(truncated), success)

    def render(self) -> np.ndarray:
        """The camera frame, upright, uint8 HxWx3."""
        use_headless_gl()
        frame = self._sim.render()
        if self._rotate_frames is None:
            self._rotate_frames = camera_is_upside_down(self._sim.model, self._sim.data, self._camera)
        if self._rotate_frames:
            frame = frame[::-1, ::-1]
        return np.ascontiguousarray(frame, dtype=np.uint8)

    def close(self) -> None:
        self._sim.close()

    def _observe(self, state: np.ndarray, fresh_frame: bool = True) -> Obs:
        state = state.astype(np.float32)
        obs: Obs = {}
        # The 39-float state holds the objects' and the goal's poses: privileged next to a camera
        # frame, so it is observed only when obs_mode asks for it (as for the gymnasium adapter).
        if "state" in self._obs_mode:
            obs["state"] = state
        obs["proprio"] = state[:_PROPRIO_DIMS].copy()
        if "rgb" in self._obs_mode:
            if fresh_frame or self._last_frame is None:
                self._last_frame = self.render()
            obs["rgb"] = self._last_frame
        obs["instruction"] = self._instruction
        return obs

    def _observation_spec(self, image_hw: tuple[int, int]) -> dict[str, ArraySpec]:
        spec: dict[str, ArraySpec] = {}
        if "state" in self._obs_mode:
            spec["state"] = ArraySpec(self._sim.sawyer_observation_space.shape, "float32")
        spec["proprio"] = ArraySpec((_PROPRIO_DIMS,), "float32")
        if "rgb" in self._obs_mode:
            spec["rgb"] = ArraySpec((*image_hw, 3), "uint8")
        spec["instruction"] = ArraySpec((), "str")
        return spec


def _check_success_bonus(bonus: float) -> None:
    if not bonus >= 0.0:  # also refuses NaN
        raise ValueError(f"MetaWorld success_bonus must be >= 0 (added to a solved step's reward), got {bonus!r}")


def _make_goal_observable_and_seedable(sim: Any, task_kwargs: dict) -> None:
    """Put a raw MetaWorld env in the state MT1 tasks use, but drawing each episode's layout from
    ``sim.np_random`` (seeded per reset) instead of a frozen, pre-drawn task vector."""
    sim._partially_observable = False
    vars(sim).pop("sawyer_observation_space", None)  # cached for the old observability: recompute
    sim._set_task_inner(**{k: v for k, v in task_kwargs.items() if k != "task_id"})
    sim._set_task_called = True
    sim._freeze_rand_vec = False
    sim.seeded_rand_vec = True


def _fast_visuals(model: Any) -> None:
    """Visual-only model settings for software GL (physics untouched), for small frames:

    * shadows and reflections off: each adds render passes, which dominate a small frame's cost;
    * no multisample anti-aliasing (``offsamples`` 4 -> 0): reading a frame back otherwise resolves
      the whole 4-sample 640x480 offscreen buffer in software, whatever the frame's size. The
      only change to the picture is on object edges, which lose their anti-aliasing.

    Must run before the first render, which creates the GL context with these settings."""
    model.light_castshadow[:] = 0
    model.mat_reflectance[:] = 0.0
    model.vis.quality.offsamples = 0


@dataclass(frozen=True)
class MetaWorldFactory:
    """Picklable ``index -> MetaWorldSubEnv``; env ``i`` runs ``tasks[(i // task_block) % len(tasks)]``
    (``task_block`` consecutive envs share a task: embodied GRPO's groups on a multi-task name)."""

    tasks: tuple[str, ...]
    obs_mode: str = "state"
    camera: str = "corner"
    image_size: int | tuple[int, int] = 128
    max_episode_steps: int = DEFAULT_MAX_EPISODE_STEPS
    terminate_on_success: bool = False
    reward_function_version: str = "v2"
    reward_mode: str = "dense"
    success_bonus: float = 0.0
    fast_render: bool = True
    task_block: int = 1

    def __post_init__(self) -> None:
        _check_success_bonus(self.success_bonus)
        if self.task_block < 1:
            raise ValueError(f"task_block must be >= 1, got {self.task_block}")

    def task_of(self, index: int) -> str:
        return self.tasks[(index // self.task_block) % len(self.tasks)]

    def __call__(self, index: int) -> MetaWorldSubEnv:
        return MetaWorldSubEnv(
            self.task_of(index),
            obs_mode=self.obs_mode,
            camera=self.camera,
            image_size=self.image_size,
            max_episode_steps=self.max_episode_steps,
            terminate_on_success=self.terminate_on_success,
            reward_function_version=self.reward_function_version,
            reward_mode=self.reward_mode,
            success_bonus=self.success_bonus,
            fast_render=self.fast_render,
        )

    def task_names(self, num_envs: int) -> list[str]:
        """The task each of ``num_envs`` envs runs (per-task evaluation metrics)."""
        return [self.task_of(index) for index in range(num_envs)]


def metaworld_factory(task: str | None, **kwargs: Any) -> MetaWorldFactory:
    """Registry entry: ``metaworld:<task>`` with a v3 task name, MT10/MT25/MT50, or a comma-separated
    list of them (``reach-v3,push-v3``: env ``i`` runs the ``i % n``-th task)."""
    names = metaworld_task_names()
    parts = [part.strip() for part in (task or "").split(",")]
    unknown = [part for part in parts if part not in names]
    if unknown:
        raise ValueError(
            f"unknown MetaWorld task {unknown[0]!r}; tasks: {', '.join(sorted(names))}"
        )
    check_obs_mode(kwargs.get("obs_mode", "state"))
    return MetaWorldFactory(tuple(name for part in parts for name in names[part]), **kwargs)


def metaworld_options(task: str | None) -> EnvOptions:
    """What ``metaworld:<task>`` takes: the fields of :class:`MetaWorldFactory` (every task takes
    the same ones, so neither the task nor MetaWorld is looked at)."""
    return EnvOptions(
        names=frozenset(f.name for f in fields(MetaWorldFactory) if f.name != "tasks"),
        choices={"obs_mode": OBS_MODES, "reward_mode": REWARD_MODES},
    )
