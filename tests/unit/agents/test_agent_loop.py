"""The multi-turn agent loop on the real HF engine and a tiny random Llama (byte tokenizer).

Single characters serve as the environment's stop strings, so the random model really ends turns
at them and the loop really runs several turns per trajectory."""

import threading
import time
from dataclasses import replace

import pytest
import torch

from infinirl.agents.loop import AgentBudget, AgentEnv, AgentRollout, AgentStep, agent_metrics, request_context
from infinirl.data.batch import ATTENTION_MASK, INPUT_IDS, POSITION_IDS, RESPONSE_MASK, ROLLOUT_LOGPROBS, pack_sequences
from infinirl.engines.base import SamplingParams
from infinirl.engines.hf_generate import HFGenerateEngine
from infinirl.engines.seeds import turn_seed
from infinirl.models.hf_causal_lm import tiny_causal_lm
from tests.unit.agents.scripted import ScriptedEngine

PROMPTS = [[5, 6, 7, 8, 9], [20, 21], [30, 31, 32]]
MANY = [[10 + i, 40 + 2 * i, 7] for i in range(16)]
STOPS = tuple("abcdefghijklmnopqrstuvwxyz0123456789")


class CountingEnv(AgentEnv):
    """Answers each turn with a fixed observation; ends the trajectory at its ``done_after``-th step."""

    stop_strings = STOPS

    def __init__(self, observation="<r>ok</r>", done_after=99, delay=0.0, fail_at=None):
        self.observation, self.done_after, self.delay, self.fail_at = observation, done_after, delay, fail_at
        self.turns: list[str] = []
        self.closed = False

    def reset(self, problem):
        self.problem = problem

    def step(self, turn):
        self.turns.append(turn)
        time.sleep(self.delay)
        if self.fail_at == len(self.turns):
            raise RuntimeError("tool broke")
        return AgentStep(observation=self.observation, done=len(self.turns) >= self.done_after)

    def close(self):
        self.closed = True


@pytest.fixture(scope="module", autouse=True)
def single_thread(one_torch_thread):
    """Every test here runs on one torch thread (see the fixture)."""


@pytest.fixture(scope="module")
def tiny(tiny_byte_llama):
    return tiny_byte_llama


@pytest.fixture
def engine(tiny):
    model, tokenizer = tiny
    return HFGenerateEngine(model, tokenizer, max_batch_size=64, eos_token_ids=[])


def rollout(tiny, engine, budget, make_env=CountingEnv, prompts=PROMPTS, sampling=None, problems=None):
    _, tokenizer = tiny
    sampling = sampling or SamplingParams(n=2, max_new_tokens=16, seed=3)
    return AgentRollout(engine, tokenizer, make_env, budget).generate(prompts, sampling, problems)


def test_multi_turn_logprobs_equal_the_trainers_on_model_tokens_only(tiny, engine):
    model, tokenizer = tiny
    results = rollout(tiny, engine, AgentBudget(max_turns=4, max_response_tokens=80, schedule="lockstep"))
    assert len(results) == len(PROMPTS) * 2
    assert max(r.extra["agent"]["turns"] for r in results) >= 2
    assert any(0 in r.response_mask for r in results)
    batch = pack_sequences([r.prompt_ids for r in results], [r.response_ids for r in results],
                           tokenizer.pad_token_id, [r.response_logprobs for r in results],
                           [r.response_mask for r in results])
    with torch.no_grad():
        logits = model(input_ids=batch[INPUT_IDS], attention_mask=batch[ATTENTION_MASK],
                       position_ids=batch[POSITION_IDS]).logits.float()
    scored = torch.zeros_like(batch[ROLLOUT_LOGPROBS])
    scored[:, 1:] = torch.log_softmax(logits[:, :-1], dim=-1).gather(-1, batch[INPUT_IDS][:, 1:, None]).squeeze(-1)
    mask = batch[RESPONSE_MASK].bool()
    torch.testing.assert_close(batch[ROLLOUT_LOGPROBS][mask], scored[mask], atol=1e-5, rtol=0)
    observation = tokenizer.encode("<r>ok</r>", add_special_tokens=False)
    for r in results:
        inserted = [i for i, m in zip(r.response_ids, r.response_mask) if not m]
        assert inserted == observation * (len(inserted) // len(observation))
        assert len(inserted) <= len(observation) * r.extra["agent"]["env_steps"]
        assert all(lp == 0.0 for lp, m in zip(r.response_logprobs, r.response_mask) if not m)
        assert r.response_mask[-1] == 1  # a trajectory ends with the model's turn


def test_each_turn_continues_from_the_exact_ids_so_far(tiny, engine):
    """The env sees the decoded turn; the next turn's context is prompt + every id, none re-tokenised."""
    _, tokenizer = tiny
    envs = []

    def make_env():
        envs.append(CountingEnv(done_after=2))
        return envs[-1]

    results = rollout(tiny, engine, AgentBudget(max_turns=4, max_response_tokens=200, schedule="lockstep"),
                      make_env=make_env, sampling=SamplingParams(n=1, max_new_tokens=16, seed=5))
    for env, result in zip(envs, results):
        model_turns, run = [], []
        for token, m in zip(result.response_ids, result.response_mask):
            if m:
                run.append(token)
            elif run:
                model_turns.append(run)
                run = []
        model_turns.append(run)
        assert [tokenizer.decode(t, skip_special_tokens=False) for t in model_turns][:len(env.turns)] == env.turns
        assert env.closed


def test_lockstep_is_reproducible_and_async_greedy_matches_it(tiny, engine):
    budget = AgentBudget(max_turns=3, max_response_tokens=60, schedule="lockstep")
    def sampled(results):  # everything but the timings
        return [(r.response_ids, r.response_logprobs, r.response_mask, r.finish_reason) for r in results]

    assert sampled(rollout(tiny, engine, budget)) == sampled(rollout(tiny, engine, budget))
    greedy = SamplingParams(n=1, max_new_tokens=12, greedy=True)
    lockstep = rollout(tiny, engine, budget, sampling=greedy)
    asynchronous = rollout(tiny, engine, AgentBudget(max_turns=3, max_response_tokens=60, schedule="async"),
                           make_env=lambda: CountingEnv(delay=0.01), sampling=greedy)
    strip = [(r.response_ids, r.response_mask) for r in lockstep]
    assert [(r.response_ids, r.response_mask) for r in asynchronous] == strip


def test_budgets_bound_turns_tokens_and_observations(tiny, engine):
    results = rollout(tiny, engine, AgentBudget(max_turns=2, max_response_tokens=40, max_observation_tokens=6),
                      make_env=lambda: CountingEnv(observation="x" * 50))
    for r in results:
        assert r.extra["agent"]["turns"] <= 2
        assert len(r.response_ids) <= 40
        inserted = len(r.response_mask) - sum(r.response_mask)
        assert inserted <= 6 * r.extra["agent"]["env_steps"]
    assert any(r.finish_reason == "length" for r in results)


def test_a_raising_tool_is_shown_to_the_model_and_counted(tiny, engine):
    _, tokenizer = tiny
    results = rollout(tiny, engine, AgentBudget(max_turns=4, max_response_tokens=120),
                      make_env=lambda: CountingEnv(fail_at=1))
    called = [r for r in results if r.extra["agent"]["env_steps"]]
    assert called and all(r.extra["agent"]["env_errors"] == 1 for r in called)
    text = tokenizer.decode([i for i, m in zip(called[0].response_ids, called[0].response_mask) if not m])
    assert "tool broke" in text
    assert agent_metrics(results)["agent/env_error_rate"] > 0


def test_async_overlaps_environment_steps_with_generation(tiny, engine):
    """While one trajectory's tool runs, others are generated: more than one env step is in
    flight at a time, and every trajectory completes."""
    running, peak, lock = [0], [0], threading.Lock()

    class SlowEnv(CountingEnv):
        def step(self, turn):
            with lock:
                running[0] += 1
                peak[0] = max(peak[0], running[0])
            try:
                return super().step(turn)
            finally:
                with lock:
                    running[0] -= 1

    results = rollout(tiny, engine, AgentBudget(max_turns=3, max_response_tokens=60, concurrency=8),
                      make_env=lambda: SlowEnv(delay=0.05))
    assert len(results) == 6 and peak[0] > 1
    metrics = agent_metrics(results)
    assert metrics["agent/turns_mean"] >= 1 and metrics["agent/env_s_total"] > 0


def test_pack_sequences_masks_inserted_tokens_and_checks_lengths():
    batch = pack_sequences([[1, 2]], [[3, 4, 5]], 0, [[-1.0, 0.0, -2.0]], [[1, 0, 1]])
    assert batch[RESPONSE_MASK].tolist() == [[0, 0, 1, 0, 1]]
    with pytest.raises(ValueError, match="response mask of 2"):
        pack_sequences([[1]], [[3, 4, 5]], 0, None, [[1, 0]])
    with pytest.raises(ValueError, match="one entry"):
        pack_sequences([[1]], [[3]], 0, None, [])


def test_budget_rejects_nonsense():
    with pytest.raises(ValueError, match="max_turns"):
        AgentBudget(max_turns=0)
    with pytest.raises(ValueError, match="schedule"):
        AgentBudget(schedule="parallel")


def test_async_steps_that_finish_together_share_a_generate_call(tiny, engine):
    """Tools of similar latency (here 50-100 ms, 10 ms apart) finish together: the async schedule
    batches their next turns as lock-step does, instead of one generate call per trajectory."""
    calls = {"lockstep": 0, "async": 0}

    class Counting(HFGenerateEngine):
        schedule = "lockstep"

        def generate(self, prompts, sampling):
            calls[self.schedule] += 1
            return super().generate(prompts, sampling)

    model, tokenizer = tiny
    for schedule in calls:
        counting = Counting(model, tokenizer, max_batch_size=64, eos_token_ids=[])
        counting.schedule = schedule
        budget = AgentBudget(max_turns=3, max_response_tokens=200, schedule=schedule, batch_window_s=0.5)
        delays = iter([0.05 + 0.01 * (i % 6) for i in range(len(MANY))])
        results = AgentRollout(counting, tokenizer, lambda d=delays: CountingEnv(delay=next(d), done_after=2),
                               budget).generate(MANY, SamplingParams(n=1, max_new_tokens=8, greedy=True))
        assert sum(r.extra["agent"]["env_steps"] for r in results) >= 8  # enough trajectories call the env
    assert calls["async"] <= calls["lockstep"] + 1


class LongestRequest(HFGenerateEngine):
    """The HF engine, noting the most tokens any of its generate calls asked it to hold."""

    longest = 0

    def generate(self, prompt_token_ids, sampling):
        self.longest = max(self.longest, max(len(p) for p in prompt_token_ids) + sampling.max_new_tokens)
        return super().generate(prompt_token_ids, sampling)


@pytest.mark.parametrize("schedule", ["async", "lockstep"])
def test_no_call_asks_the_engine_for_more_than_request_context(tiny, schedule):
    # what a vLLM engine's max_model_len is sized from: a call must never need more
    model, tokenizer = tiny
    engine = LongestRequest(model, tokenizer, max_batch_size=64, eos_token_ids=[])
    budget = AgentBudget(max_turns=6, max_response_tokens=30, schedule=schedule)
    results = rollout(tiny, engine, budget, prompts=MANY, sampling=SamplingParams(n=2, max_new_tokens=16, seed=5))
    assert max(r.extra["agent"]["turns"] for r in results) >= 2
    bound, _ = request_context(("prompt", max(len(p) for p in MANY)), ("max_new_tokens", 16), budget)
    assert 0 < engine.longest <= bound
    if schedule == "lockstep":  # reproducible: a call asked a nearly full trajectory for a whole turn
        assert engine.longest > max(len(p) for p in MANY) + budget.max_response_tokens


def test_a_trajectory_that_fills_the_context_ends_as_cut_off_instead_of_failing():
    """Every turn's room is bounded by what is left of the model's context (48 positions here, far
    below the response budget): the trajectories end with finish reason length, none fails."""
    model, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0, max_positions=48)
    engine = HFGenerateEngine(model, tokenizer, max_batch_size=64, eos_token_ids=[])
    budget = AgentBudget(max_turns=40, max_response_tokens=400)
    for schedule in ("lockstep", "async"):
        results = AgentRollout(engine, tokenizer, CountingEnv, replace(budget, schedule=schedule)).generate(
            [[5, 6, 7, 8, 9], [20, 21] * 10], SamplingParams(n=2, max_new_tokens=16, seed=3))
        for r in results:
            assert len(r.prompt_ids) + len(r.response_ids) <= 48
            assert r.finish_reason == "length"
        assert max(r.extra["agent"]["turns"] for r in results) >= 2
        assert max(len(r.prompt_ids) + len(r.response_ids) for r in results) >= 44



def test_trajectories_short_of_context_get_a_generate_call_of_their_own_size(tiny):
    """One call's max_new_tokens applies to every prompt in it: a trajectory with less context left
    goes into a call as long as its room, with a seed of its own."""
    _, tokenizer = tiny
    engine = ScriptedEngine(tokenizer, ["ab", "cd", "ef", "gh"])
    engine.context_length = 30
    results = AgentRollout(engine, tokenizer, CountingEnv, AgentBudget(max_turns=3, schedule="lockstep")).generate(
        [[1] * 3, [1] * 20], SamplingParams(n=1, max_new_tokens=16, seed=3))
    (first, first_sampling), (second, second_sampling) = engine.calls[:2]
    assert [len(p) for p in first] == [3] and first_sampling.max_new_tokens == 16
    assert [len(p) for p in second] == [20] and second_sampling.max_new_tokens == 10
    assert first_sampling.seed == turn_seed(3, 0) and second_sampling.seed == turn_seed(3, 1)
    assert engine.calls[2][1].seed == turn_seed(3, 2)  # the next turn's call: no seed used twice
    assert all(len(r.prompt_ids) + len(r.response_ids) <= 30 and r.finish_reason == "length" for r in results)
    assert results[1].extra["agent"]["turns"] == 1  # "<r>ok</r>" did not fit after its turn


class SleepyEnv(CountingEnv):
    """Its second step hangs for 5 s (a tool stuck past its own timeout)."""

    def step(self, turn):
        if len(self.turns) == 1:
            time.sleep(5)
        return super().step(turn)


@pytest.mark.parametrize("schedule", ["lockstep", "async"])
def test_a_step_past_its_time_limit_is_abandoned_and_ends_its_trajectory(tiny, engine, schedule):
    budget = AgentBudget(max_turns=4, max_response_tokens=120, step_timeout_s=0.3, schedule=schedule)
    start = time.monotonic()
    results = rollout(tiny, engine, budget, make_env=SleepyEnv)
    assert time.monotonic() - start < 4, "the rollout waited for the hanging steps"
    timed_out = [r for r in results if r.extra["agent"]["totals"].get("step_timeouts")]
    assert timed_out and all(r.finish_reason == "length" and r.extra["agent"]["env_errors"] >= 1 for r in timed_out)
    assert all(r.extra["agent"]["env_steps"] == 2 for r in timed_out)
    assert agent_metrics(results)["agent/step_timeouts_mean"] > 0


def test_an_observation_over_the_budget_is_cut_in_its_cuttable_parts_only(tiny, engine):
    _, tokenizer = tiny
    parts = (("<r>", False), ("x" * 50, True), ("</r><r>", False), ("y" * 4, True), ("</r>\n", False))

    class Wrapped(CountingEnv):
        def step(self, turn):
            super().step(turn)
            return AgentStep(parts=parts)

    results = rollout(tiny, engine, AgentBudget(max_turns=2, max_response_tokens=200, max_observation_tokens=40),
                      make_env=Wrapped)
    inserted = [tokenizer.decode([i for i, m in zip(r.response_ids, r.response_mask) if not m]) for r in results]
    cut = "<r>" + "x" * (40 - 15 - 4 - 15) + " ...[truncated]</r><r>yyyy</r>\n"  # 15 wrapper ids, 4 of y, the marker
    assert cut in inserted and all(text in ("", cut) for text in inserted)
    assert AgentStep(parts=parts).observation == "".join(text for text, _ in parts)
    with pytest.raises(ValueError, match="join to observation"):
        AgentStep(observation="other", parts=parts)
