"""The SAC collector: owns the training envs, runs the actor (inference copy), returns transitions.

Off-policy collection differs from the on-policy rollout in one way that shapes this component:
episodes are **never cut at iteration boundaries**. Envs keep running across ``collect`` calls, so
a 1,000-step episode spans several iterations, exactly as in a single-process SAC loop.

**Episode seeds are ours.** Each training env is its own single-env
:class:`~infinirl.envs.VectorEnv` (``num_workers=0``: in this process; ``1``: in a subprocess of its
own, so envs simulate in parallel via ``step_async``/``step_wait``). When an episode ends, the env
is reset explicitly with the next seed of this collector's seed generator (the vectoriser's own
auto-reset observation is discarded), so the sequence of episodes is a function of ``seed`` alone.

**Exact resume.** A simulator's internal state cannot be saved generically, but it can be
*replayed*: the collector records, per env, the seed of the current episode and the actions taken
in it since the reset. :meth:`SACCollectorWorker.load_state` resets each env with that seed and
re-applies those actions, which brings a deterministic simulator (MuJoCo, classic control) back to
the very state it was in, with the same observation (checked; a mismatch is reported). Together
with the generators' states (episode seeds, warm-up actions, policy noise) the resumed run then
collects the same transitions, bit for bit. Replaying costs at most one episode of simulation per
env, once per resume.

Actions: the actor works in ``[-1, 1]^A``; the env gets the affine map to its box. The replay
buffer stores the ``[-1, 1]`` action; warm-up actions are uniform in ``[-1, 1]^A``.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from infinirl.components.eval_metrics import task_success_metrics
from infinirl.runtime import WeightSink, Worker
from infinirl.utils.atomic import torch_save_atomic
from infinirl.utils.threads import limit_threads

__all__ = ["CollectorEnvSpec", "SACCollectorWorker"]

logger = logging.getLogger(__name__)

_SEED_LIMIT = 2**31 - 1  # training episode seeds; held-out eval seeds start at 2**31
_STATE_FILE = "collector.pt"


@dataclass(frozen=True, kw_only=True)
class CollectorEnvSpec:
    """How to build the collector's envs (picklable; the runner fills it from the config)."""

    name: str
    num_envs: int = 1
    num_workers: int = 0
    max_episode_steps: int | None = None
    kwargs: dict = field(default_factory=dict)
    seed: int = 0
    step_timeout_s: float | None = None
    """A simulator subprocess silent this long in one command is replaced (see :class:`VectorEnv`)."""
    max_restarts: int = 100
    """Sub-env crashes one vectorised env survives (see :class:`VectorEnv`)."""

    def build(self, num_envs: int = 1, num_workers: int | None = None, salt: int = 0, **overrides: Any):
        from infinirl.envs import make_env

        seed = int(np.random.SeedSequence([self.seed, salt, 0xE5]).generate_state(1)[0] % _SEED_LIMIT)
        return make_env(self.name, num_envs, seed=seed,
                        num_workers=self.num_workers if num_workers is None else num_workers,
                        max_episode_steps=self.max_episode_steps, step_timeout_s=self.step_timeout_s,
                        max_restarts=self.max_restarts, **{**self.kwargs, **overrides})


class SACCollectorWorker(Worker, WeightSink):
    """One collector rank: training envs + the actor's inference copy; evaluation and videos."""

    def __init__(self, env: CollectorEnvSpec, net, obs_dim: int, action_space, seed: int, num_threads: int = 1):
        limit_threads(num_threads)
        self.spec, self.obs_key = env, net.obs_key
        self.action_shape = tuple(action_space.shape)
        self.action_dim = int(np.prod(self.action_shape))
        low = np.asarray(action_space.low, np.float32).reshape(-1)
        high = np.asarray(action_space.high, np.float32).reshape(-1)
        self._scale, self._bias = (high - low) / 2, (high + low) / 2
        self.actor = net.build_actor(obs_dim, action_space).eval()
        self.envs = [env.build(1, salt=i) for i in range(env.num_envs)]
        self.seed_rng = np.random.default_rng([seed, 0x5EED5])
        self.action_rng = np.random.default_rng([seed, 0xAC7])
        self.generator = torch.Generator().manual_seed(int(np.random.SeedSequence([seed, 0x7A]).generate_state(1)[0]))
        self.obs: np.ndarray | None = None  # [num_envs, obs_dim], the observation each env is at
        self.episode_seed: list[int] = [0] * env.num_envs
        self.history: list[list[np.ndarray]] = [[] for _ in range(env.num_envs)]
        self.env_steps = 0
        self.episodes = 0
        self._eval_env = None

    # ---------------------------------------------------------------- weights
    def load_weights(self, named_tensors, version: int) -> None:
        own = self.actor.state_dict()
        with torch.no_grad():
            for name, tensor in named_tensors:
                if name not in own:
                    raise KeyError(f"weight {name!r} from the learner has no place in the collector's actor")
                own[name].copy_(tensor)

    # ---------------------------------------------------------------- envs
    def _obs_vector(self, obs: dict) -> np.ndarray:
        return np.asarray(obs[self.obs_key][0], dtype=np.float32)

    def _new_episode(self, i: int) -> np.ndarray:
        seed = int(self.seed_rng.integers(0, _SEED_LIMIT))
        self.episode_seed[i], self.history[i] = seed, []
        return self._obs_vector(self.envs[i].reset(seeds=[seed]))

    def _to_env(self, actions: np.ndarray) -> np.ndarray:
        return (actions * self._scale + self._bias).astype(np.float32)

    def _ensure_started(self) -> None:
        if self.obs is None:
            self.obs = np.stack([self._new_episode(i) for i in range(len(self.envs))])

    @torch.no_grad()
    def collect(self, num_steps: int, random_steps: int = 0) -> dict:
        """``num_steps`` steps of every env; the first ``random_steps`` with uniform random
        actions (warm-up), the rest sampled from the actor. Returns the transitions (time-major:
        step ``t`` of env ``i`` is row ``t * num_envs + i``) and episode statistics: of the episodes
        that ended (``episodes``) and of those still running (``open_episodes``, see :meth:`open_episodes`)."""
        self.check_weights()  # never act on weights a failed load left half-replaced
        self._ensure_started()
        n, t0 = len(self.envs), time.perf_counter()
        rows: dict[str, list] = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated", "env_step",
                                                  "logprob", "pre_tanh", "policy_mask", "valid")}
        episodes = {"return": [], "length": [], "success": []}
        infer_s = sim_s = 0.0
        restarted = 0
        for t in range(num_steps):
            start = time.perf_counter()
            if t < random_steps:
                actions = self.action_rng.uniform(-1.0, 1.0, size=(n, self.action_dim)).astype(np.float32)
                logprob, u, from_policy = np.zeros(n, np.float32), np.zeros_like(actions), False
            else:
                a, lp, pre = self.actor.sample(torch.from_numpy(self.obs), self.generator)
                actions, logprob, u, from_policy = a.numpy(), lp.numpy(), pre.numpy(), True
            env_actions = self._to_env(actions)
            infer_s += time.perf_counter() - start
            start = time.perf_counter()
            for i, env in enumerate(self.envs):
                env.step_async(env_actions[i].reshape(1, *self.action_shape))
            results = [env.step_wait() for env in self.envs]
            sim_s += time.perf_counter() - start
            for i, result in enumerate(results):
                done = bool(result.done[0])
                crashed = bool(result.info["restarted"][0])
                next_obs = self._obs_vector(result.info["final_obs"] if done else result.obs)
                rows["obs"].append(self.obs[i].copy())
                rows["action"].append(actions[i])
                rows["reward"].append(np.float32(result.reward[0]))
                rows["next_obs"].append(next_obs)
                rows["terminated"].append(np.float32(result.terminated[0]))
                rows["env_step"].append(self.env_steps)
                rows["logprob"].append(logprob[i])
                rows["pre_tanh"].append(u[i])
                rows["policy_mask"].append(from_policy)
                rows["valid"].append(not crashed)  # a crash's stand-in transition is not real data
                restarted += crashed
                if done:
                    episodes["return"].append(float(result.info["episode_return"][0]))
                    episodes["length"].append(int(result.info["episode_length"][0]))
                    episodes["success"].append(bool(result.info["episode_success"][0]))
                    self.episodes += 1
                    self.obs[i] = self._new_episode(i)
                else:
                    self.history[i].append(env_actions[i].copy())
                    self.obs[i] = next_obs
            self.env_steps += n
        valid = np.asarray(rows.pop("valid"), dtype=bool)
        batch = {key: np.asarray(value)[valid] for key, value in rows.items()}
        batch["obs"] = batch["obs"].astype(np.float32).reshape(-1, self.obs.shape[1])
        batch["next_obs"] = batch["next_obs"].astype(np.float32).reshape(-1, self.obs.shape[1])
        batch["action"] = batch["action"].astype(np.float32).reshape(-1, self.action_dim)
        batch["pre_tanh"] = batch["pre_tanh"].astype(np.float32).reshape(-1, self.action_dim)
        batch["env_step"] = batch["env_step"].astype(np.int64)
        batch["episodes"] = {k: np.asarray(v) for k, v in episodes.items()}
        batch["open_episodes"] = self.open_episodes()
        batch["version"] = self.weight_version
        batch["restarted"] = restarted
        batch["timing"] = {"rollout/inference_s": infer_s, "rollout/simulate_s": sim_s,
                           "rollout/collect_s": time.perf_counter() - t0}
        return batch

    def open_episodes(self) -> dict[str, np.ndarray]:
        """Per training env, its running episode's return so far (float64) and steps so far (int64),
        which may span several collections; 0 and 0 right after an episode ended. Read from the
        envs' own statistics, which replaying an episode on resume rebuilds exactly."""
        running = [env.open_episodes() for env in self.envs]
        return {key: np.concatenate([r[key] for r in running]) for key in ("return", "length")}

    # ---------------------------------------------------------------- state (exact resume)
    def state(self) -> dict:
        """Everything needed to continue collecting exactly (see the module docstring)."""
        self._ensure_started()
        return {
            "obs": self.obs.copy(), "episode_seed": list(self.episode_seed),
            "history": [np.asarray(h, np.float32).reshape(len(h), self.action_dim) for h in self.history],
            "seed_rng": self.seed_rng.bit_generator.state, "action_rng": self.action_rng.bit_generator.state,
            "generator": self.generator.get_state(), "env_steps": self.env_steps, "episodes": self.episodes,
        }

    def save_state(self, path: str) -> None:
        """:meth:`state` to ``path/collector.pt``, written to a temporary name and renamed."""
        torch_save_atomic(self.state(), os.path.join(path, _STATE_FILE))

    def load_state(self, path: str) -> dict:
        """Restore :meth:`save_state`'s file: generators, counters, and each env replayed to the
        state it was in. Returns ``{"replayed_steps", "mismatched_envs"}``."""
        state = torch.load(os.path.join(path, _STATE_FILE), weights_only=False)
        if len(state["episode_seed"]) != len(self.envs):
            raise ValueError(f"{path}: the checkpoint has {len(state['episode_seed'])} training envs, this run "
                             f"{len(self.envs)}; resume with the env.num_envs the run was started with")
        self.seed_rng.bit_generator.state = state["seed_rng"]
        self.action_rng.bit_generator.state = state["action_rng"]
        self.generator.set_state(state["generator"])
        self.env_steps, self.episodes = int(state["env_steps"]), int(state["episodes"])
        self.obs = np.asarray(state["obs"], np.float32).copy()
        replayed, mismatched = 0, []
        for i, env in enumerate(self.envs):
            seed, actions = int(state["episode_seed"][i]), state["history"][i]
            obs = self._obs_vector(env.reset(seeds=[seed]))
            ended = False
            for action in actions:
                result = env.step(np.asarray(action, np.float32).reshape(1, *self.action_shape))
                replayed += 1
                if result.done[0]:
                    ended = True
                    break
                obs = self._obs_vector(result.obs)
            self.episode_seed[i] = seed
            self.history[i] = [np.asarray(a, np.float32) for a in actions]
            if ended or not np.array_equal(obs, self.obs[i]):
                mismatched.append(i)
                logger.warning("env %d did not replay to its checkpointed state (non-deterministic simulator?); "
                               "it starts a new episode, so this resume is not bit-exact", i)
                self.obs[i] = self._new_episode(i)
        return {"replayed_steps": replayed, "mismatched_envs": mismatched}

    # ---------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, seeds: list[int], num_envs: int, env_kwargs: dict | None = None) -> dict:
        """One episode per (held-out) seed with the deterministic policy ``tanh(mean)``, run in
        rounds of ``num_envs`` envs in this process; return / length / success statistics, and
        success per task where the envs run several (``eval/success/<task>``)."""
        self.check_weights()  # never act on weights a failed load left half-replaced
        if self._eval_env is None or self._eval_env.num_envs != num_envs:
            if self._eval_env is not None:
                self._eval_env.close()
            self._eval_env = self.spec.build(num_envs, num_workers=0, salt=99, **(env_kwargs or {}))
        env = self._eval_env
        task_names = getattr(env, "task_names", None)
        returns, lengths, successes, tasks = [], [], [], []
        for start in range(0, len(seeds), num_envs):
            batch = [int(s) for s in seeds[start:start + num_envs]]
            obs = env.reset(seeds=batch + [batch[-1]] * (num_envs - len(batch)))
            active = np.arange(num_envs) < len(batch)
            while active.any():
                actions = self._deterministic(obs[self.obs_key])
                # autoreset=False: one episode per env and round; the next round resets it anyway
                result = env.step(actions.reshape(num_envs, *self.action_shape), env_mask=active, autoreset=False)
                for i in np.flatnonzero(result.done & active):
                    returns.append(float(result.info["episode_return"][i]))
                    lengths.append(int(result.info["episode_length"][i]))
                    successes.append(bool(result.info["episode_success"][i]))
                    tasks.append(task_names[i] if task_names else None)
                active &= ~result.done
                obs = result.obs
        return {**task_success_metrics(successes, tasks),
                "eval/return_mean": float(np.mean(returns)), "eval/return_std": float(np.std(returns)),
                "eval/return_min": float(np.min(returns)), "eval/length_mean": float(np.mean(lengths)),
                "eval/success_rate": float(np.mean(successes)), "eval/episodes": float(len(returns))}

    def _deterministic(self, obs: np.ndarray) -> np.ndarray:
        action, _, _ = self.actor.sample(torch.as_tensor(np.asarray(obs, np.float32)), deterministic=True)
        return self._to_env(action.numpy())

    @torch.no_grad()
    def record_video(self, seeds: list[int], path: str, fps: int = 30, frame_skip: int = 1,
                     max_steps: int | None = None, env_kwargs: dict | None = None) -> dict:
        """Render one deterministic episode per seed into an mp4 (MuJoCo renders off-screen on CPU
        through osmesa or egl); returns the path, frame count and each episode's return."""
        self.check_weights()  # never act on weights a failed load left half-replaced
        from infinirl.envs.video import write_mp4

        env = self.spec.build(1, num_workers=0, salt=98, **(env_kwargs or {}))
        frames, returns = [], []
        try:
            for seed in seeds:
                obs = env.reset(seeds=[int(seed)])
                frames.append(env.render()[0])
                total, t = 0.0, 0
                while True:
                    result = env.step(self._deterministic(obs[self.obs_key]).reshape(1, *self.action_shape),
                                      autoreset=False)
                    total, t = total + float(result.reward[0]), t + 1
                    last = bool(result.done[0]) or bool(max_steps and t >= max_steps)
                    # The episode's last frame whatever the frame skip: it shows how the episode
                    # ended. Stepped with autoreset=False, the env still holds that final state.
                    if last or t % frame_skip == 0:
                        frames.append(env.render()[0])
                    if last:
                        break
                    obs = result.obs
                returns.append(total)
        finally:
            env.close()
        write_mp4(path, frames, fps)
        return {"path": path, "frames": len(frames), "episode_returns": returns}

    def close(self) -> None:
        for env in [*self.envs, self._eval_env]:
            if env is not None:
                env.close()
