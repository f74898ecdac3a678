"""The embodied benchmark measures the iteration shape of the demo it names (benchmarks/embodied_pipeline.py).

Why: a hard-coded shape would drift from the demo's config and measure a loop nobody runs. The
shape comes from the demo's config; these checks fail if it is hard-coded again or an explicit
shape is ignored."""

import os
import sys

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import embodied_pipeline as bench  # noqa: E402

from infinirl.config import compose  # noqa: E402


def test_default_shape_is_the_demo_configs():
    raw = compose(bench.DEMO)
    assert bench.demo_shape() == (raw["env"]["num_envs"], raw["rollout_steps"])


def test_explicit_shape_wins_per_field():
    raw = compose(bench.DEMO)
    assert bench.demo_shape(8, 200) == (8, 200)
    assert bench.demo_shape(num_envs=6) == (6, raw["rollout_steps"])
    assert bench.demo_shape(steps=50) == (raw["env"]["num_envs"], 50)


def test_rows_run_the_shape_set_for_the_run(monkeypatch):
    monkeypatch.setattr(bench, "NUM_ENVS", 6)
    monkeypatch.setattr(bench, "STEPS", 40)
    overrides = bench.runner_overrides("pipelined", "state", 3, True, "/tmp/out")
    assert overrides["env.num_envs"] == 6 and overrides["rollout_steps"] == 40
    command = bench.row_command("single_process", "state", 3, 1, True, "/tmp/out")
    assert command[command.index("--num-envs") + 1] == "6" and command[command.index("--steps") + 1] == "40"
    assert bench.summarise([{"time/iteration_s": 1.0}], "x")["env_steps"] == 6 * 40


def test_a_shape_no_row_can_run_is_refused_before_rows_start():
    raw = compose(bench.DEMO)
    assert bench.shape_problem(raw["env"]["num_envs"], raw["rollout_steps"]) is None
    assert bench.shape_problem(8, 200) is None
    assert "--num-envs 1" in bench.shape_problem(1, 100)
    assert "--steps 300" in bench.shape_problem(16, 300)
    problem = bench.shape_problem(4, 20)  # 80 decisions: 32 mini-batches do not divide them
    assert "mini_batches=32" in problem and "80" in problem
