"""Rollout workers that act in envs refuse to act on weights a failed load left half-replaced.

The weight sink marks a rank torn when a load fails after its first tensor (see
``infinirl.runtime.weights``); collection, evaluation and video recording must then raise instead of
acting with a mix of two versions under the old version's number."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from infinirl.components.embodied_rollout import EmbodiedRolloutWorker
from infinirl.components.sac_collector import SACCollectorWorker

CALLS = {
    EmbodiedRolloutWorker: [("collect", (0, [0], 1)), ("evaluate", ([0], 1)), ("record_video", ([0], "v.mp4"))],
    SACCollectorWorker: [("collect", (1,)), ("evaluate", ([0], 1)), ("record_video", ([0], "v.mp4"))],
}


@pytest.mark.parametrize("cls", list(CALLS), ids=lambda c: c.__name__)
def test_a_torn_rank_acts_on_nothing(cls):
    worker = object.__new__(cls)  # no env is needed: the check comes before anything is built
    worker.weight_version, worker.ctx = 3, SimpleNamespace(component="rollout", rank=0)
    worker._torn_weights = (4, False)
    for method, args in CALLS[cls]:
        with pytest.raises(RuntimeError, match="loading weights version 4 failed partway"):
            getattr(worker, method)(*args)
