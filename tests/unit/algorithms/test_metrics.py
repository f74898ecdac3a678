"""Combining logged metrics over micro-batches, ranks and steps: means, except ``_max`` / ``_min``."""

import math

import pytest
import torch

from infinirl.algorithms.embodied_ppo import PPOSpec, _update_metrics
from infinirl.algorithms.metrics import MetricReducer, metric_reduction


def test_the_name_decides_the_reduction():
    assert metric_reduction("train/ratio_max") == "max"
    assert metric_reduction("train/is_weight_max") == "max"
    assert metric_reduction("train/ratio_min") == "min"
    assert metric_reduction("train/ratio_mean") == "mean"
    assert metric_reduction("train/maximum") == "mean"


@pytest.mark.parametrize("as_tensor", [False, True])
def test_two_micro_batches_report_the_larger_maximum_and_the_mean_of_the_rest(as_tensor):
    value = (lambda x: torch.tensor(x, dtype=torch.float64)) if as_tensor else float
    reducer = MetricReducer()
    reducer.add({"train/ratio_max": value(1.2), "train/ratio_min": value(0.9), "train/loss": value(1.0)})
    reducer.add({"train/ratio_max": value(1e3), "train/ratio_min": value(0.5), "train/loss": value(3.0)})
    assert reducer.result() == {"train/ratio_max": 1e3, "train/ratio_min": 0.5, "train/loss": 2.0}


def test_ranks_merge_as_if_one_rank_had_every_micro_batch():
    """Rank 0 with three micro-batches, rank 1 with one: the mean weighs every micro-batch the
    same, the extremes are those of all four."""
    parts = [{"loss": 1.0, "w_max": 2.0, "w_min": 0.3}, {"loss": 2.0, "w_max": 7.0, "w_min": 0.2},
             {"loss": 3.0, "w_max": 1.0, "w_min": 0.9}, {"loss": 10.0, "w_max": 3.0, "w_min": 0.1}]
    ranks = [MetricReducer(), MetricReducer()]
    for index, part in enumerate(parts):
        ranks[index // 3].add(part)
    combined = MetricReducer()
    for rank in ranks:
        combined.merge(rank.as_floats())
    assert combined.result() == {"loss": 4.0, "w_max": 7.0, "w_min": 0.1}


@pytest.mark.parametrize("as_tensor", [False, True])
def test_a_nan_extreme_stays_visible(as_tensor):
    value = torch.tensor if as_tensor else float
    for order in ((1.0, math.nan), (math.nan, 1.0)):
        reducer = MetricReducer()
        for x in order:
            reducer.add({"ratio_max": value(x)})
        assert math.isnan(reducer.result()["ratio_max"])


def test_the_embodied_update_combines_its_steps_by_the_same_rule():
    optimizer = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=0.1)
    steps = {"train/x_max": [torch.tensor(1.0), torch.tensor(5.0), torch.tensor(2.0)],
             "train/x_min": [torch.tensor(1.0), torch.tensor(-5.0), torch.tensor(2.0)],
             "train/x": [torch.tensor(1.0), torch.tensor(5.0), torch.tensor(3.0)]}
    metrics = _update_metrics(steps, {}, PPOSpec(critic=False), optimizer)
    assert (metrics["train/x_max"], metrics["train/x_min"], metrics["train/x"]) == (5.0, -5.0, 3.0)
