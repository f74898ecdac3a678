"""Labelled episodes from the simulated Sawyer (MetaWorld reach): the scripted expert and random
actions act, the simulated human marks success when the simulator reports it (failure after a
number of steps), and the real SuccessLabelWriter saves each marked episode, as a robot worker with
interventions.labels does."""

from __future__ import annotations

import numpy as np

from infinirl.realworld.demos import make_demo_policy
from infinirl.realworld.driver import make_robot
from infinirl.realworld.intervention.human_reward import SuccessLabelWriter
from infinirl.realworld.intervention.simulated_human import SimulatedHuman
from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
from infinirl.realworld.safety import SafeRobot, SafetyConfig

OBSERVATIONS = ("proprio", "sim_state")
FULL_SPEED = SafetyConfig(velocity_scale=1.0, command_deadline_s=None, heartbeat_deadline_s=None)


def sawyer(control_hz: float = 80.0, seed: int = 0) -> SafeRobot:
    robot = SafeRobot(make_robot("sim_sawyer", control_hz=control_hz, image_size=None, seed=seed), FULL_SPEED)
    robot.connect()
    return robot


def labelling_env(robot, max_episode_steps: int, **spec) -> RobotEnv:
    """The simulator stands in for the real world: its success ends nothing, the human's mark does."""
    return RobotEnv(robot, RobotEnvSpec(observations=OBSERVATIONS, rewards={"success": 1.0},
                                        max_episode_steps=max_episode_steps, terminate_on_success=False, **spec))


def run_marked_episode(env: RobotEnv, act, human: SimulatedHuman) -> tuple[list[dict], list[bool], str | None]:
    """One episode: its observations, the simulator's success of each, and the human's mark (None:
    the step limit came first)."""
    obs = env.reset()
    human.reset()
    observations, successes = [obs], [bool(env.last_observation.info["success"])]
    for _ in range(env.spec.max_episode_steps):
        step = env.step(act(env.last_observation))
        observations.append(step.obs)
        successes.append(bool(env.last_observation.info["success"]))
        marks = human.poll(observation=step.obs).marks
        if marks:
            return observations, successes, marks[-1]
    return observations, successes, None


def record_labels(env: RobotEnv, folder: str, expert_episodes: int, random_episodes: int, seed: int,
                  noise_std: float = 0.3) -> dict[str, int]:
    """Marked episodes of the noisy expert and of uniform random actions, labelled under ``folder``."""
    expert = make_demo_policy("sawyer_goal", env, seed=seed, noise_std=noise_std)
    rng = np.random.default_rng([seed, 7])

    def random_action(_observation):
        return rng.uniform(-1.0, 1.0, env.action_dim)

    human = SimulatedHuman(action_dim=env.action_dim, give_up_steps=env.spec.max_episode_steps - 1, seed=seed)
    human.bind(env)
    writer = SuccessLabelWriter(folder, prefix="rank0")
    marks = {"success": 0, "failure": 0}
    for act, count in ((expert.act, expert_episodes), (random_action, random_episodes)):
        for _ in range(count):
            observations, _, mark = run_marked_episode(env, act, human)
            if mark is not None:
                writer.write({"state": [o["state"] for o in observations]}, mark)
                marks[mark] += 1
    return marks


def held_out_states(env: RobotEnv, expert_episodes: int, random_episodes: int, seed: int,
                    extra_steps: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """``(states, the simulator's success of each)`` of fresh episodes; the expert's go on for
    ``extra_steps`` after its first success (the hand stays at the goal)."""
    expert = make_demo_policy("sawyer_goal", env, seed=seed, noise_std=0.3)
    rng = np.random.default_rng([seed, 11])
    states, successes = [], []
    for count, act in ((expert_episodes, expert.act), (random_episodes, lambda _o: rng.uniform(-1, 1, env.action_dim))):
        for _ in range(count):
            env.reset()
            after = 0
            for _ in range(env.spec.max_episode_steps):
                step = env.step(act(env.last_observation))
                success = bool(env.last_observation.info["success"])
                states.append(step.obs["state"])
                successes.append(success)
                after += int(success)
                if after > extra_steps:
                    break
    return np.stack(states), np.asarray(successes)
