"""Any registered gymnasium env id as a :class:`SubEnv`: ``make_env("gym:CartPole-v1", 8)``.

One generic adapter instead of one per task: classic control, Box2D and the MuJoCo locomotion
tasks (``InvertedPendulum-v5``, ``Hopper-v5``, needs ``gymnasium[mujoco]``) all map the same way:
a Box or flattened observation becomes ``state`` (float32), a rendered frame becomes ``rgb`` when
asked for, Box actions are clipped to their bounds (Gaussian policies sample outside them, and
MuJoCo tasks would apply the unclipped torque), and ``info["success"]`` / ``info["is_success"]``
becomes the success flag where a task reports one.

It also owns :func:`use_headless_gl`, shared by every simulator built on gymnasium's MuJoCo
renderer (MetaWorld too): without a display, MuJoCo must be told which off-screen GL to use.
"""

from __future__ import annotations

import ctypes.util
import difflib
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from infinirl.envs.base import ActionSpace, ArraySpec, Obs, SubStep
from infinirl.envs.options import EnvOptions, keyword_names

__all__ = ["GymnasiumFactory", "GymnasiumSubEnv", "OBS_MODES", "gymnasium_factory", "gymnasium_options",
           "use_headless_gl"]

OBS_MODES = ("state", "rgb", "state+rgb")
"""Which observation fields a rendering-capable adapter returns."""

ADAPTER_OPTIONS = ("obs_mode", "clip_actions", "instruction")
"""The options this adapter takes itself; every other one goes to ``gymnasium.make``."""


def use_headless_gl() -> str:
    """Pick MuJoCo's off-screen GL backend when none is chosen and there is no display.

    ``osmesa`` (Debian ``libosmesa6``) if installed, else ``egl`` (GPU machines). Called just before
    the first render, not at import: MuJoCo loads the chosen GL library when it is imported, so
    choosing ``osmesa`` on a machine without it would break even state-only simulation. Returns
    the backend in use.

    With ``osmesa`` (software rendering by Mesa's llvmpipe) it also sets ``LP_NUM_THREADS=0``
    unless the user exported a value: each frame is then rasterised by the thread that asked for
    it. llvmpipe's default, a rasteriser thread per CPU for every GL context, only adds hand-offs
    for frames of 64-128 pixels when every core already runs a simulator process.
    """
    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        for backend, library in (("osmesa", "OSMesa"), ("egl", "EGL")):
            if ctypes.util.find_library(library):
                os.environ["MUJOCO_GL"] = backend
                break
    backend = os.environ.get("MUJOCO_GL", "glfw")
    if backend == "osmesa":
        os.environ.setdefault("LP_NUM_THREADS", "0")  # read when the first GL context is created
    return backend


def check_obs_mode(obs_mode: str) -> None:
    if obs_mode not in OBS_MODES:
        raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")


def check_gym_id(env_id: str) -> None:
    """Fail early, in the parent, with the nearest registered ids instead of a worker traceback."""
    import gymnasium as gym

    try:
        gym.spec(env_id)
    except gym.error.Error as exc:
        close = difflib.get_close_matches(env_id, list(gym.registry), n=5, cutoff=0.5)
        hint = f"; did you mean one of {close}?" if close else ""
        raise ValueError(f"unknown gymnasium env id {env_id!r} ({exc}){hint}") from exc


class GymnasiumSubEnv:
    """One ``gymnasium.make(env_id)`` behind the :class:`SubEnv` protocol.

    ``state_id`` resets use the id as the seed: gymnasium has no table of initial states, and a
    seeded reset is reproducible, which is what a fixed state needs.
    """

    def __init__(
        self,
        env_id: str,
        *,
        obs_mode: str = "state",
        clip_actions: bool = True,
        instruction: str | None = None,
        make_kwargs: dict[str, Any] | None = None,
    ) -> None:
        import gymnasium as gym

        check_obs_mode(obs_mode)
        if "rgb" in obs_mode:
            use_headless_gl()
        self._env = gym.make(env_id, render_mode=_rgb_render_mode(env_id), **(make_kwargs or {}))
        self._obs_mode = obs_mode
        self._clip_actions = clip_actions
        self._instruction = instruction
        self._last_frame: np.ndarray | None = None  # repeated by steps nobody observes
        self._raw_obs_space = self._env.observation_space
        self.action_space = _action_space(self._env.action_space)
        self._discrete_start = int(getattr(self._env.action_space, "start", 0))
        self.observation_spec = self._observation_spec()

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs:
        obs, _ = self._env.reset(seed=state_id if state_id is not None else seed)
        return self._observe(obs)

    def step(self, action: np.ndarray, observe: bool = True) -> SubStep:
        """``observe=False``: nobody reads this step's observation (an inner step of an action
        chunk), so unless the episode ends here its ``rgb`` repeats the last frame."""
        obs, reward, terminated, truncated, info = self._env.step(self._to_gym_action(action))
        success = bool(info.get("success", info.get("is_success", False)))
        fresh_frame = observe or bool(terminated) or bool(truncated)
        return SubStep(self._observe(obs, fresh_frame), float(reward), bool(terminated), bool(truncated), success)

    def render(self) -> np.ndarray:
        use_headless_gl()
        frame = self._env.render()
        if frame is None:
            raise RuntimeError(f"{self._env.spec.id} cannot render rgb_array frames")
        return np.asarray(frame, dtype=np.uint8)

    def close(self) -> None:
        self._env.close()

    def _to_gym_action(self, action: np.ndarray) -> Any:
        if self.action_space.is_discrete:
            return int(action) + self._discrete_start
        action = np.asarray(action, dtype=self.action_space.dtype)
        if self._clip_actions:
            action = np.clip(action, self.action_space.low, self.action_space.high)
        return action

    def _observe(self, raw_obs: Any, fresh_frame: bool = True) -> Obs:
        obs: Obs = {}
        if "state" in self._obs_mode:
            obs["state"] = _flat_state(self._raw_obs_space, raw_obs)
        if "rgb" in self._obs_mode:
            if fresh_frame or self._last_frame is None:
                self._last_frame = self.render()
            obs["rgb"] = self._last_frame
        if self._instruction is not None:
            obs["instruction"] = self._instruction
        return obs

    def _observation_spec(self) -> dict[str, ArraySpec]:
        spec: dict[str, ArraySpec] = {}
        if "state" in self._obs_mode:
            sample = _flat_state(self._raw_obs_space, self._raw_obs_space.sample())
            spec["state"] = ArraySpec(sample.shape, str(sample.dtype))
        if "rgb" in self._obs_mode:
            self._env.reset(seed=0)  # a frame exists only after a reset
            spec["rgb"] = ArraySpec(self.render().shape, "uint8")
        if self._instruction is not None:
            spec["instruction"] = ArraySpec((), "str")
        return spec


@dataclass(frozen=True)
class GymnasiumFactory:
    """Picklable ``index -> GymnasiumSubEnv`` (every index gets the same task)."""

    env_id: str
    obs_mode: str = "state"
    clip_actions: bool = True
    instruction: str | None = None
    make_kwargs: dict[str, Any] = field(default_factory=dict)

    def __call__(self, index: int) -> GymnasiumSubEnv:
        return GymnasiumSubEnv(
            self.env_id,
            obs_mode=self.obs_mode,
            clip_actions=self.clip_actions,
            instruction=self.instruction,
            make_kwargs=self.make_kwargs,
        )


def gymnasium_factory(task: str | None, **kwargs: Any) -> GymnasiumFactory:
    """Registry entry: ``gym:<env id>``; unknown keyword arguments go to ``gymnasium.make``."""
    if not task:
        raise ValueError("name a gymnasium env id: make_env('gym:CartPole-v1', ...)")
    check_gym_id(task)
    own = {key: kwargs.pop(key) for key in ADAPTER_OPTIONS if key in kwargs}
    check_obs_mode(own.get("obs_mode", "state"))
    return GymnasiumFactory(task, make_kwargs=kwargs, **own)


def gymnasium_options(task: str | None) -> EnvOptions:
    """What ``gym:<task>`` takes: this adapter's options, ``gymnasium.make``'s own, and the env
    constructor's (read off its signature: the env is not built). ``render_mode`` is the
    adapter's to set."""
    if not task:
        raise ValueError("name a gymnasium env id: make_env('gym:CartPole-v1', ...)")
    check_gym_id(task)
    import gymnasium as gym

    # Loading a MuJoCo task's module imports MuJoCo, which fixes its GL backend on import: choose
    # the headless one first, as building the env would.
    use_headless_gl()
    constructor, passes_others = keyword_names(env_creator(task))
    make_options, _ = keyword_names(gym.make, skip=("id",))
    return EnvOptions(
        names=frozenset(ADAPTER_OPTIONS) | make_options | (constructor - {"render_mode"}),
        passes_others=passes_others,
        reserved={"render_mode": "the adapter sets it: rgb_array where the env can render, for rgb and videos"},
        choices={"obs_mode": OBS_MODES},
    )


def env_creator(env_id: str) -> Any:
    """The class or function ``gymnasium.make(env_id)`` calls (its module imported, nothing built)."""
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    entry_point = gym.spec(env_id).entry_point
    return load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point


def _rgb_render_mode(env_id: str) -> str | None:
    """``"rgb_array"`` if the env supports it (frames for ``rgb`` and videos), else ``None``.
    Creating a renderer is lazy in gymnasium, so asking for it costs nothing until a render."""
    modes = getattr(env_creator(env_id), "metadata", {}).get("render_modes", [])
    return "rgb_array" if "rgb_array" in modes else None


def _action_space(space: Any) -> ActionSpace:
    from gymnasium import spaces

    if isinstance(space, spaces.Discrete):
        return ActionSpace.discrete(int(space.n))
    if isinstance(space, spaces.Box):
        return ActionSpace.box(space.low, space.high, dtype="float32")
    raise NotImplementedError(
        f"gymnasium action space {space} is not supported (Box and Discrete are)"
    )


def _flat_state(space: Any, raw_obs: Any) -> np.ndarray:
    from gymnasium import spaces

    if isinstance(space, spaces.Box):
        array = np.asarray(raw_obs)
        return array.astype(np.float32) if np.issubdtype(array.dtype, np.floating) else array
    return np.asarray(spaces.flatten(space, raw_obs), dtype=np.float32)
