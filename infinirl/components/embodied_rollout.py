"""Embodied rollout: policy inference over the env's stages, recording PPO trajectories.

One rank drives one env rank: either a :class:`~infinirl.components.env_worker.StagedEnv` in this
process (env collocated with the rollout) or a remote :class:`~infinirl.components.env_worker.EnvWorker`
through an env link. The loop is the same either way (an *endpoint* hides the difference)::

    for t in 0..T:                     # T = rollout_steps decisions per env
        for stage s in 0..K-1:
            msg = endpoint.recv(s)     # stage s's step result (reward/done of the last action, next obs)
            record it; decide the next actions of stage s; endpoint.send(s, actions)

With ``K >= 2`` the env simulates stage ``s`` while this loop decides for stage ``s+1``: the
pipelining of simulation and inference. Local simulators in subprocesses (``env.num_workers >= 1``)
overlap the same way through ``step_async``/``step_wait``. The last decision's step resets no env
whose episode ends (the next iteration resets every env with its own seed; the bootstrap value of
an ended env is unused), which saves a simulator reset per env and iteration.

Weights arrive from the trainer through :func:`~infinirl.runtime.sync_weights` with a version,
which every trajectory carries (``version``), so staleness is measured, not assumed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from infinirl.components.embodied_policy import build_embodied_policy, compute_device, module_device
from infinirl.components.env_worker import EnvSpec, StagedEnv
from infinirl.components.eval_metrics import task_success_metrics
from infinirl.models.policies.base import prepare_obs
from infinirl.runtime import WeightSink, Worker
from infinirl.utils.memory import peak_memory_bytes
from infinirl.utils.threads import limit_threads

__all__ = ["EmbodiedRolloutWorker", "PolicySpec", "compiled_act", "merge_task_success", "run_eval_episodes"]


@dataclass(frozen=True, kw_only=True)
class PolicySpec:
    """Which policy to build, as the rollout and the actor both need it (picklable)."""

    name: str = "mlp_gaussian"
    options: dict = field(default_factory=dict)
    chunk: int = 1
    normalize_obs: bool = True
    normalize_keys: tuple[str, ...] | None = None
    obs_clip: float = 10.0

    def build(self, observation_spec, action_space):
        return build_embodied_policy(self.name, self.options, observation_spec, action_space, self.chunk,
                                     self.normalize_obs, self.normalize_keys, self.obs_clip)


def compiled_act(policy):
    """``policy.act`` through ``torch.compile``, for the collection loop (``rollout.compile``).

    Why: a small policy's decision is a few dozen tiny tensor ops whose interpreter overhead
    outweighs their arithmetic on CPU; compiled, they fuse into a few kernels. The decision sits on
    every env step's critical path, twice per step with two pipeline stages.

    ``fallback_random``: the compiled function draws its Gaussian noise with eager torch's own
    generator calls instead of inductor's in-kernel RNG, so a seed gives the same noise (and leaves
    the generator in the same state) either way: the compiled rollout samples the actions the eager
    one would, up to float rounding of the network. Set for this (rollout) process only.

    ``dynamic=False``: one specialised graph per stage batch size (a run has one or two). The
    options (:func:`~infinirl.engines.compiled_step.inductor_options`) are those of the policy's
    device: on CPU the kernels are called from C++, not Python."""
    import torch._inductor.config as inductor_config

    from infinirl.engines.compiled_step import inductor_options

    inductor_config.fallback_random = True
    return torch.compile(policy.act, dynamic=False, options=inductor_options(module_device(policy)))


def _sampling_generator(device: torch.device) -> torch.Generator:
    """The generator a policy's sampling on ``device`` draws from (the device's default one; a
    compiled ``act`` draws from it too, through ``fallback_random``)."""
    if device.type == "cuda":
        return torch.cuda.default_generators[device.index if device.index is not None else torch.cuda.current_device()]
    return torch.default_generator


def _held_noise_seed(stage_seed: int, window: int) -> int:
    """The seed of a stage's held exploration noise (:attr:`Policy.held_noise_every`) in one window
    of decisions: the same for every decision of the window, whatever order stages are served in."""
    return int(np.random.default_rng([stage_seed, window, 0x401D]).integers(2**62))


def host(tensor: torch.Tensor) -> np.ndarray:
    """A policy output (no grad) as a numpy array, copied off the GPU when the policy runs there."""
    return (tensor if tensor.device.type == "cpu" else tensor.cpu()).numpy()


def env_actions(actions: torch.Tensor | np.ndarray, chunk: int) -> np.ndarray:
    """Policy actions ``[B, K, ...]`` -> what the env takes: ``[B, ...]`` unchunked, else as is."""
    array = actions if isinstance(actions, np.ndarray) else host(actions.detach())
    return array[:, 0] if chunk == 1 else array


def array_obs(obs: dict) -> dict:
    """The observation's fields as arrays: text fields (``instruction``, one string per env) become
    string arrays, so they are recorded, batched and sliced like every other field and reach the
    policy (a VLA reads its instruction) at acting and at the update alike."""
    out = {}
    for key, value in obs.items():
        if isinstance(value, np.ndarray):
            out[key] = value
        elif isinstance(value, (list, tuple)) and value and all(isinstance(v, str) for v in value):
            out[key] = np.asarray(value, dtype=np.str_)
    return out


class _LocalEndpoint:
    """The env in this process: ``send`` starts a stage's step, ``recv`` collects it."""

    def __init__(self, env: StagedEnv, seeds: list[int]):
        self.env = env
        self.num_stages = env.num_stages
        self._first = env.reset(seeds)

    any_order = False  # in-process stages are stepped in turn

    def recv(self, stage: int) -> dict:
        if self._first[stage] is not None:
            message, self._first[stage] = self._first[stage], None
            return message
        return self.env.step_wait(stage)

    def send(self, stage: int, actions: np.ndarray, autoreset: bool = True) -> None:
        self.env.step_async(stage, actions, autoreset)


class _RemoteEndpoint:
    """:class:`EnvWorker` ranks over their links: one link per env rank (or stage process), each
    serving some of the stages in the order we use them. ``stage_link[s]`` is the index of the link
    that serves stage ``s``: one link for every stage (one env rank), one per stage (stage
    processes, or as many env ranks as stages), or a share of the stages each (online scaling)."""

    def __init__(self, links: list, stage_link: list[int] | int):
        if isinstance(stage_link, int):  # a number of stages: one shared link, or one per stage
            stage_link = [0] * stage_link if len(links) == 1 else list(range(stage_link))
        self.num_stages = len(stage_link)
        if sorted(set(stage_link)) != list(range(len(links))):
            raise ValueError(f"stages {stage_link} must use each of the {len(links)} env links")
        self.links = [links[i] for i in stage_link]  # per stage
        # A link per stage with a file descriptor (sockets): serve the stages as their results
        # arrive. A link serving several stages (an env process serving them in turn) or channel
        # links: in order.
        self.any_order = (self.num_stages > 1 and len(links) == self.num_stages
                          and all(hasattr(link, "fileno") for link in links))

    def ready(self, stages: list[int]) -> list[int]:
        """Stages of ``stages`` whose step result has arrived (blocks until one has), in stage
        order (``any_order`` endpoints only)."""
        from multiprocessing.connection import wait

        arrived = {id(link) for link in wait([self.links[stage] for stage in stages])}
        return [stage for stage in stages if id(self.links[stage]) in arrived]

    def recv(self, stage: int) -> dict:
        return self.links[stage].recv()

    def send(self, stage: int, actions: np.ndarray, autoreset: bool = True) -> None:
        # the env side knows the iteration's length and skips the last step's resets itself
        self.links[stage].send((stage, actions))


class _StageBuffer:
    """What one stage records over an iteration, stacked to ``[T, n, ...]`` at the end."""

    def __init__(self):
        self.obs: list[dict] = []
        self.actions, self.logprobs, self.values = [], [], []
        self.extras: list[dict] = []
        self.rewards, self.step_rewards, self.step_mask = [], [], []
        self.terminated, self.truncated, self.final_values = [], [], []
        self.bootstrap = None

    def stacked(self) -> dict:
        def stack(rows):
            return np.stack(rows)

        out = {
            "obs": {key: stack([o[key] for o in self.obs]) for key in self.obs[0]},
            "actions": stack(self.actions), "logprobs": stack(self.logprobs), "values": stack(self.values),
            "rewards": stack(self.rewards), "step_rewards": stack(self.step_rewards),
            "step_mask": stack(self.step_mask), "terminated": stack(self.terminated),
            "truncated": stack(self.truncated), "final_values": stack(self.final_values),
            "bootstrap_values": self.bootstrap,
        }
        if self.extras and self.extras[0]:
            out["extras"] = {key: stack([e[key] for e in self.extras]) for key in self.extras[0]}
        return out


class _RunningEpisodes:
    """The return and length so far of each env's episode in progress, in one stage.

    Every iteration starts by resetting every env, so both start at zero with the collection;
    the step results' per-action rewards are summed in float64, action by action in the order
    the env ran them, as the env's own episode statistics are (:meth:`VectorEnv.open_episodes`).
    Lengths count env steps (the actions that ran), not decisions."""

    def __init__(self):
        self.returns: np.ndarray | None = None
        self.lengths: np.ndarray | None = None

    def add(self, msg: dict) -> None:
        step_rewards, step_mask = msg["step_rewards"], msg["step_mask"]
        if self.returns is None:
            self.returns = np.zeros(len(step_rewards), np.float64)
            self.lengths = np.zeros(len(step_rewards), np.int64)
        for k in range(step_rewards.shape[1]):
            self.returns += np.where(step_mask[:, k], step_rewards[:, k], 0.0)
        self.lengths += step_mask.sum(axis=1)
        ended = msg["terminated"] | msg["truncated"]
        self.returns[ended] = 0.0
        self.lengths[ended] = 0


def _open_episodes(stages: list[_RunningEpisodes]) -> dict[str, np.ndarray]:
    """Per env of the rank (stage order, as the trajectory's env axis): the running episode's
    return so far (float64) and steps so far (int64); 0 and 0 where none is running."""
    return {"return": np.concatenate([s.returns for s in stages]),
            "length": np.concatenate([s.lengths for s in stages])}


def _concat_stages(parts: list[dict]) -> dict:
    """Stage buffers -> one ``[T, n_rank, ...]`` trajectory (env axis 1; bootstrap axis 0)."""
    out: dict[str, Any] = {}
    for key, first in parts[0].items():
        if isinstance(first, dict):
            out[key] = {k: np.concatenate([p[key][k] for p in parts], axis=1) for k in first}
        elif key == "bootstrap_values":
            out[key] = np.concatenate([p[key] for p in parts])
        else:
            out[key] = np.concatenate([p[key] for p in parts], axis=1)
    return out


class EmbodiedRolloutWorker(Worker, WeightSink):
    """One rollout rank: the policy (inference copy), its env endpoint, evaluation and videos.

    The policy runs on the device the placement gives this rank (``device="auto"``) or on the CPU
    (``device="cpu"``); observations go to it and actions come back to host memory each step."""

    def __init__(self, env_spec: EnvSpec, policy_spec: PolicySpec, observation_spec: dict, action_space,
                 seed: int, host_env: bool, num_threads: int = 1, compile_act: bool = False,
                 device: str = "auto"):
        limit_threads(num_threads)
        self.env_spec, self.policy_spec, self.seed = env_spec, policy_spec, seed
        self.observation_spec, self.action_space = observation_spec, action_space
        self.compute = compute_device(self.device, device)
        self.policy = policy_spec.build(observation_spec, action_space).to(self.compute).eval()
        self.env = StagedEnv(env_spec, self.rank) if host_env else None
        self.links: list = []
        self.stage_link: list[int] = []
        self._eval_env = None
        # Collection only: evaluation batches vary in size (each would compile anew) and are rare.
        self._act = compiled_act(self.policy) if compile_act else self.policy.act
        self._act_compiled = bool(compile_act)

    def compute_device(self) -> str:
        """Where this rank's policy is (``"cpu"``, ``"cuda:0"``), read off its parameters."""
        return str(module_device(self.policy))

    # ---------------------------------------------------------------- wiring
    def connect_link(self, address: dict) -> None:
        """Connect to this rank's env: one address, or ``{"stages": [...]}`` (a link per stage process)."""
        stages = self.env_spec.stages
        if "stages" in address:
            self.connect_links([(a, [s]) for s, a in enumerate(address["stages"])])
        else:
            self.connect_links([(address, list(range(stages)))])

    def connect_links(self, parts: list[tuple[dict, list[int]]]) -> None:
        """Connect to the env ranks that serve this rank: (address, the stages it serves) each;
        together they serve every stage once. Closes the links of an earlier layout first (online
        scaling re-links between iterations)."""
        from infinirl.components.env_link import connect

        served = sorted(s for _, stages in parts for s in stages)
        if served != list(range(self.env_spec.stages)):
            raise ValueError(f"env links serve stages {served}; this rank has stages 0-{self.env_spec.stages - 1}")
        self._close_links()
        self.links = [connect(address) for address, _ in parts]
        self.stage_link = [0] * self.env_spec.stages
        for index, (_, stages) in enumerate(parts):
            for stage in stages:
                self.stage_link[stage] = index

    def load_weights(self, named_tensors, version: int) -> None:
        own = self.policy.state_dict()
        with torch.no_grad():
            for name, tensor in named_tensors:
                if name not in own:
                    raise KeyError(f"weight {name!r} from the trainer has no place in the rollout policy")
                own[name].copy_(tensor)

    # ---------------------------------------------------------------- collection
    @torch.no_grad()
    def collect(self, iteration: int, seeds: list[int], num_steps: int) -> dict:
        """``num_steps`` decisions for every env of this rank; the trajectory as numpy arrays."""
        self.check_weights()  # never act on weights a failed load left half-replaced
        start = time.perf_counter()
        torch.manual_seed(int(np.random.default_rng([self.seed, iteration, self.rank, 0xAC7]).integers(2**62)))
        if self.env is not None:
            endpoint = _LocalEndpoint(self.env, seeds)
        else:
            if not self.links:
                raise RuntimeError("collect() with a remote env before connect_link()")
            endpoint = _RemoteEndpoint(self.links, self.stage_link)
        counted = [link for link in self.links if hasattr(link, "bytes_sent")] if self.env is None else []
        sent = sum(link.bytes_sent for link in counted)
        try:
            trajectory = self._collect(endpoint, iteration, num_steps)
            if counted:  # this rank's actions to its env ranks (socket links count what they send)
                trajectory["timing"]["rollout/bytes_out"] = float(sum(link.bytes_sent for link in counted) - sent)
            # The collection's own wall time: the driver's wait for a trajectory collected ahead of
            # the trainer (asynchronous runs) is no measure of it
            trajectory["timing"]["rollout/collect_s"] = time.perf_counter() - start
            return trajectory
        except BaseException:
            # Close the links so the env side stops waiting for actions that will never come; it
            # then fails with EnvLinkClosed, which the runner knows is not the root cause.
            self._close_links()
            raise

    def _collect(self, endpoint, iteration: int, num_steps: int) -> dict:
        """Serve every stage ``num_steps + 1`` times (the last result only bootstraps values), each
        in turn, or, over a link per stage process, as soon as its result is there
        (``_RemoteEndpoint.ready``): a stage whose simulation finished first is not kept waiting
        behind a slower one. The order of service does not change what is
        collected: each decision draws its noise from a seed of its own stage and step
        (:meth:`_decision_seeds`; its held part, if any, from one of its stage and window),
        and each stage records into its own buffer."""
        chunk = self.policy.chunk
        stages = endpoint.num_stages
        buffers = [_StageBuffer() for _ in range(stages)]
        episodes = [{"return": [], "length": [], "success": []} for _ in range(stages)]
        running = [_RunningEpisodes() for _ in range(stages)]
        seeds = self._decision_seeds(iteration, stages)
        generator = _sampling_generator(module_device(self.policy))
        held_every = int(getattr(self.policy, "held_noise_every", 0))  # a policy holding part of its noise
        steps_done = [0] * stages
        active = list(range(stages))
        restarted = 0
        infer_s = wait_s = record_s = 0.0
        cpu_start = time.thread_time()  # this loop's own CPU time: is the rollout CPU-bound?
        while active:
            if endpoint.any_order:
                start = time.perf_counter()
                ready = endpoint.ready(active)
                wait_s += time.perf_counter() - start
            else:  # in turn: the stage with the fewest steps served (the lowest on a tie)
                ready = [min(active, key=lambda s: (steps_done[s], s))]
            for stage in ready:
                t, buf = steps_done[stage], buffers[stage]
                start = time.perf_counter()
                msg = endpoint.recv(stage)
                wait_s += time.perf_counter() - start
                start = time.perf_counter()
                obs = array_obs(msg["obs"])
                tensors = prepare_obs(obs, self.compute)
                steps_done[stage] = t + 1
                if t == num_steps:
                    active.remove(stage)
                    self._record_result(buf, msg, episodes[stage], running[stage])
                    restarted += msg["restarted"]
                    buf.bootstrap = self._values(tensors, next(iter(obs.values())).shape[0])
                    infer_s += time.perf_counter() - start
                    continue
                generator.manual_seed(seeds[stage] + t)
                if held_every:
                    self.policy.hold_noise(_held_noise_seed(seeds[stage], t // held_every))
                step = self._act(tensors)
                policy_actions = host(step.actions)  # one copy off the device, for the env and the record
                actions = env_actions(policy_actions, chunk)
                infer_s += time.perf_counter() - start
                # The env waits for these actions: send first, record afterwards (off its critical path).
                endpoint.send(stage, actions, autoreset=t < num_steps - 1)
                start = time.perf_counter()
                if t > 0:
                    self._record_result(buf, msg, episodes[stage], running[stage])
                    restarted += msg["restarted"]
                buf.obs.append(obs)
                buf.actions.append(policy_actions)
                buf.logprobs.append(host(step.logprobs).astype(np.float32))
                n = step.actions.shape[0]
                buf.values.append(np.zeros(n, np.float32) if step.values is None
                                  else host(step.values).astype(np.float32))
                buf.extras.append({k: host(v) for k, v in step.extras.items()})
                record_s += time.perf_counter() - start
        trajectory = _concat_stages([buf.stacked() for buf in buffers])
        trajectory["version"] = self.weight_version
        trajectory["episodes"] = {key: np.asarray([x for stage in episodes for x in stage[key]])
                                  for key in episodes[0]}
        trajectory["open_episodes"] = _open_episodes(running)
        trajectory["timing"] = {"rollout/inference_s": infer_s, "rollout/wait_env_s": wait_s,
                                "rollout/record_s": record_s, "rollout/cpu_s": time.thread_time() - cpu_start,
                                "rollout/peak_memory_bytes": peak_memory_bytes(self.compute),
                                "rollout/act_compiled": float(self._act_compiled)}  # which path produced the timings
        trajectory["restarted"] = restarted
        return trajectory

    def _decision_seeds(self, iteration: int, stages: int) -> list[int]:
        """Per stage, the seed of its first decision this iteration; step ``t`` uses ``seed + t``."""
        return [int(np.random.default_rng([self.seed, iteration, self.rank, stage, 0xD0]).integers(2**62))
                for stage in range(stages)]

    def _values(self, tensors: dict, n: int) -> np.ndarray:
        if not getattr(self.policy.policy, "has_value_head", False):
            return np.zeros(n, np.float32)
        return host(self.policy.value(tensors)).astype(np.float32)

    def _record_result(self, buf: _StageBuffer, msg: dict, episodes: dict, running: _RunningEpisodes) -> None:
        running.add(msg)
        n = len(msg["reward"])
        buf.rewards.append(msg["reward"])
        buf.step_rewards.append(msg["step_rewards"])
        buf.step_mask.append(msg["step_mask"])
        buf.terminated.append(msg["terminated"])
        buf.truncated.append(msg["truncated"])
        final_values = np.zeros(n, np.float32)
        ended = msg["ended"]
        if len(ended):
            truncated = msg["truncated"][ended]
            if truncated.any():  # truncated episodes bootstrap from V(final obs)
                rows = ended[truncated]
                final = {k: v[truncated] for k, v in array_obs(msg["final_obs"]).items()}
                final_values[rows] = self._values(prepare_obs(final, self.compute), len(rows))
            episodes["return"].extend(msg["episode_return"].tolist())
            episodes["length"].extend(msg["episode_length"].tolist())
            episodes["success"].extend(msg["episode_success"].tolist())
        buf.final_values.append(final_values)

    # ---------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, seeds: list[int], num_envs: int, deterministic: bool = True,
                 env_kwargs: dict | None = None, max_episode_steps: int | None = None) -> dict:
        """One episode per seed (held-out seeds) with the (deterministic) policy; episode stats."""
        self.check_weights()  # never act on weights a failed load left half-replaced
        if self._eval_env is None or self._eval_env.num_envs != num_envs:
            if self._eval_env is not None:
                self._eval_env.close()
            self._eval_env = self.env_spec.build(num_envs, stage=99, num_workers=0, max_episode_steps=max_episode_steps,
                                                 **(env_kwargs or {}))
        result = run_eval_episodes(self.policy, self._eval_env, seeds, deterministic)
        return result

    @torch.no_grad()
    def record_video(self, seeds: list[int], path: str, frame_skip: int = 1, fps: int = 30,
                     env_kwargs: dict | None = None, deterministic: bool = True,
                     max_episode_steps: int | None = None) -> dict:
        """Render one episode per seed into an mp4 (MuJoCo frames on CPU via osmesa/egl)."""
        self.check_weights()  # never act on weights a failed load left half-replaced
        from infinirl.envs.video import write_mp4

        env = self.env_spec.build(1, stage=98, num_workers=0, max_episode_steps=max_episode_steps, **(env_kwargs or {}))
        frames, successes = [], []
        try:
            for seed in seeds:
                obs = env.reset(seeds=[int(seed)])
                frames.append(env.render()[0])
                done, t = False, 0
                while not done:
                    step = self.policy.act(prepare_obs(array_obs(obs), self.compute), deterministic=deterministic)
                    result = env.step(env_actions(step.actions, self.policy.chunk), autoreset=False)
                    done, t = bool(result.done[0]), t + 1
                    # The episode's last frame whatever the frame skip: it shows how the episode
                    # ended (the success). Stepped with autoreset=False, the env still holds that
                    # final state to render.
                    if done or t % frame_skip == 0:
                        frames.append(env.render()[0])
                    if done:
                        successes.append(bool(result.info["episode_success"][0]))
                    obs = result.obs
        finally:
            env.close()
        write_mp4(path, frames, fps)
        return {"path": path, "frames": len(frames), "episode_success": successes}

    def close(self) -> None:
        for env in (self.env, self._eval_env):
            if env is not None:
                env.close()
        self._close_links()

    def _close_links(self) -> None:
        for link in self.links:
            link.close()
        self.links = []


def run_eval_episodes(policy, env, seeds: list[int], deterministic: bool = True) -> dict:
    """Run one episode per seed on ``env`` (rounds of ``env.num_envs``); success/return/length.

    Where the env's sub-envs run different tasks (``env.task_names``, e.g. ``metaworld:reach-v3,
    push-v3``), also ``eval/success/<task>`` and ``eval/episodes/<task>`` for each task.

    The policy's own randomness (a flow policy's initial noise, even when acting deterministically)
    is seeded from the episode seeds on a forked RNG: the same weights on the same seeds score the
    same in every run and at every evaluation, and training's random stream is left as it was."""
    device = module_device(policy)
    cuda = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=cuda):
        torch.manual_seed(int(seeds[0]) if len(seeds) else 0)
        return _eval_episodes(policy, env, seeds, deterministic, device)


def _eval_episodes(policy, env, seeds: list[int], deterministic: bool, device: torch.device) -> dict:
    num_envs = env.num_envs
    chunk = policy.chunk
    successes, returns, lengths, tasks = [], [], [], []
    task_names = getattr(env, "task_names", None)
    for start in range(0, len(seeds), num_envs):
        batch = [int(s) for s in seeds[start:start + num_envs]]
        used = len(batch)
        obs = env.reset(seeds=batch + [batch[-1]] * (num_envs - used))
        active = np.arange(num_envs) < used
        while active.any():
            step = policy.act(prepare_obs(array_obs(obs), device), deterministic=deterministic)
            # autoreset=False: an env runs one episode per round; the next round resets it anyway
            result = env.step(env_actions(step.actions, chunk), env_mask=active, autoreset=False)
            ended = np.flatnonzero(result.done & active)
            for i in ended:
                successes.append(bool(result.info["episode_success"][i]))
                returns.append(float(result.info["episode_return"][i]))
                lengths.append(int(result.info["episode_length"][i]))
                tasks.append(task_names[i] if task_names else None)
            active &= ~result.done
            obs = result.obs
    metrics = {"eval/success_rate": float(np.mean(successes)), "eval/return_mean": float(np.mean(returns)),
               "eval/length_mean": float(np.mean(lengths)), "eval/episodes": len(successes)}
    return {**metrics, **task_success_metrics(successes, tasks)}


def merge_task_success(results: list[dict]) -> dict:
    """Per-task success of evaluations run in parts (one per rollout rank), weighted by each part's
    episodes of that task: ``eval/success/<task>`` and ``eval/episodes/<task>``."""
    counts: dict[str, float] = {}
    successes: dict[str, float] = {}
    for result in results:
        for key, value in result.items():
            if key.startswith("eval/episodes/"):
                task = key[len("eval/episodes/"):]
                counts[task] = counts.get(task, 0.0) + value
                successes[task] = successes.get(task, 0.0) + value * result[f"eval/success/{task}"]
    merged = {}
    for task, count in counts.items():
        merged[f"eval/success/{task}"] = successes[task] / count
        merged[f"eval/episodes/{task}"] = count
    return merged
