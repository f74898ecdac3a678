"""SAC learns InvertedPendulum-v5 with the shipped demo config (slow).

The held-out return (10 seeded episodes, deterministic policy) starts far below and reaches the
1000-step maximum (curve: docs/results.md)."""

import pytest

pytest.importorskip("mujoco")

from infinirl.config import compose, to_dataclass  # noqa: E402
from infinirl.runners.sac import run  # noqa: E402
from infinirl.runners.sac_config import SACConfig  # noqa: E402


@pytest.mark.slow
def test_sac_balances_the_inverted_pendulum(ray_cluster, tmp_path):
    raw = compose("sac_inverted_pendulum")  # the shipped demo config, as `infinirl train` reads it
    raw.update(output_dir=str(tmp_path), resume=False, cluster={"log_to_driver": False})
    raw["eval"]["video_episodes"] = 1
    summary = run(to_dataclass(SACConfig, raw))
    assert summary["eval_before"] < 50, summary
    assert summary["eval_after"] >= 900, summary  # "clearly improves": ~8 -> ~1000
    assert summary["first_eval_at_target"] is not None, summary
    assert (tmp_path / "curves.png").exists() and (tmp_path / "eval.mp4").stat().st_size > 0
    assert list((tmp_path / "tensorboard").iterdir())
