"""Config sections shared by the runners that train in simulators (embodied PPO/GRPO, SAC)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from infinirl.config import ConfigError, bounded
from infinirl.runners.run_config import EvalSchedule

__all__ = ["EVAL_SEED_BASE", "SimEnvConfig", "SimEvalConfig", "check_env_options", "episode_metrics", "eval_seeds"]

EVAL_SEED_BASE = 2**31
"""First held-out evaluation seed; training episode seeds are below 2**31 - 1, so the two never meet."""


def eval_seeds(seed: int, count: int) -> list[int]:
    """The held-out episodes' seeds: the same for every runner, disjoint from every training seed."""
    return [EVAL_SEED_BASE + seed + i for i in range(count)]


@dataclass(kw_only=True)
class SimEnvConfig:
    name: str = "gym:Pendulum-v1"
    """``family:task`` as `make_env` takes it: metaworld:reach-v3, gym:Hopper-v5, maniskill:PushCube-v1, ..."""
    num_envs: int = bounded(1, ge=1)
    """Training envs stepped together (over all env ranks)."""
    num_workers: int = bounded(0, ge=0)
    """Simulator subprocesses; 0 = the sub-envs run in the process that owns them (cheapest for
    fast simulators)."""
    max_episode_steps: int | None = bounded(None, ge=1)
    """Extra time limit (None: the simulator's own)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options passed to the env family (checked against the family before any worker starts)."""
    step_timeout_s: float | None = bounded(300.0, gt=0)
    """A simulator subprocess (num_workers >= 1) silent this long in one reset, step or render is
    killed and replaced, its episodes reported truncated (a hung simulator would otherwise stop the
    run forever); generous, since a step may render or reset a large scene. None: wait forever.
    Sub-envs in the owning process (num_workers=0) are not timed."""
    max_restarts: int = bounded(100, ge=0)
    """Sub-env crashes (a step that raised, a worker process lost or timed out) one vectorised env
    survives in total; one more stops the run with the last crash's traceback."""

    def vla_checkpoint(self) -> str | None:
        """``kwargs.vla.checkpoint``: the frozen VLA a ``vla_noise`` env folds in (None: not set)."""
        vla = self.kwargs.get("vla")
        checkpoint = vla.get("checkpoint") if isinstance(vla, dict) else None
        return checkpoint if isinstance(checkpoint, str) else None

    def validate(self) -> None:
        from infinirl.envs.registry import ENVS

        family = self.name.partition(":")[0]
        if family not in ENVS:
            raise ConfigError(f"env.name={self.name!r}: unknown env family {family!r}; registered: "
                              f"{', '.join(ENVS.names())} (write family:task, e.g. gym:Pendulum-v1)")


@dataclass(kw_only=True)
class SimEvalConfig(EvalSchedule):
    episodes: int = bounded(10, ge=1)
    """Held-out episodes, seeds 2**31 + eval.seed + i (disjoint from every training seed)."""
    num_envs: int = bounded(5, ge=1)
    """Envs the held-out episodes run on, in rounds."""
    seed: int = bounded(0, ge=0)
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options of the evaluation (and video) envs on top of env.kwargs."""
    target: float | None = None
    """The summary names the first evaluation whose headline metric reached this."""
    video_episodes: int = bounded(2, ge=0)
    """Episodes rendered into eval.mp4 after training (0 = no video)."""
    video_fps: int = bounded(30, ge=1)
    video_frame_skip: int = bounded(2, ge=1)
    video_env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options of the video env on top of eval.env_kwargs (e.g. a larger image size)."""


def check_env_options(name: str, options_by_key: dict[str, dict]) -> None:
    """Every env option mapping of a run (``config key -> options``) against the env family, in the
    driver: an option the env does not take is a ConfigError naming the key, not a failure at the
    first evaluation after minutes of training."""
    from infinirl.envs import check_env_kwargs

    for where, options in options_by_key.items():
        try:
            check_env_kwargs(name, options, where)
        except (ValueError, KeyError) as exc:
            message = str(exc.args[0]) if exc.args else str(exc)
            raise ConfigError(message if message.startswith(where) else f"{name} (env.name): {message}") from None


def episode_metrics(finished: dict, still_open: dict | None = None) -> dict:
    """``rollout/*`` statistics of an iteration's episodes.

    ``finished``: arrays ``return``, ``length`` (and ``success``) of the episodes that ended during
    the iteration; their means are logged only when at least one ended, never as NaN.
    ``still_open``: ``return`` / ``length`` so far of the episode running in each env at its end
    (length 0: none running), so a task whose episodes outlast an iteration still shows its returns."""
    import numpy as np

    count = len(finished["return"])
    metrics = {"rollout/episodes": float(count)}
    if count:
        metrics["rollout/episode_return_mean"] = float(np.mean(finished["return"]))
        metrics["rollout/episode_length_mean"] = float(np.mean(finished["length"]))
        if "success" in finished:
            metrics["rollout/success_rate"] = float(np.mean(finished["success"]))
    running = np.asarray(still_open["length"]) > 0 if still_open is not None else np.zeros(0, dtype=bool)
    if running.any():
        metrics["rollout/open_episode_return_mean"] = float(np.mean(np.asarray(still_open["return"])[running]))
        metrics["rollout/open_episode_length_mean"] = float(np.mean(np.asarray(still_open["length"])[running]))
    return metrics
