"""The algorithm registries. The generic ``Registry`` lives in ``infinirl.registry`` (torch-free,
so env workers and config validation can use it without importing torch)."""

from __future__ import annotations

from infinirl.registry import Registry, UnknownNameError

__all__ = [
    "ADVANTAGES",
    "AGGREGATIONS",
    "KL_ESTIMATORS",
    "POLICY_LOSSES",
    "Registry",
    "UnknownNameError",
]

ADVANTAGES: Registry = Registry("advantage estimator")
POLICY_LOSSES: Registry = Registry("policy loss")
KL_ESTIMATORS: Registry = Registry("KL estimator")
AGGREGATIONS: Registry = Registry("loss aggregation mode")
