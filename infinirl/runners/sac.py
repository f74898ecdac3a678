"""Soft Actor-Critic in vectorised simulators: the macro flow.

Read top to bottom: every iteration the **collector** (training envs + the actor's inference copy)
steps its envs ``steps_per_iteration`` times, with uniformly random actions until
``algorithm.learning_starts`` env steps have been collected; the **learner** puts the transitions
into its replay buffer and runs ``utd_ratio`` x (new env steps) SAC updates (twin-Q critics with
Polyak-averaged targets, squashed-Gaussian actor, auto-tuned entropy temperature), then its actor
weights are synced into the collector with the iteration number as version. The collector records
the version on every batch, so staleness is measured: 0 by default (collection waits for the
sync); 1 with ``collect_ahead``, which collects iteration i+1's steps while the learner trains on
iteration i's (collection and learning pipelined, same code, one config key).

Where the two run is placement (``placement.collector`` / ``placement.learner``), not code.
Checkpoints hold the learner (weights, optimisers, generators, update count), the replay buffer
and the collector's state (generators, counters, each env's episode seed and actions so far, to be
replayed); a resumed run continues exactly, bit for bit.
"""

from __future__ import annotations

import math
import os
import time
from fractions import Fraction

import numpy as np
import torch

from infinirl.components.sac_collector import CollectorEnvSpec, SACCollectorWorker
from infinirl.components.sac_learner import SACLearnerWorker, SACNetSpec, SACUpdateSpec
from infinirl.config import ConfigError
from infinirl.runners import register_runner
from infinirl.runners.curves import Panel
from infinirl.runners.loop import LoopSpec, ProgressField, RunLoop
from infinirl.runners.run_support import run_components, run_start_time
from infinirl.runners.sac_config import SACConfig
from infinirl.runners.sim_config import check_env_options, episode_metrics, eval_seeds
from infinirl.runtime import sync_weights
from infinirl.utils import torch_save_atomic
from infinirl.utils.threads import spin_wait_env

_PENDING = "pending_batch.pt"  # with collect_ahead: the next iteration's batch, collected before the save


def preflight(cfg: SACConfig) -> tuple[int, object, SACNetSpec]:
    """The env task, its options and spaces (one sub-env built in the driver) and the networks built
    once, before any worker starts (``infinirl validate`` runs it too); ``(obs size, action space, net)``."""
    obs_dim, action_space = _probe(cfg)
    net = _net_spec(cfg)
    check_net_builds(net, obs_dim, action_space)
    return obs_dim, action_space, net


@register_runner("sac", SACConfig,
                 "Soft Actor-Critic (twin Q, auto-tuned entropy, replay buffer) in gymnasium/MuJoCo simulators",
                 preflight=preflight)
def run(cfg: SACConfig) -> dict:
    with RunLoop(cfg, run_start_time()) as loop:
        obs_dim, action_space, net = preflight(cfg)  # bad task names / spaces fail here, before any worker starts
        alg = cfg.algorithm
        update = SACUpdateSpec(gamma=alg.gamma, tau=alg.tau, batch_size=alg.batch_size, actor_lr=alg.actor_lr,
                               critic_lr=alg.critic_lr, alpha_lr=alg.alpha_lr, init_alpha=alg.init_alpha,
                               autotune_alpha=alg.autotune_alpha, target_entropy=alg.target_entropy,
                               policy_delay=alg.policy_delay, target_update_every=alg.target_update_every,
                               buffer_capacity=cfg.buffer.capacity, seed=cfg.seed)
        env = collector_env_spec(cfg)
        launches = {
            "learner": (SACLearnerWorker, (net, update, obs_dim, action_space, cfg.learner.num_threads,
                                           cfg.learner.device), spin_wait_env(cfg.learner.num_threads)),
            "collector": (SACCollectorWorker, (env, net, obs_dim, action_space, cfg.seed, cfg.collector.num_threads),
                          spin_wait_env(cfg.collector.num_threads)),
        }
        return run_components(cfg, loop, lambda plan: launches,
                              lambda groups, plan: SACFlow(cfg, groups["collector"], groups["learner"]))


def collector_env_spec(cfg: SACConfig) -> CollectorEnvSpec:
    """How the collector builds its envs, from the run's ``env`` section."""
    return CollectorEnvSpec(name=cfg.env.name, num_envs=cfg.env.num_envs, num_workers=cfg.env.num_workers,
                            max_episode_steps=cfg.env.max_episode_steps, kwargs=dict(cfg.env.kwargs), seed=cfg.seed,
                            step_timeout_s=cfg.env.step_timeout_s, max_restarts=cfg.env.max_restarts)


def check_net_builds(net: SACNetSpec, obs_dim: int, action_space, cameras: dict | None = None) -> None:
    """Build the actor once in the driver: bad network options (an unknown flow_matching keyword, a
    camera too small for the conv stack) fail as a one-line ConfigError, not in a worker."""
    try:
        net.build_actor(obs_dim, action_space, cameras)
    except (ValueError, TypeError, KeyError) as exc:
        raise ConfigError(f"network (actor={net.actor}, encoder={net.encoder}): {exc}") from exc


def _net_spec(cfg: SACConfig) -> SACNetSpec:
    network = cfg.network
    return SACNetSpec(actor_hidden=tuple(network.actor_hidden), critic_hidden=tuple(network.critic_hidden),
                      num_critics=network.num_critics, activation=network.activation,
                      log_std_min=network.log_std_min, log_std_max=network.log_std_max, obs_key=network.obs_key,
                      layer_norm=network.layer_norm,
                      actor=network.actor, flow=dict(network.flow))


def _probe(cfg: SACConfig) -> tuple[int, object]:
    """Observation size and action space of the env, from one sub-env built in the driver; the env
    options of training, evaluation and the video are checked against the env family first."""
    from infinirl.envs.registry import ENVS, split_env_name

    check_env_options(cfg.env.name, {"env.kwargs": cfg.env.kwargs, "eval.env_kwargs": cfg.eval.env_kwargs,
                                     "eval.video_env_kwargs": cfg.eval.video_env_kwargs})
    try:
        family, task = split_env_name(cfg.env.name)
        sub_env = ENVS.get(family)(task, **cfg.env.kwargs)(0)
    except (ValueError, TypeError, KeyError, OSError) as exc:  # OSError: a file the env reads (a VLA) is missing
        raise ConfigError(f"env.name={cfg.env.name!r}: {exc}") from exc
    try:
        spec, space = dict(sub_env.observation_spec), sub_env.action_space
    finally:
        sub_env.close()
    key = cfg.network.obs_key
    if key not in spec or spec[key].is_text or len(spec[key].shape) != 1:
        raise ConfigError(f"network.obs_key={key!r}: {cfg.env.name} observations are {spec}; SAC here reads one "
                          "flat float vector (e.g. obs_mode=state)")
    if space.is_discrete:
        raise ConfigError(f"{cfg.env.name} has discrete actions ({space.num_choices}); "
                          "SAC needs a continuous (Box) space")
    if not (np.isfinite(space.low).all() and np.isfinite(space.high).all()):
        raise ConfigError(f"{cfg.env.name} has an unbounded action box; SAC's tanh squash needs finite bounds")
    return int(spec[key].shape[0]), space


class SACFlow:
    """The iteration logic (the loop drives it: see :mod:`infinirl.runners.loop`)."""

    def __init__(self, cfg: SACConfig, collector, learner):
        self.cfg, self.collector, self.learner = cfg, collector, learner
        self.env_steps = 0
        self.pending = None  # the next iteration's batch: a collection in flight, or restored from a checkpoint
        headline = f"eval/{cfg.eval.headline}"
        self.spec = LoopSpec(
            name="sac", title=f"SAC {cfg.env.name}", headline=headline, target=cfg.eval.target,
            progress=(ProgressField(label="ret", key="rollout/episode_return_mean", format=".0f",
                                    fallback="rollout/open_episode_return_mean"),
                      ProgressField(label="eval", key=headline, format=".2f" if "success" in headline else ".0f"),
                      ProgressField(label="alpha", key="train/alpha", format=".3f")),
            panels=(Panel(title=f"held-out {cfg.eval.headline} (deterministic)", y=(headline,), x="env/steps",
                          x_label="env steps"),
                    Panel(title=f"held-out {cfg.eval.headline}", y=(headline,), x="time/elapsed_s",
                          x_label="wall time incl. start-up (s)"),
                    Panel(title="training episode return", y=("rollout/episode_return_mean",
                                                              "rollout/open_episode_return_mean"),
                          x="env/steps", x_label="env steps"),
                    Panel(title="temperature alpha / entropy", y=("train/alpha", "train/entropy"), x="env/steps",
                          x_label="env steps")))

    def start(self, iteration: int) -> None:
        sync_weights(self.learner, self.collector, version=iteration)

    def step(self, iteration: int) -> dict:
        cfg, t0 = self.cfg, time.perf_counter()
        num_envs, steps = cfg.env.num_envs, cfg.steps_per_iteration
        if self.pending is None:
            self.pending = self._collect(iteration)
        batch = self.pending.wait()[0]
        # collect_ahead: the next iteration's steps are collected (with this iteration's weights,
        # one version stale) while the learner trains on this batch.
        self.pending = self._collect(iteration + 1) if cfg.collect_ahead else None
        t1 = time.perf_counter()
        before, self.env_steps = self.env_steps, self.env_steps + steps * num_envs
        num_updates = self._updates_due(self.env_steps) - self._updates_due(before)
        train = self.learner.add_and_update(batch, num_updates, self.env_steps).wait()[0]
        t2 = time.perf_counter()
        if self.pending is not None:  # the sync would queue behind the collection in flight anyway
            self.pending.wait()
        t3 = time.perf_counter()
        sync = sync_weights(self.learner, self.collector, version=iteration + 1)
        return {
            **train, **batch["timing"],
            "rollout/reward_mean": float(np.mean(batch["reward"])) if len(batch["reward"]) else float("nan"),
            **episode_metrics(batch["episodes"], batch.get("open_episodes")),
            "rollout/random_action_fraction": self._random_steps(iteration) / steps,
            "rollout/max_staleness": float(iteration - batch["version"]),
            "env/steps": self.env_steps,
            "env/restarts": float(batch["restarted"]),
            "time/wait_for_data_s": t1 - t0,
            "time/train_s": t2 - t1,
            "time/wait_for_collector_s": t3 - t2,
            "time/weight_sync_s": sync.seconds,
            "time/iteration_s": time.perf_counter() - t0,
            "time/env_steps_per_s": steps * num_envs / max(batch["timing"]["rollout/collect_s"], 1e-9),
        }

    def _random_steps(self, iteration: int) -> int:
        """Warm-up steps (uniform random actions) of ``iteration``'s collection, per env."""
        cfg = self.cfg
        collected_before = iteration * cfg.steps_per_iteration * cfg.env.num_envs
        remaining = cfg.algorithm.learning_starts - collected_before
        return min(cfg.steps_per_iteration, max(0, math.ceil(remaining / cfg.env.num_envs)))

    def _collect(self, iteration: int):
        return self.collector.collect(self.cfg.steps_per_iteration, self._random_steps(iteration))

    def _updates_due(self, env_steps: int) -> int:
        """Total gradient updates owed after ``env_steps`` collected steps: ``utd_ratio`` per step
        past ``learning_starts`` (integer bookkeeping, so fractional ratios add up exactly)."""
        ratio = Fraction(repr(self.cfg.algorithm.utd_ratio))  # exact: 0.29 * 100 is 29, not 28.999...
        return math.floor(ratio * max(0, env_steps - self.cfg.algorithm.learning_starts))

    def evaluate(self) -> dict:
        cfg = self.cfg.eval
        seeds = eval_seeds(cfg.seed, cfg.episodes)
        result = self.collector.evaluate(seeds, min(cfg.num_envs, cfg.episodes), dict(cfg.env_kwargs)).wait()[0]
        return {**result, "env/steps": self.env_steps}

    # ------------------------------------------------------------------ checkpoints
    def save(self, folder: str) -> dict:
        """Learner (weights, optimisers, generators, replay buffer) and the collector's state (every
        file written atomically); with collect_ahead, the batch already collected for the next iteration."""
        saving = [self.learner.save_checkpoint(os.path.join(folder, "learner")),
                  self.collector.save_state(os.path.join(folder, "collector"))]
        for handle in saving:
            handle.wait()
        if self.pending is not None:  # collected ahead (complete: the weight sync waited for it)
            torch_save_atomic(self.pending.wait()[0], os.path.join(folder, _PENDING))
        return {"env_steps": self.env_steps}

    def load(self, folder: str, state: dict) -> None:
        loading = [self.learner.load_checkpoint(os.path.join(folder, "learner")),
                   self.collector.load_state(os.path.join(folder, "collector"))]
        loading[0].wait()
        replay = loading[1].wait()[0]
        pending = os.path.join(folder, _PENDING)
        if os.path.exists(pending):  # collected ahead before the save: the collector's state is past it
            self.pending = _Ready(torch.load(pending, weights_only=False))
        self.env_steps = int(state["env_steps"])
        note = f"; envs {replay['mismatched_envs']} did not replay exactly" if replay["mismatched_envs"] else ""
        print(f"restored the collector's envs (replayed {replay['replayed_steps']} env steps{note})", flush=True)

    # ------------------------------------------------------------------ the end
    def finish(self, output_dir: str) -> dict:
        cfg = self.cfg
        video = None
        if cfg.eval.video_episodes:
            try:
                video = self.collector.record_video(
                    eval_seeds(cfg.eval.seed, cfg.eval.video_episodes), os.path.join(output_dir, "eval.mp4"),
                    cfg.eval.video_fps, cfg.eval.video_frame_skip, cfg.eval.video_max_steps,
                    {**cfg.eval.env_kwargs, **cfg.eval.video_env_kwargs}).wait()[0]
            except Exception as exc:  # a missing GL library must not lose the trained run
                print(f"eval video skipped: {exc}", flush=True)
        return {
            "env_steps": self.env_steps, "video": video["path"] if video else None,
            "actor_weights_sha256": self.learner.actor_digest().wait()[0],
            "weights_sha256": self.learner.weights_digest().wait()[0],
            "buffer_sha256": self.learner.buffer_digest().wait()[0],
            "devices": {"learner": self.learner_device()},
        }

    def learner_device(self) -> str:
        """Where the learner computes (``learner.device``), read off its parameters."""
        return self.learner.compute_device().wait()[0]

    def close(self) -> None:
        try:
            self.collector.close().wait(timeout=30)
        except Exception:  # best effort: the group is killed right after
            pass


class _Ready:
    """A batch that is already here, with the ``wait()`` of a collection in flight."""

    def __init__(self, value):
        self.value = value

    def wait(self, timeout: float | None = None) -> list:
        return [self.value]
