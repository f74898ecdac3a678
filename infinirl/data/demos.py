"""Demonstrations from scripted experts, stored as a LeRobotDataset v3.0 (``infinirl demos``).

``collect_demos("metaworld", DemoSpec(tasks=("reach-v3", "push-v3"), episodes_per_task=50,
out="data/mw"))`` runs MetaWorld's scripted expert of each task in our MetaWorld env (one env, in
this process), records every step, and keeps the episodes the expert finished successfully (a
failed demonstration would teach failure); the report gives the expert's success rate per task.

Recorded per step (LeRobot's names): ``observation.state`` (hand xyz + gripper opening, what a
real robot knows), ``observation.environment_state`` (the simulator's full 39-d state, goal
included: privileged, for state-based policies), ``observation.images.<camera>`` (the upright
camera frame), ``action`` (the action executed), ``next.reward``, ``next.success``, ``next.done``.
An episode ends at the expert's first success (or the env's time limit, then it is dropped).

Instructions (``instructions=``): ``"env"`` stores the env's own ``obs["instruction"]``, exactly
the string a policy is given when it is evaluated in that env; ``"natural"`` stores a sentence
from :data:`METAWORLD_INSTRUCTIONS` (the Meta-World paper's task descriptions, MT10 tasks).

A source is a :class:`DemoSource` entry of :data:`DEMO_SOURCES`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from infinirl.data.lerobot_dataset import LeRobotDatasetWriter
from infinirl.registry import Registry

__all__ = [
    "DEMO_SOURCES",
    "INSTRUCTION_STYLES",
    "METAWORLD_CAMERAS",
    "METAWORLD_FPS",
    "METAWORLD_INSTRUCTIONS",
    "METAWORLD_STATE_NAMES",
    "DemoReport",
    "DemoSource",
    "DemoSpec",
    "TaskReport",
    "collect_demos",
    "collect_metaworld_demos",
    "demos_command",
    "metaworld_features",
    "record_episode",
    "record_policy_episodes",
    "resolve_metaworld_tasks",
]

METAWORLD_FPS = 80
"""MetaWorld's control rate: each action is applied for 5 MuJoCo steps of 2.5 ms."""

INSTRUCTION_STYLES = ("env", "natural")

METAWORLD_INSTRUCTIONS = {
    "reach-v3": "reach a goal position",
    "push-v3": "push the puck to a goal",
    "pick-place-v3": "pick and place a puck to a goal",
    "door-open-v3": "open a door with a revolving joint",
    "drawer-open-v3": "open a drawer",
    "drawer-close-v3": "push and close a drawer",
    "button-press-topdown-v3": "press a button from the top",
    "peg-insert-side-v3": "insert a peg sideways",
    "window-open-v3": "push and open a window",
    "window-close-v3": "push and close a window",
}
"""The Meta-World paper's one-line description of each MT10 task."""

METAWORLD_CAMERAS = ("topview", "corner", "corner2", "corner3", "corner4", "behindGripper", "gripperPOV")
"""The cameras every MetaWorld v3 scene has."""

_HAND = ["hand_x", "hand_y", "hand_z", "gripper_opening"]
_OBJECTS = [f"{obj}_{part}" for obj in ("obj1", "obj2") for part in ("x", "y", "z", "qw", "qx", "qy", "qz")]
METAWORLD_STATE_NAMES = [*_HAND, *_OBJECTS, *(f"prev_{name}" for name in (*_HAND, *_OBJECTS)),
                         "goal_x", "goal_y", "goal_z"]
"""The 39 entries of MetaWorld's state: this frame's hand and objects, the previous frame's, the goal."""


@dataclass(frozen=True, kw_only=True)
class DemoSpec:
    """What to collect. ``max_attempts_per_task``: episodes tried per task at most (default
    ``3 * episodes_per_task``), so an expert that keeps failing cannot loop forever."""

    tasks: tuple[str, ...]
    episodes_per_task: int
    out: str
    image_size: int = 64
    camera: str = "corner"
    seed: int = 0
    noise_std: float = 0.0
    instructions: str = "env"
    max_attempts_per_task: int | None = None
    overwrite: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        if not self.tasks:
            raise ValueError("DemoSpec.tasks is empty: name at least one task")
        if self.episodes_per_task < 1:
            raise ValueError(f"episodes_per_task must be >= 1, got {self.episodes_per_task}")
        if self.image_size < 2 or self.image_size % 2:
            raise ValueError(f"image_size must be even and >= 2 (H.264 yuv420p video), got {self.image_size}")
        if self.instructions not in INSTRUCTION_STYLES:
            raise ValueError(f"instructions={self.instructions!r} is not one of {list(INSTRUCTION_STYLES)}")
        if self.noise_std < 0:
            raise ValueError(f"noise_std must be >= 0, got {self.noise_std}")
        if self.max_attempts_per_task is not None and self.max_attempts_per_task < self.episodes_per_task:
            raise ValueError(f"max_attempts_per_task={self.max_attempts_per_task} is below episodes_per_task="
                             f"{self.episodes_per_task}")

    @property
    def attempts_per_task(self) -> int:
        return self.max_attempts_per_task or 3 * self.episodes_per_task


@dataclass(frozen=True, kw_only=True)
class TaskReport:
    task: str
    instruction: str
    attempts: int
    successes: int
    frames: int

    @property
    def success_rate(self) -> float:
        return self.successes / self.attempts if self.attempts else 0.0


@dataclass(frozen=True, kw_only=True)
class DemoReport:
    root: Path
    tasks: tuple[TaskReport, ...]
    episodes_per_task: int

    @property
    def episodes(self) -> int:
        return sum(t.successes for t in self.tasks)

    @property
    def frames(self) -> int:
        return sum(t.frames for t in self.tasks)

    def lines(self) -> list[str]:
        """What ``infinirl demos`` prints: where, how much, the expert's success rate per task."""
        out = [f"wrote {self.episodes} episodes, {self.frames} frames to {self.root}"]
        for t in self.tasks:
            short = "" if t.successes >= self.episodes_per_task else (
                f"  (short of {self.episodes_per_task}: the attempt limit was reached)")
            out.append(f"  {t.task}: expert success {t.successes}/{t.attempts} = {t.success_rate:.0%}, "
                       f"{t.frames} frames, task {t.instruction!r}{short}")
        return out


@dataclass(frozen=True, kw_only=True)
class DemoSource:
    """A family of scripted experts: ``resolve_tasks`` turns the ``--tasks`` text into task names,
    ``collect`` records a :class:`DemoSpec`."""

    resolve_tasks: Callable[[str], tuple[str, ...]]
    collect: Callable[[DemoSpec], DemoReport]


DEMO_SOURCES: Registry[DemoSource] = Registry("demonstration source")


def collect_demos(source: str, spec: DemoSpec) -> DemoReport:
    """Collect ``spec`` from ``source`` (an entry of :data:`DEMO_SOURCES`, e.g. ``"metaworld"``)."""
    return DEMO_SOURCES.get(source).collect(spec)


def resolve_metaworld_tasks(text: str) -> tuple[str, ...]:
    """``"reach-v3,push-v3"`` or a benchmark name (``"MT10"``) -> the task names; an unknown name
    fails listing the valid ones."""
    from infinirl.envs.metaworld_env import metaworld_task_names

    names = metaworld_task_names()
    tasks: list[str] = []
    for name in (part.strip() for part in text.split(",") if part.strip()):
        if name not in names:
            raise ValueError(f"unknown MetaWorld task {name!r}; tasks: {', '.join(sorted(names))}")
        tasks += [task for task in names[name] if task not in tasks]
    if not tasks:
        raise ValueError(f"no MetaWorld task in {text!r}: give e.g. reach-v3,push-v3 or MT10")
    return tuple(tasks)


def metaworld_features(camera: str, image_size: int) -> dict[str, dict[str, Any]]:
    """The dataset features :func:`collect_metaworld_demos` writes."""
    return {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": _HAND},
        "observation.environment_state": {"dtype": "float32", "shape": (39,), "names": METAWORLD_STATE_NAMES},
        f"observation.images.{camera}": {"dtype": "video", "shape": (image_size, image_size, 3),
                                         "names": ["height", "width", "channels"]},
        "action": {"dtype": "float32", "shape": (4,), "names": ["hand_dx", "hand_dy", "hand_dz", "gripper_effort"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    }


def _derived_seed(*parts: int) -> int:
    """An independent seed for each (run seed, task, attempt, purpose)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0])


def record_episode(env: Any, expert: Any, seed: int, image_key: str) -> tuple[dict[str, np.ndarray], bool, str]:
    """Run ``expert`` in the single-env ``env`` from the layout of ``seed`` until it succeeds or the
    episode ends: ``(frames, succeeded, env instruction)``."""
    obs = env.reset(seeds=[seed])
    instruction = obs["instruction"][0]
    steps = _new_steps()
    while True:
        row = {key: value[0] for key, value in obs.items()}
        action = expert.act(row)
        result = env.step(action[None], autoreset=False)
        success, done = bool(result.info["success"][0]), bool(result.done[0])
        for key, value in (("state", row["proprio"]), ("env_state", row["state"]), ("rgb", row["rgb"]),
                           ("action", action), ("reward", result.reward[0]), ("success", success), ("done", done)):
            steps[key].append(value)
        obs = result.obs
        if success or done:
            break
    frames = _episode_frames(steps, image_key)
    return frames, success, instruction


def _episode_frames(steps: dict[str, list], image_key: str) -> dict[str, np.ndarray]:
    """One recorded episode's per-step lists -> the dataset's columns (:func:`metaworld_features`)."""
    return {
        "observation.state": np.stack(steps["state"]).astype(np.float32),
        "observation.environment_state": np.stack(steps["env_state"]).astype(np.float32),
        image_key: np.stack(steps["rgb"]),
        "action": np.stack(steps["action"]).astype(np.float32),
        "next.reward": np.asarray(steps["reward"], dtype=np.float32),
        "next.success": np.asarray(steps["success"], dtype=bool),
        # The recording stops at the first success: the stored episode ends there either way.
        "next.done": np.asarray([*([False] * (len(steps["done"]) - 1)), True]),
    }


def _new_steps() -> dict[str, list]:
    return {key: [] for key in ("state", "env_state", "rgb", "action", "reward", "success", "done")}


def record_policy_episodes(env: Any, policy: Any, seeds: list[int],
                           image_key: str) -> list[tuple[dict[str, np.ndarray], bool]]:
    """Run a chunked ``policy`` (acting deterministically: a flow policy's ODE sampler from a fresh
    noise draw) in ``env``, a vector env stepping one action at a time, once from the layout of each
    of ``seeds`` (rounds of ``env.num_envs``); every step is recorded as :func:`record_episode`
    records it, until the first success or the episode's end. Per seed: ``(frames, succeeded)``.

    The envs of a round start together, so they all plan (``policy.act``, ``policy.chunk`` actions
    executed) at the same steps: one batched forward pass per chunk for the episodes still running."""
    from infinirl.models.policies.base import prepare_obs

    out: list[tuple[dict[str, np.ndarray], bool]] = []
    num_envs, chunk = env.num_envs, int(policy.chunk)
    for start in range(0, len(seeds), num_envs):
        batch = [int(s) for s in seeds[start:start + num_envs]]
        obs = env.reset(seeds=batch + [batch[-1]] * (num_envs - len(batch)))
        active = np.arange(num_envs) < len(batch)
        steps = [_new_steps() for _ in batch]
        succeeded = np.zeros(len(batch), dtype=bool)
        plan, t = None, 0
        while active.any():
            if t % chunk == 0:  # only the episodes still running plan: a solved one costs nothing more
                rows = np.flatnonzero(active)
                running = {key: np.asarray(value)[rows] for key, value in obs.items()}
                planned = policy.act(prepare_obs(running), deterministic=True).actions.detach().cpu().numpy()
                plan = np.zeros((num_envs, chunk, planned.size // (len(rows) * chunk)), dtype=planned.dtype)
                plan[rows] = planned.reshape(len(rows), chunk, -1)
            action = plan[:, t % chunk]
            result = env.step(action, env_mask=active, autoreset=False)
            for i in np.flatnonzero(active):
                success, done = bool(result.info["success"][i]), bool(result.done[i])
                for key, value in (("state", obs["proprio"][i]), ("env_state", obs["state"][i]),
                                   ("rgb", obs["rgb"][i]), ("action", action[i]), ("reward", result.reward[i]),
                                   ("success", success), ("done", done)):
                    steps[i][key].append(value)
                if success or done:
                    succeeded[i] = success
                    active[i] = False
            obs, t = result.obs, t + 1
        out += [(_episode_frames(s, image_key), bool(ok)) for s, ok in zip(steps, succeeded, strict=True)]
    return out


def _instruction(task: str, env_instruction: str, style: str) -> str:
    if style == "env":
        return env_instruction
    if task not in METAWORLD_INSTRUCTIONS:
        raise ValueError(f"instructions='natural' has sentences for the MT10 tasks only "
                         f"({', '.join(METAWORLD_INSTRUCTIONS)}); {task!r} has none: use instructions='env'")
    return METAWORLD_INSTRUCTIONS[task]


def collect_metaworld_demos(spec: DemoSpec) -> DemoReport:
    """MetaWorld's scripted experts on ``spec.tasks`` (v3 names), successful episodes only."""
    from tqdm import tqdm

    from infinirl.envs.experts import make_expert
    from infinirl.envs.registry import make_env

    if spec.camera not in METAWORLD_CAMERAS:
        raise ValueError(f"unknown MetaWorld camera {spec.camera!r}; cameras: {', '.join(METAWORLD_CAMERAS)}")
    if spec.instructions == "natural":
        for task in spec.tasks:
            _instruction(task, "", "natural")  # refuse before any episode runs
    image_key = f"observation.images.{spec.camera}"
    reports = []
    features = metaworld_features(spec.camera, spec.image_size)
    writer = LeRobotDatasetWriter(spec.out, fps=METAWORLD_FPS, features=features, robot_type="sawyer",
                                  overwrite=spec.overwrite)
    with writer, tqdm(total=len(spec.tasks) * spec.episodes_per_task, desc="demos", unit="episode",
                      disable=not spec.progress) as bar:
        for position, task in enumerate(spec.tasks):
            noise_seed = _derived_seed(spec.seed, position, 1)
            expert = make_expert("metaworld", task, noise_std=spec.noise_std, seed=noise_seed)
            with make_env(f"metaworld:{task}", 1, num_workers=0, seed=spec.seed, obs_mode="state+rgb",
                          camera=spec.camera, image_size=spec.image_size, terminate_on_success=True) as env:
                reports.append(_collect_task(env, expert, task, position, spec, writer, bar, image_key))
    return DemoReport(root=writer.root, tasks=tuple(reports), episodes_per_task=spec.episodes_per_task)


def _collect_task(env: Any, expert: Any, task: str, position: int, spec: DemoSpec, writer: LeRobotDatasetWriter,
                  bar: Any, image_key: str) -> TaskReport:
    attempts = successes = frames_kept = 0
    instruction = ""
    while successes < spec.episodes_per_task and attempts < spec.attempts_per_task:
        frames, success, env_instruction = record_episode(
            env, expert, _derived_seed(spec.seed, position, 0, attempts), image_key)
        attempts += 1
        instruction = _instruction(task, env_instruction, spec.instructions)
        if success:
            writer.add_episode(frames, task=instruction)
            successes += 1
            frames_kept += len(frames["action"])
            bar.update(1)
        bar.set_postfix_str(f"{task} expert success {successes}/{attempts}")
    return TaskReport(task=task, instruction=instruction, attempts=attempts, successes=successes, frames=frames_kept)


DEMO_SOURCES.add("metaworld", DemoSource(resolve_tasks=resolve_metaworld_tasks, collect=collect_metaworld_demos))


def demos_command(args: argparse.Namespace) -> int:
    """``infinirl demos SOURCE --tasks ... --episodes-per-task N --out DIR``: collect, print where the
    dataset went and the expert's success rate; a bad argument is one line on stderr, exit 2."""
    try:
        source = DEMO_SOURCES.get(args.source)
        spec = DemoSpec(tasks=source.resolve_tasks(args.tasks), episodes_per_task=args.episodes_per_task,
                        out=args.out, image_size=args.image_size, camera=args.camera, seed=args.seed,
                        noise_std=args.noise_std, instructions=args.instructions, overwrite=args.overwrite,
                        progress=not args.no_progress)
        report = source.collect(spec)
    except ValueError as exc:
        message = " ".join(part.strip() for part in str(exc).splitlines() if part.strip())
        print(f"infinirl: demos: {message}", file=sys.stderr)
        return 2
    print("\n".join(report.lines()))
    return 0
