"""benchmarks/chunk_frames.py: its env is the demo config's, and a tiny run prints its ratio line.

Why: a hard-coded env would drift from the demo's config and measure a loop nobody runs."""

import json
import os
import subprocess
import sys

import pytest

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import chunk_frames as bench  # noqa: E402

from infinirl.config import compose  # noqa: E402


def test_the_env_is_the_demo_configs():
    raw = compose(bench.DEMO)
    env = bench.demo_env()
    assert env["env"] == raw["env"]["name"] and env["kwargs"] == raw["env"]["kwargs"]
    assert env["num_envs"] == raw["env"]["num_envs"] and env["chunk"] == raw["policy"]["chunk"]


def test_summarise_totals_rounds():
    result = bench.summarise([1.0, 3.0], [100, 300])
    assert result["env_steps"] == 400 and result["env_steps_per_s"] == 100.0


def test_a_tiny_run_prints_the_ratio():
    pytest.importorskip("metaworld")
    out = subprocess.run(
        [sys.executable, os.path.join(BENCHMARKS, "chunk_frames.py"), "--num-envs", "2", "--num-workers", "0",
         "--chunks", "3", "--rounds", "1", "--image-size", "32"],
        capture_output=True, text=True, timeout=300, check=True,
    ).stdout
    final = json.loads(out.strip().splitlines()[-1])
    assert final["ratios"]["chunk_frames_skip_vs_full"] > 0
    assert final["results"]["skip"]["env_steps"] == final["results"]["full"]["env_steps"] == 2 * 3 * 4
