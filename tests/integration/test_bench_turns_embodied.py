"""The embodied benchmark's turn-taking on the real runner (benchmarks/_bench_turns.py): a row that
runs `infinirl.runners.embodied` behind ``gate_embodied_runner`` takes one turn per iteration and
one more for what follows its loop, and the conductor sees it through to its exit. A gate that
wrapped a method the run loop no longer calls left every runner row of embodied_pipeline.py
crashing at start."""

import json
import os
import sys

import pytest

pytest.importorskip("gymnasium")

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
BENCHMARKS = os.path.join(REPO, "benchmarks")
sys.path.insert(0, BENCHMARKS)

from _bench_turns import Conductor  # noqa: E402

ROW = """
import sys
sys.path[:0] = [{repo!r}, {benchmarks!r}]
import _bench_turns
_bench_turns.gate_embodied_runner()
from infinirl.config import to_dataclass
from infinirl.runners.embodied import run
from infinirl.runners.embodied_config import EmbodiedConfig
run(to_dataclass(EmbodiedConfig, {raw!r}))
"""


@pytest.mark.slow  # default-suite budget: the gate's patching has a unit test
def test_a_runner_row_takes_one_turn_per_iteration_and_exits(tmp_path):
    iterations = 2
    raw = {"iterations": iterations, "rollout_steps": 8, "output_dir": str(tmp_path / "run"), "save_every": 0,
           "loggers": [], "env": {"name": "gym:Pendulum-v1", "num_envs": 2},
           "algorithm": {"epochs": 1, "mini_batches": 1},
           "eval": {"every": 0, "at_start": False, "episodes": 1, "num_envs": 1, "video_episodes": 0},
           "placement": {"env": "0", "rollout": "0", "actor": "0"}, "cluster": {"log_to_driver": False}}
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [REPO, os.environ.get("PYTHONPATH")]))}
    command = [sys.executable, "-c", ROW.format(repo=REPO, benchmarks=BENCHMARKS, raw=raw)]
    Conductor({"runner": command}, env=env).run(iterations)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "time/iteration_s" in r] == [1, 2]
    assert "eval/success_rate" in rows[-1]  # the final evaluation ran in the last turn
