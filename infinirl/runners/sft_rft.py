"""Rejection-sampling fine-tuning rounds of the SFT runner (``rft.every``): RL through cloning.

Each round, the policy being trained acts (π0's ODE sampler, as evaluated) in every task's MetaWorld
env from new training layouts; the episodes it solves are written as a LeRobotDataset to
``<output_dir>/rft/round_<k>`` and join the frames the SFT loss draws from. A policy cloning its own
successes raises the probability of what solved each layout: the REINFORCE update of a 0/1 success
reward with the behaviour-cloning loss standing in for the log-likelihood (expert iteration; RFT /
ReST in language models). The demonstrations stay in the data, so the policy cannot drift far from them.

A round is a pure function of the weights and ``(rft.seed, round)``: the layouts and the sampling
noise derive from them. A resumed run reads the rounds its checkpoint counts back from disk
(rounds written after that checkpoint are collected again, identically, and overwrite them).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import torch

from infinirl.config import ConfigError
from infinirl.runners.sft_config import SFTConfig
from infinirl.runners.sim_config import EVAL_SEED_BASE

__all__ = ["RFT_DIR", "RejectionSampling", "round_dir", "round_seeds"]

RFT_DIR = "rft"


def round_dir(output_dir: str, round_index: int) -> Path:
    return Path(output_dir) / RFT_DIR / f"round_{round_index:04d}"


def round_seeds(seed: int, round_index: int, task_position: int, count: int) -> list[int]:
    """The layouts of a round's episodes of one task: distinct per (seed, round, task), never held out."""
    state = np.random.SeedSequence([seed, round_index, task_position]).generate_state(count, dtype=np.uint64)
    return [int(s % EVAL_SEED_BASE) for s in state]  # held-out layouts start at EVAL_SEED_BASE


def _noise_seed(seed: int, round_index: int) -> int:
    return int(np.random.SeedSequence([seed, round_index, 2**20]).generate_state(1)[0])


class RejectionSampling:
    """The rounds of one SFT run: when they are due, collecting one, and reading them back."""

    def __init__(self, cfg: SFTConfig, tasks: dict[str, tuple[str, str]], camera_key: str, image_size: int):
        self.cfg, self.tasks = cfg, tasks
        self.camera_key, self.image_size = camera_key, image_size
        self.camera = camera_key.rsplit(".", 1)[-1]  # observation.images.<camera>: the env's camera name
        self.kept: list[int] = []
        """Successful episodes kept by each round so far (round k is ``kept[k - 1]``)."""
        self.envs: dict[str, object] = {}

    @property
    def enabled(self) -> bool:
        return self.cfg.rft.every > 0

    def due(self, iteration: int) -> bool:
        every = self.cfg.rft.every
        if not every or iteration % every:
            return False
        return iteration > 0 or self.cfg.model.init is not None

    def _env(self, task: str):
        from infinirl.envs.registry import make_env

        if task not in self.envs:
            rft = self.cfg.rft
            self.envs[task] = make_env(f"metaworld:{task}", min(rft.num_envs, rft.episodes_per_task), seed=rft.seed,
                                       num_workers=0, obs_mode="state+rgb", camera=self.camera,
                                       image_size=self.image_size, terminate_on_success=True)
        return self.envs[task]

    def collect(self, policy, vla) -> tuple[Path | None, dict]:
        """Run the next round with ``policy`` (``vla`` switched to eval mode meanwhile); returns the
        folder of its kept episodes (None: none solved) and the round's metrics."""
        from infinirl.data.demos import METAWORLD_FPS, metaworld_features, record_policy_episodes
        from infinirl.data.lerobot_dataset import LeRobotDatasetWriter

        rft, round_index, t0 = self.cfg.rft, len(self.kept) + 1, time.perf_counter()
        features = metaworld_features(self.camera, self.image_size)
        writer = LeRobotDatasetWriter(round_dir(self.cfg.output_dir, round_index), fps=METAWORLD_FPS,
                                      features=features, robot_type="sawyer", overwrite=True)
        metrics: dict[str, float] = {}
        kept = tried = frames = 0
        was_training = vla.training
        vla.eval()
        try:
            with torch.random.fork_rng(), torch.no_grad():
                torch.manual_seed(_noise_seed(rft.seed, round_index))
                for position, (task, (_, wording)) in enumerate(self.tasks.items()):
                    seeds = round_seeds(rft.seed, round_index, position, rft.episodes_per_task)
                    episodes = record_policy_episodes(self._env(task), policy, seeds, self.camera_key)
                    solved = [episode for episode, success in episodes if success]
                    for episode in solved:
                        writer.add_episode(episode, task=wording)
                        frames += len(episode["action"])
                    metrics[f"rft/success/{task}"] = len(solved) / len(episodes)
                    kept, tried = kept + len(solved), tried + len(episodes)
            path = writer.finalize() if kept else None
            if not kept:
                writer.abort()
                shutil.rmtree(round_dir(self.cfg.output_dir, round_index), ignore_errors=True)  # an older try's
        except BaseException:
            writer.abort()
            raise
        finally:
            vla.train(was_training)
        self.kept.append(kept)
        metrics.update({"rft/round": round_index, "rft/success_rate": kept / tried, "rft/kept_episodes": kept,
                        "rft/kept_frames": frames, "time/rft_s": time.perf_counter() - t0})
        return path, metrics

    def saved_rounds(self) -> list[Path]:
        """The folders of the rounds counted in :attr:`kept` that kept episodes (a resumed run's data)."""
        folders = [round_dir(self.cfg.output_dir, k + 1) for k, count in enumerate(self.kept) if count]
        for folder in folders:
            if not folder.is_dir():
                raise ConfigError(f"resume: the RFT round {folder} is missing: the checkpoint counts its episodes "
                                  "among the data it trains on; restore it, or start the run again in a new "
                                  "output_dir (or with resume=false)")
        return folders

    def close(self) -> None:
        for env in self.envs.values():
            env.close()
        self.envs = {}
