"""The reasoning runner end to end on a tiny random model: it runs, logs, checkpoints, resumes exactly."""

import json
import shutil

import pytest

from infinirl.config import to_dataclass
from infinirl.runners.async_rollout import load_ahead_batches
from infinirl.runners.reasoning import run
from infinirl.runners.reasoning_config import ReasoningConfig
from tests.integration.pins import check_pinned
from tests.integration.resume import killed_after_checkpoint


def _merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for key, value in extra.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def make_cfg(model_dir, output_dir, iterations, **extra):
    raw = {
        "iterations": iterations, "prompts_per_step": 2, "eval": {"every": 2}, "output_dir": str(output_dir),
        "save_every": 2, "loggers": ["tensorboard"],
        "model": {"path": model_dir},
        "rollout": {"group_size": 2, "max_new_tokens": 6},
        # A toy reward that varies with any output: a random tiny model never solves the task, and
        # all-zero rewards would leave weights unchanged (making the resume check vacuous).
        "task": {"eval_size": 2, "verifier": "infinirl.tasks.toy_rewards:response_length"},
        "actor": {"lr": 1e-3, "micro_batch_size": 2},
        "cluster": {"log_to_driver": False},
    }
    return to_dataclass(ReasoningConfig, _merge(raw, extra))


def test_runs_logs_and_resumes_exactly(ray_cluster, tiny_llama_dir, tmp_path):
    straight = run(make_cfg(tiny_llama_dir, tmp_path / "straight", iterations=4))
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    resumed = run(make_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=4))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]

    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 1, 2, 3, 4]
    assert all(r["train/grad_norm"] > 0 for r in rows[3:]), "the resumed half must move the weights"
    for key in ("rollout/reward_mean", "train/loss", "train/grad_norm", "train/logprob_mismatch_mean",
                "train/logprob_mismatch_max", "rollout/max_staleness", "time/train_s", "rollout/tokens_per_s"):
        assert key in rows[1], key
    assert rows[1]["train/logprob_mismatch_mean"] < 1e-3  # rollout and trainer agree on log-probs
    assert any(r["train/grad_norm"] > 0 for r in rows[1:])
    resumed_rows = [json.loads(line) for line in (tmp_path / "resumed" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in resumed_rows] == [0, 1, 2, 3, 4]
    for a, b in zip(rows[1:], resumed_rows[1:]):
        assert (a["rollout/reward_mean"] == b["rollout/reward_mean"]
                and a["train/loss"] == pytest.approx(b["train/loss"], abs=1e-7))
    assert (tmp_path / "straight" / "curves.png").exists()
    assert list((tmp_path / "straight" / "tensorboard").iterdir())
    check_pinned("reasoning", tmp_path / "straight", [
        "rollout/reward_mean", "rollout/response_length_mean", "train/loss", "train/grad_norm",
        "train/clip_fraction", "eval/greedy_accuracy"])


def read_rows(folder):
    return [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]


def assert_tokens_per_s_of_the_rollouts_own_time(rows, samples=4):
    """rollout/tokens_per_s is per second of the rollout ranks' own generation, not of the trainer's
    wait for its batch (near zero when batches are generated ahead): no agent, so every response
    token was sampled."""
    for r in rows:
        assert r["time/rollout_generate_s"] > 0
        assert r["rollout/tokens_per_s"] * r["time/rollout_generate_s"] == pytest.approx(
            samples * r["rollout/response_length_mean"], rel=1e-6)


PPO = {
    # PPO: a critic and GAE; KL both as a loss term and as a reward penalty, against a separate
    # reference (the actor trains in full, so its own weights are no reference).
    "algorithm": {"advantage": "gae", "advantage_kwargs": {"gamma": 1.0, "lam": 0.95}, "whiten_advantages": True,
                  "kl_reward_coef": 0.05, "objective": {"kl_coef": 0.05}},
    "critic": {"lr": 1e-3, "micro_batch_size": 2},
    "eval": {"every": 100}, "save_every": 1,
}


@pytest.mark.slow  # two runs of five components each
def test_ppo_with_critic_and_reference_resumes_exactly(ray_cluster, tiny_llama_dir, tmp_path):
    straight = run(make_cfg(tiny_llama_dir, tmp_path / "straight", iterations=3, **PPO))
    # Resume from the straight run's step-2 checkpoint: the third step must come out identical.
    resumed_dir = tmp_path / "resumed" / "checkpoints"
    resumed_dir.mkdir(parents=True)
    shutil.copytree(tmp_path / "straight" / "checkpoints" / "iter_000002", resumed_dir / "iter_000002")
    resumed = run(make_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=3, **PPO))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]
    assert resumed["critic_weights_sha256"] == straight["critic_weights_sha256"]

    rows = read_rows(tmp_path / "straight")
    assert [r["step"] for r in rows] == [0, 1, 2, 3]
    # Step 1 trains the initial policy: it *is* the (separate) reference, so every KL is 0.
    assert rows[1]["train/kl"] == pytest.approx(0.0, abs=1e-6)
    assert rows[1]["train/kl_in_reward"] == pytest.approx(0.0, abs=1e-6)
    assert rows[3]["train/kl"] > 1e-6 and abs(rows[3]["train/kl_in_reward"]) > 1e-6
    resumed_row = read_rows(tmp_path / "resumed")[-1]
    assert resumed_row["step"] == 3
    for key in ("rollout/reward_mean", "train/loss", "train/value_loss", "train/kl"):
        assert resumed_row[key] == pytest.approx(rows[3][key], abs=1e-7), key


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_ppo_with_a_lora_actor_scores_kl_against_its_base(ray_cluster, tiny_llama_dir, tmp_path):
    """PPO end to end in one short run: critic + GAE, KL as loss term and reward penalty, and
    reference.mode=auto with a LoRA actor, i.e. the actor's base with the adapter off (no
    reference component)."""
    cfg = make_cfg(tiny_llama_dir, tmp_path, iterations=3, resume=False, **_merge(PPO, {
        "save_every": 0, "actor": {"lr": 5e-2, "lora": {"r": 4, "alpha": 8}},
        "critic": {"lora": {"r": 4, "alpha": 8}}}))
    assert cfg.reference_mode == "actor_base"
    assert cfg.components() == ["actor", "rollout", "reward", "critic"]
    summary = run(cfg)
    assert "critic_weights_sha256" in summary
    rows = read_rows(tmp_path)
    for key in ("train/value_loss", "train/explained_variance", "train/value_clip_fraction", "train/kl",
                "train/kl_in_reward", "train/critic_grad_norm", "train/return_mean", "time/logprobs_and_values_s"):
        assert key in rows[1], key
    # Step 1 trains the initial policy, which the adapter-off base is: KL exactly 0 (the adapter
    # adds B @ A = 0). After updates the policy has moved away from it.
    assert rows[1]["train/kl"] == pytest.approx(0.0, abs=1e-7)
    assert rows[1]["train/kl_in_reward"] == pytest.approx(0.0, abs=1e-7)
    assert rows[3]["train/kl"] > 1e-6 and abs(rows[3]["train/kl_in_reward"]) > 1e-6
    assert rows[1]["train/explained_variance"] == 0.0  # the value head starts at 0
    assert all(r["train/value_loss"] > 0 for r in rows[1:])


def test_a_lora_actor_on_the_top_layer_sends_the_rollout_only_what_it_changes(ray_cluster, tiny_llama_dir,
                                                                              tmp_path):
    """The main job's actor (LoRA on the top layers): after the first weight sync, only the merged
    adapted layers go to the rollout, whose model stays exactly the trainer's: batches 2 and 3,
    generated after syncs of versions that moved far (lr 5e-2), the second changed-only, score as
    the rollout sampled them."""
    lora = {"actor": {"lr": 5e-2, "lora": {"r": 4, "alpha": 8, "target_modules": "all-linear", "top_layers": 1}}}
    run(make_cfg(tiny_llama_dir, tmp_path, iterations=3, save_every=0, eval={"every": 0}, **lora))
    rows = [r for r in read_rows(tmp_path) if "train/loss" in r]
    assert len(rows) == 3 and all(r["train/grad_norm"] > 0 for r in rows)
    assert all(r["train/logprob_mismatch_mean"] < 1e-3 for r in rows), [r["train/logprob_mismatch_mean"] for r in rows]


def test_a_prompt_over_max_prompt_length_fails_naming_the_key(tiny_llama_dir, tmp_path):
    from infinirl.engines.base import SamplingParams
    from infinirl.runners.reasoning import ReasoningFlow
    from infinirl.runners.reasoning_data import PromptTooLongError, build_problem_sources

    # Eval prompts are checked up front, before any worker starts (no Ray cluster needed here).
    cfg = make_cfg(tiny_llama_dir, tmp_path, iterations=1, rollout={"max_prompt_length": 8})
    with pytest.raises(PromptTooLongError, match=r"rollout.max_prompt_length=8: eval prompt .* is \d+ tokens long.*"
                                                 r"Raise rollout.max_prompt_length to at least \d+"):
        run(cfg)
    # Training prompts are checked as they are encoded, before anything is generated.
    train_stream, _, tokenizer = build_problem_sources(cfg)
    flow = ReasoningFlow(cfg, actor=None, rollout=None, reward=None, tokenizer=tokenizer)
    with pytest.raises(PromptTooLongError, match=r"train prompt"):
        flow.generate_and_score(train_stream.next_batch(2), SamplingParams(n=2, max_new_tokens=4))
    # At the limit itself is fine: the check is "longer than", not "as long as".
    from infinirl.runners.reasoning_data import encode_checked

    problems = train_stream.next_batch(2)
    longest = max(len(ids) for ids in encode_checked(problems, tokenizer, None, 10_000, "train"))
    encode_checked(problems, tokenizer, None, longest, "train")


@pytest.mark.slow  # two whole runs compared; streaming's own tests stay in the default tier
def test_streamed_chunks_give_the_same_run_on_one_or_two_rollout_ranks(ray_cluster, tiny_llama_dir, tmp_path):
    """Generation streams rollout -> reward -> driver through channels in chunks; each chunk's seed
    follows its index, so spreading chunks over two rollout and two reward ranks changes nothing."""
    common = {"rollout": {"stream_chunk_prompts": 1}, "save_every": 0, "eval": {"every": 1}}
    one = run(make_cfg(tiny_llama_dir, tmp_path / "one", iterations=1, **common))
    two = run(make_cfg(tiny_llama_dir, tmp_path / "two", iterations=1, **common,
                       placement={"actor": "0", "rollout": "0-1", "reward": "0-1"}))
    assert one["actor_weights_sha256"] == two["actor_weights_sha256"]
    assert (read_rows(tmp_path / "one")[1]["rollout/reward_mean"]
            == read_rows(tmp_path / "two")[1]["rollout/reward_mean"])


@pytest.mark.slow  # two whole runs compared; the eta=1 run and its exact resume stay in the default tier
def test_asynchronous_eta_0_is_the_synchronous_run(ray_cluster, tiny_llama_dir, tmp_path):
    quiet = {"eval": {"every": 100, "at_start": False}, "save_every": 100}
    synchronous = run(make_cfg(tiny_llama_dir, tmp_path / "sync", iterations=2, **quiet))
    eta0 = run(make_cfg(tiny_llama_dir, tmp_path / "eta0", iterations=2, **quiet,
                        algorithm={"asynchronous": {"max_staleness": 0}}))
    assert eta0["actor_weights_sha256"] == synchronous["actor_weights_sha256"]
    rows = read_rows(tmp_path / "eta0")
    assert [r["async/staleness_max"] for r in rows if "async/staleness_max" in r] == [0.0, 0.0]


def test_asynchronous_eta_1_trains_one_version_stale_corrected_and_resumes_exactly(
        ray_cluster, tiny_llama_dir, tmp_path):
    eta1 = {"algorithm": {"asynchronous": {"max_staleness": 1}, "objective": {"is_cap": 2.0, "is_cap_mode": "mask"}}}
    straight = run(make_cfg(tiny_llama_dir, tmp_path / "straight", iterations=4, **eta1))
    rows = [r for r in read_rows(tmp_path / "straight") if "train/loss" in r]
    # batch 0 and batch 1 are both produced by the initial weights; from then on, one version behind
    assert [r["async/staleness_max"] for r in rows] == [0.0, 1.0, 1.0, 1.0]
    assert all("train/is_weight_mean" in r and "train/is_capped_fraction" in r for r in rows)
    assert rows[2]["train/behaviour_logprob_abs_diff"] > rows[0]["train/behaviour_logprob_abs_diff"]
    assert_tokens_per_s_of_the_rollouts_own_time(rows)
    # Every evaluation first waits for the batches in flight (their generation is training time,
    # not the evaluation's); the pins below show the wait changes no sample.
    evals = [r for r in read_rows(tmp_path / "straight") if "eval/greedy_accuracy" in r]
    assert [r["step"] for r in evals] == [0, 2, 4] and all(r["time/eval_drain_s"] >= 0 for r in evals)
    check_pinned("reasoning_async", tmp_path / "straight", [
        "rollout/reward_mean", "train/loss", "train/grad_norm", "train/is_weight_mean", "eval/greedy_accuracy"])

    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    assert (tmp_path / "resumed" / "checkpoints" / "iter_000002" / "ahead_batches.pkl").exists()
    resumed = run(make_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=4, **eta1))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]
    resumed_rows = [r for r in read_rows(tmp_path / "resumed") if "train/loss" in r]
    assert [r["rollout/reward_mean"] for r in resumed_rows] == [r["rollout/reward_mean"] for r in rows]


def test_asynchronous_eta_2_resumes_with_every_sample_used_once(ray_cluster, tiny_llama_dir, tmp_path):
    """eta=2 keeps two batches ahead: the checkpoint of iteration 2 holds batches 2 and 3 (produced by
    versions 0 and 1, which the resumed run never loads), and the resumed run trains on exactly
    those, then on batch 4 produced by version 2: the straight run's weights and metrics."""
    eta2 = {"algorithm": {"asynchronous": {"max_staleness": 2}, "objective": {"is_cap": 2.0, "is_cap_mode": "mask"}},
            "eval": {"every": 100, "at_start": False}}
    straight = run(make_cfg(tiny_llama_dir, tmp_path / "straight", iterations=4, **eta2))
    rows = [r for r in read_rows(tmp_path / "straight") if "train/loss" in r]
    assert [r["async/staleness_max"] for r in rows] == [0.0, 1.0, 2.0, 2.0]
    assert_tokens_per_s_of_the_rollouts_own_time(rows)

    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    saved = load_ahead_batches(str(tmp_path / "resumed" / "checkpoints" / "iter_000002"))
    assert sorted(saved) == [2, 3]
    assert [{r.weight_version for r in saved[k][1]} for k in (2, 3)] == [{0}, {1}]
    resumed = run(make_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=4, **eta2))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]
    resumed_rows = [r for r in read_rows(tmp_path / "resumed") if "train/loss" in r]
    assert [r["step"] for r in resumed_rows] == [1, 2, 3, 4]  # each iteration once: none lost, none twice
    for key in ("rollout/reward_mean", "rollout/response_length_mean", "async/staleness_mean", "train/loss"):
        assert [r[key] for r in resumed_rows] == pytest.approx([r[key] for r in rows], abs=1e-7), key


@pytest.mark.slow  # two runs of partial rollouts; the exact eta=1 and eta=2 resumes stay in the default tier
def test_partial_rollouts_resume_on_the_batch_they_saved(ray_cluster, tiny_llama_dir, tmp_path):
    """Partial rollouts are not bit-reproducible (where a weight update lands in a generation depends
    on timing), but what a checkpoint holds is: the resumed run's first step trains the checkpoint's
    weights on the checkpoint's batch, exactly as the straight run did, and no iteration is lost or
    repeated."""
    partial = {"algorithm": {"asynchronous": {"max_staleness": 1, "partial_rollout": True},
                             "objective": {"is_cap": 2.0, "is_cap_mode": "mask"}},
               "eval": {"every": 100, "at_start": False}}
    run(make_cfg(tiny_llama_dir, tmp_path / "straight", iterations=3, **partial))
    rows = {r["step"]: r for r in read_rows(tmp_path / "straight") if "train/loss" in r}
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    saved = load_ahead_batches(str(tmp_path / "resumed" / "checkpoints" / "iter_000002"))
    assert sorted(saved) == [2]
    run(make_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=3, **partial))
    resumed = {r["step"]: r for r in read_rows(tmp_path / "resumed") if "train/loss" in r}
    assert sorted(resumed) == [1, 2, 3]
    for key in ("rollout/reward_mean", "async/token_staleness_mean", "async/interrupted_fraction", "train/loss",
                "train/grad_norm"):
        assert resumed[3][key] == pytest.approx(rows[3][key], abs=1e-7), key
    assert resumed[3]["rollout/reward_mean"] == pytest.approx(float(saved[2][2].mean()), abs=1e-7)


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_partial_rollouts_train_within_the_bound_and_log_per_token_staleness(ray_cluster, tiny_llama_dir, tmp_path):
    """Where a weight update lands in a generation depends on timing (the engine test pins the
    switch itself); here the run trains, every sample stays within the bound, and tokens are never
    staler than the samples that hold them."""
    partial = {"algorithm": {"asynchronous": {"max_staleness": 1, "partial_rollout": True},
                             "objective": {"is_cap": 2.0, "is_cap_mode": "mask"}},
               "eval": {"every": 100, "at_start": False}, "save_every": 100}
    run(make_cfg(tiny_llama_dir, tmp_path, iterations=3, **partial))
    rows = [r for r in read_rows(tmp_path) if "train/loss" in r]
    assert len(rows) == 3
    for r in rows:
        assert r["async/staleness_max"] <= 1.0
        assert 0.0 <= r["async/token_staleness_mean"] <= r["async/staleness_mean"]
        assert 0.0 <= r["async/interrupted_fraction"] <= 1.0
