"""HG-DAgger on robots: the policy acts, a human (or a simulated one) takes over when it drifts, and
the policy is cloned from every state the human ever labelled.

Read top to bottom. Components: ``robot`` (one rank per robot:
:class:`~infinirl.realworld.robot_worker.RobotActorWorker` with the run's intervention device) and
``learner`` (:class:`~infinirl.realworld.intervention.bc_learner.BCLearnerWorker`: the aggregate
dataset and behaviour cloning).

* **start**: robot rank 0 records ``dagger.initial_demos`` episodes of a scripted demo policy; the
  initial policy is cloned from them (every step labelled; few demonstrations: a weak policy) and
  sent to the robots. A resumed run restores the learner (policy, optimiser, dataset) instead.
* **one iteration**: every robot runs ``dagger.episodes_per_iteration`` episodes of the present
  policy (deterministic by default) with the human watching; the human's steps (flag
  ``intervened``, the human's executed action) are added to the aggregate, the policy trains
  ``bc.updates_per_iteration`` mini-batches on the whole aggregate and the new version goes to the
  robots. Metrics: ``rollout/success_rate`` (with the human's help), ``intervention/rate``
  (intervened steps / steps), ``intervention/episode_rate``, ``intervention/takeovers_per_episode``,
  ``dagger/dataset_rows``, ``train/bc_loss``, ``dagger/novice_error`` (the policy's squared error
  on the iteration's human labels before training on them), and the robots' counters over the run
  (``env/steps``, ``robot/late_steps``, ``robot/safety_aborts``, ``robot/safety_clips``,
  ``robot/safety_events``; a resumed run goes on from its checkpoint's).
* **evaluation**: ``eval.episodes`` deterministic episodes per robot with no human
  (``eval/success_rate``: the policy alone; the robots' control loops hold the device off, so a
  take-over is refused until the next iteration's episodes); after the last iteration robot rank 0 films
  ``eval.video_episodes`` more into ``<output_dir>/eval.mp4`` (a robot without a camera: none).
"""

from __future__ import annotations

import os
import time

import numpy as np

from infinirl.config import ConfigError
from infinirl.runners import register_runner
from infinirl.runners.curves import Panel
from infinirl.runners.hg_dagger_config import HGDAggerConfig
from infinirl.runners.loop import LoopSpec, ProgressField, RunLoop
from infinirl.runners.run_support import launch_all, run_staged, run_start_time

__all__ = ["HGDAggerFlow", "run"]


def preflight(cfg: HGDAggerConfig):
    """The robot env's spec and the policy network, built in the driver before anything starts
    (``infinirl validate`` runs it too): what the robot workers and the learner would otherwise
    refuse with a traceback; ``(env spec, network spec)``."""
    from infinirl.runners.realworld_sac import check_actor_options, env_spec_of, net_spec_of

    try:
        env = env_spec_of(cfg)
    except ValueError as exc:
        raise ConfigError(f"task: {exc}") from None
    net = net_spec_of(cfg)
    check_actor_options(net)
    return env, net


@register_runner("hg_dagger", HGDAggerConfig,
                 "HG-DAgger on robots: a human takes over when the policy drifts; behaviour cloning on the aggregate",
                 preflight=preflight)
def run(cfg: HGDAggerConfig) -> dict:
    from infinirl.realworld.discovery import with_driver_discovery
    from infinirl.realworld.robot_worker import RobotActorWorker
    from infinirl.runners.realworld_sac import robot_setup_of

    env, net = preflight(cfg)
    setup = robot_setup_of(cfg)
    intervention = intervention_spec_of(cfg)

    def start(plan, groups: dict, on_exit: list):
        groups.update(launch_all(plan, {"robot": (RobotActorWorker, (setup, env, net, cfg.seed, cfg.actor.num_threads,
                                                                     intervention))}))
        described = groups["robot"].describe().wait()
        groups.update(launch_all(plan, {"learner": _learner_launch(cfg, net, described[0])}))
        return HGDAggerFlow(cfg, groups["robot"], groups["learner"])

    with RunLoop(cfg, run_start_time()) as loop:
        return run_staged(cfg, loop, start, with_driver_discovery(cfg.cluster))


def intervention_spec_of(cfg):
    """The robots' :class:`~infinirl.realworld.intervention.spec.InterventionSpec` (None without a device)."""
    from infinirl.realworld.intervention.spec import InterventionSpec

    section = cfg.interventions
    if section.device is None:
        return None
    labels = os.path.abspath(os.path.join(cfg.output_dir, "success_labels")) if section.labels else None
    return InterventionSpec(device=section.device, options=dict(section.options), reward=section.reward,
                            labels_dir=labels)


def _learner_launch(cfg: HGDAggerConfig, net, described: dict):
    from infinirl.realworld.intervention.bc_learner import BCLearnerWorker, BCSpec

    bc = cfg.bc
    spec = BCSpec(loss=bc.loss, lr=bc.lr, batch_size=bc.batch_size, weight_decay=bc.weight_decay, seed=cfg.seed)
    return BCLearnerWorker, (net, spec, described["obs_dim"], described["action_dim"], cfg.learner.num_threads)


class HGDAggerFlow:
    """The iteration logic (the loop drives it: see :mod:`infinirl.runners.loop`)."""

    def __init__(self, cfg: HGDAggerConfig, robots, learner):
        from infinirl.runners.realworld_sac import RunCounts

        self.cfg, self.robots, self.learner = cfg, robots, learner
        self.counts = RunCounts()
        self.spec = LoopSpec(
            name="hg_dagger", headline="eval/success_rate", target=cfg.eval.target,
            title=f"HG-DAgger {cfg.robot.kind} with {cfg.interventions.device}",
            progress=(ProgressField(label="succ", key="rollout/success_rate", format=".2f"),
                      ProgressField(label="eval", key="eval/success_rate", format=".2f"),
                      ProgressField(label="interv", key="intervention/rate", format=".2f"),
                      ProgressField(label="rows", key="dagger/dataset_rows", format=".0f")),
            panels=(Panel(title="success rate (policy alone)", y=("eval/success_rate",), x="step",
                          x_label="iteration"),
                    Panel(title="intervention rate (intervened steps / steps)", y=("intervention/rate",), x="step",
                          x_label="iteration"),
                    Panel(title="rollouts with the human (success)", y=("rollout/success_rate",), x="step",
                          x_label="iteration"),
                    Panel(title="behaviour cloning loss", y=("train/bc_loss",), x="step", x_label="iteration")))

    # ------------------------------------------------------------------ start
    def start(self, iteration: int) -> None:
        dagger = self.cfg.dagger
        size = self.learner.dataset_size().wait()[0]
        if iteration == 0 and size == 0 and dagger.initial_demos:
            episodes = self.robots.call("demonstrations", dagger.initial_demos, dagger.demo_policy, self.cfg.seed,
                                        dagger.demo_noise_std, dict(dagger.demo_options), ranks=[0]).wait()[0]
            added = self.learner.aggregate(episodes, True).wait()[0]
            trained = self.learner.train(self.cfg.bc.updates_per_iteration).wait()[0]
            print(f"initial policy cloned from {len(episodes)} demonstration episodes ({added['added']} steps, "
                  f"loss {trained['loss']:.4f})", flush=True)
        self._sync()

    def _sync(self) -> None:
        from infinirl.runtime import start_weight_sync

        version = self.learner.published_version().wait()[0]
        if version > 0:
            start_weight_sync(self.learner, self.robots, version).wait(timeout=120)

    # ------------------------------------------------------------------ one iteration
    def step(self, iteration: int) -> dict:
        from infinirl.realworld.intervention.metrics import InterventionStats, intervention_metrics
        from infinirl.runners.realworld_sac import robot_counts

        cfg = self.cfg
        started = time.perf_counter()
        episodes = [e for batch in self.robots.collect(cfg.dagger.episodes_per_iteration, cfg.dagger.deterministic)
                    .wait(timeout=3600) for e in batch]
        novice_error = self.learner.action_error(episodes).wait()[0]
        added = self.learner.aggregate(episodes).wait()[0]
        trained = self.learner.train(cfg.bc.updates_per_iteration).wait()[0]
        self._sync()
        robots = self.robots.stats().wait(timeout=60)
        recent = [e for r in robots for e in r["episodes"]]
        stats = [InterventionStats(steps=e["length"], intervened_steps=e["intervened_steps"], takeovers=e["takeovers"])
                 for e in recent]
        metrics = {**intervention_metrics(stats),
                   "dagger/added_rows": float(added["added"]), "dagger/dataset_rows": float(added["size"]),
                   "train/bc_loss": trained["loss"],
                   "train/updates": float(trained["updates"]), "pipeline/version": float(trained["version"]),
                   **self.counts.update(robot_counts(robots)),
                   "time/iteration_s": time.perf_counter() - started}
        if novice_error == novice_error:  # NaN: the human labelled no step this iteration
            metrics["dagger/novice_error"] = novice_error
        if recent:
            metrics.update({"rollout/success_rate": float(np.mean([e["success"] for e in recent])),
                            "rollout/episode_length_mean": float(np.mean([e["length"] for e in recent])),
                            "rollout/episodes": float(len(recent))})
        return metrics

    # ------------------------------------------------------------------ evaluation
    def evaluate(self) -> dict:
        results = [r for r in self.robots.evaluate(self.cfg.eval.episodes).wait() if r]
        return {key: float(np.mean([r[key] for r in results])) for key in results[0]} if results else {}

    # ------------------------------------------------------------------ checkpoints
    def save(self, folder: str) -> dict:
        self.learner.save_checkpoint(os.path.join(folder, "learner")).wait()
        return {"counts": dict(self.counts.totals)}

    def load(self, folder: str, state: dict) -> None:
        from infinirl.runners.realworld_sac import RunCounts, robot_counts

        self.learner.load_checkpoint(os.path.join(folder, "learner")).wait()
        self.counts.restore(RunCounts.saved(state), robot_counts(self.robots.stats().wait(timeout=60)))

    def finish(self, output_dir: str) -> dict:
        from infinirl.runners.realworld_sac import record_eval_video

        video = record_eval_video(self.robots, self.cfg.eval.video_episodes, output_dir)
        size = self.learner.dataset_size().wait()[0]
        return {"dataset_rows": size, "version": self.learner.published_version().wait()[0], "video": video}

    def close(self) -> None:
        try:
            self.robots.close().wait(timeout=60)
        except Exception:  # best effort: the groups are shut down right after
            pass
