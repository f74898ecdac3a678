"""A robot driver as an RL environment: observations, normalised actions, rewards, episode ends.

:class:`RobotEnv` wraps one :class:`~infinirl.realworld.driver.RobotDriver` (simulated or real;
normally a :class:`~infinirl.realworld.safety.SafeRobot`, so every command passes the safety
filter) and gives the learning code what it expects of an environment:

* **observation**: ``{"state": float32 vector, "pixels.<camera>": uint8 HxWx3, ...}``. The state
  concatenates the :data:`OBSERVATIONS` sources the spec names, in order (``proprio``: the robot's
  present target, joints or end effector, then the gripper; ``sim_state``: what a simulator alone
  knows, e.g. MetaWorld's object and goal positions; ``last_action``: the previous action).
  Cameras the spec names come as pixels, resized to ``spec.frame_size`` where it is set and named
  ``spec.camera_names[camera]`` where it renames them;
* **action**: a vector in ``[-1, 1]`` of ``spec.command_size`` entries. ``action_mode="delta"``
  moves the arm's target (joints or end effector) by ``action * max_step`` from the last target,
  where ``max_step`` is the motion the safety filter allows per control period; ``"absolute"``
  maps the action affinely onto the spec's command bounds. The gripper entry is always absolute
  (``-1`` closed, ``1`` open). The command is clipped to the spec's command bounds. A NaN or
  infinite entry holds that entry for the step (:meth:`RobotEnv.hold_action`) and is reported
  (``RobotStep.non_finite``); :meth:`RobotEnv.hold_action` is the action that keeps the robot where it is;
* **pace**: one :meth:`RobotEnv.step` is one control period in wall-clock time: the env sleeps
  until the period after the previous step ends (a late step is not made up for), then observes;
* **reward**: a weighted sum of :data:`REWARDS` components over the observation after the step
  (``success``: the simulator's ``info["success"]``; ``goal_distance`` / ``block_distance``: minus
  the end effector's distance to the goal or the cube, where the simulator reports them;
  ``classifier``: 1 when a learned success classifier, loaded when the env is built, predicts
  success, :mod:`~infinirl.realworld.success_classifier`). A component with options (the
  classifier's ``path``, ``threshold``) takes them from ``spec.reward_options[name]``;
* **success**: the robot's ``info["success"]`` where it reports one (a simulator), else a
  component's prediction (the classifier's: a real robot knows no success of its own);
* **episode end**: the robot's success (``terminated``, when ``terminate_on_success``), a predicted
  success of a component told to end the episode on it (the classifier's ``terminate_on_success``
  option), or ``max_episode_steps`` (``truncated``: the value still bootstraps). ``reset`` goes
  through the driver and takes its wall-clock time.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from infinirl.realworld.driver import RobotDriver, RobotObservation, RobotSpec
from infinirl.realworld.safety import SafetyConfig
from infinirl.registry import Registry

__all__ = ["OBSERVATIONS", "REWARDS", "ObservationSource", "RewardComponent", "RewardTerm", "RobotEnv",
           "RobotEnvSpec", "RobotStep", "action_to_command"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ObservationSource:
    """One part of the state vector: ``read(env, observation)`` (``env`` is the :class:`RobotEnv`:
    its ``robot_spec``, and ``last_action``, the normalised action of the previous step)."""

    read: Callable[[Any, RobotObservation], np.ndarray]
    description: str = ""


@dataclass(frozen=True, kw_only=True)
class RewardTerm:
    """What a built reward component gives for one step."""

    value: float
    success: bool | None = None
    """The component's prediction of success (None: it predicts none)."""
    terminates: bool = False
    """The episode ends here (terminated)."""


BuiltReward = Callable[[RobotObservation, dict[str, np.ndarray]], RewardTerm]
"""A reward built on one env: ``(the robot's observation, the env's observation dict) -> RewardTerm``."""


@dataclass(frozen=True, kw_only=True)
class RewardComponent:
    """``reward(observation) -> float``; ``needs`` names the ``info`` key a simulator must report.

    A component with options or state (a model to load) gives ``build(env, **options)`` instead,
    called once when the env is built, returning a :data:`BuiltReward`; ``options`` names the
    options it takes, ``required_options`` those without a default."""

    reward: Callable[[RobotObservation], float] | None = None
    build: Callable[..., BuiltReward] | None = None
    options: tuple[str, ...] = ()
    required_options: tuple[str, ...] = ()
    needs: str | None = None
    description: str = ""

    def bind(self, env: Any, options: Mapping[str, Any]) -> BuiltReward:
        """This component's reward on ``env``."""
        if self.build is not None:
            return self.build(env, **dict(options))
        plain = self.reward
        return lambda observation, obs: RewardTerm(value=plain(observation))


OBSERVATIONS: Registry[ObservationSource] = Registry("robot observation source")
REWARDS: Registry[RewardComponent] = Registry("robot reward component")


def _info(observation: RobotObservation, key: str, what: str) -> Any:
    if key not in observation.info:
        raise KeyError(f"{what} needs info[{key!r}], which this robot does not report (a simulator-only fact)")
    return observation.info[key]


def _proprio(env: RobotEnv, observation: RobotObservation) -> np.ndarray:
    spec = env.robot_spec
    target = observation.current_target(spec)
    if target is None:
        raise KeyError(f"{spec.kind} reports no {spec.control_mode} state, so observation 'proprio' is unknown")
    return target


OBSERVATIONS.add("proprio", ObservationSource(read=_proprio, description="present target (joints or ee) + gripper"))
OBSERVATIONS.add("ee_position", ObservationSource(
    read=lambda env, o: np.asarray(o.ee_position if o.ee_position is not None else _info(o, "ee_position", "ee"),
                                    np.float64), description="end-effector xyz"))
OBSERVATIONS.add("sim_state", ObservationSource(
    read=lambda env, o: np.asarray(_info(o, "state", "observation 'sim_state'"), np.float64),
    description="the simulator's task state (MetaWorld: hand, objects, goal)"))
OBSERVATIONS.add("block_position", ObservationSource(
    read=lambda env, o: np.asarray(_info(o, "block_position", "observation 'block_position'"), np.float64),
    description="the SO-101 scene's cube position"))
OBSERVATIONS.add("last_action", ObservationSource(
    read=lambda env, o: env.last_action,
    description="the previous step's normalised action (zeros after a reset): a command's effect shows a "
                "control period or more later, so the policy needs to know what it already asked for"))


def _goal_distance(observation: RobotObservation) -> float:
    state = np.asarray(_info(observation, "state", "reward 'goal_distance'"), np.float64)
    return -float(np.linalg.norm(state[:3] - state[-3:]))  # MetaWorld: hand first, goal last


def _block_distance(observation: RobotObservation) -> float:
    block = np.asarray(_info(observation, "block_position", "reward 'block_distance'"), np.float64)
    return -float(np.linalg.norm(np.asarray(observation.ee_position, np.float64) - block))


REWARDS.add("success", RewardComponent(reward=lambda o: float(bool(_info(o, "success", "reward 'success'"))),
                                       needs="success", description="1 when the simulator reports success"))
REWARDS.add("goal_distance", RewardComponent(reward=_goal_distance, needs="state",
                                             description="minus the hand-goal distance (MetaWorld state)"))
REWARDS.add("block_distance", RewardComponent(reward=_block_distance, needs="block_position",
                                              description="minus the gripper-cube distance (SO-101 scene)"))


def _classifier_reward(env: RobotEnv, **options: Any) -> BuiltReward:
    from infinirl.realworld.success_classifier.reward import classifier_reward  # torch: loaded only when used

    return classifier_reward(env, **options)


REWARDS.add("classifier", RewardComponent(
    build=_classifier_reward, options=("path", "threshold", "terminate_on_success"), required_options=("path",),
    description="1 when the learned success classifier at reward_options.classifier.path predicts success "
                "(probability >= threshold, default the one saved with it); terminate_on_success (default true) "
                "ends the episode there"))


@dataclass(frozen=True, kw_only=True)
class RobotEnvSpec:
    """How a robot becomes an environment (see the module docstring)."""

    observations: tuple[str, ...] = ("proprio",)
    cameras: tuple[str, ...] = ()
    frame_size: tuple[int, int] | None = None
    """(height, width) every camera frame is resized to before anyone sees it (the training
    resolution; the camera streams its own, which stays with the robot). None: as the camera gives."""
    camera_names: Mapping[str, str] = field(default_factory=dict)
    """Robot camera -> the name its frames carry in the observations (``pixels.<name>``), where it
    differs: robots of different kinds sharing one policy map their cameras to one name."""
    rewards: Mapping[str, float] = field(default_factory=lambda: {"success": 1.0})
    reward_options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """Options of the reward components that take some, e.g. ``{"classifier": {"path": ...}}``."""
    max_episode_steps: int = 100
    action_mode: Literal["delta", "absolute"] = "delta"
    terminate_on_success: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "observations", tuple(self.observations))
        object.__setattr__(self, "cameras", tuple(self.cameras))
        if self.frame_size is not None:
            size = tuple(self.frame_size)
            if len(size) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size):
                raise ValueError(f"RobotEnvSpec.frame_size must be [height, width] of positive ints, got "
                                 f"{self.frame_size!r}")
            object.__setattr__(self, "frame_size", size)
        object.__setattr__(self, "camera_names", dict(self.camera_names))
        stray = sorted(set(self.camera_names) - set(self.cameras))
        if stray:
            raise ValueError(f"RobotEnvSpec.camera_names renames {stray}, which are not among the cameras "
                             f"{list(self.cameras)}")
        named = [self.camera_names.get(name, name) for name in self.cameras]
        if len(set(named)) != len(named):
            raise ValueError(f"RobotEnvSpec.camera_names gives two cameras one name: {named}")
        object.__setattr__(self, "rewards", dict(self.rewards))
        object.__setattr__(self, "reward_options", {k: dict(v) for k, v in self.reward_options.items()})
        for name in self.observations:
            OBSERVATIONS.get(name)  # unknown names fail listing the registered ones
        for name in self.rewards:
            self._check_reward_options(name)
        stray = sorted(set(self.reward_options) - set(self.rewards))
        if stray:
            raise ValueError(f"RobotEnvSpec.reward_options: {stray} are not among the rewards {sorted(self.rewards)}; "
                             "add them to rewards or drop their options")
        if not self.observations:
            raise ValueError("RobotEnvSpec.observations: name at least one source, e.g. ['proprio']")
        if self.max_episode_steps < 1:
            raise ValueError(f"RobotEnvSpec.max_episode_steps must be >= 1, got {self.max_episode_steps}")
        if self.action_mode not in ("delta", "absolute"):
            raise ValueError(f"RobotEnvSpec.action_mode must be 'delta' or 'absolute', got {self.action_mode!r}")

    def _check_reward_options(self, name: str) -> None:
        component = REWARDS.get(name)
        given = self.reward_options.get(name, {})
        unknown = sorted(set(given) - set(component.options))
        if unknown:
            raise ValueError(f"RobotEnvSpec.reward_options.{name}: unknown {unknown}; reward {name!r} takes "
                             f"{list(component.options) or 'no options'}")
        missing = [option for option in component.required_options if option not in given]
        if missing:
            raise ValueError(f"reward {name!r} needs reward_options.{name}.{missing[0]} (it takes "
                             f"{list(component.options)})")


@dataclass(frozen=True, kw_only=True)
class RobotStep:
    """What one :meth:`RobotEnv.step` returns."""

    obs: dict[str, np.ndarray]
    reward: float
    terminated: bool
    truncated: bool
    success: bool
    late: bool
    """The step ran past its control period (the policy or the link was too slow)."""
    non_finite: bool = False
    """Entries of the action were NaN or infinite; those entries held (see :meth:`RobotEnv.step`)."""


def max_target_step(spec: RobotSpec, safety: SafetyConfig) -> np.ndarray:
    """The largest move of the target entries per control period that the safety filter lets through."""
    if spec.control_mode == "joint_position":
        return spec.max_joint_velocity * safety.velocity_scale * spec.control_period_s
    return np.full(spec.target_size, spec.max_ee_speed * safety.velocity_scale * spec.control_period_s)


def action_to_command(action: np.ndarray, reference: np.ndarray, spec: RobotSpec, mode: str,
                      max_step: np.ndarray) -> np.ndarray:
    """The command for a normalised ``action`` in ``[-1, 1]`` (see the module docstring); ``reference``
    is the last command sent (or the present target)."""
    action = np.clip(np.asarray(action, np.float64).reshape(-1), -1.0, 1.0)
    if action.shape != (spec.command_size,):
        raise ValueError(f"{spec.kind}: an action has {spec.command_size} entries in [-1, 1], got {action.shape}")
    low, high = spec.action_low, spec.action_high
    absolute = low + (action + 1.0) / 2.0 * (high - low)
    if mode == "absolute":
        return absolute
    size = spec.target_size
    command = absolute.copy()  # the gripper stays absolute
    command[:size] = np.clip(reference[:size] + action[:size] * max_step, low[:size], high[:size])
    return command


class RobotEnv:
    """One robot as an episodic environment (see the module docstring). Not thread-safe: one
    thread steps it. ``robot`` must be connected."""

    def __init__(self, robot: RobotDriver, spec: RobotEnvSpec, safety: SafetyConfig | None = None) -> None:
        self.robot, self.spec = robot, spec
        self.robot_spec = robot.spec
        cameras = {camera.name for camera in self.robot_spec.cameras}
        missing = [name for name in spec.cameras if name not in cameras]
        if missing:
            raise ValueError(f"{self.robot_spec.kind} has cameras {sorted(cameras)}; it has no {missing}")
        self.max_step = max_target_step(self.robot_spec, safety or getattr(robot, "config", SafetyConfig()))
        self._reference: np.ndarray | None = None
        self.last_observation: RobotObservation | None = None
        self.last_action = np.zeros(self.robot_spec.command_size)
        self._next_step_at = 0.0
        self.steps = 0
        self.episode_return = 0.0
        self.late_steps = 0
        self.non_finite_actions = 0
        self.rewards = [(weight, REWARDS.get(name).bind(self, spec.reward_options.get(name, {})))
                        for name, weight in spec.rewards.items()]

    @property
    def action_dim(self) -> int:
        return self.robot_spec.command_size

    def observation_size(self) -> int:
        """Entries of ``obs["state"]`` (reads the robot's present observation)."""
        return int(self._state(self.robot.observe()).shape[0])

    def camera_shapes(self) -> dict[str, tuple[int, int]]:
        """Camera name -> (height, width) of its frames in the observations (``spec.frame_size``
        where set, else the camera's own), for each camera the spec names."""
        own = {camera.name: (camera.height, camera.width) for camera in self.robot_spec.cameras}
        return {self.spec.camera_names.get(name, name): self.spec.frame_size or own[name] for name in self.spec.cameras}

    def observation_shapes(self) -> dict[str, tuple[int, ...]]:
        """Key -> shape of each entry of the observation dict (reads the robot's present observation)."""
        return {key: tuple(value.shape) for key, value in self._obs(self.robot.observe()).items()}

    def reset(self) -> dict[str, np.ndarray]:
        observation = self.last_observation = self.robot.reset()
        self._heartbeat()
        self._reference = observation.current_target(self.robot_spec)
        self._next_step_at = time.monotonic() + self.robot_spec.control_period_s
        self.steps, self.episode_return = 0, 0.0
        self.last_action = np.zeros(self.robot_spec.command_size)
        return self._obs(observation)

    def hold_action(self) -> np.ndarray:
        """The normalised action that keeps the robot where it is: its command is the present target
        (the last command sent, or after ``reset`` the observed target). Delta entries are zero; the
        absolute ones (every entry in ``"absolute"`` mode, the gripper in ``"delta"`` mode) map the
        target back into ``[-1, 1]`` (a target beyond the command bounds holds at the nearest bound)."""
        if self._reference is None:
            raise RuntimeError("RobotEnv.hold_action before reset()")
        low, high = self.robot_spec.action_low, self.robot_spec.action_high
        span = high - low
        # an entry whose bounds coincide has one command whatever the action: 0 stands for it
        action = np.divide(2.0 * (self._reference - low), span, out=np.ones_like(span), where=span > 0) - 1.0
        action = np.clip(action, -1.0, 1.0)
        if self.spec.action_mode == "delta":
            action[:self.robot_spec.target_size] = 0.0
        return action

    def step(self, action: np.ndarray) -> RobotStep:
        """One control period with ``action``. A NaN or infinite entry (a diverged policy) holds that
        entry (:meth:`hold_action`'s value) for this step; the step reports it (``non_finite``, and
        :attr:`non_finite_actions` counts such steps) and neither the target nor ``last_action`` ever
        holds a non-finite value, so the next finite action moves the robot again."""
        if self._reference is None:
            raise RuntimeError("RobotEnv.step before reset()")
        action = np.asarray(action, np.float64).reshape(-1)
        bad = ~np.isfinite(action)
        non_finite = action.shape == (self.action_dim,) and bool(bad.any())  # a wrong shape fails below
        if non_finite:
            self.non_finite_actions += 1
            logger.warning("%s: action %s has non-finite entries %s; holding them this step", self.robot_spec.kind,
                           action.tolist(), np.flatnonzero(bad).tolist())
            action = np.where(bad, self.hold_action(), action)
        command = action_to_command(action, self._reference, self.robot_spec, self.spec.action_mode, self.max_step)
        sent = self.robot.act(command)
        # The safety layer may clip the command; the next delta must start from what the robot was
        # told, or a clipped target drifts away from the real one step after step.
        self._reference = command if sent is None else np.asarray(sent, np.float64)
        self.last_action = np.clip(action, -1.0, 1.0)
        self._heartbeat()
        late = self._wait_for_period()
        observation = self.last_observation = self.robot.observe()
        obs = self._obs(observation)
        terms = [(weight, reward(observation, obs)) for weight, reward in self.rewards]
        reward = sum(weight * term.value for weight, term in terms)
        predicted = [term.success for _, term in terms if term.success is not None]
        if "success" in observation.info:
            success = bool(observation.info["success"])
            terminated = success and self.spec.terminate_on_success
        else:
            success, terminated = any(predicted), False
        terminated = terminated or any(term.terminates for _, term in terms)
        self.steps += 1
        self.episode_return += reward
        truncated = not terminated and self.steps >= self.spec.max_episode_steps
        return RobotStep(obs=obs, reward=float(reward), terminated=terminated, truncated=truncated,
                         success=success, late=late, non_finite=non_finite)

    def _wait_for_period(self) -> bool:
        period = self.robot_spec.control_period_s
        now = time.monotonic()
        late = now > self._next_step_at
        if late:  # never catch up: the next period starts now
            self.late_steps += 1
            self._next_step_at = now + period
            return True
        time.sleep(self._next_step_at - now)
        self._next_step_at += period
        return False

    def _heartbeat(self) -> None:
        beat = getattr(self.robot, "heartbeat", None)
        if beat is not None:
            beat()

    def _state(self, observation: RobotObservation) -> np.ndarray:
        parts = [np.asarray(OBSERVATIONS.get(name).read(self, observation), np.float64).reshape(-1)
                 for name in self.spec.observations]
        return np.concatenate(parts).astype(np.float32)

    def _obs(self, observation: RobotObservation) -> dict[str, np.ndarray]:
        obs = {"state": self._state(observation)}
        for name in self.spec.cameras:
            obs[f"pixels.{self.spec.camera_names.get(name, name)}"] = self._frame(
                np.asarray(observation.frames[name], np.uint8))
        return obs

    def _frame(self, frame: np.ndarray) -> np.ndarray:
        """A camera frame at ``spec.frame_size`` (Pillow's bilinear resize, antialiased when shrinking)."""
        size = self.spec.frame_size
        if size is None or frame.shape[:2] == size:
            return frame
        from PIL import Image

        return np.asarray(Image.fromarray(frame).resize((size[1], size[0]), Image.BILINEAR))
