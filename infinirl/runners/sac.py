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

import json
import math
import os
import time
from fractions import Fraction

import numpy as np
import torch

from infinirl.components.sac_collector import CollectorEnvSpec, SACCollectorWorker
from infinirl.components.sac_learner import SACLearnerWorker, SACNetSpec, SACUpdateSpec
from infinirl.config import ConfigError, to_plain
from infinirl.runners import register_runner
from infinirl.runners.metrics_log import MetricsLogger, read_metrics
from infinirl.runners.run_support import CheckpointFolders, launch_all, run_start_time
from infinirl.runners.sac_config import COMPONENTS, SACConfig
from infinirl.runtime import Cluster, place, sync_weights
from infinirl.utils import torch_save_atomic

EVAL_SEED_BASE = 2**31
"""First held-out evaluation seed; training episode seeds are below 2**31 - 1, so the two never meet."""

_PENDING = "pending_batch.pt"  # with collect_ahead: the next iteration's batch, collected before the save


@register_runner("sac", SACConfig,
                 "Soft Actor-Critic (twin Q, auto-tuned entropy, replay buffer) in gymnasium/MuJoCo simulators")
def run(cfg: SACConfig) -> dict:
    started = run_start_time()
    os.makedirs(cfg.output_dir, exist_ok=True)
    obs_dim, action_space = _probe(cfg)  # bad task names / spaces fail here, before any worker starts
    network = cfg.network
    net = SACNetSpec(actor_hidden=tuple(network.actor_hidden), critic_hidden=tuple(network.critic_hidden),
                     num_critics=network.num_critics, activation=network.activation,
                     log_std_min=network.log_std_min, log_std_max=network.log_std_max, obs_key=network.obs_key,
                     actor=network.actor, flow=dict(network.flow))
    try:  # bad network options (e.g. an unknown flow_matching keyword) fail here, not in a worker
        net.build_actor(obs_dim, action_space)
    except (ValueError, TypeError, KeyError) as exc:
        raise ConfigError(f"network (actor={cfg.network.actor}): {exc}") from exc
    alg = cfg.algorithm
    update = SACUpdateSpec(gamma=alg.gamma, tau=alg.tau, batch_size=alg.batch_size, actor_lr=alg.actor_lr,
                           critic_lr=alg.critic_lr, alpha_lr=alg.alpha_lr, init_alpha=alg.init_alpha,
                           autotune_alpha=alg.autotune_alpha, target_entropy=alg.target_entropy,
                           policy_delay=alg.policy_delay, target_update_every=alg.target_update_every,
                           buffer_capacity=cfg.buffer.capacity, seed=cfg.seed)
    env = CollectorEnvSpec(name=cfg.env.name, num_envs=cfg.env.num_envs, num_workers=cfg.env.num_workers,
                           max_episode_steps=cfg.env.max_episode_steps, kwargs=dict(cfg.env.kwargs), seed=cfg.seed)
    with Cluster(cfg.cluster) as cluster:
        plan = place(cluster.inventory, cfg.placement, components=COMPONENTS)
        for name in COMPONENTS:
            if plan.world_size(name) != 1:
                raise ConfigError(f"placement.{name}={cfg.placement[name]!r} gives {plan.world_size(name)} ranks; "
                                  f"the SAC runner runs one {name} rank")
        print(plan.describe(), flush=True)
        groups = launch_all(plan, {
            "learner": (SACLearnerWorker, (net, update, obs_dim, action_space, cfg.learner.num_threads,
                                           cfg.learner.device)),
            "collector": (SACCollectorWorker, (env, net, obs_dim, action_space, cfg.seed, cfg.collector.num_threads)),
        })
        flow = SACFlow(cfg, groups["collector"], groups["learner"], started)
        print(f"learner computes on: {flow.learner_device()}", flush=True)
        try:
            return flow.train()
        finally:
            flow.close()
            for group in groups.values():
                group.shutdown()


def _probe(cfg: SACConfig) -> tuple[int, object]:
    """Observation size and action space of the env, from one sub-env built in the driver."""
    from infinirl.envs.registry import ENVS

    family, _, task = cfg.env.name.partition(":")
    try:
        sub_env = ENVS.get(family)(task or None, **cfg.env.kwargs)(0)
    except (ValueError, TypeError, KeyError) as exc:
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
    """The iteration logic, separated from process start-up so tests can drive it directly."""

    def __init__(self, cfg: SACConfig, collector, learner, started: float):
        self.cfg, self.collector, self.learner = cfg, collector, learner
        self.started = started
        self.env_steps = 0
        self.elapsed_before = 0.0  # wall time of the earlier runs of a resumed job
        self.logger: MetricsLogger | None = None
        self.pending = None  # the next iteration's batch: a collection in flight, or restored from a checkpoint

    # ------------------------------------------------------------------ the loop
    def train(self) -> dict:
        from tqdm import tqdm

        cfg = self.cfg
        start = self._maybe_resume()
        self.logger = MetricsLogger(cfg.output_dir, cfg.loggers, to_plain(cfg), start_step=start)
        sync_weights(self.learner, self.collector, version=start)
        if start == 0 and cfg.eval.at_start:
            self.logger.log({**self.evaluate(), "env/steps": 0, "time/elapsed_s": self.elapsed()}, step=0)
        progress = tqdm(range(start, cfg.iterations), initial=start, total=cfg.iterations, desc="sac", unit="it")
        for iteration in progress:
            metrics = self.iteration(iteration)
            done = iteration + 1
            if (cfg.eval.every and done % cfg.eval.every == 0) or done == cfg.iterations:
                metrics.update(self.evaluate())
            metrics["time/elapsed_s"] = self.elapsed()
            self.logger.log(metrics, step=done)
            progress.set_postfix(ret=f"{metrics['rollout/episode_return_mean']:.0f}",
                                 eval=f"{metrics.get('eval/return_mean', float('nan')):.0f}",
                                 alpha=f"{metrics.get('train/alpha', float('nan')):.3f}")
            if (cfg.save_every and done % cfg.save_every == 0) or done == cfg.iterations:
                self.save(done)
        return self.finish()

    def iteration(self, iteration: int) -> dict:
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
        episodes = batch["episodes"]
        returns = episodes["return"]
        return {
            **train, **batch["timing"],
            "rollout/reward_mean": float(np.mean(batch["reward"])) if len(batch["reward"]) else float("nan"),
            "rollout/episodes": float(len(returns)),
            "rollout/episode_return_mean": float(np.mean(returns)) if len(returns) else float("nan"),
            "rollout/episode_length_mean": float(np.mean(episodes["length"])) if len(returns) else float("nan"),
            "rollout/success_rate": float(np.mean(episodes["success"])) if len(returns) else float("nan"),
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
        cfg, t0 = self.cfg.eval, time.perf_counter()
        seeds = [EVAL_SEED_BASE + cfg.seed + i for i in range(cfg.episodes)]
        result = self.collector.evaluate(seeds, min(cfg.num_envs, cfg.episodes), dict(cfg.env_kwargs)).wait()[0]
        result["time/eval_s"] = time.perf_counter() - t0
        return result

    def elapsed(self) -> float:
        return self.elapsed_before + time.time() - self.started

    # ------------------------------------------------------------------ checkpoints
    def _checkpoint_root(self) -> str:
        return os.path.join(self.cfg.output_dir, "checkpoints")

    def save(self, iteration: int) -> str:
        """One folder per checkpoint, built under a temporary name and renamed into place (every
        file in it is itself written to a temporary name and renamed), so a crash at any point
        leaves the previous checkpoint usable."""
        folders = self._checkpoints()
        tmp = folders.begin(iteration)
        saving = [self.learner.save_checkpoint(os.path.join(tmp, "learner")),
                  self.collector.save_state(os.path.join(tmp, "collector"))]
        for handle in saving:
            handle.wait()
        if self.pending is not None:  # collected ahead (complete: the weight sync waited for it)
            torch_save_atomic(self.pending.wait()[0], os.path.join(tmp, _PENDING))
        final = folders.commit(tmp, iteration, {"iteration": iteration, "env_steps": self.env_steps,
                                                "elapsed_s": self.elapsed()})
        if self.cfg.keep_checkpoints:
            folders.prune(self.cfg.keep_checkpoints)
        return final

    def _checkpoints(self) -> CheckpointFolders:
        return CheckpointFolders(self.cfg.output_dir, "iter_")

    def _maybe_resume(self) -> int:
        found = self._checkpoints().latest() if self.cfg.resume else None
        if found is None:
            return 0
        latest, state = found
        loading = [self.learner.load_checkpoint(os.path.join(latest, "learner")),
                   self.collector.load_state(os.path.join(latest, "collector"))]
        loading[0].wait()
        replay = loading[1].wait()[0]
        pending = os.path.join(latest, _PENDING)
        if os.path.exists(pending):  # collected ahead before the save: the collector's state is past it
            self.pending = _Ready(torch.load(pending, weights_only=False))
        self.env_steps = int(state["env_steps"])
        self.elapsed_before = float(state["elapsed_s"])
        self.started = time.time()
        note = f"; envs {replay['mismatched_envs']} did not replay exactly" if replay["mismatched_envs"] else ""
        print(f"resumed from {latest} at iteration {state['iteration']} (replayed {replay['replayed_steps']} "
              f"env steps to restore the envs{note})", flush=True)
        return int(state["iteration"])

    # ------------------------------------------------------------------ the end
    def finish(self) -> dict:
        cfg = self.cfg
        video = None
        if cfg.eval.video_episodes:
            seeds = [EVAL_SEED_BASE + cfg.eval.seed + i for i in range(cfg.eval.video_episodes)]
            try:
                video = self.collector.record_video(
                    seeds, os.path.join(cfg.output_dir, "eval.mp4"), cfg.eval.video_fps, cfg.eval.video_frame_skip,
                    cfg.eval.video_max_steps, {**cfg.eval.env_kwargs, **cfg.eval.video_env_kwargs}).wait()[0]
            except Exception as exc:  # a missing GL library must not lose the trained run
                print(f"eval video skipped: {exc}", flush=True)
        self.logger.close()
        rows = read_metrics(self.logger.path)
        curves = plot_sac_curves(rows, os.path.join(cfg.output_dir, "curves.png"), f"SAC {cfg.env.name}")
        evals = [r for r in rows if "eval/return_mean" in r]
        summary = {
            "eval_return_before": evals[0]["eval/return_mean"] if evals else None,
            "eval_return_after": evals[-1]["eval/return_mean"] if evals else None,
            "eval_return_best": max(r["eval/return_mean"] for r in evals) if evals else None,
            "first_eval_at_target": _first_reaching(evals, cfg.eval.target_return),
            "iterations": cfg.iterations, "env_steps": self.env_steps, "elapsed_s": round(self.elapsed(), 1),
            "curves": curves, "video": video["path"] if video else None, "metrics": self.logger.path,
            "actor_weights_sha256": self.learner.actor_digest().wait()[0],
            "weights_sha256": self.learner.weights_digest().wait()[0],
            "buffer_sha256": self.learner.buffer_digest().wait()[0],
            "devices": {"learner": self.learner_device()},
        }
        print(json.dumps(summary), flush=True)
        return summary

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


def _first_reaching(evals: list[dict], target: float | None) -> dict | None:
    if target is None:
        return None
    for row in evals:
        if row["eval/return_mean"] >= target:
            return {"iteration": row["step"], "env_steps": row.get("env/steps"), "elapsed_s": row.get("time/elapsed_s")}
    return None


def plot_sac_curves(rows: list[dict], path: str, title: str) -> str | None:
    """One PNG: held-out return vs env steps and vs wall time, training episode return vs env
    steps, and the temperature / policy entropy vs env steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    evals = [r for r in rows if "eval/return_mean" in r and "env/steps" in r]
    train = [r for r in rows if np.isfinite(r.get("rollout/episode_return_mean", float("nan")))]
    alpha = [r for r in rows if "train/alpha" in r and "env/steps" in r]
    if not evals and not train:
        return None
    fig, axes = plt.subplots(1, 4, figsize=(20, 3.6))
    panels = [
        (axes[0], evals, "env/steps", ["eval/return_mean"], "held-out return (deterministic)", "env steps"),
        (axes[1], [r for r in evals if "time/elapsed_s" in r], "time/elapsed_s", ["eval/return_mean"],
         "held-out return", "wall time incl. start-up (s)"),
        (axes[2], train, "env/steps", ["rollout/episode_return_mean"], "training episode return", "env steps"),
        (axes[3], alpha, "env/steps", ["train/alpha", "train/entropy"], "temperature alpha / entropy", "env steps"),
    ]
    for ax, data, x_key, y_keys, label, x_label in panels:
        for y_key in y_keys:
            points = [(r[x_key], r[y_key]) for r in data if y_key in r]
            ax.plot([p[0] for p in points], [p[1] for p in points], marker="o", markersize=3, label=y_key)
        if len(y_keys) > 1:
            ax.legend(fontsize=8)
        ax.set_title(label)
        ax.set_xlabel(x_label)
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
