"""The embodied demos learn, with their shipped configs (slow: 1-6 minutes each on 2 cores).

PPO + MLP on MetaWorld reach-v3: held-out success (50 seeded layouts never trained on,
deterministic policy) measured with this config (16 envs x 100 steps, session 19): 0.14 at
iteration 10 -> 0.94 at 40 -> 0.96 at 50; the last evaluation over seeds 0-4 was 0.96-1.00
(docs/embodied.md). The issue's target is >= 90%; the test asserts it at the end of the run, and
that the run wrote its curve and video. The config's earlier 8 envs x 200 steps failed it on
session 19's host (0.88): it sampled half the layouts.
"""

import pytest

pytest.importorskip("metaworld")

from infinirl.cli import build_config  # noqa: E402
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


#: Other demos as tests: (config, overrides, start at most, end at least). Measured on 2 cores
#: (session 20's host), held-out success at start -> 10 -> 20 -> 30 -> 40 iterations: GRPO 0.00 ->
#: 0.10 -> 0.36 -> 0.70 -> 0.70 in 66 s (session 7's host: 0.62 at 40; seed 1 0.30); flow-PPO 0.00
#: -> 0.20 -> 0.48 -> 0.62 -> 0.78 in 68 s (0.92 on an earlier host); the CNN from pixels, the
#: first 20 of its 40 iterations (20 held-out episodes), 0.00 -> 0.30 -> 0.35 in 229 s (0.45 at 20
#: on session 4's host). The bounds leave room for how far a host's floating point moves a curve
#: (docs/embodied.md) and still fail a run that does not learn: the first evaluation, before any
#: update, is 0.00 for all four.
DEMOS = {
    "embodied GRPO": ("grpo_metaworld_reach", [], 0.1, 0.25),
    "flow-matching PPO": ("ppo_flow_metaworld_reach", [], 0.1, 0.4),
    "CNN from pixels": ("ppo_pixels_metaworld_reach", ["iterations=20"], 0.1, 0.15),
    # push-v3, the first 150 of the demo's 600 iterations on its learning-rate schedule: 0.80 at
    # 150 on an earlier loaded host, 0.60 on session 19's, 0.60 in 344 s on session 21's (0.00 at
    # 0, 50 and 100: push learns late).
    "PPO on push-v3": ("ppo_metaworld_push", ["iterations=150", "actor.anneal_iterations=600"], 0.1, 0.3),
}


@pytest.mark.slow
@pytest.mark.parametrize("demo", list(DEMOS))
def test_demo_improves_held_out_success(ray_cluster, tmp_path, demo):
    name, overrides, start_at_most, end_at_least = DEMOS[demo]
    # as `infinirl train <name> <overrides...>` reads them
    _, cfg = build_config(name, [*overrides, f"output_dir={tmp_path}", "resume=false",
                                 "cluster.log_to_driver=false", "eval.video_episodes=1"])
    assert cfg.eval.at_start, "the first evaluation must be the untrained policy's"
    summary = run(cfg)
    assert summary["eval_success_before"] <= start_at_most, summary
    assert summary["eval_success_after"] >= end_at_least, summary
    assert summary["eval_success_after"] >= summary["eval_success_before"] + min(0.2, end_at_least), summary
    assert (tmp_path / "curves.png").exists() and (tmp_path / "eval.mp4").stat().st_size > 0
    assert list((tmp_path / "tensorboard").iterdir())


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # numpy 2 notes in ManiSkill
def test_ppo_learns_maniskill_push_cube(ray_cluster, tmp_path):
    """The ManiSkill demo (SAPIEN CPU physics, ~4.5 min here). Session 20's host: training success
    (sampled actions) 0.05 (first 10 iterations) -> 0.51 (20-30) -> 0.72-0.79 (50-150); held-out
    success (deterministic) 0.00 -> 0.06 (25) -> 0.08 (50) -> 0.40 (75) -> 0.32 -> 0.24 -> 0.18
    (150): the mean action does worse than the sampled ones late in training (docs/embodied.md)."""
    pytest.importorskip("mani_skill", reason="ManiSkill not installed: pip install mani-skill")
    import json

    raw = compose("ppo_maniskill_pushcube")
    raw.update(output_dir=str(tmp_path), resume=False, cluster={"log_to_driver": False})
    raw["eval"]["video_episodes"] = 1
    try:
        summary = run(to_dataclass(EmbodiedConfig, raw))
    except RuntimeError as error:
        if "rendering device" in str(error):
            pytest.skip("SAPIEN finds no Vulkan device: install Mesa >= 23 mesa-vulkan-drivers "
                        "from bookworm-backports (docs/envs.md)")
        raise
    rows = [json.loads(line) for line in open(tmp_path / "metrics.jsonl")]
    trained = [r["rollout/success_rate"] for r in rows if "rollout/success_rate" in r]
    evals = [r["eval/success_rate"] for r in rows if "eval/success_rate" in r]
    assert sum(trained[:5]) / 5 <= 0.2, trained[:5]
    assert sum(trained[-20:]) / 20 >= 0.5, trained[-20:]
    assert summary["eval_success_before"] <= 0.1 and max(evals) >= 0.2, evals
    assert (tmp_path / "curves.png").exists() and (tmp_path / "eval.mp4").stat().st_size > 0
