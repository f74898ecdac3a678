"""PPO + MLP learns MetaWorld reach-v3 with the shipped demo config (slow: ~2 minutes on 2 cores).

Held-out success (50 seeded layouts never trained on, deterministic policy) measured with this
config (16 envs x 100 steps, session 19): 0.14 at iteration 10 -> 0.94 at 40 -> 0.96 at 50; the
last evaluation over seeds 0-4 was 0.96-1.00 (docs/embodied.md). The issue's target is >= 90%; the
test asserts it at the end of the run, and that the run wrote its curve and video. The config's
earlier 8 envs x 200 steps failed it on session 19's host (0.88): it sampled half the layouts.
"""

import pytest

pytest.importorskip("metaworld")

from infinirl.config import compose, to_dataclass  # noqa: E402
from infinirl.runners.embodied import run  # noqa: E402
from infinirl.runners.embodied_config import EmbodiedConfig  # noqa: E402


@pytest.mark.slow
def test_ppo_reaches_the_goal_on_held_out_layouts(ray_cluster, tmp_path):
    raw = compose("ppo_metaworld_reach")  # the shipped demo config, as `infinirl train` reads it
    raw.update(output_dir=str(tmp_path), resume=False, cluster={"log_to_driver": False})
    raw["eval"]["video_episodes"] = 1
    summary = run(to_dataclass(EmbodiedConfig, raw))
    assert summary["eval_success_before"] <= 0.6, summary  # the first evaluation (iteration 10) is far from solved
    assert summary["eval_success_after"] >= 0.9, summary
    assert summary["first_eval_at_0.9"] is not None, summary
    assert (tmp_path / "curves.png").exists() and (tmp_path / "eval.mp4").stat().st_size > 0
    assert list((tmp_path / "tensorboard").iterdir())
