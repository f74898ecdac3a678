"""Reasoning RL (GRPO / Dr.GRPO / RLOO / REINFORCE++ / DAPO / PPO) on a Hugging Face model: the macro flow.

Read top to bottom: each step samples prompts, generates a group of responses per prompt, scores
them, runs the forward passes the update needs (reference log-probs for KL, critic values for
PPO), turns rewards into advantages, updates the actor (and the critic), and syncs the actor's
weights into the rollout engine with a new version. Where components run (collocated or not) is
placement, not code.

Asynchronous (``algorithm.asynchronous.max_staleness`` = eta): the batches of the next eta
iterations are generated and scored while the trainer works (:mod:`infinirl.runners.async_rollout`);
the weight sync only publishes, and the rollout ranks load the new version between requests.
"""

from __future__ import annotations

import itertools
import os
import sys
import time
import uuid
from dataclasses import dataclass, replace

import numpy as np
import torch

from infinirl.agents.loop import agent_metrics
from infinirl.algorithms import (
    TokenAdvantageInputs,
    aggregation_normaliser,
    compute_advantages,
    explained_variance,
    kl_penalty,
    masked_mean,
    masked_whiten,
    overlong_penalty,
)
from infinirl.algorithms.filters import group_is_informative
from infinirl.algorithms.metrics import MetricReducer
from infinirl.components.actor import ActorWorker
from infinirl.components.critic import CriticWorker
from infinirl.components.reference import ReferenceWorker
from infinirl.components.reward import RewardWorker
from infinirl.components.rollout import RolloutWorker
from infinirl.data.batch import ATTENTION_MASK, INPUT_IDS, POSITION_IDS, RESPONSE_MASK, pack_sequences
from infinirl.engines.base import SamplingParams
from infinirl.engines.vllm_options import with_context_length
from infinirl.runners import register_runner
from infinirl.runners.async_rollout import (
    RolloutAhead,
    WeightPusher,
    load_ahead_batches,
    partial_rollout_metrics,
    save_ahead_batches,
    staleness_metrics,
)
from infinirl.runners.curves import Panel
from infinirl.runners.loop import LoopSpec, ProgressField, RunLoop
from infinirl.runners.reasoning_config import ReasoningConfig
from infinirl.runners.reasoning_data import build_problem_sources, encode_checked
from infinirl.runners.run_support import run_components, run_start_time
from infinirl.runtime import Channel, Tracer, sync_weights
from infinirl.tasks.sources import answer_format_for, verifier_for
from infinirl.utils.threads import spin_wait_env

# Batch keys filled before the update: log-probs of the policy before it (PPO's pi_old), of the
# reference (KL), and the critic's values and regression targets.
OLD_LOGPROBS, REF_LOGPROBS, VALUES, RETURNS = "old_logprobs", "ref_logprobs", "values", "returns"
# What a forward-only pass needs of a batch (the rest stays in the driver); the response mask lets
# the engine skip the LM head over prompt positions.
_FORWARD_KEYS = (INPUT_IDS, ATTENTION_MASK, POSITION_IDS, RESPONSE_MASK)
# Rollout engines that take changed-only weight syncs after a full one (a LoRA actor then sends its
# merged layers only); vLLM's sleep mode may discard weights, so it gets every weight each time.
CHANGED_ONLY_ENGINES = frozenset({"hf"})


@dataclass
class _Generation:
    """A generation + scoring in flight: its stream key, chunk count and workers' handles (the
    rollout ranks' first)."""

    key: str
    chunks: int
    handles: list
    rollout_handles: int = 0


@dataclass
class _AheadBatch:
    """One iteration's batch on its way (asynchronous mode): the prompts and their generation."""

    problems: list
    generation: _Generation


def preflight(cfg: ReasoningConfig):
    """The task's problems (its data files read and checked), the tokenizer and every eval prompt's
    length, in the driver before any worker starts (``infinirl validate`` runs it too; train prompts
    are checked as they are drawn); ``(train stream, eval problems, tokenizer)``."""
    train_stream, eval_problems, tokenizer = build_problem_sources(cfg)
    encode_checked(eval_problems, tokenizer, cfg.task.system_prompt, cfg.rollout.max_prompt_length, "eval",
                   cfg.task.few_shot)
    return train_stream, eval_problems, tokenizer


@register_runner("reasoning", ReasoningConfig, "GRPO/PPO-family RL with verifiable rewards on an HF causal LM",
                 preflight=preflight)
def run(cfg: ReasoningConfig) -> dict:
    if cfg.algorithm.asynchronous.max_staleness and cfg.algorithm.objective.is_cap is None:
        print(f"infinirl: algorithm.asynchronous.max_staleness={cfg.algorithm.asynchronous.max_staleness} trains on "
              "samples from older weights without an importance-weight correction; set algorithm.objective.is_cap "
              "(e.g. 2.0) to correct for it", file=sys.stderr, flush=True)
    with RunLoop(cfg, run_start_time()) as loop:
        train_stream, eval_problems, tokenizer = preflight(cfg)
        return run_components(
            cfg, loop, lambda plan: _launches(cfg),
            lambda groups, plan: ReasoningFlow(cfg, groups["actor"], groups["rollout"], groups["reward"], tokenizer,
                                               train_stream, eval_problems, critic=groups.get("critic"),
                                               reference=groups.get("reference")))


def _launches(cfg: ReasoningConfig) -> dict:
    """Every component's worker class and arguments, in a fixed order of names (they start at once,
    model loading overlapping)."""
    specs = {
        "actor": (ActorWorker, (cfg.model.path, cfg.actor, cfg.algorithm.objective, cfg.num_threads)),
        "rollout": (RolloutWorker, (cfg.model.path, cfg.model.rollout_dtype, cfg.rollout.max_batch_size,
                                    cfg.rollout.num_threads or cfg.num_threads, cfg.rollout.engine,
                                    with_context_length(cfg.rollout.engine, cfg.rollout.engine_options,
                                                        cfg.rollout_context()[0]),
                                    cfg.rollout.agent)),
        # Problems name their own verifier; this one (the task source's, as `infinirl eval` uses)
        # serves any that name none.
        "reward": (RewardWorker, (cfg.model.path, verifier_for(cfg.task, "test"), cfg.task.format_bonus,
                                  answer_format_for(cfg.task) or "marker")),
        "critic": (CriticWorker, (cfg.critic_model_path, cfg.critic, cfg.critic.value_clip, cfg.num_threads)),
        "reference": (ReferenceWorker, (cfg.model.path, _reference_engine(cfg), cfg.num_threads)),
    }
    spins = worker_process_env(cfg)
    return {name: (*specs[name], spins[name]) for name in cfg.components()}


def worker_process_env(cfg: ReasoningConfig) -> dict[str, dict[str, str]]:
    """Per component, the environment variables its processes start with: OpenMP spins briefly in
    a rank that computes with several threads (``spin_wait_env``): generation and the update are
    thousands of short parallel regions each, and under the workers' passive waiting every one of
    them would wake a sleeping helper thread."""
    rollout_threads = cfg.rollout.num_threads or cfg.num_threads
    return {"actor": spin_wait_env(cfg.num_threads), "rollout": spin_wait_env(rollout_threads),
            "reward": {}, "critic": spin_wait_env(cfg.num_threads), "reference": spin_wait_env(cfg.num_threads)}


def _reference_engine(cfg: ReasoningConfig):
    """The reference scores exactly like the initial actor: same dtype, temperature, chunking."""
    micro = cfg.reference.micro_batch_size or cfg.actor.micro_batch_size
    return replace(cfg.actor, micro_batch_size=micro)


class ReasoningFlow:
    """The step logic (the loop drives it: see :mod:`infinirl.runners.loop`); tests drive it directly too."""

    def __init__(self, cfg: ReasoningConfig, actor, rollout, reward, tokenizer, train_stream=None,
                 eval_problems=(), critic=None, reference=None):
        self.cfg, self.actor, self.rollout, self.reward, self.tokenizer = cfg, actor, rollout, reward, tokenizer
        self.train_stream, self.eval_problems = train_stream, list(eval_problems)
        self.critic, self.reference = critic, reference
        if cfg.uses_critic and critic is None:
            raise ValueError("algorithm.advantage=gae needs a critic group")
        if cfg.reference_mode == "separate" and reference is None:
            raise ValueError("reference.mode resolves to 'separate' but no reference group was given")
        self.tracer = Tracer()
        self.pad_id = tokenizer.pad_token_id if tokenizer.pad_token_id is not None else 0
        self._channels: dict[str, Channel] = {}
        self._generation_ids = itertools.count()
        eta = cfg.algorithm.asynchronous.max_staleness
        self.weights = WeightPusher(actor, rollout, asynchronous=eta is not None,
                                    interrupt=cfg.algorithm.asynchronous.partial_rollout,
                                    changed_only=(cfg.rollout.sync_changed_only
                                                  and cfg.rollout.engine in CHANGED_ONLY_ENGINES))
        self.ahead = None if eta is None else RolloutAhead(eta, cfg.iterations, self._submit_ahead,
                                                           self._collect_ahead, self.weights)
        self.spec = LoopSpec(
            name="reasoning", title="reasoning RL", headline="eval/greedy_accuracy",
            progress=(ProgressField(label="reward", key="rollout/reward_mean"),
                      ProgressField(label="acc", key="eval/greedy_accuracy")),
            panels=(Panel(title="train reward", y=("rollout/reward_mean",)),
                    Panel(title="held-out greedy accuracy", y=("eval/greedy_accuracy",), y_range=(-0.02, 1.02)),
                    Panel(title="response length (tokens)", y=("rollout/response_length_mean",))))

    def start(self, iteration: int) -> None:
        if iteration:  # resumed: the rollout engine still holds the initial weights
            sync_weights(self.actor, self.rollout, version=iteration)
            self.weights.sent_full()

    def step(self, step: int) -> dict:
        t0 = time.perf_counter()
        if self.ahead is not None:
            problems, results, rewards, gen_metrics = self.ahead.take(step)
        else:
            problems, results, rewards, gen_metrics = self.generate_batch(step)
        generate_s = gen_metrics.pop("time/rollout_generate_s")
        t_gen = time.perf_counter()
        batch = pack_sequences([r.prompt_ids for r in results], [r.response_ids for r in results],
                               self.pad_id, [r.response_logprobs for r in results],
                               [r.response_mask for r in results])
        self.score_tokens(batch)
        t_score = time.perf_counter()
        adv_metrics = self.add_advantages(batch, rewards)
        train_metrics = self.update(batch)
        t_train = time.perf_counter()
        sync_s, async_metrics, cfg_async = self.weights.push(step + 1), {}, self.cfg.algorithm.asynchronous
        if self.ahead is not None:
            async_metrics = staleness_metrics(step, [r.weight_version for r in results])
            if cfg_async.partial_rollout:
                async_metrics.update(partial_rollout_metrics(step, results))
        lengths = [len(r.response_ids) for r in results]
        return {
            **gen_metrics, **adv_metrics, **train_metrics, **async_metrics, **agent_metrics(results),
            "rollout/response_length_mean": float(np.mean(lengths)),
            "rollout/truncated_fraction": float(np.mean([r.finish_reason == "length" for r in results])),
            # The rollout ranks' own generation time: the trainer's wait (t_gen - t0) is near zero
            # when batches are generated ahead of it.
            "rollout/tokens_per_s": sum(r.sampled_count for r in results) / max(generate_s, 1e-9),
            "time/rollout_generate_s": generate_s,
            "rollout/max_staleness": float(step - min(r.weight_version for r in results)),
            "time/generate_and_score_s": t_gen - t0,
            "time/logprobs_and_values_s": t_score - t_gen,
            "time/train_s": t_train - t_score,
            "time/weight_sync_s": sync_s,
            "time/step_s": time.perf_counter() - t0,
        }

    # ------------------------------------------------------------------ asynchronous batches
    def _submit_ahead(self, step: int) -> _AheadBatch:
        problems = self.train_stream.next_batch(self.cfg.prompts_per_step)
        return _AheadBatch(problems, self.submit_generation(problems, self._sampling(step, 0)))

    def _collect_ahead(self, batch: _AheadBatch):
        results, scored, generate_s = self.collect_generation(batch.generation)
        rewards, zeroed = self.rewards_of(results, scored)
        errors = sum(s.error is not None for s in scored)
        metrics = self._reward_metrics(rewards.tolist(), errors, rounds=1, dropped=0, zeroed=zeroed)
        return batch.problems, results, rewards, {**metrics, "time/rollout_generate_s": generate_s}

    # ------------------------------------------------------------------ stages
    def generate_batch(self, step: int):
        """Prompts -> groups of responses -> rewards; with DAPO dynamic sampling, keep only
        informative groups and generate more rounds (capped) until the batch is full."""
        cfg = self.cfg
        want, group = cfg.prompts_per_step, cfg.rollout.group_size
        kept_problems, kept_results, kept_rewards = [], [], []
        rounds, dropped, errors, zeroed, generate_s = 0, 0, 0, 0, 0.0
        all_rewards = []
        while len(kept_problems) < want:
            problems = self.train_stream.next_batch(want - len(kept_problems) if rounds else want)
            results, scored, round_s = self.collect_generation(self.submit_generation(problems,
                                                                                      self._sampling(step, rounds)))
            generate_s += round_s
            rewards, round_zeroed = self.rewards_of(results, scored)
            all_rewards.extend(rewards.tolist())
            errors += sum(s.error is not None for s in scored)
            zeroed += round_zeroed
            for i, problem in enumerate(problems):
                block = slice(i * group, (i + 1) * group)
                informative = bool(group_is_informative(rewards[block], group)[0])
                if cfg.algorithm.dynamic_sampling and not informative and rounds < cfg.algorithm.max_extra_rounds:
                    dropped += 1
                    continue
                kept_problems.append(problem)
                kept_results.extend(results[block])
                kept_rewards.extend(rewards[block].tolist())
            rounds += 1
            if not cfg.algorithm.dynamic_sampling:
                break
        metrics = self._reward_metrics(all_rewards, errors, rounds, dropped, zeroed)
        metrics["time/rollout_generate_s"] = generate_s
        return kept_problems, kept_results, torch.tensor(kept_rewards), metrics

    def rewards_of(self, results, scored) -> tuple[torch.Tensor, int]:
        """The rewards trained on, and how many non-zero rewards of cut-off responses were zeroed
        (``algorithm.truncated_reward=zero``). Zeroed here, before DAPO's group filter and the
        advantages, so both see the rewards the update uses."""
        rewards = torch.tensor([s.reward for s in scored], dtype=torch.float32)
        if self.cfg.algorithm.truncated_reward != "zero":
            return rewards, 0
        cut = torch.tensor([r.finish_reason == "length" for r in results], dtype=torch.bool)
        zeroed = int((cut & (rewards != 0)).sum())
        return rewards.masked_fill(cut, 0.0), zeroed

    def _reward_metrics(self, rewards: list[float], errors: int, rounds: int, dropped: int, zeroed: int) -> dict:
        metrics = {
            "rollout/reward_mean": float(np.mean(rewards)),
            "rollout/accuracy": float(np.mean([r > 0.5 for r in rewards])),
            "rollout/reward_errors": float(errors),
            "rollout/generation_rounds": float(rounds),
            "rollout/dropped_groups": float(dropped),
        }
        if self.cfg.algorithm.truncated_reward == "zero":
            metrics["rollout/truncated_zeroed"] = float(zeroed)
        return metrics

    def generate_and_score(self, problems, sampling: SamplingParams, split: str = "train"):
        """Rollout -> reward -> driver, streamed through two channels: prompts are cut into chunks,
        rollout ranks put each generated chunk into ``generated`` as soon as it is done, reward ranks
        score chunks as they arrive and put them into ``scored``; the driver restores prompt order.
        The same code serves one process or many (placement only changes who runs what)."""
        results, scored, _ = self.collect_generation(self.submit_generation(problems, sampling, split))
        return results, scored

    def submit_generation(self, problems, sampling: SamplingParams, split: str = "train") -> _Generation:
        """Start :meth:`generate_and_score` without waiting. Each generation streams under its own
        channel key, so several can be in flight (batches ahead, an evaluation)."""
        prompt_ids = encode_checked(problems, self.tokenizer, self.cfg.task.system_prompt,
                                    self.cfg.rollout.max_prompt_length, split, self.cfg.task.few_shot)
        key = f"{split}-{next(self._generation_ids)}"
        per_chunk = self.cfg.rollout.stream_chunk_prompts or -(-len(problems) // self.rollout.world_size)
        chunks = [list(range(s, min(s + per_chunk, len(problems)))) for s in range(0, len(problems), per_chunk)]
        by_rank = _split(list(enumerate(chunks)), self.rollout.world_size)
        with_problems = self.cfg.rollout.agent is not None  # agent environments may need the problem
        handles = [self.rollout.call("generate_to", self.channels["generated"],
                                     [(i, [prompt_ids[j] for j in chunk]) for i, chunk in work], sampling, key,
                                     [[problems[j] for j in chunk] for _, chunk in work] if with_problems else None,
                                     ranks=[r])
                   for r, work in enumerate(by_rank) if work]
        generating = len(handles)
        chunk_problems = {i: [problems[j] for j in chunk for _ in range(sampling.n)] for i, chunk in enumerate(chunks)}
        counts = [len(part) for part in _split(list(range(len(chunks))), self.reward.world_size)]
        handles += [self.reward.call("score_stream", self.channels["generated"], self.channels["scored"],
                                     chunk_problems, count, key, ranks=[r]) for r, count in enumerate(counts) if count]
        return _Generation(key, len(chunks), handles, rollout_handles=generating)

    def collect_generation(self, generation: _Generation):
        """Wait for a generation's scored chunks: results and scores in prompt order, and the
        rollout ranks' own generation time (the longest rank's; they generate side by side)."""
        done: dict[int, tuple] = {}
        while len(done) < generation.chunks:
            try:
                index, results, scored = self.channels["scored"].get(key=generation.key, timeout=1.0)
                done[index] = (results, scored)
            except TimeoutError:
                for handle in generation.handles:  # a failed stage raises its root cause here instead of hanging
                    if handle.done():
                        handle.wait()
        returned = [handle.wait()[0] for handle in generation.handles]
        results = [r for i in range(generation.chunks) for r in done[i][0]]
        scored = [s for i in range(generation.chunks) for s in done[i][1]]
        return results, scored, max(returned[:generation.rollout_handles], default=0.0)

    def score_tokens(self, batch) -> None:
        """The forward passes the update needs, issued together (separate groups run at once):
        pi_old log-probs when the batch serves several updates or a KL reward, reference
        log-probs for KL, critic values for GAE."""
        cfg, pending = self.cfg, {}
        if self._needs_old_logprobs():
            pending[OLD_LOGPROBS] = self._scatter(self.actor, "compute_logprobs", batch)
        if cfg.reference_mode == "actor_base":
            pending[REF_LOGPROBS] = self._scatter(self.actor, "compute_ref_logprobs", batch)
        elif cfg.reference_mode == "separate":
            pending[REF_LOGPROBS] = self._scatter(self.reference, "compute_logprobs", batch)
        if self.critic is not None:
            pending[VALUES] = self._scatter(self.critic, "compute_values", batch)
        for key, handle in pending.items():
            batch[key] = torch.cat(handle.wait())

    def add_advantages(self, batch, rewards: torch.Tensor) -> dict:
        cfg, algo = self.cfg, self.cfg.algorithm
        mask = batch[RESPONSE_MASK]
        metrics = {}
        if algo.overlong_buffer:
            rewards = rewards + overlong_penalty(batch["response_lengths"], cfg.max_response_tokens,
                                                 algo.overlong_buffer, algo.overlong_penalty)
        token_rewards = None
        if algo.kl_reward_coef > 0:
            token_rewards = kl_penalty(batch[OLD_LOGPROBS], batch[REF_LOGPROBS], mask, algo.kl_reward_coef,
                                       algo.kl_reward_estimator)
            metrics["train/kl_in_reward"] = float(masked_mean(-token_rewards / algo.kl_reward_coef, mask))
        values = batch[VALUES] if VALUES in batch.keys() else None
        inputs = TokenAdvantageInputs(rewards=rewards, response_mask=mask, values=values,
                                      token_rewards=token_rewards, group_size=cfg.rollout.group_size)
        out = compute_advantages(algo.advantage, inputs, **algo.advantage_kwargs)
        advantages = masked_whiten(out.advantages, mask) if algo.whiten_advantages else out.advantages
        batch["advantages"] = advantages.float()
        metrics["train/advantage_abs_mean"] = float((advantages.abs() * mask).sum() / mask.sum().clamp(min=1))
        if self.critic is not None:
            batch[RETURNS] = out.returns.float()
            metrics["train/explained_variance"] = float(explained_variance(values, out.returns, mask))
            metrics["train/return_mean"] = float(masked_mean(out.returns, mask))
        return metrics

    def update(self, batch) -> dict:
        """Epochs x mini-batches optimizer steps; each mini-batch split over the actor's ranks
        (and, with a critic, the same mini-batch over the critic's ranks, at the same time)."""
        cfg, world = self.cfg, self.actor.world_size
        several = cfg.algorithm.mini_batches > 1 or cfg.algorithm.epochs > 1
        size = batch.batch_size[0]
        per_mini = size // cfg.algorithm.mini_batches
        actor_keys = [k for k in batch.keys() if k not in (VALUES, RETURNS)]
        steps = MetricReducer()  # means over the steps; a _max / _min key: the extreme of the steps
        for _ in range(cfg.algorithm.epochs):
            order = torch.randperm(size) if several else torch.arange(size)
            for start in range(0, size, per_mini):
                mini = batch[order[start : start + per_mini]]
                normaliser = aggregation_normaliser(
                    mini["response_mask"], cfg.algorithm.objective.aggregation,
                    **({"max_response_length": cfg.max_response_tokens}
                       if cfg.algorithm.objective.aggregation == "seq-mean-token-sum-norm" else {}))
                actor_mini = mini.select(*actor_keys)
                shares = [(actor_mini[s], normaliser) for s in _slices(per_mini, world)]
                handles = [self.actor.call_each("train_step", shares)]
                if self.critic is not None:
                    critic_mini = mini.select(*_FORWARD_KEYS, VALUES, RETURNS)
                    tokens = aggregation_normaliser(mini["response_mask"], "token-mean")
                    handles.append(self.critic.call_each(
                        "train_step", [(critic_mini[s], tokens) for s in _slices(per_mini, self.critic.world_size)]))
                metrics = {}
                for handle in handles:
                    metrics.update(handle.wait()[0])  # rank 0's: already combined over the ranks
                steps.add(metrics)
        return steps.result()

    def _needs_old_logprobs(self) -> bool:
        algo = self.cfg.algorithm
        return algo.mini_batches > 1 or algo.epochs > 1 or algo.kl_reward_coef > 0

    @staticmethod
    def _scatter(group, method: str, batch):
        """``method`` on every rank of ``group`` with its contiguous share of the batch's ids."""
        ids = batch.select(*_FORWARD_KEYS)
        return group.call_each(method, [(ids[s],) for s in _slices(batch.batch_size[0], group.world_size)])

    def evaluate(self) -> dict:
        metrics = {}
        if self.ahead is not None:
            # The batches in flight first (RolloutAhead.settle): their generation is training time.
            # Then the weight loads queued behind them, which the evaluation would queue behind
            # anyway: a load that failed raises its own error here instead of being evaluated past.
            start = time.perf_counter()
            self.ahead.settle()
            self.weights.wait()
            metrics["time/eval_drain_s"] = time.perf_counter() - start
        start = time.perf_counter()
        metrics["eval/greedy_accuracy"] = self.greedy_accuracy(self.eval_problems)
        metrics["time/eval_s"] = time.perf_counter() - start
        return metrics

    def greedy_accuracy(self, problems) -> float:
        if not problems:
            return float("nan")
        greedy = SamplingParams(n=1, max_new_tokens=self.cfg.rollout.max_new_tokens, greedy=True,
                                stop_strings=tuple(self.cfg.rollout.stop_strings))
        _, scored = self.generate_and_score(problems, greedy, split="eval")
        return float(np.mean([s.correct for s in scored]))

    def _sampling(self, step: int, round_: int) -> SamplingParams:
        r = self.cfg.rollout
        return SamplingParams(n=r.group_size, max_new_tokens=r.max_new_tokens, temperature=r.temperature,
                              top_p=r.top_p, top_k=r.top_k, stop_strings=tuple(r.stop_strings),
                              seed=(self.cfg.seed * 1_000_003 + step * 101 + round_) % (2**31))

    # ------------------------------------------------------------------ checkpoints
    def save(self, folder: str) -> dict:
        if self.ahead is not None:  # the batches generated ahead are part of the run's state
            save_ahead_batches(folder, self.ahead.drain())
        saving = [self.actor.save_checkpoint(os.path.join(folder, "actor"))]
        if self.critic is not None:
            saving.append(self.critic.save_checkpoint(os.path.join(folder, "critic")))
        for handle in saving:
            handle.wait()
        return {"data": self.train_stream.state_dict()}

    def load(self, folder: str, state: dict) -> None:
        loading = [self.actor.load_checkpoint(os.path.join(folder, "actor"))]
        if self.critic is not None:
            if not os.path.isdir(os.path.join(folder, "critic")):
                raise RuntimeError(
                    f"{folder} has no critic/ checkpoint (it was written by a run without a critic, i.e. not "
                    "algorithm.advantage=gae); resume it with its own algorithm, or start over with resume=false "
                    "or a new output_dir"
                )
            loading.append(self.critic.load_checkpoint(os.path.join(folder, "critic")))
        for handle in loading:
            handle.wait()
        self.train_stream.load_state_dict(state["data"])
        if self.ahead is not None:
            self.ahead.restore(load_ahead_batches(folder))

    def finish(self, output_dir: str) -> dict:
        self.weights.wait()
        summary = {"actor_weights_sha256": self.actor.weights_digest().wait()[0]}
        if self.critic is not None:
            summary["critic_weights_sha256"] = self.critic.weights_digest().wait()[0]
        return summary

    @property
    def channels(self) -> dict[str, Channel]:
        """The stages' streams, made on first use (unique names: flows may share a Ray cluster)."""
        if not self._channels:
            tag = uuid.uuid4().hex[:8]
            self._channels = {name: Channel.create(f"reasoning-{name}-{tag}", pipeline_depth=2)
                              for name in ("generated", "scored")}
        return self._channels

    def close(self) -> None:
        for channel in self._channels.values():
            channel.destroy()
        self._channels = {}


def _split(items: list, parts: int) -> list[list]:
    """Contiguous shards, so concatenated shard results keep the prompt order."""
    return [items[s] for s in _slices(len(items), parts)]


def _slices(size: int, parts: int) -> list[slice]:
    per = -(-size // parts)
    return [slice(i * per, min(size, (i + 1) * per)) for i in range(parts)]
