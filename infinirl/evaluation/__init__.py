"""Evaluation: `infinirl eval` (greedy accuracy, pass@1, pass@k) of a model or a training checkpoint.

- `passk.py`: the unbiased pass@k estimator, pure.
- `config.py`: `EvalConfig` and its resolution against a training run's folder.
- `evaluator.py`: generation over rollout ranks, scoring in reward workers, aggregation.
- `runner.py`: the flow, registered as runner ``eval`` (config ``infinirl/configs/eval.yaml``).
"""

from infinirl.evaluation.passk import mean_pass_at_k, pass_at_k

__all__ = ["mean_pass_at_k", "pass_at_k"]
