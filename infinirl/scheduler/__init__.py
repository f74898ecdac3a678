"""Automatic placement from measured profiles (docs/scheduler.md).

* :mod:`.profile`: short real runs under probe placements, measured from the tracer's spans, cached;
* :mod:`.cost`: predicted step time and memory of a placement (pure functions);
* :mod:`.search`: every placement and depth worth trying on a cluster, ranked;
* :mod:`.simulate`: the same planning on a simulated cluster of 8 to 1,024 GPUs;
* :mod:`.auto`: ``infinirl plan`` and ``placement: auto``;
* :mod:`.workloads`: what the scheduler knows of each runner (a registry).
"""

from infinirl.scheduler.cost import Allocation, Candidate, Phase, Prediction, WorkCost, Workload, predict
from infinirl.scheduler.search import PlanEntry, search
from infinirl.scheduler.workloads import RUNNER_MODELS, RunnerModel

__all__ = ["RUNNER_MODELS", "Allocation", "Candidate", "Phase", "PlanEntry", "Prediction", "RunnerModel",
           "WorkCost", "Workload", "predict", "search"]
