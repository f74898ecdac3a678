"""A rollout rank's weight load failing in an asynchronous run: the load's own error stops the run,
before anything is generated, trained on or evaluated with the weights it should have replaced."""

from __future__ import annotations

import json

import pytest

import infinirl.runners.reasoning as reasoning
from infinirl.components.rollout import RolloutWorker
from infinirl.runtime.errors import WorkerError
from tests.conftest import ship_by_value
from tests.integration.test_reasoning_pipeline import make_cfg

ship_by_value(__name__)

FAILING_VERSION = 2  # the last version of a 2-iteration run: the final evaluation's weights


class RolloutLoadFailsUntouched(RolloutWorker):
    """Loading ``FAILING_VERSION`` fails before a tensor is copied: the rank keeps the previous
    version, whole, and would go on generating with it."""

    def load_weights(self, named_tensors, version: int, changed_only: bool = False) -> None:
        if version == FAILING_VERSION:
            raise OSError(f"disk full while loading version {version}")
        super().load_weights(named_tensors, version, changed_only)


class RolloutLoadFailsTorn(RolloutWorker):
    """Loading ``FAILING_VERSION`` fails after taking a tensor: the rank's weights count as torn."""

    def load_weights(self, named_tensors, version: int, changed_only: bool = False) -> None:
        if version == FAILING_VERSION:
            next(iter(named_tensors))
            raise OSError(f"disk full while loading version {version}")
        super().load_weights(named_tensors, version, changed_only)


# The torn case in the slow tier (the default suite's time budget): torn loads are refused in
# tests/unit/test_torn_weights_refused.py; this one adds their reporting in asynchronous runs.
@pytest.mark.parametrize("rollout_cls", [RolloutLoadFailsUntouched,
                                         pytest.param(RolloutLoadFailsTorn, marks=pytest.mark.slow)],
                         ids=["untouched", "torn"])
def test_a_failed_load_raises_its_own_error_and_nothing_is_evaluated_on_the_old_weights(
        ray_cluster, tiny_llama_dir, tmp_path, monkeypatch, rollout_cls):
    launches = reasoning._launches

    def with_failing_rollout(cfg):
        specs = launches(cfg)
        return {**specs, "rollout": (rollout_cls, *specs["rollout"][1:])}

    monkeypatch.setattr(reasoning, "_launches", with_failing_rollout)
    cfg = make_cfg(tiny_llama_dir, tmp_path, iterations=FAILING_VERSION, save_every=0, resume=False, loggers=[],
                   eval={"every": 100, "at_start": False},
                   algorithm={"asynchronous": {"max_staleness": 1}, "objective": {"is_cap": 2.0}})
    with pytest.raises(WorkerError, match=f"disk full while loading version {FAILING_VERSION}") as failure:
        reasoning.run(cfg)
    assert "_infinirl_receive_weights" in str(failure.value)  # the load itself, not a symptom of it
    # The final evaluation would have scored the version before: it must not have run.
    metrics = tmp_path / "metrics.jsonl"
    rows = [json.loads(line) for line in metrics.read_text().splitlines()] if metrics.exists() else []
    assert not any("eval/greedy_accuracy" in row for row in rows), rows
