"""EnvWorker: the env component. One rank owns a slice of the training envs, split into stages.

What one rank holds is a :class:`StagedEnv`: its ``num_envs`` envs as ``stages`` separate
vectorised envs (``make_env``), so that one stage can be simulated while the policy decides for
another. The :class:`StagedEnv` is the whole env logic; it runs either

* in the env component's own process (:class:`EnvWorker`, a Ray worker), serving the rollout over
  an :mod:`~infinirl.components.env_link` (env and rollout placed on disjoint resources), or
* inside the rollout's process (env and rollout collocated: the placement says they take turns on
  the same CPU slots/devices, so a hop between two processes would buy nothing), or
* one stage per process (``env.stage_processes``): the EnvWorker supervises a process per stage,
  each holding a one-stage :class:`StagedEnv` and its own link (:mod:`.env_stages`).

Messages are :class:`StageStep` dicts of numpy arrays: what the rollout needs to record a step
and decide the next one (observation, reward, episode ends, the final observation of episodes that
ended, per-action rewards of chunks, and statistics of finished episodes).

Seeds. Every reset is seeded by the caller (the runner derives training seeds from ``(seed,
iteration)``), so the envs' state at an iteration boundary is a function of the iteration and a
resumed run continues exactly. Training seeds are below ``2**31 - 1``; held-out evaluation seeds
start at :data:`EVAL_SEED_BASE` = ``2**31``, so the two never meet.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from infinirl.runtime import Worker
from infinirl.utils.threads import limit_threads

__all__ = ["EVAL_SEED_BASE", "EnvSpec", "EnvWorker", "StagedEnv", "env_shares", "iteration_seeds", "probe_env_specs",
           "serve_stages", "stage_seeds"]

EVAL_SEED_BASE = 2**31
"""First held-out evaluation seed; training seeds (iteration resets and auto-resets) are below it."""

_TRAIN_SEED_LIMIT = 2**31 - 1  # VectorEnv draws auto-reset seeds below this too


@dataclass(frozen=True, kw_only=True)
class EnvSpec:
    """How to build the envs of one rank (picklable; the runner fills it from the config).

    ``num_envs`` is this rank's total, split over ``stages`` (equal sizes, the remainder to the
    first stages). ``num_workers`` is the number of simulator subprocesses *per stage* (0: the
    sub-envs run in the owning process). ``stage_processes``: an :class:`EnvWorker` runs each stage
    in a process of its own that streams straight to the rollout (see :mod:`.env_stages`).
    ``step_timeout_s`` and ``max_restarts`` go to every :class:`~infinirl.envs.vector.VectorEnv`
    built (a hung simulator subprocess is replaced; too many crashes stop the run).
    """

    name: str
    num_envs: int
    stages: int = 1
    num_workers: int = 0
    max_episode_steps: int | None = None
    chunk_size: int = 1
    seed: int = 0
    kwargs: dict = field(default_factory=dict)
    stage_processes: bool = False
    step_timeout_s: float | None = None
    max_restarts: int = 100

    def stage_sizes(self) -> list[int]:
        base, extra = divmod(self.num_envs, self.stages)
        return [base + (1 if s < extra else 0) for s in range(self.stages)]

    def build(self, num_envs: int, stage: int = 0, num_workers: int | None = None,
              max_episode_steps: int | None = None, **overrides: Any):
        """One vectorised env of ``num_envs`` (chunked when ``chunk_size > 1``); ``overrides`` go to
        the simulator, ``max_episode_steps`` replaces the spec's time limit when given."""
        from infinirl.envs import make_env

        return make_env(
            self.name,
            num_envs,
            seed=_mix(self.seed, stage),
            num_workers=self.num_workers if num_workers is None else num_workers,
            max_episode_steps=self.max_episode_steps if max_episode_steps is None else max_episode_steps,
            chunk_size=self.chunk_size if self.chunk_size > 1 else None,
            step_timeout_s=self.step_timeout_s,
            max_restarts=self.max_restarts,
            **{**self.kwargs, **overrides},
        )


def iteration_seeds(seed: int, iteration: int, num_envs: int, group_size: int = 1) -> list[int]:
    """The reset seed of every training env at the start of ``iteration`` (all below 2**31 - 1).

    ``group_size > 1`` (embodied GRPO): ``num_envs / group_size`` distinct seeds, each given to
    ``group_size`` consecutive envs, so every group starts from one state. The envs keep their
    global order through the split into ranks and pipeline stages and back (the runner merges the
    ranks' trajectories in rank order), so a group may straddle a rank or stage boundary.
    """
    rng = np.random.default_rng([seed, iteration, 0x5EED])
    if group_size == 1:
        return [int(s) for s in rng.integers(0, _TRAIN_SEED_LIMIT, size=num_envs)]
    if group_size < 1 or num_envs % group_size:
        raise ValueError(f"group_size={group_size} must be >= 1 and divide num_envs={num_envs}")
    groups = num_envs // group_size
    draws = rng.integers(0, _TRAIN_SEED_LIMIT, size=groups)
    while len(set(draws.tolist())) < groups:  # distinct groups (a collision is ~1e-9 likely)
        draws = rng.integers(0, _TRAIN_SEED_LIMIT, size=groups)
    return [int(s) for s in draws for _ in range(group_size)]


def env_shares(env_ranks: int, rollout_ranks: int, stages: int) -> list[tuple[int, tuple[int, ...]]]:
    """Per env rank: the rollout rank it serves and which of that rollout rank's pipeline stages.

    Each rollout rank's ``stages`` are shared out evenly over ``env_ranks / rollout_ranks``
    consecutive env ranks: 1 env rank per rollout rank serves all its stages; 2 serve half each
    (online scaling grows and shrinks the env component this way). Where a stage is served never
    changes what it simulates (see :class:`StagedEnv`)."""
    if env_ranks < 1 or rollout_ranks < 1 or env_ranks % rollout_ranks:
        raise ValueError(f"env ranks ({env_ranks}) must be a multiple of rollout ranks ({rollout_ranks}): each "
                         "rollout rank is served by the same number of env ranks")
    per = env_ranks // rollout_ranks
    if stages % per:
        raise ValueError(f"{per} env ranks per rollout rank cannot share its {stages} pipeline stage(s) evenly; "
                         f"use a divisor of rollout.pipeline_stages={stages} env ranks per rollout rank")
    width = stages // per
    return [(e // per, tuple(range((e % per) * width, (e % per + 1) * width))) for e in range(env_ranks)]


def stage_seeds(seeds: list[int], sizes: list[int], stages: tuple[int, ...]) -> list[int]:
    """The reset seeds of ``stages``' envs, out of a rollout rank's ``seeds`` (stage ``s`` has
    ``sizes[s]`` envs, in stage order)."""
    starts = np.cumsum([0, *sizes])
    return [seed for s in stages for seed in seeds[starts[s]:starts[s + 1]]]


def probe_env_specs(name: str, kwargs: dict, where: str = "env.kwargs") -> tuple[dict, Any]:
    """Observation spec and (single-step) action space of env ``name``, from one sub-env built in
    this process. Also validates the name and options (``where``: their config key, for the
    error), listing the valid ones on error."""
    from infinirl.envs.registry import ENVS, check_env_kwargs, split_env_name

    check_env_kwargs(name, kwargs, where)
    family, task = split_env_name(name)
    factory = ENVS.get(family)(task, **kwargs)
    sub_env = factory(0)
    try:
        return dict(sub_env.observation_spec), sub_env.action_space
    finally:
        sub_env.close()


def _mix(seed: int, stage: int) -> int:
    return int(np.random.default_rng([seed, stage, 0xE4]).integers(0, _TRAIN_SEED_LIMIT))


StageStep = dict[str, Any]
"""One stage's step as the env reports it (see :meth:`StagedEnv.step_wait`)."""


class StagedEnv:
    """A rank's envs as ``spec.stages`` vectorised envs; ``step_async``/``step_wait`` per stage.

    ``stages`` picks a subset of the rank's stages (a stage process holds one): the envs built are
    exactly those the whole rank would build for them, so where a stage runs never changes what it
    simulates. ``stage_ids`` are the rank-wide indices of the stages held, in order.
    """

    def __init__(self, spec: EnvSpec, rank: int = 0, stages: list[int] | None = None):
        self.spec = spec
        sizes = spec.stage_sizes()
        if min(sizes) < 1:
            raise ValueError(f"{spec.num_envs} envs cannot fill {spec.stages} pipeline stages")
        self.stage_ids = list(range(spec.stages)) if stages is None else [int(s) for s in stages]
        self.sizes = [sizes[s] for s in self.stage_ids]
        self.rank = rank
        self._seeded = EnvSpec(**{**spec.__dict__, "seed": _mix(spec.seed, 1000 + rank)})
        self.envs = [self._seeded.build(sizes[s], stage=s) for s in self.stage_ids]
        self.num_stages = len(self.envs)
        self._pending: list[bool] = [False] * self.num_stages

    def regroup(self, stages: list[int]) -> None:
        """Hold ``stages`` from now on (online scaling moved stages between env ranks): the envs of
        stages kept stay as they are, those of stages given up are closed, new ones are built.
        Between iterations only (no step pending)."""
        if any(p is not False for p in self._pending):
            raise RuntimeError("regroup() with a step pending")
        sizes = self.spec.stage_sizes()
        held = dict(zip(self.stage_ids, self.envs))
        wanted = [int(s) for s in stages]
        for stage_id, env in held.items():
            if stage_id not in wanted:
                env.close()
        self.envs = [held[s] if s in held else self._seeded.build(sizes[s], stage=s) for s in wanted]
        self.stage_ids, self.sizes = wanted, [sizes[s] for s in wanted]
        self.num_stages = len(self.envs)
        self._pending = [False] * self.num_stages

    @property
    def observation_spec(self) -> dict:
        return dict(self.envs[0].observation_spec)

    @property
    def action_space(self):
        return self.envs[0].action_space

    def reset(self, seeds: list[int]) -> list[StageStep]:
        """Reset every env with its seed; the first message of each stage (no reward yet)."""
        if len(seeds) != sum(self.sizes):
            raise ValueError(f"expected {sum(self.sizes)} seeds (one per env of these stages), got {len(seeds)}")
        messages, start = [], 0
        for env, n in zip(self.envs, self.sizes):
            obs = env.reset(seeds=[int(s) for s in seeds[start:start + n]])
            start += n
            messages.append(_first_message(obs, n, self.spec.chunk_size))
        return messages

    @property
    def simulates_in_background(self) -> bool:
        """True when ``step_async`` returns while the simulators run (sub-envs in worker
        processes); False when the sub-envs run in this process, inside ``step_wait``."""
        env = self.envs[0]
        return hasattr(env, "step_async") and getattr(env, "num_workers", 0) > 0

    def step_async(self, stage: int, actions: np.ndarray, autoreset: bool = True) -> None:
        """Start stage ``stage``'s step. ``autoreset=False`` on an iteration's last step: the next
        iteration resets every env with its own seed, so restarting episodes that end now would
        simulate resets whose observations nobody reads (their bootstrap values are masked)."""
        env = self.envs[stage]
        if hasattr(env, "step_async"):  # a VectorEnv: the simulators run while we return
            env.step_async(actions, autoreset=autoreset)
            self._pending[stage] = True
        else:  # a chunked env steps K times, so it cannot be split; it runs in step_wait
            self._pending[stage] = (actions, autoreset)

    def step_wait(self, stage: int) -> StageStep:
        pending, self._pending[stage] = self._pending[stage], False
        env = self.envs[stage]
        if pending is True:
            result = env.step_wait()
        elif pending is False:
            raise RuntimeError(f"step_wait({stage}) without step_async({stage})")
        else:
            actions, autoreset = pending
            result = env.step(actions, autoreset=autoreset)
        return _step_message(result, self.spec.chunk_size)

    def step(self, stage: int, actions: np.ndarray, autoreset: bool = True) -> StageStep:
        self.step_async(stage, actions, autoreset)
        return self.step_wait(stage)

    def close(self) -> None:
        for env in self.envs:
            env.close()


def _first_message(obs: dict, n: int, chunk: int) -> StageStep:
    return {"obs": obs, "first": True}


def _step_message(result, chunk: int) -> StageStep:
    info = result.info
    done = np.asarray(result.terminated | result.truncated)
    ended = np.flatnonzero(done)
    msg: StageStep = {
        "obs": result.obs,
        "reward": np.asarray(result.reward, dtype=np.float32),
        "terminated": np.asarray(result.terminated, dtype=bool),
        "truncated": np.asarray(result.truncated, dtype=bool),
        "success": np.asarray(info["success"], dtype=bool),
        "ended": ended,
        "final_obs": {k: (v[ended] if isinstance(v, np.ndarray) else [v[i] for i in ended])
                      for k, v in info["final_obs"].items()},
        "episode_return": np.asarray(info["episode_return"])[ended],
        "episode_length": np.asarray(info["episode_length"])[ended],
        "episode_success": np.asarray(info["episode_success"])[ended],
        "restarted": int(np.asarray(info["restarted"]).sum()),
    }
    if chunk > 1:
        msg["step_rewards"] = np.asarray(info["step_rewards"], dtype=np.float32)
        msg["step_mask"] = np.asarray(info["step_mask"], dtype=bool)
    else:
        msg["step_rewards"] = msg["reward"][:, None]
        msg["step_mask"] = np.ones((len(msg["reward"]), 1), dtype=bool)
    return msg


class EnvWorker(Worker):
    """The env component in its own process: a rank's stages served to one rollout rank.

    Rank ``r`` pairs with rollout rank ``r`` (or, with more env ranks than rollout ranks, serves its
    share of a rollout rank's stages: :func:`env_shares`; online scaling moves shares with
    :meth:`assign`) through a link (``open_link`` + ``accept_link`` here,
    ``connect_link`` on the rollout). Per iteration the runner calls :meth:`serve`, which resets
    the envs with the given seeds and then answers each stage's actions with its next step, in the
    order the rollout sends them; simulation of one stage overlaps the rollout's inference for
    another because the two run in different processes.

    Where the stages run: in this process (a :class:`StagedEnv`, one link) or, with
    ``spec.stage_processes``, each in a process of its own with its own link to the rollout
    (:class:`~infinirl.components.env_stages.StageProcess`), so stages also simulate at the same
    time as each other and no message is relayed through this process.
    """

    def __init__(self, spec: EnvSpec, num_threads: int = 1, rollout_ranks: int | None = None):
        limit_threads(num_threads)
        self.spec = spec
        self.link = None
        self._server = None
        # The rollout rank and stages this rank serves: all of rollout rank r's stages, or (online
        # scaling, ``rollout_ranks`` given) this rank's share for the group's size at its start.
        self.serves: tuple[int, tuple[int, ...]] = (self.rank, tuple(range(spec.stages)))
        if rollout_ranks is not None:
            self.serves = env_shares(self.world_size, rollout_ranks, spec.stages)[self.rank]
        if spec.stage_processes:
            from infinirl.components.env_stages import StageProcess

            self.env = None
            self.stage_processes = [StageProcess(spec, self.rank, stage) for stage in range(spec.stages)]
            try:
                for stage in self.stage_processes:  # they build in parallel; a bad option fails here
                    stage.wait_ready()
            except BaseException:
                for stage in self.stage_processes:
                    stage.close()
                raise
        else:
            self.env = StagedEnv(spec, self.serves[0], list(self.serves[1]))
            self.stage_processes = []

    def assign(self, rollout_rank: int, stages: list[int]) -> None:
        """Serve ``stages`` of ``rollout_rank`` from now on (online scaling rebalanced the env
        ranks); the link is re-opened afterwards (:meth:`close_link`, :meth:`open_link`)."""
        if self.stage_processes:
            raise RuntimeError("an env rank with stage processes serves one rollout rank's stages; it cannot be "
                               "reassigned (env.stage_processes=true does not scale online)")
        if rollout_rank != self.env.rank:
            self.env.close()
            self.env = StagedEnv(self.spec, rollout_rank, list(stages))
        else:
            self.env.regroup(list(stages))
        self.serves = (rollout_rank, tuple(stages))

    def served(self) -> tuple[int, tuple[int, ...]]:
        """The rollout rank this rank serves and which of its stages."""
        return self.serves

    def _drop_link(self) -> None:
        """:meth:`close_link` on the way out of a failure: a second error while closing must not
        hide the one being raised."""
        try:
            self.close_link()
        except Exception:  # noqa: BLE001 - the failure being raised is the one to report
            self.link = self._server = None

    def close_link(self) -> None:
        """Close the link to the rollout (and a listener it never connected to) and keep the envs."""
        if self._server is not None:
            from infinirl.components.env_link import close_server

            close_server(self._server)
            self._server = None
        if self.link is not None:
            self.link.close()
            self.link = None

    def open_link(self, transport: str, channel_names: tuple[str, str] | None = None,
                  family: str | None = None) -> Any:
        """Start listening for this rank's rollout; returns the address to connect to (with stage
        processes: ``{"stages": [address of each stage]}``)."""
        if self.stage_processes:
            if transport != "socket":
                raise ValueError(f"env stage processes stream over sockets; rollout.transport={transport!r} "
                                 "needs env.stage_processes=false")
            return {"stages": [stage.open_link(family) for stage in self.stage_processes]}
        from infinirl.components.env_link import open_server

        self._server, address = open_server(transport, channel_names, family=family)
        return address

    def accept_link(self) -> None:
        if self.stage_processes:
            for stage in self.stage_processes:
                stage.accept_link()
            for stage in self.stage_processes:
                stage.wait_accepted()
            return
        from infinirl.components.env_link import accept

        self.link = accept(self._server)

    def serve(self, seeds: list[int], num_steps: int) -> dict:
        """One iteration: reset, then ``num_steps`` rounds of (actions in, step out) per stage;
        see :func:`serve_stages`. With stage processes each serves its own stage and seeds."""
        if self.stage_processes:
            from infinirl.components.env_stages import serve_in_stage_processes

            return serve_in_stage_processes(self.stage_processes, self.spec.stage_sizes(), seeds, num_steps)
        if self.link is None:
            raise RuntimeError("serve() before the link to the rollout was opened (open_link/accept_link)")
        start, sent = time.perf_counter(), getattr(self.link, "bytes_sent", None)
        try:
            stats = serve_stages(self.env, self.link, seeds, num_steps)
        except BaseException:
            # The rollout is blocked reading this link: closing it makes the rollout fail at once
            # with EnvLinkClosed (a symptom the runner sets aside for this error, the root cause)
            # instead of waiting forever for a step that will never come (stage processes do the
            # same in env_stages._stage_main).
            self._drop_link()
            raise
        # the fraction of the collection this rank simulated (1 - its bubble): the scaling signal
        stats["env/busy_ratio"] = stats["env/simulate_s"] / max(time.perf_counter() - start, 1e-9)
        if sent is not None:  # a socket link counts what it sends (observations to the rollout)
            stats["env/bytes_out"] = float(self.link.bytes_sent - sent)
        return stats

    def close(self) -> None:
        for stage in self.stage_processes:
            stage.close()
        if self._server is not None:
            from infinirl.components.env_link import close_server

            close_server(self._server)
        if self.link is not None:
            self.link.close()
        if self.env is not None:
            self.env.close()


def serve_stages(env: StagedEnv, link, seeds: list[int], num_steps: int) -> dict:
    """Serve one iteration of ``env``'s stages over ``link``: reset, then ``num_steps`` rounds of
    (actions in, step out) per stage, in the order the rollout uses them.

    With simulator subprocesses (``env.num_workers >= 1``) stages are started as soon as their
    actions arrive and finished only when the rollout needs their result: after starting stage
    ``s`` we finish stage ``s+1`` (started one round earlier), whose result the rollout asks for
    next, so the stages simulate at the same time as each other and while the rollout decides.
    With the sub-envs in this process (``env.num_workers=0``) a stage is simulated as soon as its
    actions arrive and its result sent at once: while this process simulates stage ``s`` the
    rollout decides for stage ``s-1``, and the actions for stage ``s+1`` are already waiting when
    it is done, so the simulator never idles. ``K = 1`` reduces to step-then-reply either way.
    """
    import time

    stages = env.num_stages
    busy = 0.0
    for message in env.reset(seeds):
        link.send(message)
    pending = [False] * stages
    background = env.simulates_in_background
    for step_index in range(num_steps):
        autoreset = step_index < num_steps - 1  # the next iteration resets every env itself
        for stage in range(stages):
            got_stage, actions = link.recv()
            if got_stage != env.stage_ids[stage]:
                raise RuntimeError(f"env expected actions for stage {env.stage_ids[stage]}, got stage {got_stage}")
            start = time.perf_counter()
            if not background:
                message = env.step(stage, actions, autoreset)
                busy += time.perf_counter() - start
                link.send(message)
                continue
            env.step_async(stage, actions, autoreset)
            pending[stage] = True
            following = (stage + 1) % stages
            if pending[following]:
                message = env.step_wait(following)
                pending[following] = False
                busy += time.perf_counter() - start
                link.send(message)
            else:
                busy += time.perf_counter() - start
    for stage in range(stages):  # the last round's results, in the order the rollout reads them
        if pending[stage]:
            start = time.perf_counter()
            message = env.step_wait(stage)
            busy += time.perf_counter() - start
            link.send(message)
    return {"env/simulate_s": busy}
