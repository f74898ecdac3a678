"""SAC on robots that run in real time: the fully asynchronous pipeline, and its synchronous twin.

Read top to bottom. Components: ``robot`` (one rank per robot: the driver behind the safety layer,
the policy's inference copy, :class:`~infinirl.realworld.robot_worker.RobotActorWorker`) and
``learner`` (SAC on a persistent replay store under ``<output_dir>/replay``,
:class:`~infinirl.realworld.learner_worker.RealWorldLearnerWorker`). Time on a robot cannot be
sped up, so an iteration is a wall-clock window (``pipeline.iteration_s``).

* ``pipeline.mode=async``: each robot runs episodes back to back at its own rate with the newest
  weights it has and streams finished episodes (every step stamped with the policy version that
  chose it) over a channel; the learner stores them and updates continuously, publishing a new
  version every ``publish_every`` updates; the driver only moves each new version to the robots
  (staged beside their control loops) and reads counters. Nothing waits for anything else.
* ``pipeline.mode=sync``: the same components take turns: every robot collects one episode, the
  learner stores them and runs ``utd_ratio`` updates per collected step, the weights go to the
  robots, and so on (the robot idles while the learner updates).

``pipeline.transport=edge``: the robot's control loop runs in an edge node that dials the driver
over the mutual-TLS link of :mod:`infinirl.edge` instead of in a Ray worker; the driver's
:class:`~infinirl.edge.trainer_link.TrainerLink` puts its episodes on the same channel (the
learner reports their ids back once committed to its store, and only then does the edge forget
them), publishes each version on the link, and the iteration logic below is the same (docs/edge.md).

RLPD (``demos.episodes > 0``): robot rank 0 records scripted demonstrations into
``<output_dir>/demos`` once, and every mini-batch draws ``demos.fraction`` of its rows from them.
With an intervention device (``interventions.device``) and ``interventions.as_demos``, the
stretches of each episode where the human acted also go into the demonstrations store.

Networks: the SAC runner's (``network.actor``: gaussian or flow); ``network.encoder=cnn`` puts a conv
encoder over the ``task.cameras`` frames in front (the robots act from their current frames, the
learner samples the stored ones, the weights the robots receive carry the encoder).

Checkpoints hold the learner (agent, sampler state, version) and the run's cumulative counters
(:class:`RunCounts`: steps, late steps, safety clips and events, the edge link's); the replay store is
on disk already and is reopened on resume with everything appended after the checkpoint, so a killed
run resumes with its experience intact. A start without a checkpoint on a store an earlier run left
folds its episodes into the learner's state statistics before training samples them.
"""

from __future__ import annotations

import math
import os
import time
import uuid

import numpy as np

from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
from infinirl.config import ConfigError
from infinirl.runners import register_runner
from infinirl.runners.curves import Panel
from infinirl.runners.loop import LoopSpec, ProgressField, RunLoop
from infinirl.runners.realworld_sac_config import RealWorldNetworkConfig, RealWorldSACConfig
from infinirl.runners.run_support import launch_all, run_staged, run_start_time

__all__ = ["RealWorldSACFlow", "RunCounts", "check_actor_options", "env_spec_of", "net_spec_of", "record_eval_video",
           "robot_counts", "robot_setup_of", "run"]


def preflight(cfg: RealWorldSACConfig) -> SACNetSpec:
    """The trainer's edge link files and the actor head's options, in the driver before anything
    starts (``infinirl validate`` runs it too; the encoder is checked once the robots report their
    cameras); the network spec."""
    if cfg.pipeline.transport == "edge":
        cfg.edge.check_trainer_files()  # here, not in the config's check: the edge node holds other files
    net = net_spec_of(cfg)
    check_actor_options(net)
    return net


@register_runner("realworld_sac", RealWorldSACConfig,
                 "SAC / RLPD on robots in real time (simulated or real): asynchronous robot and learner workers",
                 preflight=preflight)
def run(cfg: RealWorldSACConfig) -> dict:
    from infinirl.realworld.discovery import with_driver_discovery
    from infinirl.runners.hg_dagger import intervention_spec_of
    from infinirl.runtime import Channel

    net = preflight(cfg)
    intervention = intervention_spec_of(cfg)

    def start(plan, groups: dict, on_exit: list):
        # Created first: its actor starts while the robots connect, not on a robot's time.
        channel = Channel.create(f"realworld-{uuid.uuid4().hex[:12]}")
        on_exit.append(channel.destroy)
        edge = None
        if cfg.pipeline.transport == "edge":
            edge, robots = _edge_robots(cfg, channel)
            on_exit.append(edge.close)
        else:
            _check_fleet(cfg, len(plan.ranks("robot")))
            robots = _robot_workers(cfg, plan, intervention, groups)
        shape = _robot_shape(cfg, robots)
        groups.update(launch_all(plan, {"learner": _learner_launch(cfg, net, shape)}))
        channel.qsize()  # returns once the channel's actor is up
        return RealWorldSACFlow(cfg, robots, groups["learner"], channel,
                                send_weights=edge.send_weights if edge is not None else None,
                                link_metrics=edge.metrics if edge is not None else None)

    with RunLoop(cfg, run_start_time()) as loop:
        return run_staged(cfg, loop, start, with_driver_discovery(cfg.cluster))


def check_actor_options(net: SACNetSpec) -> None:
    """The actor head's options (e.g. flow_matching keywords) as a ConfigError before any worker
    starts; the encoder is checked against the cameras once the robots report them (:func:`_robot_shape`)."""
    from dataclasses import replace

    from infinirl.realworld.robot_worker import unit_box
    from infinirl.runners.sac import check_net_builds

    check_net_builds(replace(net, encoder="state", encoder_options={}, augment_pad=0), 1, unit_box(1))


def _robot_workers(cfg: RealWorldSACConfig, plan, intervention, groups: dict):
    """``pipeline.transport=ray``: one robot worker per robot rank of the placement."""
    from infinirl.realworld.robot_worker import RobotActorWorker

    setup, env, net = robot_setup_of(cfg), env_spec_of(cfg), net_spec_of(cfg)
    groups.update(launch_all(plan, {"robot": (RobotActorWorker, (setup, env, net, cfg.seed, cfg.actor.num_threads,
                                                                 intervention))}))
    return groups["robot"]


def _edge_robots(cfg: RealWorldSACConfig, channel):
    """``pipeline.transport=edge``: the hub, and the robot at the edge once it connected; its
    episodes go on ``channel`` like a robot worker's."""
    from infinirl.edge.trainer_link import TrainerLink

    edge = TrainerLink(cfg, channel, key="episodes").start()
    try:
        return edge, edge.robots()
    except BaseException:
        edge.close()
        raise


def _check_fleet(cfg: RealWorldSACConfig, robot_ranks: int) -> None:
    fleet = cfg.robot.fleet
    if fleet and len(fleet) != robot_ranks:
        raise ConfigError(f"robot.fleet has {len(fleet)} entries but placement.robot={cfg.placement['robot']!r} gives "
                          f"{robot_ranks} robot ranks; give one rank per entry")


def robot_setup_of(cfg: RealWorldSACConfig):
    """The robot every rank drives, or with ``robot.fleet`` one per rank."""
    from infinirl.realworld.robot_worker import RobotSetup
    from infinirl.realworld.safety import SafetyConfig

    robot = cfg.robot
    safety = SafetyConfig(velocity_scale=robot.velocity_scale, max_lead_s=robot.max_lead_s,
                          command_deadline_s=robot.command_deadline_s,
                          heartbeat_deadline_s=robot.heartbeat_deadline_s)
    if robot.fleet:
        return tuple(RobotSetup(kind=e.kind, options=dict(e.options), safety=safety) for e in robot.fleet)
    return RobotSetup(kind=robot.kind, options=dict(robot.options), safety=safety)


def env_spec_of(cfg: RealWorldSACConfig):
    from infinirl.realworld.robot_env import RobotEnvSpec

    def spec(task):
        return RobotEnvSpec(observations=tuple(task.observations), cameras=tuple(task.cameras),
                            frame_size=None if task.frame_size is None else tuple(task.frame_size),
                            camera_names=dict(task.camera_names),
                            rewards=dict(task.rewards), reward_options=dict(task.reward_options),
                            max_episode_steps=task.max_episode_steps,
                            action_mode=task.action_mode, terminate_on_success=task.terminate_on_success)

    if cfg.robot.fleet:
        return tuple(spec(cfg.task_of(index)) for index in range(len(cfg.robot.fleet)))
    return spec(cfg.task)


def net_spec_of(cfg) -> SACNetSpec:
    """The networks of a real-world runner's config (its ``network`` section: this runner's, with an
    observation encoder, or the plain SAC one of the runners that share the robot workers)."""
    network = cfg.network
    encoder = network.encoder_spec() if isinstance(network, RealWorldNetworkConfig) else {}
    return SACNetSpec(actor_hidden=tuple(network.actor_hidden), critic_hidden=tuple(network.critic_hidden),
                      num_critics=network.num_critics, activation=network.activation,
                      log_std_min=network.log_std_min, log_std_max=network.log_std_max, obs_key="state",
                      layer_norm=network.layer_norm, actor=network.actor, flow=dict(network.flow),
                      normalize_state=bool(getattr(network, "normalize_state", False)), **encoder)


def _robot_shape(cfg: RealWorldSACConfig, robots) -> dict:
    """Lay the robots out in the shared policy (:func:`~infinirl.realworld.robot_worker.policy_layouts`)
    and return the policy's observation and action sizes and the recorded cameras."""
    from infinirl.realworld.control_loop import embodiment_action_mask
    from infinirl.realworld.robot_worker import policy_layouts, unit_box
    from infinirl.runners.sac import check_net_builds

    described = robots.describe().wait()
    if len({tuple(sorted(d["cameras"].items())) for d in described}) > 1:
        shown = "; ".join(f"{d['kind']}: {d['cameras']}" for d in described)
        raise ConfigError(f"task.cameras: the robots record different camera frames ({shown}); a run stores one set: "
                          "give them one name (task.camera_names) and one size (task.frame_size)")
    layouts = policy_layouts(described)
    check_net_builds(net_spec_of(cfg), layouts[0].obs_dim, unit_box(layouts[0].action_dim), described[0]["cameras"])
    robots.call_each("configure", [(layout,) for layout in layouts]).wait()
    if layouts[0].num_embodiments > 1:
        print("one policy for " + ", ".join(f"rank {i} {d['kind']} (obs {d['obs_dim']}, action {d['action_dim']})"
                                            for i, d in enumerate(described))
              + f": observations padded to {layouts[0].obs_dim} with a kind one-hot, actions to "
                f"{layouts[0].action_dim}", flush=True)
    return {"obs_dim": layouts[0].obs_dim, "action_dim": layouts[0].action_dim, "cameras": described[0]["cameras"],
            "kinds": [d["kind"] for d in described], "action_mask": embodiment_action_mask(layouts),
            "embodiments": layouts[0].num_embodiments}


def _learner_launch(cfg: RealWorldSACConfig, net: SACNetSpec, shape: dict):
    from infinirl.realworld.learner_worker import LearnerLoopSpec, RealWorldLearnerWorker

    alg, pipeline = cfg.algorithm, cfg.pipeline
    update = SACUpdateSpec(gamma=alg.gamma, tau=alg.tau, batch_size=alg.batch_size, actor_lr=alg.actor_lr,
                           critic_lr=alg.critic_lr, alpha_lr=alg.alpha_lr, init_alpha=alg.init_alpha,
                           autotune_alpha=alg.autotune_alpha, target_entropy=alg.target_entropy,
                           policy_delay=alg.policy_delay, target_update_every=alg.target_update_every, seed=cfg.seed)
    replay = os.path.abspath(cfg.replay.path or os.path.join(cfg.output_dir, "replay"))
    interventions = cfg.interventions.device is not None
    as_demos = interventions and cfg.interventions.as_demos
    demos = os.path.abspath(os.path.join(cfg.output_dir, "demos")) if cfg.demos.episodes or as_demos else None
    loop = LearnerLoopSpec(replay_dir=replay, demo_dir=demos, demo_fraction=cfg.demos.fraction,
                           interventions=interventions, interventions_as_demos=as_demos,
                           learning_starts=alg.learning_starts, publish_every=pipeline.publish_every,
                           max_staleness=pipeline.max_staleness, staleness_action=pipeline.staleness_action,
                           max_updates_per_step=pipeline.max_updates_per_step, durable=pipeline.durable,
                           cameras=dict(shape["cameras"]))
    return RealWorldLearnerWorker, (net, update, loop, shape["obs_dim"], shape["action_dim"], cfg.learner.num_threads,
                                    cfg.learner.device, shape.get("action_mask"), shape.get("embodiments", 1))


def record_eval_video(robots, episodes: int, output_dir: str) -> str | None:
    """``episodes`` deterministic episodes of robot rank 0 filmed into ``<output_dir>/eval.mp4``; None
    when there are none, or when the robot has no camera (the run says so)."""
    if not episodes:
        return None
    result = robots.call("record_video", episodes, os.path.join(output_dir, "eval.mp4"), ranks=[0]).wait()[0]
    if "skipped" in result:
        print(f"eval video skipped: {result['skipped']}", flush=True)
        return None
    return result["path"]


def robot_counts(robots: list[dict]) -> dict[str, float]:
    """The robots' cumulative counters as metrics, from their ``stats()``: ``env/steps`` (training
    steps), ``robot/late_steps`` (steps that overran their control period), ``robot/safety_aborts``
    (episodes the safety layer ended), ``robot/safety_clips`` (command entries it clipped) and
    ``robot/safety_events`` (watchdog holds, heartbeat stops, unknown poses, servo faults). Each robot
    counts from when its control loop was built; :class:`RunCounts` makes them the run's."""
    return {"env/steps": float(sum(r["counts"].get("steps", 0) for r in robots)),
            "robot/late_steps": float(sum(r["counts"].get("late_steps", 0) for r in robots)),
            "robot/safety_aborts": float(sum(r["counts"].get("safety_aborts", 0) for r in robots)),
            "robot/safety_clips": float(sum(sum(r["safety_clips"].values()) for r in robots)),
            "robot/safety_events": float(sum(sum(r["safety_events"].values()) for r in robots))}


class RunCounts:
    """Cumulative counters logged every iteration (:func:`robot_counts`, the edge link's), counted
    over the whole run. The components count from when they started, so a resumed run starts from what
    its checkpoint counted, less what they had already counted when it resumed (an edge node may
    outlive the trainer it served; new workers have counted nothing)."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        """As of the last :meth:`update`: what a checkpoint saves."""
        self.offsets: dict[str, float] = {}

    def update(self, counted: dict[str, float]) -> dict[str, float]:
        """The run's counts of the keys of ``counted`` (what the components counted so far)."""
        self.totals.update({key: self.offsets.get(key, 0.0) + float(value) for key, value in counted.items()})
        return {key: self.totals[key] for key in counted}

    def restore(self, totals: dict[str, float], counted: dict[str, float]) -> None:
        """Continue from a checkpoint's ``totals``; ``counted``: what the components had counted when
        the run resumed (a key absent there: nothing yet)."""
        self.totals = {key: float(value) for key, value in totals.items()}
        self.offsets = {key: value - float(counted.get(key, 0.0)) for key, value in self.totals.items()}

    @staticmethod
    def saved(state: dict) -> dict[str, float]:
        """The totals a checkpoint's flow state holds; checkpoints of earlier versions saved only the
        steps (``env_steps``), or nothing."""
        return {"env/steps": float(state.get("env_steps", 0)), **state.get("counts", {})}


_LINK_GAUGES = ("link/connected",)
"""The edge link's metrics that are states, not counters (the others go on across a resume)."""


def _per_kind(robots: list[dict]) -> dict:
    """``rollout/<kind>/success_rate`` and ``.../episode_return_mean`` of the window's training
    episodes, when the run has several kinds."""
    kinds = sorted({r["kind"] for r in robots})
    if len(kinds) < 2:
        return {}
    metrics = {}
    for kind in kinds:
        episodes = [e for r in robots if r["kind"] == kind for e in r["episodes"]]
        if episodes:
            metrics[f"rollout/{kind}/success_rate"] = float(np.mean([e["success"] for e in episodes]))
            metrics[f"rollout/{kind}/episode_return_mean"] = float(np.mean([e["return"] for e in episodes]))
    return metrics


class RealWorldSACFlow:
    """The iteration logic (the loop drives it: see :mod:`infinirl.runners.loop`)."""

    def __init__(self, cfg: RealWorldSACConfig, robots, learner, channel, send_weights=None, link_metrics=None):
        from infinirl.runtime import start_weight_sync

        self.cfg, self.robots, self.learner, self.channel = cfg, robots, learner, channel
        self.send_weights = send_weights or start_weight_sync  # (learner, robots, version, interrupt) -> pending
        self.link_metrics = link_metrics  # pipeline.transport=edge: (robots' stats) -> link/..., edge/... metrics
        self.synced_version = 0
        self.pending_sync = None
        self.running = False
        self.owed_updates = 0.0  # sync mode: fractional updates carried to the next turn
        self.counts = RunCounts()
        self.resumed = False
        self.spec = LoopSpec(
            name="realworld_sac", headline="eval/success_rate",
            title=f"SAC ({cfg.pipeline.mode}) {'+'.join(e.kind for e in cfg.robot.fleet) or cfg.robot.kind}",
            target=cfg.eval.target,
            progress=(ProgressField(label="succ", key="rollout/success_rate", format=".2f"),
                      ProgressField(label="eval", key="eval/success_rate", format=".2f"),
                      ProgressField(label="upd/s", key="train/updates_per_s", format=".0f"),
                      ProgressField(label="ver", key="pipeline/version", format=".0f")),
            panels=(Panel(title="success rate (eval, deterministic)", y=("eval/success_rate",), x="time/elapsed_s",
                          x_label="wall time (s)"),
                    Panel(title="training episodes", y=("rollout/success_rate",), x="time/elapsed_s",
                          x_label="wall time (s)"),
                    Panel(title="learner updates per second", y=("train/updates_per_s",), x="time/elapsed_s",
                          x_label="wall time (s)"),
                    Panel(title="staleness (versions)", y=("pipeline/staleness_mean", "pipeline/staleness_max"),
                          x="time/elapsed_s", x_label="wall time (s)")))

    # ------------------------------------------------------------------ start
    def start(self, iteration: int) -> None:
        if not self.resumed:
            self._fold_earlier_episodes()
        demos = self.cfg.demos
        if demos.episodes:
            have = self.learner.demo_episodes().wait()[0]
            if have < demos.episodes:  # a resumed run keeps the demonstrations it recorded
                episodes = self.robots.call("demonstrations", demos.episodes - have, demos.policy, self.cfg.seed,
                                            demos.noise_std, dict(demos.options), ranks=[0]).wait()[0]
                held = self.learner.add_demonstrations(episodes).wait()[0]
                print(f"recorded {len(episodes)} demonstration episodes ({held} in {self.cfg.output_dir}/demos)",
                      flush=True)
        status = self.learner.status().wait()[0]  # the rate of the first iteration counts from here
        self._sync(status["version"], wait=True)
        if self.cfg.pipeline.mode == "async":
            self.learner.start(self.channel).wait()
            self.robots.start(self.channel).wait()
            self.running = True

    def _fold_earlier_episodes(self) -> None:
        """A start without a checkpoint on stores an earlier run left (one stopped before its first
        checkpoint, ``resume=false``, a shared ``replay.path``): training samples their episodes from
        its first update on, so the learner folds them into its state statistics first, as a resumed
        one has them from its checkpoint. Said in one line: the run does not start from nothing."""
        folded = self.learner.observe_stored().wait()[0]
        status = self.learner.status().wait()[0]
        demos = self.learner.demo_episodes().wait()[0]
        if not status["store_episodes"] and not demos:
            return
        replay = self.cfg.replay.path or os.path.join(self.cfg.output_dir, "replay")
        normaliser = f"; their states are folded into the state normaliser ({folded} episodes)" if folded else ""
        print(f"no checkpoint to resume, but {replay} holds {status['store_episodes']} episodes "
              f"({status['store_transitions']} transitions) and the demonstrations store {demos}, from an earlier "
              f"run: training samples them too{normaliser}", flush=True)

    def _sync(self, version: int, wait: bool = False) -> None:
        """Send the learner's published weights to the robots when they are newer than theirs."""
        if version <= self.synced_version:
            return
        if self.pending_sync is not None and not self.pending_sync.done():
            return  # one sync in flight at a time; the next poll sends the newest version
        self.pending_sync = self.send_weights(self.learner, self.robots, version, interrupt=self.running)
        self.synced_version = version
        if wait:
            self.pending_sync.wait(timeout=60)

    # ------------------------------------------------------------------ one iteration
    def step(self, iteration: int) -> dict:
        cfg = self.cfg
        started = time.perf_counter()
        deadline = started + cfg.pipeline.iteration_s
        if cfg.pipeline.mode == "async":
            while time.perf_counter() < deadline:
                time.sleep(min(cfg.pipeline.sync_poll_s, max(0.0, deadline - time.perf_counter())))
                self._sync(self.learner.published_version().wait(timeout=60)[0])
            status = self.learner.status().wait(timeout=60)[0]
        else:
            status = self._sync_turns(deadline)
        robots = self.robots.stats().wait(timeout=60)
        link = self.link_metrics(robots) if self.link_metrics is not None else {}
        counted = {**robot_counts(robots), **{key: value for key, value in link.items() if key not in _LINK_GAUGES}}
        return {**self._metrics(status, robots, time.perf_counter() - started), **_per_kind(robots), **link,
                **self.counts.update(counted)}

    def _sync_turns(self, deadline: float) -> dict:
        """Collect one episode per robot, then update on it, until the window ends."""
        while True:
            episodes = [e for batch in self.robots.collect(1).wait(timeout=600) for e in batch]
            self.owed_updates += self.cfg.algorithm.utd_ratio * sum(len(e["action"]) for e in episodes)
            num = math.floor(self.owed_updates)
            self.owed_updates -= num
            version = self.learner.add_and_update(episodes, num, publish=True).wait(timeout=600)[0]
            self._sync(version, wait=True)
            if time.perf_counter() >= deadline:
                return self.learner.status().wait(timeout=60)[0]

    def _metrics(self, status: dict, robots: list[dict], seconds: float) -> dict:
        counts = status["counts"]
        episodes = [e for r in robots for e in r["episodes"]]
        policy_steps = max(counts.get("policy_steps", 0.0), 1.0)
        metrics = {
            **status["metrics"],
            "train/updates": float(status["updates"]),
            "train/updates_per_s": float(status["updates_per_s"]),
            "pipeline/version": float(status["version"]),
            "pipeline/robot_versions_min": float(min(r["policy_version"] for r in robots)),
            "pipeline/staleness_mean": counts.get("lag_sum", 0.0) / policy_steps,
            "pipeline/staleness_max": float(counts.get("lag_max", 0.0)),
            "pipeline/stale_episodes": float(counts.get("stale_episodes", 0.0)),
            "pipeline/dropped_episodes": float(counts.get("dropped_episodes", 0.0)),
            "replay/transitions": float(status["store_transitions"]),
            "replay/episodes": float(status["store_episodes"]),
            "replay/demo_transitions": float(status["demo_transitions"]),
            "time/iteration_s": seconds,
        }
        if episodes:
            metrics.update({"rollout/success_rate": float(np.mean([e["success"] for e in episodes])),
                            "rollout/episode_return_mean": float(np.mean([e["return"] for e in episodes])),
                            "rollout/episode_length_mean": float(np.mean([e["length"] for e in episodes])),
                            "rollout/episodes": float(len(episodes))})
        if self.cfg.interventions.device is not None:
            from infinirl.realworld.intervention.metrics import InterventionStats, intervention_metrics

            metrics.update(intervention_metrics([InterventionStats(steps=e["length"], takeovers=e["takeovers"],
                                                                   intervened_steps=e["intervened_steps"])
                                                 for e in episodes]))
            metrics["replay/intervention_demo_steps"] = float(counts.get("intervention_demo_steps", 0.0))
        return metrics

    # ------------------------------------------------------------------ evaluation
    def evaluate(self) -> dict:
        """``eval.episodes`` deterministic episodes on every robot at once; means over all of them
        (and per robot kind when the run has several). The policy acts alone: each robot's control
        loop holds its intervention device off for them (a take-over is refused)."""
        results = self.robots.evaluate(self.cfg.eval.episodes).wait()
        kinds = self.robots.describe().wait()
        merged = {key: float(np.mean([r[key] for r in results if key in r])) for key in results[0]}
        if len({k["kind"] for k in kinds}) > 1:
            for kind in sorted({k["kind"] for k in kinds}):
                ours = [r for r, k in zip(results, kinds) if k["kind"] == kind and r]
                for key in ("success_rate", "return_mean"):
                    merged[f"eval/{kind}/{key}"] = float(np.mean([r[f"eval/{key}"] for r in ours]))
        return merged

    # ------------------------------------------------------------------ checkpoints
    def save(self, folder: str) -> dict:
        self.learner.save_checkpoint(os.path.join(folder, "learner")).wait()
        return {"mode": self.cfg.pipeline.mode, "counts": dict(self.counts.totals)}

    def load(self, folder: str, state: dict) -> None:
        self.learner.load_checkpoint(os.path.join(folder, "learner")).wait()
        robots = self.robots.stats().wait(timeout=60)
        counted = robot_counts(robots)
        if self.link_metrics is not None:
            # The edge node may outlive the trainer, and counted on; the link's hub started with this
            # process, so all it counted is new (its keys count from the checkpoint's totals).
            counted.update({k: v for k, v in self.link_metrics(robots).items() if k.startswith("edge/")})
        self.counts.restore(RunCounts.saved(state), counted)
        self.resumed = True
        status = self.learner.status().wait()[0]
        print(f"restored the learner at version {status['version']} ({status['updates']} updates); the replay "
              f"store holds {status['store_episodes']} episodes ({status['store_transitions']} transitions)",
              flush=True)

    # ------------------------------------------------------------------ the end
    def finish(self, output_dir: str) -> dict:
        video = self._record_video(output_dir)
        self._stop()
        status = self.learner.status().wait()[0]
        return {"updates": status["updates"], "version": status["version"],
                "replay_transitions": status["store_transitions"], "replay_episodes": status["store_episodes"],
                "video": video}

    def _record_video(self, output_dir: str) -> str | None:
        """``eval.video_episodes`` of robot rank 0 into ``eval.mp4`` (while the robots still run: the
        control loop films them between two training episodes)."""
        if self.cfg.eval.video_episodes and self.cfg.pipeline.transport == "edge":  # only training data goes up
            print("eval video skipped: the robot is at the edge, and its camera frames stay there", flush=True)
            return None
        return record_eval_video(self.robots, self.cfg.eval.video_episodes, output_dir)

    def _stop(self) -> None:
        if self.running:
            self.running = False
            self.robots.stop().wait(timeout=120)
            self.learner.stop().wait(timeout=120)

    def close(self) -> None:
        try:
            self._stop()
            self.robots.close().wait(timeout=60)
            self.learner.close().wait(timeout=60)
        except Exception:  # best effort: the groups are shut down right after
            pass
