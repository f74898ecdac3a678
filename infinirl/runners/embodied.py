"""Embodied RL (PPO, embodied GRPO) in vectorised simulators: the macro flow.

Read top to bottom: every iteration collects ``rollout_steps`` decisions per env (the rollout
component runs the policy, the env component simulates), turns rewards into advantages, runs the
PPO-clip update on the actor, and syncs the actor's weights into the rollout with a new version.

The algorithm (``algorithm.name``, looked up in
:data:`~infinirl.runners.embodied_config.ALGORITHMS`) decides the advantages: ``ppo`` uses
embodied GAE (chunk or action level) on the trained value head; ``grpo`` resets the envs in groups
of ``algorithm.group_size`` with one seed per group and uses each env's first-episode return,
normalised within its group (``embodied_grpo``): no critic, and the estimator's mask keeps the
decisions after an env's first episode end out of the update.

How it runs is placement, not code:

* ``env`` and ``rollout`` on the **same** slots (collocated): the env lives in the rollout's
  process and the two take turns (no hop per step);
* on **disjoint** slots: the env has its own process and streams observations/actions to the
  rollout; with ``rollout.pipeline_stages: K >= 2`` the env batch is split into K stages so
  simulation of one stage overlaps inference of another (hybrid, with the actor time-sharing the
  same CPUs/devices between rollouts).

Online scaling (env and rollout on disjoint slots): the env component grows or shrinks between
iterations on a command (``<output_dir>/scale.json``, :meth:`EmbodiedFlow.request_scale`) or on its
measured busy ratio (``scaling.auto``); each rollout rank's stages are then shared out over the env
ranks that serve it (:meth:`EmbodiedFlow.scale_env`, :mod:`infinirl.runtime.scaling`).

Asynchronous (``algorithm.asynchronous.max_staleness`` = eta): the next eta iterations'
trajectories are collected while the actor trains (:mod:`infinirl.runners.async_rollout`), and
``algorithm.is_cap`` corrects for the version gap (decoupled PPO).
"""

from __future__ import annotations

import dataclasses
import os
import queue
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from infinirl.algorithms import EnvAdvantageInputs, compute_advantages, normalize_per_task
from infinirl.algorithms.embodied_ppo import PPOSpec, critic_parameter_ids
from infinirl.components.demo_anchor import DemoAnchor, DemoAnchorSpec
from infinirl.components.embodied_actor import EmbodiedActorWorker
from infinirl.components.embodied_policy import ReturnNormalizer, critic_lr_of
from infinirl.components.embodied_rollout import EmbodiedRolloutWorker, PolicySpec, merge_task_success
from infinirl.components.env_worker import (
    EnvSpec,
    EnvWorker,
    env_shares,
    iteration_seeds,
    probe_env_specs,
    stage_seeds,
)
from infinirl.config import ConfigError
from infinirl.engines.master_weights import low_precision_trainable
from infinirl.engines.parallel import DATA_PARALLEL
from infinirl.engines.policy_lora import apply_policy_lora
from infinirl.runners import register_runner
from infinirl.runners.async_rollout import (
    RolloutAhead,
    WeightPusher,
    load_ahead_batches,
    save_ahead_batches,
    staleness_metrics,
)
from infinirl.runners.curves import Panel
from infinirl.runners.embodied_config import ALGORITHMS, EmbodiedConfig
from infinirl.runners.loop import LoopSpec, ProgressField, RunLoop
from infinirl.runners.run_support import run_components, run_start_time
from infinirl.runners.sim_config import check_env_options, episode_metrics, eval_seeds
from infinirl.runtime import sync_weights
from infinirl.runtime.placement import place, resized_spec
from infinirl.runtime.scaling import BusyRatioPolicy, ScaleCommands
from infinirl.utils.threads import spin_wait_env


def _check_env_and_policy(cfg: EmbodiedConfig):
    """The env task, its options and the policy's, checked in the driver before any worker starts: the
    runner's preflight (``infinirl validate`` runs it too); ``(observation spec, action space, policy spec)``."""
    check_env_options(cfg.env.name, {"env.kwargs": cfg.env.kwargs, "eval.env_kwargs": cfg.eval.env_kwargs,
                                     "eval.video_env_kwargs": cfg.eval.video_env_kwargs})
    try:
        observation_spec, action_space = probe_env_specs(cfg.env.name, cfg.env.kwargs)
        policy_spec = PolicySpec(name=cfg.policy.name, options=dict(cfg.policy.kwargs), chunk=cfg.policy.chunk,
                                 normalize_obs=cfg.normalizes_obs(),
                                 normalize_keys=tuple(cfg.policy.normalize_keys) or None, obs_clip=cfg.policy.obs_clip)
        policy = policy_spec.build(observation_spec, action_space)
    except (ValueError, TypeError, KeyError, OSError) as exc:  # OSError: a checkpoint folder or file missing
        raise ConfigError(f"{cfg.env.name} / policy {cfg.policy.name}: {exc}") from exc
    if cfg.actor.lora is not None and policy.policy.lora_refusal:
        raise ConfigError(f"actor.lora: policy {cfg.policy.name}: {policy.policy.lora_refusal}; remove actor.lora")
    if cfg.actor.lora is not None:  # the layers it names must exist: checked on the policy just built
        try:
            apply_policy_lora(policy, cfg.actor.lora)
        except ValueError as exc:
            raise ConfigError(f"policy {cfg.policy.name}: {exc}") from None
    if cfg.actor.value_lr is not None:
        _check_value_lr(cfg, policy)
    if cfg.actor.compile:
        _check_compiled_step_precision(cfg, policy)
    if cfg.algorithm.critic_warmup:
        _check_critic_warmup(cfg, policy)
    if ALGORITHMS[cfg.algorithm.name].grouped:
        _check_one_task_per_group(cfg)
        if cfg.algorithm.normalize_advantages_per_task:
            raise ConfigError(f"algorithm.normalize_advantages_per_task: algorithm.name={cfg.algorithm.name} "
                              "normalises its advantages within groups of one task already; remove it")
    if cfg.algorithm.bc.data is not None:
        _check_bc_anchor(cfg, policy)
    return observation_spec, action_space, policy_spec


@register_runner("embodied", EmbodiedConfig, "PPO / embodied GRPO for robot policies in vectorised simulators "
                 "(env/rollout pipelined or collocated)", preflight=_check_env_and_policy)
def run(cfg: EmbodiedConfig) -> dict:
    with RunLoop(cfg, run_start_time()) as loop:
        observation_spec, action_space, policy_spec = _check_env_and_policy(cfg)
        ppo = ppo_spec(cfg)

        process_env = worker_process_env(cfg)

        def launches(plan) -> dict:
            host_env, env_spec = _layout(cfg, plan)
            where = ("inside the rollout process (collocated)" if host_env else
                     "in a process per pipeline stage (streamed)" if cfg.env.stage_processes else
                     "in its own process (streamed)")
            print(f"env {where}, {cfg.rollout.pipeline_stages} pipeline stage(s) per env rank", flush=True)
            launched = {
                "rollout": (EmbodiedRolloutWorker, (env_spec, policy_spec, observation_spec, action_space, cfg.seed,
                                                    host_env, cfg.rollout.num_threads, cfg.rollout.compile,
                                                    cfg.rollout.device), process_env["rollout"]),
                "actor": (EmbodiedActorWorker, (policy_spec, observation_spec, action_space, ppo,
                                                cfg.actor.num_threads, cfg.actor.device, cfg.actor.lora,
                                                anchor_spec(cfg)),
                          process_env["actor"]),
            }
            if not host_env:
                launched["env"] = (EnvWorker, (env_spec, cfg.rollout.num_threads, plan.world_size("rollout")))
            return launched

        def make_flow(groups, plan) -> EmbodiedFlow:
            flow = EmbodiedFlow(cfg, groups.get("env"), groups["rollout"], groups["actor"], plan)
            print("policy computes on: " + ", ".join(f"{k} {v}" for k, v in flow.devices().items()), flush=True)
            if flow.env is not None:
                flow.connect()
            return flow

        return run_components(cfg, loop, launches, make_flow)


def worker_process_env(cfg: EmbodiedConfig) -> dict[str, dict[str, str]]:
    """The environment variables the rollout and actor ranks' processes start with: OpenMP spins
    briefly in a rank that computes with several threads (``spin_wait_env``; measured on the VLA
    demos' acting by ``benchmarks/omp_wait.py``)."""
    return {"rollout": spin_wait_env(cfg.rollout.num_threads), "actor": spin_wait_env(cfg.actor.num_threads)}


def anchor_spec(cfg: EmbodiedConfig) -> DemoAnchorSpec | None:
    """The actor's behaviour-cloning anchor (``algorithm.bc``), or None."""
    bc = cfg.algorithm.bc
    if bc.data is None:
        return None
    # resolved here: the actor's process may start in another working directory
    return DemoAnchorSpec(data=str(Path(bc.data).resolve()), coef=bc.coef, decay=bc.decay, batch_size=bc.batch_size,
                          augment_shift=bc.augment_shift, camera_key=bc.camera_key, seed=cfg.seed)


def _check_bc_anchor(cfg: EmbodiedConfig, policy) -> None:
    """``algorithm.bc``: a policy that can clone, a dataset that exists, and its frames through the
    policy's cloning loss once (cameras, state and action sizes), all before any worker starts."""
    from infinirl.data.lerobot_dataset import LeRobotDatasetError

    bc = cfg.algorithm.bc
    if policy.policy.demo_refusal:
        raise ConfigError(f"algorithm.bc: policy {cfg.policy.name}: {policy.policy.demo_refusal}; "
                          "remove algorithm.bc.data")
    if not Path(bc.data).is_dir():
        raise ConfigError(f"algorithm.bc.data={bc.data}: no such folder; `infinirl train sft_vla_metaworld` "
                          "generates the demonstrations it clones into its data.path")
    spec = anchor_spec(cfg)
    try:
        anchor = DemoAnchor(dataclasses.replace(spec, batch_size=min(2, bc.batch_size)), policy.policy.demo_chunk)
        with torch.no_grad():
            anchor.loss(policy, 0, 0)
    except LeRobotDatasetError as exc:
        raise ConfigError(f"algorithm.bc.data: {exc}") from None
    except ConfigError as exc:
        message = str(exc).replace("data.camera_key", "algorithm.bc.camera_key")  # DemoFrames names SFT's keys
        raise ConfigError(message.replace("data.path", "algorithm.bc.data")) from None
    except (ValueError, KeyError, RuntimeError) as exc:
        raise ConfigError(f"algorithm.bc.data={bc.data}: its frames do not fit policy {cfg.policy.name}: "
                          f"{exc}") from None


def _check_value_lr(cfg: EmbodiedConfig, policy) -> None:
    """``actor.value_lr`` needs a critic that trains: a PPO-style algorithm and a policy with one."""
    if not ALGORITHMS[cfg.algorithm.name].critic:
        raise ConfigError(f"actor.value_lr is the critic's learning rate, and algorithm.name={cfg.algorithm.name} "
                          "trains no critic; remove actor.value_lr")
    if cfg.actor.compile:
        raise ConfigError("actor.value_lr gives the critic a learning rate of its own, which actor.compile's fused "
                          "step (one learning rate) cannot take; set actor.compile=false or remove actor.value_lr")
    lr_of = critic_lr_of(policy, cfg.actor.lr, cfg.actor.value_lr)
    if not any(lr_of(name) == cfg.actor.value_lr for name, _ in policy.named_parameters()):
        raise ConfigError(f"actor.value_lr: policy {cfg.policy.name} has no critic parameters (its value head is "
                          "off, or it names no critic_modules); remove actor.value_lr")


def _check_compiled_step_precision(cfg: EmbodiedConfig, policy) -> None:
    """``actor.compile`` on a policy that trains bf16/fp16 weights (a VLA loaded with ``policy.kwargs.dtype``
    bfloat16, full or LoRA, whose adapters take the base layer's dtype): the actor's Adam steps them through
    float32 masters (``engines.master_weights``), which the compiled whole step (plain Adam on the weights
    themselves) does not keep. Asked of the policy built here, with LoRA applied, so only what the actor's
    optimizer will hold is refused (frozen bf16 VLAs under float32 heads compile, and so does bf16 that this
    host loads as float32); the compiled step would otherwise refuse it only in the first update, after the
    workers started and the first rollout ran. Under FSDP2 only the loss is compiled and Adam stays eager."""
    if DATA_PARALLEL.get(cfg.actor.strategy).whole_step is None:
        return
    low = low_precision_trainable(policy.parameters())
    if not low:
        return
    names = "/".join(str(dtype).removeprefix("torch.") for dtype in low)
    asked = cfg.policy.kwargs.get("dtype")
    key, fix = (f" (policy.kwargs.dtype={asked})", " or policy.kwargs.dtype=float32") if asked is not None else ("", "")
    raise ConfigError(f"actor.compile=true: policy {cfg.policy.name} trains {names} weights{key}, which Adam steps "
                      "through float32 master copies that actor.compile's fused step (plain Adam) does not keep; "
                      f"set actor.compile=false{fix}")


def _check_critic_warmup(cfg: EmbodiedConfig, policy) -> None:
    """``algorithm.critic_warmup`` needs a critic to warm up and iterations left to train the policy."""
    warmup = cfg.algorithm.critic_warmup
    if not ALGORITHMS[cfg.algorithm.name].critic:
        raise ConfigError(f"algorithm.critic_warmup={warmup}: algorithm.name={cfg.algorithm.name} trains no critic; "
                          "remove algorithm.critic_warmup")
    if warmup >= cfg.iterations:
        raise ConfigError(f"algorithm.critic_warmup={warmup} >= iterations={cfg.iterations}: the policy would never "
                          "train; set algorithm.critic_warmup below iterations")
    if not critic_parameter_ids(policy):
        raise ConfigError(f"algorithm.critic_warmup: policy {cfg.policy.name} has no critic parameters (its value "
                          "head is off, or it names no critic_modules); remove algorithm.critic_warmup")


def ppo_spec(cfg: EmbodiedConfig) -> PPOSpec:
    """The actor's update settings; grouped (GRPO) advantages are used as they are, no critic is trained."""
    alg, algorithm = cfg.algorithm, ALGORITHMS[cfg.algorithm.name]
    horizon = cfg.actor.anneal_iterations or cfg.iterations
    return PPOSpec(lr=cfg.actor.lr, value_lr=cfg.actor.value_lr, anneal_lr=cfg.actor.anneal_lr,
                   total_iterations=horizon, epochs=alg.epochs,
                   mini_batches=alg.mini_batches, clip=alg.clip, value_clip=alg.value_clip,
                   value_coef=alg.value_coef, entropy_coef=alg.entropy_coef, max_grad_norm=alg.max_grad_norm,
                   normalize_advantages=alg.normalize_advantages and not algorithm.grouped,
                   gae_level=alg.gae_level, adam_eps=cfg.actor.adam_eps, strategy=cfg.actor.strategy,
                   seed=cfg.seed, critic=algorithm.critic, compile=cfg.actor.compile, is_cap=alg.is_cap,
                   is_cap_mode=alg.is_cap_mode, critic_warmup=alg.critic_warmup,
                   desired_kl=cfg.actor.desired_kl, warmup_steps=cfg.actor.warmup_steps)


def _env_tasks(cfg: EmbodiedConfig) -> tuple[list[str], bool]:
    """The tasks ``env.name`` spreads over its envs (names, or indices as text; none for a
    one-task env), and whether its factory can give consecutive envs one task (``task_block``)."""
    from dataclasses import fields, is_dataclass

    from infinirl.envs.registry import ENVS

    family, _, task = cfg.env.name.partition(":")
    factory = ENVS.get(family)(task or None, **cfg.env.kwargs)
    tasks = getattr(factory, "tasks", None) or getattr(factory, "task_indices", None) or ()
    blocks = is_dataclass(factory) and any(f.name == "task_block" for f in fields(factory))
    return [str(t) for t in tasks], blocks


def _env_task_count(cfg: EmbodiedConfig) -> tuple[int, bool]:
    """How many tasks ``env.name`` spreads over its envs, and whether its factory can give
    consecutive envs one task (``task_block``)."""
    tasks, blocks = _env_tasks(cfg)
    return max(len(tasks), 1), blocks


def task_block(cfg: EmbodiedConfig) -> int:
    """Consecutive training envs that run one task: ``algorithm.group_size`` for a grouped algorithm
    (embodied GRPO) on a multi-task env, so that a group shares its task as well as its reset
    state; 1 otherwise (env ``i`` runs task ``i mod T``)."""
    if not ALGORITHMS[cfg.algorithm.name].grouped:
        return 1
    tasks, _ = _env_task_count(cfg)
    return cfg.algorithm.group_size if tasks > 1 else 1


def env_task_columns(cfg: EmbodiedConfig, rollout_ranks: int) -> tuple[torch.Tensor, list[str]]:
    """The task index of every env column of an iteration's trajectory, and the tasks' names.

    The trajectory joins the rollout ranks' envs in rank order, each rank's pipeline stages in
    order; env ``i`` of a stage runs task ``(i // task_block) % tasks`` (the env factories'
    rule)."""
    names = _env_tasks(cfg)[0] or ["0"]
    tasks, block = len(names), task_block(cfg)
    sizes = EnvSpec(name=cfg.env.name, num_envs=cfg.env.num_envs // rollout_ranks,
                    stages=cfg.rollout.pipeline_stages).stage_sizes()
    stage = [(torch.arange(size) // block) % tasks for size in sizes]
    return torch.cat(stage * rollout_ranks), names


def _check_one_task_per_group(cfg: EmbodiedConfig) -> None:
    """A group of consecutive envs shares one reset seed, so it must share its task too: on a
    multi-task env (metaworld:MT10, a LIBERO suite) every group gets a block of one task, which
    needs the env family's ``task_block`` and ``env.num_envs`` a multiple of group_size x tasks
    (every task then has as many groups). Refused before anything starts otherwise."""
    tasks, blocks = _env_task_count(cfg)
    if tasks == 1:
        return
    size, envs = cfg.algorithm.group_size, cfg.env.num_envs
    if not blocks:
        raise ConfigError(f"algorithm.name={cfg.algorithm.name} compares envs reset to the same state, but "
                          f"env.name={cfg.env.name} runs {tasks} tasks across the envs and cannot give a group one "
                          "task; use one task per run with grpo, or algorithm.name=ppo")
    if envs % (size * tasks):
        raise ConfigError(f"algorithm.name={cfg.algorithm.name} on env.name={cfg.env.name} ({tasks} tasks) runs "
                          f"groups of algorithm.group_size={size} envs, one task each, every task as often: "
                          f"env.num_envs={envs} must be a multiple of {size * tasks} (group_size x tasks)")


def task_blocks_conflict(cfg: EmbodiedConfig, rollout_ranks: int, stages: int) -> str | None:
    """Why ``rollout_ranks`` ranks of ``stages`` pipeline stages cannot give every group of a grouped
    algorithm on a multi-task env one task (each stage's env count a multiple of group_size x tasks),
    or None when they can. The runner refuses such a layout; the scheduler never proposes one."""
    block = task_block(cfg)
    if block == 1:
        return None
    tasks, _ = _env_task_count(cfg)
    sizes = EnvSpec(name=cfg.env.name, num_envs=cfg.env.num_envs // rollout_ranks, stages=stages).stage_sizes()
    if any(size % (block * tasks) for size in sizes):
        return (f"algorithm.name={cfg.algorithm.name} on {tasks} tasks gives each group of {block} envs one task, in "
                f"every rollout rank and pipeline stage: their env counts {sizes} must be multiples of "
                f"{block * tasks}; use fewer ranks/stages or more envs")
    return None


def _layout(cfg: EmbodiedConfig, plan) -> tuple[bool, EnvSpec]:
    """Collocated env (inside the rollout's process) or not, and one env rank's :class:`EnvSpec`."""
    host_env = plan.relation("env", "rollout") == "collocated"
    env_ranks, rollout_ranks = plan.world_size("env"), plan.world_size("rollout")
    stages = cfg.rollout.pipeline_stages
    if host_env and env_ranks != rollout_ranks:
        raise ConfigError(f"placement gives env {env_ranks} rank(s) and rollout {rollout_ranks} on the same slots; "
                          "a collocated env lives in its rollout rank's process, so give them the same number of "
                          "ranks")
    try:
        env_shares(env_ranks, rollout_ranks, stages)
    except ValueError as exc:
        raise ConfigError(f"placement of env and rollout: {exc}") from None
    if cfg.env.stage_processes and env_ranks != rollout_ranks:
        raise ConfigError(f"env.stage_processes=true runs each rollout rank's stages under one env rank; the "
                          f"placement gives env {env_ranks} rank(s) for {rollout_ranks} rollout rank(s): give them "
                          "the same number of ranks or set env.stage_processes=false")
    if cfg.env.num_envs % (rollout_ranks * stages):
        raise ConfigError(f"env.num_envs={cfg.env.num_envs} must be divisible by rollout ranks ({rollout_ranks}) x "
                          f"rollout.pipeline_stages ({stages})")
    if host_env and cfg.env.stage_processes:
        raise ConfigError("env.stage_processes=true needs the env on its own resources, but the placement "
                          f"collocates it with the rollout (placement.env={cfg.placement['env']!r}, "
                          f"placement.rollout={cfg.placement['rollout']!r}): place them on disjoint slots "
                          "or set env.stage_processes=false")
    kwargs = dict(cfg.env.kwargs)
    block = task_block(cfg)
    if block > 1:
        conflict = task_blocks_conflict(cfg, rollout_ranks, stages)
        if conflict:
            raise ConfigError(conflict)
        kwargs["task_block"] = block
    spec = EnvSpec(name=cfg.env.name, num_envs=cfg.env.num_envs // rollout_ranks, stages=stages,
                   num_workers=cfg.env.num_workers, max_episode_steps=cfg.env.max_episode_steps,
                   chunk_size=cfg.policy.chunk, seed=cfg.seed, kwargs=kwargs,
                   stage_processes=cfg.env.stage_processes, step_timeout_s=cfg.env.step_timeout_s,
                   max_restarts=cfg.env.max_restarts)
    return host_env, spec


def eval_env_kwargs(training_task_block: int, kwargs: dict) -> dict:
    """The evaluation's env options: the training envs' task blocks undone (env ``i`` runs task
    ``i mod T`` again, so every task gets its share of the held-out episodes)."""
    return {**kwargs, "task_block": 1} if training_task_block > 1 else dict(kwargs)


ENV_WATCH_S = 5.0
"""How often the driver looks at the env ranks while it waits for the rollout ranks' trajectories."""


def _wait_collecting(collecting, serving, watch_s: float = ENV_WATCH_S) -> list:
    """The rollout ranks' results; meanwhile an env rank's own failure (not a closed link) is raised
    at once. A failing env rank closes its link, so its rollout rank fails too; this watch keeps the
    driver from waiting on a rollout rank that never learns of it (a link left open by an env
    process that could not close it)."""
    while serving is not None:
        try:
            return collecting.wait(timeout=watch_s)
        except TimeoutError:
            pass
        try:
            serving.wait(timeout=0)
            serving = None  # every env rank has served its iteration: nothing left to watch
        except TimeoutError:
            pass
        except BaseException as env_error:
            if not _is_link_closed(env_error):
                raise
            serving = None  # the rollout closed the link: its own error is on the way
    return collecting.wait()


def _raise_env_root_cause(serving, rollout_error: BaseException, timeout_s: float = 60.0) -> None:
    """When the rollout failed while the env served it, raise the env's error if it is the root cause.

    A failing env closes its link, so the rollout fails too, with ``EnvLinkClosed``: a symptom. A
    failing rollout closes its links, so the env fails with ``EnvLinkClosed``: also a symptom. The
    error to show is the one that is not a closed link."""
    if serving is None or not _is_link_closed(rollout_error):
        return
    try:
        serving.wait(timeout=timeout_s)
    except TimeoutError:
        return
    except BaseException as env_error:
        if not _is_link_closed(env_error):
            raise env_error from None


def _is_link_closed(error: BaseException) -> bool:
    """True for ``EnvLinkClosed``, raised here or on a worker (a WorkerError carrying its traceback)."""
    from infinirl.components.env_link import EnvLinkClosed
    from infinirl.runtime.errors import WorkerError

    if isinstance(error, EnvLinkClosed):
        return True
    if isinstance(error, WorkerError):
        lines = error.traceback_text.rstrip().splitlines()
        return bool(lines) and "EnvLinkClosed" in lines[-1]
    return False


class EmbodiedFlow:
    """The iteration logic (the loop drives it: see :mod:`infinirl.runners.loop`)."""

    def __init__(self, cfg: EmbodiedConfig, env, rollout, actor, plan=None):
        self.cfg, self.env, self.rollout, self.actor, self.plan = cfg, env, rollout, actor, plan
        self.task_block = task_block(cfg)  # the training envs' task blocks, undone for evaluation
        self.algorithm = ALGORITHMS[cfg.algorithm.name]
        self.group_size = cfg.algorithm.group_size if self.algorithm.grouped else 1
        self.return_norm = ReturnNormalizer(cfg.env.num_envs, cfg.algorithm.gamma)
        self.env_tasks = (env_task_columns(cfg, rollout.world_size) if cfg.algorithm.normalize_advantages_per_task
                          else None)
        self.env_steps = 0
        eta = cfg.algorithm.asynchronous.max_staleness
        self.weights = WeightPusher(actor, rollout, asynchronous=eta is not None)
        self.ahead = None if eta is None else RolloutAhead(eta, cfg.iterations, self._submit_collect,
                                                           self._finish_collect, self.weights)
        self._link_generation = 0
        # The channels of the channel transport's links: the driver creates them, and Ray kills an
        # actor (a channel) whose every handle is gone, so they are held here while the links live.
        self._link_channels: list = []
        scaling = cfg.scaling
        self.scale_requests: queue.SimpleQueue = queue.SimpleQueue()
        self.commands = ScaleCommands(scaling.command_file or os.path.join(cfg.output_dir, "scale.json"),
                                      ["env"]) if scaling.commands and env is not None else None
        self.policy = BusyRatioPolicy(scaling) if scaling.auto and env is not None else None
        self.spec = LoopSpec(
            name="embodied", title=f"{cfg.algorithm.name.upper()} {cfg.env.name}", headline="eval/success_rate",
            target=cfg.eval.target,
            progress=(ProgressField(label="sr", key="rollout/success_rate"),
                      ProgressField(label="ret", key="rollout/episode_return_mean", format=".0f",
                                    fallback="rollout/open_episode_return_mean"),
                      ProgressField(label="eval", key="eval/success_rate"),
                      ProgressField(label="sps", key="time/env_steps_per_s", format=".0f")),
            panels=(Panel(title="held-out success rate", y=("eval/success_rate",), x="env/steps",
                          x_label="env steps", y_range=(-0.02, 1.02), target=cfg.eval.target),
                    Panel(title="held-out success rate", y=("eval/success_rate",), x="time/elapsed_s",
                          x_label="wall time incl. start-up (s)", y_range=(-0.02, 1.02), target=cfg.eval.target),
                    Panel(title="training episode return", y=("rollout/episode_return_mean",
                                                              "rollout/open_episode_return_mean"),
                          x="env/steps", x_label="env steps")))

    def devices(self) -> dict[str, str]:
        """Where rank 0 of the rollout and of the actor compute (``rollout.device`` / ``actor.device``)."""
        return {name: group.call("compute_device", ranks=[0]).wait()[0]
                for name, group in (("rollout", self.rollout), ("actor", self.actor))}

    # ------------------------------------------------------------------ wiring
    def connect(self) -> None:
        """Open one link per env rank to the rollout rank it serves (a Unix socket on one node, TCP
        across nodes); a rollout rank served by several env ranks gets a link from each."""
        transport, plan = self.cfg.rollout.transport, self.plan
        self._link_generation += 1
        shares = self.env.call("served").wait()
        per_rank, channels = [], []
        for e, (env_rank, (r, _)) in enumerate(zip(plan.ranks("env"), shares)):
            family = "AF_UNIX" if env_rank.node_id == plan.ranks("rollout")[r].node_id else "AF_INET"
            names = None
            if transport == "channel":
                from infinirl.runtime import Channel

                prefix = f"embodied-{os.getpid()}-{self._link_generation}-{e}"
                names = (f"{prefix}-to-rollout", f"{prefix}-to-env")
                channels += [Channel.create(name, pipeline_depth=2, exist_ok=True) for name in names]
            per_rank.append((transport, names, family))
        addresses = self.env.call_each("open_link", per_rank).wait()
        accepted = self.env.accept_link()
        if self.cfg.env.stage_processes:  # one env rank per rollout rank, a link per stage process
            self.rollout.call_each("connect_link", [(a,) for a in addresses]).wait()
        else:
            parts: list[list] = [[] for _ in range(self.rollout.world_size)]
            for address, (r, stages) in zip(addresses, shares):
                parts[r].append((address, list(stages)))
            self.rollout.call_each("connect_links", [(p,) for p in parts]).wait()
        accepted.wait()
        self._link_channels = channels  # an earlier layout's channels go once both ends closed them

    # ------------------------------------------------------------------ online scaling
    def request_scale(self, component: str, ranks: int) -> None:
        """Ask for ``component`` to have ``ranks`` ranks; applied after the current iteration
        (thread-safe: another thread of the driver may call it while the run goes on)."""
        self.scale_requests.put({component: ranks})

    def _scale_between_iterations(self, busy_ratio: float | None, measured_ranks: float | None = None) -> None:
        """Apply a scaling request (:meth:`request_scale`, then the command file), else the busy-ratio
        policy's decision on ``busy_ratio``, measured with ``measured_ranks`` env ranks (an
        asynchronous run's trajectory may come from the layout before a resize: the policy ignores
        it). A request the layout cannot take is refused with its reason; the run goes on."""
        wanted, source = None, None
        while not self.scale_requests.empty():
            wanted, source = self.scale_requests.get().get("env", wanted), "request"
        if self.commands is not None:
            command = self.commands.poll()
            if "env" in command:
                wanted, source = command["env"], "command"
        if wanted is None and self.policy is not None and busy_ratio is not None:
            measured = None if measured_ranks is None else int(measured_ranks)
            wanted, source = self.policy.decide(self.env.world_size, busy_ratio, measured), "policy"
        if wanted is None or wanted == self.env.world_size:
            return
        try:
            self.scale_env(wanted)
        except ValueError as exc:
            if source == "command":
                self.commands.reject(str(exc))
            else:
                print(f"scaling env to {wanted} rank(s) refused ({source}): {exc}", flush=True)

    def scale_env(self, ranks: int) -> None:
        """Give the env component ``ranks`` ranks without stopping the run: collections in flight
        finish first (their samples are kept), then ranks are added or removed where the env's
        placement puts them, every env rank gets its share of the rollout ranks' stages, and the
        links are re-opened. Raises ValueError (nothing changed) for a count the layout does not
        allow."""
        if self.env is None:
            raise ValueError("the env runs inside the rollout's process (collocated placement); place env and "
                             "rollout on disjoint slots to scale the env")
        if self.cfg.env.stage_processes:
            raise ValueError("env.stage_processes=true does not scale online; set env.stage_processes=false")
        shares = env_shares(ranks, self.rollout.world_size, self.cfg.rollout.pipeline_stages)
        spec = resized_spec(self.cfg.placement_spec()["env"], ranks, "env")
        placed = place(self.plan.inventory, {"env": spec}).ranks("env")
        if self.ahead is not None:
            self.ahead.drain()  # collections in flight complete on the old layout and are kept
        old = self.env.world_size
        self.env.close_link().wait()
        self.env.resize(ranks, placement=placed)
        for handle in [self.env.call("assign", *shares[e], ranks=[e]) for e in range(min(old, ranks))]:
            handle.wait()  # ranks started by the resize took their share when they started
        self.plan = self.plan.with_component("env", placed)
        self.connect()
        print(f"scaled env {old} -> {ranks} rank(s) ({spec})", flush=True)

    def start(self, iteration: int) -> None:
        sync_weights(self.actor, self.rollout, version=iteration)

    def step(self, iteration: int) -> dict:
        t0 = time.perf_counter()
        if self.ahead is not None:
            trajectory, rollout_metrics = self.ahead.take(iteration)
        else:
            trajectory, rollout_metrics = self.collect(iteration)
        t1 = time.perf_counter()
        batch, advantage_metrics = self.advantages(trajectory)
        train_metrics = self.actor.update(batch, iteration).wait()[0]
        t2 = time.perf_counter()
        sync_s = self.weights.push(iteration + 1)
        self._scale_between_iterations(rollout_metrics.get("env/busy_ratio"), rollout_metrics.get("env/ranks"))
        steps = int(trajectory["step_mask"].sum())
        self.env_steps += steps
        if self.ahead is not None:
            rollout_metrics.update(staleness_metrics(iteration, [int(trajectory["version"])]))
        return {
            **rollout_metrics, **advantage_metrics, **train_metrics,
            "env/steps": self.env_steps,
            "rollout/max_staleness": float(iteration - trajectory["version"]),
            "time/collect_s": t1 - t0,
            "time/train_s": t2 - t1,
            "time/weight_sync_s": sync_s,
            "time/iteration_s": time.perf_counter() - t0,
            # per second of the rollout ranks' own collection, not of the driver's wait for it (near
            # zero when trajectories are collected ahead of the trainer)
            "time/env_steps_per_s": steps / max(rollout_metrics["rollout/collect_s"], 1e-9),
        }

    # ------------------------------------------------------------------ stages
    def collect(self, iteration: int) -> tuple[dict, dict]:
        """Every env rank runs ``rollout_steps`` decisions with its rollout rank; one trajectory."""
        return self._finish_collect(self._submit_collect(iteration))

    def _submit_collect(self, iteration: int) -> tuple:
        """Start :meth:`collect` without waiting: the env ranks' and rollout ranks' handles."""
        cfg, ranks = self.cfg, self.rollout.world_size
        seeds = iteration_seeds(cfg.seed, iteration, cfg.env.num_envs, self.group_size)
        per = cfg.env.num_envs // ranks
        shards = [seeds[r * per:(r + 1) * per] for r in range(ranks)]
        serving = None
        if self.env is not None:
            if cfg.env.stage_processes:
                serving = self.env.call_each("serve", [(s, cfg.rollout_steps) for s in shards])
            else:  # each env rank resets its share of its rollout rank's stages
                sizes = EnvSpec(name=cfg.env.name, num_envs=per, stages=cfg.rollout.pipeline_stages).stage_sizes()
                shares = env_shares(self.env.world_size, ranks, cfg.rollout.pipeline_stages)
                serving = self.env.call_each("serve", [(stage_seeds(shards[r], sizes, stages), cfg.rollout_steps)
                                                       for r, stages in shares])
        collecting = self.rollout.call_each("collect", [(iteration, s, cfg.rollout_steps) for s in shards])
        return serving, collecting

    def _finish_collect(self, pending: tuple) -> tuple[dict, dict]:
        serving, collecting = pending
        try:
            parts = _wait_collecting(collecting, serving)
        except BaseException as rollout_error:
            _raise_env_root_cause(serving, rollout_error)
            raise
        env_stats = serving.wait() if serving is not None else [{}]
        busy = [stats["env/busy_ratio"] for stats in env_stats if "env/busy_ratio" in stats]
        if busy:
            env_stats[0] = {**env_stats[0], "env/busy_ratio": float(np.mean(busy)), "env/ranks": float(len(busy))}
        sent = [stats["env/bytes_out"] for stats in env_stats if "env/bytes_out" in stats]
        if sent:  # every env rank's observations to the rollout, summed
            env_stats[0] = {**env_stats[0], "env/bytes_out": float(sum(sent))}
        trajectory = _merge(parts)
        # the rollout ranks collect side by side: the collection took as long as the slowest
        collect_s = max(part["timing"].get("rollout/collect_s", 0.0) for part in parts)
        metrics = {
            "rollout/reward_mean": float(trajectory["rewards"].mean()),
            **episode_metrics(trajectory["episodes"], trajectory.get("open_episodes")),
            "env/restarts": float(trajectory["restarted"]),
            **{k: v for k, v in parts[0]["timing"].items()},
            "rollout/collect_s": collect_s,
            **env_stats[0],
        }
        return trajectory, metrics

    def advantages(self, traj: dict) -> tuple[dict, dict]:
        """The algorithm's estimator (``ALGORITHMS[algorithm.name].advantage`` in ``ADVANTAGES``) on
        this iteration's trajectory, at chunk or action level; a flat batch for the actor.

        PPO: embodied GAE, rewards optionally scaled by the running return std. GRPO: group-normalised
        first-episode returns over groups of ``group_size`` consecutive envs (one reset seed each).
        The estimator's mask travels in the batch as ``advantage_mask`` (all true for GAE)."""
        alg, algorithm = self.cfg.algorithm, self.algorithm
        t, n = traj["rewards"].shape
        action_level = alg.gae_level == "action"
        rewards = _tensor(traj["step_rewards"] if action_level else traj["rewards"]).to(torch.float32)
        terminated = _tensor(traj["terminated"])
        # A step both terminated and out of time (gymnasium's TimeLimit sets truncated whatever
        # terminated says) ended the task: no bootstrap from V(final obs).
        truncated = _tensor(traj["truncated"]) & ~terminated
        dones = terminated | truncated
        final_values = _tensor(traj["final_values"])
        scale_rewards = alg.normalize_rewards and not algorithm.grouped
        if scale_rewards:
            rewards = self.return_norm.scale(rewards, dones)
            # Every iteration resets every env: a return running on would join unrelated episodes.
            self.return_norm.end_episodes()
        values = _tensor(traj["values"])
        if action_level:
            # One value per chunk ([T, N]): action-level GAE gives every action of the chunk that
            # baseline and runs the return on to the next chunk's value.
            if algorithm.grouped:
                values = values[..., None].expand_as(rewards)
            else:
                dones, truncated, final_values = _at_last_executed_action(
                    _tensor(traj["step_mask"]), dones, truncated, final_values)
        inputs = EnvAdvantageInputs(rewards=rewards, dones=dones, values=values,
                                    bootstrap_values=_tensor(traj["bootstrap_values"]),
                                    truncations=truncated, final_values=final_values,
                                    group_size=self.group_size if algorithm.grouped else None)
        out = compute_advantages(algorithm.advantage, inputs, **algorithm.advantage_kwargs(alg))
        task_metrics = {}
        if self.env_tasks is not None:
            columns, names = self.env_tasks
            for k, name in enumerate(names):  # each task's scale before, to see what the normalisation evens out
                task_metrics[f"train/advantage_std/{name}"] = float(out.advantages[:, columns == k].std())
            out = dataclasses.replace(out, advantages=normalize_per_task(out.advantages, columns, out.mask))

        def flat(array: Any) -> Any:
            if isinstance(array, dict):
                return {k: flat(v) for k, v in array.items()}
            if isinstance(array, torch.Tensor):
                array = array.numpy()
            return np.ascontiguousarray(array.reshape(t * n, *array.shape[2:]))

        batch = {key: flat(traj[key]) for key in ("obs", "actions", "logprobs", "step_mask", "values")}
        if "extras" in traj:
            batch["extras"] = flat(traj["extras"])
        batch["advantages"] = flat(out.advantages.to(torch.float32))
        batch["returns"] = flat(out.returns.to(torch.float32))
        batch["advantage_mask"] = flat(out.mask.to(torch.bool))
        metrics = {"train/advantage_mean": float(out.advantages.mean()),
                   "train/advantage_std": float(out.advantages.std()), "train/return_mean": float(out.returns.mean())}
        metrics.update(task_metrics)
        if scale_rewards:
            metrics["train/reward_scale"] = 1.0 / float(torch.sqrt(self.return_norm.rms.var + self.return_norm.epsilon))
        if algorithm.grouped:
            metrics.update(group_metrics(out, n, self.group_size))
        return batch, metrics

    def evaluate(self) -> dict:
        """Success rate etc. over the held-out seeded episodes, shared out over the rollout ranks."""
        cfg, ranks = self.cfg.eval, self.rollout.world_size
        # The collections in flight first (RolloutAhead.settle): their time is training time. Then
        # the weight loads queued behind them, which the evaluation would queue behind anyway: a
        # load that failed raises its own error here instead of being evaluated past.
        drained = {}
        if self.ahead is not None:
            start = time.perf_counter()
            self.ahead.settle()
            self.weights.wait()
            drained["time/eval_drain_s"] = time.perf_counter() - start
        t0 = time.perf_counter()
        seeds = eval_seeds(cfg.seed, cfg.episodes)
        handles = [self.rollout.call("evaluate", seeds[r::ranks], min(cfg.num_envs, len(seeds[r::ranks])),
                                     cfg.deterministic, eval_env_kwargs(self.task_block, cfg.env_kwargs),
                                     cfg.max_episode_steps, ranks=[r])
                   for r in range(min(ranks, len(seeds)))]
        results = [handle.wait()[0] for handle in handles]
        total = sum(r["eval/episodes"] for r in results)
        merged = {key: sum(r[key] * r["eval/episodes"] for r in results) / total
                  for key in ("eval/success_rate", "eval/return_mean", "eval/length_mean")}
        merged["eval/episodes"] = float(total)
        merged.update(merge_task_success(results))
        merged["time/eval_s"] = time.perf_counter() - t0
        merged["env/steps"] = self.env_steps
        return {**merged, **drained}

    # ------------------------------------------------------------------ checkpoints
    def save(self, folder: str) -> dict:
        if self.ahead is not None:  # the trajectories collected ahead are part of the run's state
            save_ahead_batches(folder, self.ahead.drain())
        self.actor.save_checkpoint(os.path.join(folder, "actor")).wait()
        state = {"env_steps": self.env_steps, "return_normalizer": self.return_norm.state_dict()}
        if self.env is not None:  # online scaling may have changed it from the placement's count
            state["env_ranks"] = self.env.world_size
        return state

    def load(self, folder: str, state: dict) -> None:
        self.actor.load_checkpoint(os.path.join(folder, "actor")).wait()
        self.return_norm.load_state_dict(state["return_normalizer"])
        self.env_steps = int(state["env_steps"])
        self._restore_env_ranks(state.get("env_ranks"))
        if self.ahead is not None:
            self.ahead.restore(load_ahead_batches(folder))

    def _restore_env_ranks(self, saved: int | None) -> None:
        """Resume with the env rank count the run had when it saved (scaling changed it from the
        placement's); if this layout cannot take it, say so and go on with the placement's count."""
        if self.env is None or saved is None or saved == self.env.world_size:
            return
        try:
            self.scale_env(int(saved))
        except ValueError as exc:
            print(f"resume: the env had {saved} rank(s) when saved; this layout cannot take that ({exc}); "
                  f"going on with {self.env.world_size}", flush=True)

    def finish(self, output_dir: str) -> dict:
        cfg = self.cfg
        self.weights.wait()
        video = None
        if cfg.eval.video_episodes:
            try:
                video = self.rollout.call("record_video", eval_seeds(cfg.eval.seed, cfg.eval.video_episodes),
                                          os.path.join(output_dir, "eval.mp4"), cfg.eval.video_frame_skip,
                                          cfg.eval.video_fps, eval_env_kwargs(self.task_block, {
                                              **cfg.eval.env_kwargs, **cfg.eval.video_env_kwargs}),
                                          cfg.eval.deterministic, cfg.eval.max_episode_steps, ranks=[0]).wait()[0]
            except Exception as exc:  # a missing GL library must not lose the trained run
                print(f"eval video skipped: {exc}", flush=True)
        return {"env_steps": self.env_steps, "video": video["path"] if video else None,
                "actor_weights_sha256": self.actor.weights_digest().wait()[0], "devices": self.devices()}

    def close(self) -> None:
        for group in (self.rollout, self.env):
            if group is None:
                continue
            try:
                group.close().wait(timeout=30)
            except Exception:  # best effort: the group is killed right after
                pass


def group_metrics(out, num_envs: int, group_size: int) -> dict:
    """GRPO diagnostics: each env's first-episode return (``out.returns`` at step 0) by group.

    ``train/group_return_std_zero_frac``: groups whose returns are all equal (they carry no
    learning signal); ``train/advantage_mask_frac``: decisions inside the first episode (the ones
    trained on; well below 1 means rollout_steps is longer than the episodes)."""
    first = out.returns[0].reshape(num_envs, -1)[:, 0].reshape(-1, group_size)
    kept = out.mask.to(torch.bool)
    advantages = out.advantages[kept].to(torch.float32)
    return {
        "train/return_mean": float(first.mean()),
        "train/advantage_mean": float(advantages.mean()) if advantages.numel() else 0.0,
        "train/advantage_std": float(advantages.std()) if advantages.numel() > 1 else 0.0,
        "train/group_return_std_mean": float(first.std(dim=1).mean()) if group_size > 1 else 0.0,
        "train/group_return_std_zero_frac": float((first.amax(dim=1) == first.amin(dim=1)).to(torch.float32).mean()),
        "train/advantage_mask_frac": float(kept.to(torch.float32).mean()),
    }


def _at_last_executed_action(step_mask: torch.Tensor, *per_chunk: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``[T, N]`` episode-end flags (and values) of chunks placed on the chunk's last executed action
    (``step_mask`` ``[T, N, C]``): an env stops at the action its episode ended on, so the actions
    after it never ran and must not stand between that action and the end in action-level GAE."""
    chunk = step_mask.shape[-1]
    last = chunk - 1 - step_mask.flip(-1).to(torch.int64).argmax(-1)
    at_last = torch.nn.functional.one_hot(last, chunk).bool()
    return tuple(torch.where(at_last, flags[..., None], torch.zeros((), dtype=flags.dtype)) for flags in per_chunk)


def _tensor(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.array(array, copy=True))  # Ray hands out read-only arrays


def _merge(parts: list[dict]) -> dict:
    """Per-rank trajectories -> one, envs concatenated in rank order."""
    if len(parts) == 1:
        return parts[0]
    out: dict[str, Any] = {}
    for key, first in parts[0].items():
        if key in ("episodes", "open_episodes"):
            out[key] = {k: np.concatenate([p[key][k] for p in parts]) for k in first}
        elif key in ("timing",):
            out[key] = first
        elif key == "version":
            out[key] = min(p[key] for p in parts)
        elif key == "restarted":
            out[key] = sum(p[key] for p in parts)
        elif key == "bootstrap_values":
            out[key] = np.concatenate([p[key] for p in parts])
        elif isinstance(first, dict):
            out[key] = {k: np.concatenate([p[key][k] for p in parts], axis=1) for k in first}
        else:
            out[key] = np.concatenate([p[key] for p in parts], axis=1)
    return out
