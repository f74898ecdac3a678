"""Reasoning config: bad values fail at validation, naming the key and the valid choices."""

import pytest

from infinirl.config import ConfigError, to_dataclass
from infinirl.runners.reasoning_config import ReasoningConfig


def build(**raw):
    return to_dataclass(ReasoningConfig, raw)


def test_defaults_validate():
    cfg = build()
    assert cfg.algorithm.advantage == "grpo" and cfg.rollout.group_size == 8


@pytest.mark.parametrize("raw, message", [
    ({"algorithm": {"advantage": "grpoo"}}, r"algorithm.advantage='grpoo' is not registered; registered: .*grpo"),
    ({"algorithm": {"objective": {"aggregation": "mean"}}}, r"aggregation='mean' is not registered; registered: .*token-mean"),
    ({"algorithm": {"mini_batches": 3}}, r"mini_batches=3 does not divide the batch of prompts_per_step\*group_size=64"),
    ({"algorithm": {"advantage": "gae"}}, r"gae needs a critic"),
    ({"algorithm": {"objective": {"kl_coef": 0.1}}}, r"kl_coef > 0 needs a reference"),
    ({"rollout": {"group_size": 0}}, r"rollout.group_size=0 must be >= 1"),
    ({"loggers": ["tensorbord"]}, r"unknown logger 'tensorbord'"),
    ({"placement": {"actor": "0", "rollout": "0"}}, r"missing \['reward'\]"),
    ({"placement": {"actor": "0", "rollout": "0", "reward": "x"}}, r"placement.reward"),
    ({"task": {"source": "hub"}}, r"task.source='hub' is not allowed.*reasoning_gym, dataset"),
    ({"rollout": {"max_new_token": 5}}, r"Did you mean 'rollout.max_new_tokens'"),
    ({"model": {"path": "/no/such/model"}}, r"model.path='/no/such/model' is not a folder"),
])
def test_bad_values_are_named(raw, message):
    with pytest.raises(ConfigError, match=message):
        build(**raw)
