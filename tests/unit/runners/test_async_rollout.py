"""The asynchronous schedule: which weights version produces each batch, whatever the timing."""

import pytest

from infinirl.engines.base import GenerationResult
from infinirl.runners.async_rollout import (
    RolloutAhead,
    WeightPusher,
    partial_rollout_metrics,
    producing_version,
    staleness_metrics,
    unfinished_loads,
)


class FakeRollout:
    """A rollout rank that runs calls in submission order: a batch sees the last version loaded."""

    def __init__(self):
        self.version, self.log = 0, []

    def load(self, version):
        self.version = version
        self.log.append(("load", version))

    def submit(self, k):
        self.log.append(("submit", k))
        return (k, self.version)

    @staticmethod
    def collect(pending):
        return pending


def train(rollout, eta, iterations, start=0, ahead=None):
    """The trainer's loop: take batch k, train, publish version k + 1."""
    ahead = ahead or RolloutAhead(eta, iterations, rollout.submit, rollout.collect)
    used = []
    for k in range(start, iterations):
        used.append(ahead.take(k))
        rollout.load(k + 1)
    return used, ahead


@pytest.mark.parametrize("eta", [0, 1, 2, 3])
def test_each_batch_is_produced_by_version_k_minus_eta(eta):
    used, _ = train(FakeRollout(), eta, iterations=8)
    assert used == [(k, producing_version(k, eta)) for k in range(8)]
    assert all(k - version <= eta for k, version in used)


def test_eta_zero_is_the_synchronous_order():
    rollout = FakeRollout()
    train(rollout, 0, iterations=3)
    assert rollout.log == [("submit", 0), ("load", 1), ("submit", 1), ("load", 2), ("submit", 2), ("load", 3)]


def test_nothing_is_produced_past_the_last_iteration():
    rollout = FakeRollout()
    train(rollout, 2, iterations=3)
    assert sorted(k for what, k in rollout.log if what == "submit") == [0, 1, 2]


def test_drain_and_restore_resume_the_same_batches():
    rollout = FakeRollout()
    straight, _ = train(rollout, 2, iterations=6)

    rollout = FakeRollout()
    ahead = RolloutAhead(2, 6, rollout.submit, rollout.collect)
    first, ahead = train(rollout, 2, iterations=3, ahead=ahead)
    saved = ahead.drain()  # a checkpoint after iteration 2: batches 3 and 4 were produced ahead
    assert sorted(saved) == [3, 4]

    resumed_rollout = FakeRollout()
    resumed_rollout.version = 3  # the resumed run loads the checkpoint's weights
    resumed = RolloutAhead(2, 6, resumed_rollout.submit, resumed_rollout.collect)
    resumed.restore(saved)
    rest, _ = train(resumed_rollout, 2, iterations=6, start=3, ahead=resumed)
    assert first + rest == straight


def test_a_skipped_batch_is_an_error_not_a_silent_loss():
    rollout = FakeRollout()
    ahead = RolloutAhead(1, 5, rollout.submit, rollout.collect)
    ahead.take(0)
    with pytest.raises(RuntimeError, match="never used"):
        ahead.take(2)


def test_staleness_metrics():
    assert staleness_metrics(5, [5, 4, 4, 3]) == {"async/staleness_mean": 1.0, "async/staleness_max": 2.0}


def test_partial_rollout_metrics_weigh_each_token_by_its_own_version():
    def result(version, n, versions=None):
        return GenerationResult(prompt_ids=[1], response_ids=[2] * n, response_logprobs=[0.0] * n,
                                finish_reason="length", weight_version=version, response_versions=versions)

    results = [result(3, 2), result(3, 4, [3, 3, 4, 4])]  # at iteration 4: gaps 1,1 and 1,1,0,0
    assert partial_rollout_metrics(4, results) == {"async/token_staleness_mean": 4 / 6,
                                                   "async/interrupted_fraction": 0.5}


def test_partial_rollout_metrics_count_only_the_tokens_the_model_sampled():
    """An agent's trajectory: turn 1 sampled by version 2, an observation the environment inserted
    (stamped with the version before it, yet sampled by none), turn 2 by version 4. At iteration 4
    the sampled tokens' gaps are 2, 2, 0: the inserted ones must not pull the mean towards 2."""
    agent = GenerationResult(prompt_ids=[1], response_ids=[5] * 8, response_logprobs=[0.0] * 8,
                             finish_reason="stop", weight_version=2,
                             response_versions=[2, 2, 2, 2, 2, 2, 2, 4], response_mask=[1, 1, 0, 0, 0, 0, 0, 1])
    assert partial_rollout_metrics(4, [agent])["async/token_staleness_mean"] == 4 / 3


class LoadFinishingNow:
    """A sync whose load fails just after it was first asked whether it is done."""

    def __init__(self):
        self.asked = 0

    def done(self) -> bool:
        self.asked += 1
        return self.asked > 1

    def wait(self):
        raise ValueError("load of version 3 failed")


def test_a_load_failing_between_two_checks_is_raised_at_the_next_one():
    loading = [LoadFinishingNow()]
    loading = unfinished_loads(loading)  # not done when asked: kept, not dropped unchecked
    assert len(loading) == 1
    with pytest.raises(ValueError, match="version 3 failed"):
        unfinished_loads(loading)


@pytest.mark.parametrize("eta", [1, 2])
def test_settling_before_an_evaluation_waits_for_the_batches_in_flight_and_changes_none(eta):
    """An evaluation queues behind the batches in flight; the flows settle them first so that their
    generation counts as training time. They stay for take(), produced by the same versions."""
    straight, _ = train(FakeRollout(), eta, iterations=6)
    collected = []
    rollout = FakeRollout()
    ahead = RolloutAhead(eta, 6, rollout.submit, lambda pending: collected.append(pending[0]) or pending)
    used = []
    for k in range(6):
        used.append(ahead.take(k))
        rollout.load(k + 1)
        if k % 2 == 1:  # an evaluation after iterations 2, 4, 6
            in_flight = ahead.in_flight
            waited = ahead.settle()
            assert waited >= 0 and ahead.in_flight == [] and set(in_flight) <= set(collected)
    assert used == straight


class Load:
    """A published version's load on the rollout ranks: done; ``error`` if it failed."""

    def __init__(self, version, error=None):
        self.version, self.error, self.waited = version, error, False

    def done(self) -> bool:
        return True

    def wait(self, timeout=None):
        self.waited = True
        if self.error is not None:
            raise self.error


def pusher_with(loads):
    pusher = WeightPusher(trainer=None, rollout=None, asynchronous=True)
    pusher._loading = list(loads)
    return pusher


def test_a_batch_produced_after_a_failed_load_is_never_used():
    """A load that failed before copying anything leaves the rank on the version before, whole: the
    batch generated after it would be one version staler than the bound. Taking it raises the load's
    own error; loads of later versions (not yet due) are not waited for."""
    rollout = FakeRollout()
    failed, later = Load(1, OSError("disk full while loading version 1")), Load(2)
    ahead = RolloutAhead(1, 5, rollout.submit, rollout.collect, pusher_with([failed, later]))
    ahead.take(0)
    ahead.take(1)  # produced by version 0: the load of version 1 is not yet due
    with pytest.raises(OSError, match="disk full while loading version 1"):
        ahead.take(2)  # produced by version 1
    assert not later.waited


def test_a_collection_that_failed_raises_the_failed_load_behind_it():
    """A rank refuses to generate on weights a load tore; the collection's error is a symptom, the
    load's is the root cause, raised with the symptom as its context."""
    def collect(pending):
        raise RuntimeError("rollout[rank 0]: loading weights version 1 failed partway")

    rollout = FakeRollout()
    ahead = RolloutAhead(0, 3, rollout.submit, collect,
                         pusher_with([Load(1, OSError("disk full while loading version 1"))]))
    with pytest.raises(OSError, match="disk full") as failure:
        ahead.take(1)
    assert "failed partway" in str(failure.value.__context__)


def test_raising_iterations_on_resume_is_exact_from_a_checkpoint_eta_before_the_end(capsys):
    """The batches never produced past a run's end cannot come from the versions a longer straight
    run gives them: a resume that needs them says so; one from a checkpoint eta before the end of the
    shorter run needs none of them and is exact."""
    straight, _ = train(FakeRollout(), 2, iterations=8)

    def extended(checkpoint_at):
        short = FakeRollout()
        first, ahead = train(short, 2, iterations=checkpoint_at,
                             ahead=RolloutAhead(2, 5, short.submit, short.collect))
        saved = ahead.drain()
        resumed_rollout = FakeRollout()
        resumed_rollout.version = checkpoint_at
        resumed = RolloutAhead(2, 8, resumed_rollout.submit, resumed_rollout.collect)
        resumed.restore(saved)
        rest, _ = train(resumed_rollout, 2, iterations=8, start=checkpoint_at, ahead=resumed)
        return first + rest

    assert extended(3) == straight  # the checkpoint of iteration 3 of 5 holds batches 3 and 4
    assert capsys.readouterr().err == ""
    assert extended(5) != straight  # the final checkpoint holds nothing: batches 5, 6 by version 5
    warning = capsys.readouterr().err
    assert "resuming at iteration 5 with max_staleness=2: the checkpoint holds no batch 5, 6" in warning
    assert "produced by version 5, not version 3, 4" in warning and "iterations=8" in warning
