"""`infinirl eval` end to end on a tiny random model: the plain model, data parallel over two
rollout ranks, and the checkpoint of a 2-step training run, whose weights must be the trained ones."""

import json

import pytest

from infinirl.config import to_dataclass
from infinirl.evaluation import mean_pass_at_k
from infinirl.evaluation.config import EvalConfig
from infinirl.evaluation.runner import run as run_eval
from infinirl.runners.metrics_log import read_metrics
from infinirl.runners.reasoning import run as run_train
from infinirl.runners.reasoning_config import ReasoningConfig

# Varies with any output of a random model, so a 2-step GRPO run moves the weights.
VERIFIER = "infinirl.tasks.toy_rewards:uppercase_fraction"
TASK = {"eval_size": 4, "verifier": VERIFIER}


def eval_cfg(**raw):
    raw.setdefault("cluster", {"log_to_driver": False})
    raw.setdefault("progress", False)
    return to_dataclass(EvalConfig, {"samples": 3, "k": [1, 2, 3], **raw})


def results_of(summary):
    with open(summary["output"]) as handle:
        return json.load(handle)


def check_metrics_match_records(summary, results, samples=3):
    records = results["per_problem"]
    assert len(records) == summary["problems"] and all(r["samples"] == samples for r in records)
    counts = [r["correct"] for r in records]
    assert summary["eval/pass@1"] == pytest.approx(sum(counts) / (samples * len(records)))
    for k in range(2, samples + 1):
        assert summary[f"eval/pass@{k}"] == pytest.approx(mean_pass_at_k([samples] * len(records), counts, k))
    assert summary["eval/greedy_accuracy"] == pytest.approx(sum(r["greedy_correct"] for r in records) / len(records))


def test_base_model_eval_writes_results_and_one_summary_line(ray_cluster, tiny_llama_dir, tmp_path, capsys):
    summary = run_eval(eval_cfg(model={"path": tiny_llama_dir}, task=TASK, max_new_tokens=6,
                                output=str(tmp_path / "out" / "base.json")))
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == summary
    results = results_of(summary)
    assert summary["problems"] == 4 and summary["weights_sha256"] is None and summary["weight_versions"] == [0]
    assert results["max_new_tokens"] == 6 and results["task_config"]["verifier"] == VERIFIER
    assert [r["uid"] for r in results["per_problem"]] == [f"chain_sum/eval/{i}" for i in range(4)]
    check_metrics_match_records(summary, results)
    assert 0 <= summary["eval/pass@1"] <= summary["eval/pass@2"] <= summary["eval/pass@3"] <= 1


@pytest.mark.slow
def test_checkpoint_eval_serves_the_trained_weights_and_ranks_do_not_change_results(ray_cluster, tiny_llama_dir,
                                                                                    tmp_path):
    run_dir = tmp_path / "run"
    trained = run_train(to_dataclass(ReasoningConfig, {
        "iterations": 2, "prompts_per_step": 2, "eval": {"every": 2}, "save_every": 2, "loggers": [],
        "output_dir": str(run_dir), "model": {"path": tiny_llama_dir}, "task": TASK,
        "rollout": {"group_size": 2, "max_new_tokens": 6}, "actor": {"lr": 1e-3, "micro_batch_size": 2},
        "cluster": {"log_to_driver": False}}))
    train_evals = [r["eval/greedy_accuracy"] for r in read_metrics(str(run_dir / "metrics.jsonl"))
                   if "eval/greedy_accuracy" in r]

    # The plain model on the run's held-out problems, on two rollout ranks and on one.
    base = dict(model={"path": tiny_llama_dir}, task=TASK, max_new_tokens=6)
    two_ranks = run_eval(eval_cfg(**base, output=str(tmp_path / "base2.json"),
                                  placement={"rollout": "0-1", "reward": "0"}))
    one_rank = run_eval(eval_cfg(**base, output=str(tmp_path / "base1.json")))
    base_records = results_of(one_rank)["per_problem"]
    assert results_of(two_ranks)["per_problem"] == base_records  # same samples whatever the rank count
    assert one_rank["eval/greedy_accuracy"] == train_evals[0]  # what training measured before step 1

    # The run's checkpoint: the run's model, task and response length come from its config.json.
    ckpt = run_eval(eval_cfg(run_dir=str(run_dir)))
    assert ckpt["step"] == 2 and ckpt["output"].startswith(str(run_dir / "eval" / "chain_sum-iter_000002-"))
    assert ckpt["weights_sha256"] == trained["actor_weights_sha256"]  # the trained weights were loaded
    assert ckpt["weight_versions"] == [2]  # ... and every sample came from them, after the sync
    assert ckpt["eval/greedy_accuracy"] == train_evals[-1]  # what training measured after step 2
    results = results_of(ckpt)
    assert results["max_new_tokens"] == 6 and results["task_config"]["verifier"] == VERIFIER
    check_metrics_match_records(ckpt, results)
    # Same prompts, different weights: the model's log-probs of its greedy answers moved.
    assert all(a["greedy_logprob"] != b["greedy_logprob"] for a, b in zip(results["per_problem"], base_records))
