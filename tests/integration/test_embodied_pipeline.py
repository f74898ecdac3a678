"""The embodied runner end to end on a fast gymnasium task (Pendulum-v1): it runs in the collocated
and the pipelined placement with the same code, logs, checkpoints, and resumes exactly (the actor's
weights after 4 iterations equal those after 2 + resume + 2, bit for bit); embodied GRPO likewise."""

import json
import os
import shutil
import time

import pytest

pytest.importorskip("gymnasium")

from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.runners.embodied import run  # noqa: E402
from infinirl.runners.embodied_config import EmbodiedConfig, find_cxx_compiler  # noqa: E402
from infinirl.runtime.errors import WorkerError  # noqa: E402
from tests.integration.pins import check_pinned  # noqa: E402
from tests.integration.resume import killed_after_checkpoint  # noqa: E402

PLACEMENTS = {
    "collocated": ({"env": "0", "rollout": "0", "actor": "0"}, 1),
    "pipelined": ({"env": "0", "rollout": "1", "actor": "0-1"}, 2),  # hybrid: actor time-shares both
}


def make_cfg(output_dir, iterations, placement, stages, **extra):
    raw = {
        "iterations": iterations, "rollout_steps": 32, "output_dir": str(output_dir), "save_every": 2,
        "env": {"name": "gym:Pendulum-v1", "num_envs": 4},
        "algorithm": {"epochs": 2, "mini_batches": 4},
        "actor": {"anneal_lr": False},  # the schedule depends on `iterations`; 2 and 4 must match
        "rollout": {"pipeline_stages": stages},
        "eval": {"every": 1, "episodes": 4, "num_envs": 2, "video_episodes": 0},
        "placement": placement, "cluster": {"log_to_driver": False}, **extra,
    }
    return to_dataclass(EmbodiedConfig, raw)


def straight_and_resumed(tmp_path, iterations, placement, stages, **extra):
    """``iterations`` in one run, and the same run resumed from its checkpoint halfway: the resumed
    half trains (moves the weights) and ends bit for bit where the straight run did."""
    extra = {"save_every": iterations // 2, **extra}
    straight = run(make_cfg(tmp_path / "straight", iterations, placement, stages, **extra))
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", iterations // 2)
    resumed = run(make_cfg(tmp_path / "resumed", iterations, placement, stages, **extra))
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert all(r["train/grad_norm"] > 0 for r in rows[iterations // 2 + 1:]), "the resumed half must train"
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]
    return straight, resumed


@pytest.mark.parametrize("mode", list(PLACEMENTS))
def test_runs_and_resumes_exactly(ray_cluster, tmp_path, mode):
    placement, stages = PLACEMENTS[mode]
    straight, resumed = straight_and_resumed(tmp_path, 4, placement, stages)
    assert resumed["env_steps"] == straight["env_steps"] == 4 * 4 * 32
    assert straight["devices"] == {"rollout": "cpu", "actor": "cpu"}  # CPU slots: the policy computes on CPU

    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 1, 2, 3, 4]
    for key in ("rollout/reward_mean", "train/policy_loss", "train/value_loss", "train/grad_norm",
                "train/logprob_mismatch", "rollout/max_staleness", "eval/success_rate", "eval/return_mean",
                "time/env_steps_per_s", "env/steps"):
        assert key in rows[1], key
    assert rows[1]["rollout/act_compiled"] == 0.0  # eager unless rollout.compile
    assert rows[1]["train/peak_memory_bytes"] > 0 and rows[1]["rollout/peak_memory_bytes"] > 0
    # the actor's own PPO update, inside the runner's train time (which also moves the batch there)
    assert 0 < rows[1]["time/actor_update_s"] < rows[1]["time/train_s"]
    assert rows[1]["train/logprob_mismatch"] < 1e-5  # trainer and rollout agree on log-probs
    assert rows[1]["rollout/max_staleness"] == 0.0  # on-policy
    resumed_rows = [json.loads(line) for line in (tmp_path / "resumed" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in resumed_rows] == [0, 1, 2, 3, 4]
    for a, b in zip(rows[1:], resumed_rows[1:]):
        assert a["rollout/reward_mean"] == b["rollout/reward_mean"]
        assert a["eval/return_mean"] == b["eval/return_mean"]
    assert (tmp_path / "straight" / "curves.png").exists()
    assert list((tmp_path / "straight" / "tensorboard").iterdir())
    if mode == "pipelined":  # env and rollout in two processes: the link counts what crosses it
        assert rows[1]["env/bytes_out"] > rows[1]["rollout/bytes_out"] > 0  # observations outweigh actions
    if mode == "collocated":
        check_pinned("embodied", tmp_path / "straight", [
            "rollout/reward_mean", "train/policy_loss", "train/value_loss", "train/approx_kl", "train/grad_norm",
            "train/advantage_std", "eval/return_mean"])


def test_grpo_on_two_tasks_trains_a_task_per_group_and_evaluates_both(ray_cluster, tmp_path):
    """Embodied GRPO on a multi-task name: each group of envs runs one task (task blocks), and the
    evaluation's envs cycle through the tasks again, so both get their held-out episodes."""
    pytest.importorskip("metaworld")
    from infinirl.runners.embodied import run

    cfg = make_cfg(tmp_path / "run", 1, PLACEMENTS["collocated"][0], 1,
                   algorithm={"name": "grpo", "group_size": 2, "epochs": 1, "mini_batches": 2},
                   env={"name": "metaworld:reach-v3,push-v3", "num_envs": 4, "max_episode_steps": 8},
                   rollout_steps=8, eval={"every": 1, "episodes": 4, "num_envs": 2, "video_episodes": 0,
                                          "max_episode_steps": 8})
    summary = run(cfg)
    assert summary["iterations"] == 1
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    last = rows[-1]
    assert last["eval/episodes/reach-v3"] == 2 and last["eval/episodes/push-v3"] == 2
    assert "train/group_return_std_mean" in last

def test_ppo_on_two_tasks_normalises_advantages_per_task_and_grpo_refuses_it(ray_cluster, tmp_path):
    """``algorithm.normalize_advantages_per_task``: each task's advantage scale before the
    normalisation is logged (two pipeline stages: the columns' tasks restart in each); grpo, whose
    groups are normalised already, is refused before anything starts."""
    pytest.importorskip("metaworld")
    two = {"name": "metaworld:reach-v3,push-v3", "num_envs": 4, "max_episode_steps": 8}
    cfg = make_cfg(tmp_path / "run", 1, PLACEMENTS["pipelined"][0], 2, env=two, rollout_steps=8,
                   algorithm={"epochs": 1, "mini_batches": 2, "normalize_advantages_per_task": True},
                   eval={"every": 0, "episodes": 2, "num_envs": 2, "video_episodes": 0})
    run(cfg)
    last = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()][-1]
    assert last["train/advantage_std/reach-v3"] > 0 and last["train/advantage_std/push-v3"] > 0
    assert abs(last["train/advantage_std"] - 1.0) < 0.05  # the trainer's advantages: each task at std 1
    assert last["train/grad_norm"] > 0
    grpo = make_cfg(tmp_path / "grpo", 1, PLACEMENTS["collocated"][0], 1, env=two, rollout_steps=8,
                    algorithm={"name": "grpo", "group_size": 2, "mini_batches": 2,
                               "normalize_advantages_per_task": True})
    with pytest.raises(ConfigError, match=r"^algorithm.normalize_advantages_per_task: algorithm.name=grpo "
                                          r"normalises its advantages within groups of one task already") as error:
        run(grpo)
    assert "\n" not in str(error.value) and not (tmp_path / "grpo").exists()


def test_grpo_runs_and_resumes_exactly(ray_cluster, tmp_path):
    """Embodied GRPO (collocated: the cheap placement; seed groups across ranks and stages are
    checked in tests/unit/test_embodied_grpo.py): 20-step episodes in 32-step rollouts, so each env's
    decisions after its first episode are masked out (20 of 32 trained)."""
    placement, stages = PLACEMENTS["collocated"]
    grpo = {"algorithm": {"name": "grpo", "group_size": 2, "epochs": 2, "mini_batches": 4},
            "env": {"name": "gym:Pendulum-v1", "num_envs": 4, "max_episode_steps": 20},
            "actor": {"num_threads": 0}}  # every core: resumes exactly all the same
    straight_and_resumed(tmp_path, 2, placement, stages, **grpo)

    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 1, 2]
    for key in ("train/group_return_std_zero_frac", "train/group_return_std_mean", "train/advantage_mask_frac",
                "train/policy_loss", "train/logprob_mismatch", "train/approx_kl", "train/grad_norm",
                "rollout/episode_return_mean", "eval/success_rate", "eval/return_mean"):
        assert key in rows[1], key
    assert "train/value_loss" not in rows[1] and "train/reward_scale" not in rows[1]  # no critic, no reward scaling
    assert rows[1]["train/advantage_mask_frac"] == 20 / 32
    assert rows[1]["train/group_return_std_zero_frac"] == 0.0  # sampled actions: returns differ in a group
    assert rows[1]["train/num_threads"] == len(os.sched_getaffinity(0))  # actor.num_threads=0: every core
    assert rows[1]["train/logprob_mismatch"] < 1e-5


@pytest.mark.slow  # compiles on CPU; the compiled step and act have unit tests
@pytest.mark.skipif(find_cxx_compiler() is None,
                    reason="torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")
def test_compiled_actor_and_rollout_train_and_resume_exactly(ray_cluster, tmp_path):
    """actor.compile + rollout.compile: the actor compiles its whole optimizer step, the rollout its
    policy's act, each in its own process; the trainer's log-probs agree with the rollout's, and a
    resumed run recompiles both and continues bit for bit."""
    placement, stages = PLACEMENTS["collocated"]
    compiled = {"actor": {"anneal_lr": False, "compile": True}, "rollout": {"pipeline_stages": stages, "compile": True}}
    straight_and_resumed(tmp_path, 2, placement, stages, **compiled)
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert rows[1]["rollout/act_compiled"] == 1.0
    assert rows[1]["train/logprob_mismatch"] < 1e-5
    assert rows[2]["train/value_loss"] == rows[2]["train/value_loss"]  # not NaN


def test_compile_without_a_compiler_fails_before_workers_start(tmp_path, monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(ConfigError, match="actor.compile=true needs a C\\+\\+ compiler.*set actor.compile=false"):
        make_cfg(tmp_path, 1, PLACEMENTS["collocated"][0], 1, actor={"compile": True})
    with pytest.raises(ConfigError, match="rollout.compile=true needs a C\\+\\+ compiler.*set rollout.compile=false"):
        make_cfg(tmp_path, 1, PLACEMENTS["collocated"][0], 1, rollout={"compile": True})
    make_cfg(tmp_path, 1, PLACEMENTS["collocated"][0], 1)  # compile off: no compiler needed


@pytest.mark.slow  # two whole runs compared
def test_stage_processes_change_where_stages_run_not_what_is_learned(ray_cluster, tmp_path):
    """env.stage_processes: each stage in a process of its own, streaming to the rollout; the same
    envs, seeds and actions as the env worker simulating both stages itself, so the same weights."""
    placement, stages = PLACEMENTS["pipelined"]
    env = {"name": "gym:Pendulum-v1", "num_envs": 4}
    plain = run(make_cfg(tmp_path / "plain", 2, placement, stages, env=env))
    staged = run(make_cfg(tmp_path / "staged", 2, placement, stages, env={**env, "stage_processes": True}))
    assert staged["actor_weights_sha256"] == plain["actor_weights_sha256"]
    rows = [json.loads(line) for line in (tmp_path / "staged" / "metrics.jsonl").read_text().splitlines()]
    assert rows[1]["env/simulate_max_stage_s"] > 0


def test_stage_processes_need_the_env_on_its_own_resources(ray_cluster, tmp_path):
    env = {"name": "gym:Pendulum-v1", "num_envs": 4, "stage_processes": True}
    cfg = make_cfg(tmp_path, 1, PLACEMENTS["collocated"][0], 1, env=env)
    with pytest.raises(ConfigError, match="env.stage_processes=true needs the env on its own resources"):
        run(cfg)
    with pytest.raises(ConfigError, match="rollout.transport=channel is not supported with it"):
        make_cfg(tmp_path, 1, PLACEMENTS["pipelined"][0], 2, env=env,
                 rollout={"pipeline_stages": 2, "transport": "channel"})


@pytest.mark.timeout(300)  # without the env's error reaching the rollout, the run waited forever
# The socket transport in the slow tier (the default suite's time budget): the root cause travels
# the same way; the channel transport, the one with its own waits, stays in the default suite.
@pytest.mark.parametrize("transport", [pytest.param("socket", marks=pytest.mark.slow), "channel"])
def test_an_env_failing_mid_collection_stops_the_run_with_its_root_cause(ray_cluster, tmp_path, transport):
    """The env on its own slot, in its own process (no stage processes): its envs reset, then the
    first step raises (gravity is not a number) and max_restarts=0 makes that crash final. The env
    rank closes its link, the rollout stops waiting, and the run fails with the env's error."""
    placement, stages = PLACEMENTS["pipelined"]
    env = {"name": "gym:Pendulum-v1", "num_envs": 4, "kwargs": {"g": "not a number"}, "max_restarts": 0}
    cfg = make_cfg(tmp_path / "run", 2, placement, stages, env=env,
                   rollout={"pipeline_stages": stages, "transport": transport},
                   eval={"every": 100, "at_start": False, "episodes": 2, "num_envs": 2, "video_episodes": 0})
    start = time.monotonic()
    with pytest.raises(WorkerError) as raised:
        run(cfg)
    assert time.monotonic() - start < 180
    error = raised.value
    assert error.component == "env", error
    assert "EnvCrashError" in error.traceback_text and "unsupported operand" in error.traceback_text


def test_closing_a_channel_link_ends_the_other_ends_wait(ray_cluster):
    """Over the channel transport as over a socket: what was sent still arrives, then the other
    end's recv fails with EnvLinkClosed instead of waiting forever (a channel link used to only
    flush on close)."""
    import uuid

    from infinirl.components.env_link import EnvLinkClosed, accept, connect, open_server
    from infinirl.runtime import Channel

    names = (f"link-{uuid.uuid4().hex}-to-rollout", f"link-{uuid.uuid4().hex}-to-env")
    channels = [Channel.create(name, pipeline_depth=2) for name in names]  # held: Ray kills unreferenced actors
    server, address = open_server("channel", names)
    env_side = accept(server)
    rollout_side = connect(address)
    env_side.send({"obs": 1})
    env_side.close()
    env_side.close()  # closing twice is harmless
    assert rollout_side.recv() == {"obs": 1}
    with pytest.raises(EnvLinkClosed):
        rollout_side.recv()
    rollout_side.close()
    with pytest.raises(EnvLinkClosed):
        env_side.recv()
    for channel in channels:
        channel.destroy()


def test_bad_names_fail_before_workers_start():
    with pytest.raises(ConfigError, match="unknown env family 'gymm'.*registered: .*gym.*metaworld"):
        make_cfg("/tmp/x", 1, PLACEMENTS["collocated"][0], 1, env={"name": "gymm:Pendulum-v1", "num_envs": 4})
    with pytest.raises(ConfigError, match="policy.name='mlp'.*registered: .*mlp_gaussian"):
        make_cfg("/tmp/x", 1, PLACEMENTS["collocated"][0], 1, policy={"name": "mlp"})
    with pytest.raises(ConfigError, match="mini_batches=3 does not divide"):
        make_cfg("/tmp/x", 1, PLACEMENTS["collocated"][0], 1, algorithm={"mini_batches": 3})
    with pytest.raises(ConfigError, match="placement.learner: the embodied runner has no such component; its "
                                          "components are env, rollout, actor"):
        make_cfg("/tmp/x", 1, {"env": "0", "rollout": "0", "learner": "0"}, 1)
    with pytest.raises(ConfigError, match="actor.num_threads=-1 must be >= 0"):
        make_cfg("/tmp/x", 1, PLACEMENTS["collocated"][0], 1, actor={"num_threads": -1})
    with pytest.raises(ConfigError, match="rollout.pipeline_stages=0 must be >= 1"):
        make_cfg("/tmp/x", 1, PLACEMENTS["collocated"][0], 0)
    with pytest.raises(ConfigError, match="algorithm.group_size=3 does not divide env.num_envs=4"):
        make_cfg("/tmp/x", 1, PLACEMENTS["collocated"][0], 1, algorithm={"name": "grpo", "group_size": 3})


def test_unknown_task_fails_in_the_driver(tmp_path):
    cfg = make_cfg(tmp_path, 1, PLACEMENTS["collocated"][0], 1, env={"name": "gym:Pendulum-v9", "num_envs": 4})
    with pytest.raises(ConfigError, match="Pendulum-v9"):
        run(cfg)


@pytest.mark.slow  # two whole runs compared; the eta=1 run stays in the default tier
def test_asynchronous_eta_0_is_the_synchronous_run(ray_cluster, tmp_path):
    placement, stages = PLACEMENTS["collocated"]
    quiet = {"eval": {"every": 100, "at_start": False, "episodes": 2, "num_envs": 2, "video_episodes": 0},
             "save_every": 100}
    synchronous = run(make_cfg(tmp_path / "sync", 2, placement, stages, **quiet))
    eta0 = run(make_cfg(tmp_path / "eta0", 2, placement, stages, **quiet,
                        algorithm={"epochs": 2, "mini_batches": 4, "asynchronous": {"max_staleness": 0}}))
    assert eta0["actor_weights_sha256"] == synchronous["actor_weights_sha256"]


def test_asynchronous_eta_1_with_decoupled_ppo_resumes_exactly(ray_cluster, tmp_path):
    """Pipelined (env in its own process): the env's serve calls queue ahead like the rollout's."""
    placement, stages = PLACEMENTS["pipelined"]
    algorithm = {"epochs": 2, "mini_batches": 4, "asynchronous": {"max_staleness": 1}, "is_cap": 2.0,
                 "is_cap_mode": "mask"}
    straight_and_resumed(tmp_path, 4, placement, stages, algorithm=algorithm)
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    trained = [r for r in rows if "train/policy_loss" in r]
    assert [r["async/staleness_max"] for r in trained] == [0.0, 1.0, 1.0, 1.0]
    # the proximal policy is the trainer's own: batch 0 is on-policy, later ones carry a version gap
    assert trained[0]["train/behaviour_logprob_abs_diff"] < 1e-5 < trained[2]["train/behaviour_logprob_abs_diff"]
    assert all(0 < r["train/is_weight_mean"] for r in trained)
    # env steps per second of the rollout ranks' own collection, not of the trainer's wait for a
    # trajectory collected ahead (near zero)
    steps = [b["env/steps"] - a for a, b in zip([0] + [r["env/steps"] for r in trained], trained)]
    assert all(r["time/env_steps_per_s"] * r["rollout/collect_s"] == pytest.approx(n, rel=1e-6)
               for r, n in zip(trained, steps))
    # Every evaluation first waits for the collections in flight (their time is training time, not
    # the evaluation's); the pins below show the wait changes no sample.
    evals = [r for r in rows if "eval/success_rate" in r]
    assert len(evals) == 5 and all(r["time/eval_drain_s"] >= 0 for r in evals)
    check_pinned("embodied_async", tmp_path / "straight", [
        "rollout/reward_mean", "train/policy_loss", "train/value_loss", "train/is_weight_mean", "eval/success_rate"])
