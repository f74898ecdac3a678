"""Bad input through the command line, as a new user types it: every case exits with code 2 and
one line naming the key or file and the fix, with no traceback, and starts no worker (nor Ray,
where the config and the files alone show the error).

The cases run in-process through ``infinirl.cli.main``; Ray's start and every worker launch are
patched to fail the test if reached, except for the few cases that need the cluster's inventory
to be known (a placement beyond the cluster's slots), which must still start no worker.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from infinirl.cli import main


@pytest.fixture
def no_workers(monkeypatch):
    """Fails the test if any component starts; ``cluster_ok=False`` also if Ray starts."""
    import ray

    from infinirl.runtime import worker

    state = {"cluster_ok": False}
    real_init = ray.init

    def launch(*args, **kwargs):
        raise AssertionError("a worker was started although the input was bad")

    def init(*args, **kwargs):
        if not state["cluster_ok"]:
            raise AssertionError("Ray was started although the config and files show the error")
        return real_init(*args, **kwargs)

    monkeypatch.setattr(worker.WorkerGroup, "launch", classmethod(launch))
    monkeypatch.setattr(ray, "init", init)
    return state


def _files(tmp_path, tiny_llama_dir) -> dict[str, str]:
    """Files the cases point at: a broken model folder, data files, an unwritable output folder."""
    paths = {"model": tiny_llama_dir, "tmp": str(tmp_path)}
    bad_json = tmp_path / "bad_json_model"
    bad_json.mkdir()
    (bad_json / "config.json").write_text("{not json")
    paths["bad_json_model"] = str(bad_json)
    unknown_arch = tmp_path / "unknown_arch_model"
    unknown_arch.mkdir()
    (unknown_arch / "config.json").write_text(json.dumps({"model_type": "no_such_architecture"}))
    paths["unknown_arch_model"] = str(unknown_arch)
    no_config = tmp_path / "no_config_model"
    no_config.mkdir()
    paths["no_config_model"] = str(no_config)
    (tmp_path / "empty.jsonl").write_text("")
    (tmp_path / "malformed.jsonl").write_text('{"question": "1+1", "answer": "2"}\n{broken\n')
    (tmp_path / "no_answer.jsonl").write_text('{"question": "1+1"}\n' * 4)
    (tmp_path / "few.jsonl").write_text('{"question": "1+1", "answer": "2"}\n' * 2)
    (tmp_path / "table.csv").write_text("question,answer\n1+1,2\n")
    paths.update({name: str(tmp_path / f"{name}.jsonl") for name in ("empty", "malformed", "no_answer", "few")})
    paths["csv"] = str(tmp_path / "table.csv")
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    paths["unwritable"] = str(blocker / "run")  # a folder inside a file cannot be made
    return paths


# (command line, a fragment the one-line error must contain). <key> expands to _files()'s paths.
R = ["train", "default", "output_dir=<tmp>/out"]
TINY = [*R, "model.path=<model>"]
DATA = [*TINY, "task.source=dataset", "task.verifier=math"]
REACH = ["train", "ppo_metaworld_reach", "output_dir=<tmp>/out"]
GYM = [*REACH, "env.name=gym:Pendulum-v1", "eval.env_kwargs={}"]
SAC = ["train", "sac_inverted_pendulum", "output_dir=<tmp>/out"]
CASES = {
    # the command line itself
    "unknown config": (["train", "defualt"], "no config named 'defualt'"),
    "unknown key": ([*R, "iteratons=3"], "Did you mean 'iterations'"),
    "unknown nested key": ([*R, "rollout.max_new_token=5"], "Did you mean 'rollout.max_new_tokens'"),
    "override without =": ([*R, "iterations"], "has no '='"),
    "override syntax": ([*R, "iterations=[1,2"], "no viable alternative"),
    "wrong type": ([*R, "iterations=many"], "iterations: expected an integer, got 'many'"),
    "section given a number": ([*R, "actor=3"], "actor: expected a mapping"),
    "runner changed": ([*R, "runner=embodied"], "runner=embodied: config 'default' is for the 'reasoning' runner"),
    "eval of a training config": (["eval", "default"], "is a training config"),
    "old and new key together": ([*R, "steps=3", "iterations=4"], "both 'steps' and its new name 'iterations'"),
    "renamed key with a bad value": ([*R, "steps=0"], "iterations=0 must be >= 1"),
    "not a choice": ([*R, "reference.mode=copy"], "reference.mode='copy' is not allowed"),
    "unknown logger": ([*R, "loggers=[tensorbord]"], "unknown logger 'tensorbord'"),
    "logger as a string": ([*R, "loggers=tensorboard"], "loggers: expected a list"),
    # reasoning: numbers
    "zero iterations": ([*R, "iterations=0"], "iterations=0 must be >= 1"),
    "zero prompts": ([*R, "prompts_per_step=0"], "prompts_per_step=0 must be >= 1"),
    "negative learning rate": ([*R, "actor.lr=-1e-4"], "actor.lr=-0.0001 must be > 0"),
    "zero micro-batch": ([*R, "actor.micro_batch_size=0"], "actor.micro_batch_size=0 must be >= 1"),
    "zero new tokens": ([*R, "rollout.max_new_tokens=0"], "rollout.max_new_tokens=0 must be >= 1"),
    "zero group": ([*R, "rollout.group_size=0"], "rollout.group_size=0 must be >= 1"),
    "zero temperature": ([*R, "rollout.temperature=0"], "rollout.temperature=0.0 must be > 0"),
    "top_p above one": ([*R, "rollout.top_p=1.5"], "rollout.top_p=1.5 must be in (0, 1]"),
    "negative eval cadence": ([*R, "eval.every=-1"], "eval.every=-1 must be >= 0"),
    "negative keep": ([*R, "keep_checkpoints=-2"], "keep_checkpoints=-2 must be >= 0"),
    "mini-batches not dividing": ([*R, "algorithm.mini_batches=3"], "algorithm.mini_batches=3 does not divide"),
    "warmup negative": ([*R, "actor.warmup_steps=-1"], "actor.warmup_steps=-1 must be >= 0"),
    "negative gradient clip": ([*R, "actor.grad_clip=-1"], "actor.grad_clip=-1.0 must be >= 0"),
    "Adam beta above one": ([*R, "actor.betas=[1.5,0.9]"], "actor.betas=[1.5, 0.9]: every entry must be in [0, 1)"),
    "one Adam beta": ([*R, "actor.betas=[0.9]"], "actor.betas: expected 2 values, got [0.9]"),
    "LoRA rank zero": ([*R, "actor.lora.r=0"], "actor.lora.r=0 must be >= 1"),
    "LoRA dropout above one": ([*R, "actor.lora.dropout=2.0"], "actor.lora.dropout=2.0 must be in [0, 1)"),
    "LoRA negative top layers": ([*R, "actor.lora.top_layers=-1"], "actor.lora.top_layers=-1 must be >= 0"),
    "critic LoRA rank zero": ([*R, "algorithm.advantage=gae", "critic.lora={r: 0}"], "critic.lora.r=0 must be >= 1"),
    "unknown rollout dtype": ([*R, "model.rollout_dtype=bf17"], "model.rollout_dtype='bf17' is not a dtype"),
    "negative held-out seed": ([*R, "task.eval_seed=-1"], "task.eval_seed=-1 must be >= 0"),
    # reasoning: names
    "unknown advantage": ([*R, "algorithm.advantage=grpoo"], "algorithm.advantage='grpoo' is not registered"),
    "unknown rollout engine": ([*R, "rollout.engine=sglang"], "rollout.engine='sglang' is not registered"),
    "unknown verifier": ([*R, "task.verifier=exact"], "task.verifier='exact': unknown verifier"),
    "verifier module missing": ([*R, "task.verifier=no_such_pkg.rewards:score"], "cannot import module"),
    "verifier function missing": ([*R, "task.verifier=infinirl.tasks.toy_rewards:no_such"],
                                  "has no attribute 'no_such'"),
    "unknown task source": ([*R, "task.source=hub"], "task.source='hub' is not registered"),
    "unknown generator": ([*TINY, "task.name=no_such_task"], "unknown reasoning-gym task 'no_such_task'"),
    "KL reward ignored by grpo": ([*R, "algorithm.kl_reward_coef=0.1"], "kl_reward_coef > 0 with algorithm.advantage"),
    "reference base without LoRA": ([*R, "actor.lora=null", "reference.mode=actor_base",
                                     "algorithm.objective.kl_coef=0.1"], "reference.mode=actor_base needs actor.lora"),
    "gae option misspelt": ([*R, "algorithm.advantage=gae", "algorithm.advantage_kwargs={lambda: 0.9}"],
                            "gae takes gamma, lam, not lambda"),
    "prompt over the limit": ([*TINY, "rollout.max_prompt_length=4"], "rollout.max_prompt_length=4: eval prompt"),
    # reasoning: files
    "model folder missing": ([*R, "model.path=/no/such/model"], "model.path='/no/such/model' is not a folder"),
    "model config not JSON": ([*R, "model.path=<bad_json_model>"], "config.json is not valid JSON"),
    "model of unknown architecture": ([*R, "model.path=<unknown_arch_model>"], "model_type 'no_such_architecture'"),
    "model folder without config": ([*R, "model.path=<no_config_model>"], "has no config.json"),
    "critic folder missing": ([*R, "algorithm.advantage=gae", "critic.model_path=/no/critic"],
                              "critic.model_path='/no/critic' is not a folder"),
    "data file missing": ([*DATA, "task.name=<tmp>/none.jsonl"], "is neither a dataset preset"),
    "data file empty": ([*DATA, "task.name=<empty>"], "has no rows"),
    "data file malformed": ([*DATA, "task.name=<malformed>"], "malformed.jsonl:2: not valid JSON"),
    "data rows without the answer": ([*DATA, "task.name=<no_answer>"], "has no key 'answer'"),
    "data file all held out": ([*DATA, "task.name=<few>", "task.eval_size=2"], "which leaves none to train on"),
    "data file of unknown type": ([*DATA, "task.name=<csv>"], "unsupported file type '.csv'"),
    "data rows and the gym verifier": ([*TINY, "task.source=dataset", "task.name=<few>"],
                                       "task.verifier=reasoning_gym cannot score rows of a data file"),
    "output folder unwritable": (["train", "default", "output_dir=<unwritable>"], "cannot be written"),
    # placement
    "unknown component": ([*R, "placement.critc=0"], "placement.critc: the reasoning runner has no such component"),
    "malformed placement": ([*R, "placement.actor=0-x"], "placement.actor"),
    "placement as a list": ([*R, "placement.actor=[0,1]"], "placement.actor: expected a string"),
    # embodied
    "unknown env family": ([*REACH, "env.name=gymm:Pendulum-v1"], "unknown env family 'gymm'"),
    "unknown env task": ([*GYM, "env.name=gym:NoSuchEnv-v0"], "NoSuchEnv-v0"),
    "env option of another simulator": ([*REACH, "env.name=gym:Pendulum-v1"],
                                        "eval.env_kwargs: gym env 'Pendulum-v1' does not take 'terminate_on_success'"),
    "unknown env option": ([*GYM, "env.kwargs={bogus: 1}"], "env.kwargs: gym env 'Pendulum-v1' does not take 'bogus'"),
    "unknown video option": ([*GYM, "eval.video_env_kwargs={bogus: 1}"], "eval.video_env_kwargs"),
    "unknown policy": ([*REACH, "policy.name=mlp"], "policy.name='mlp' is not registered"),
    "unknown policy option": ([*GYM, "policy.kwargs={bogus: 1}"], "bogus"),
    "unknown policy option key": ([*GYM, "policy.kwargs.hiddn=[1]"], "hiddn"),
    "cloning data missing": ([*REACH, "algorithm.bc.data=/nonexistent"], "algorithm.bc"),
    "ppo clip above one": ([*REACH, "algorithm.clip=1.5"], "algorithm.clip=1.5 must be in (0, 1)"),
    "zero discount": ([*REACH, "algorithm.gamma=0"], "algorithm.gamma=0.0 must be in (0, 1]"),
    "grpo groups not dividing": ([*REACH, "algorithm.name=grpo", "algorithm.group_size=3"],
                                 "algorithm.group_size=3 does not divide env.num_envs=16"),
    "grpo group of one": ([*REACH, "algorithm.name=grpo", "algorithm.group_size=1"], "group_size=1 must be >= 2"),
    "anneal horizon short": ([*REACH, "actor.anneal_iterations=5"], "actor.anneal_iterations=5 < iterations=50"),
    "embodied mini-batches": ([*REACH, "algorithm.mini_batches=7"], "algorithm.mini_batches=7 does not divide"),
    "stage processes over a channel": ([*REACH, "env.stage_processes=true", "rollout.transport=channel"],
                                       "rollout.transport=channel is not supported"),
    "embodied unknown component": ([*REACH, "placement.learner=0"], "placement.learner: the embodied runner"),
    "zero pipeline stages": ([*REACH, "rollout.pipeline_stages=0"], "rollout.pipeline_stages=0 must be >= 1"),
    "negative eval seed": ([*REACH, "eval.seed=-1"], "eval.seed=-1 must be >= 0"),
    # SAC
    "warm-up below the batch": ([*SAC, "algorithm.learning_starts=10"], "learning_starts=10 must be >="),
    "two learner ranks": ([*SAC, "placement.learner=0-1"], "runs one learner rank"),
    "observation field missing": ([*SAC, "network.obs_key=pixels"], "network.obs_key='pixels'"),
    "discrete actions": ([*SAC, "env.name=gym:CartPole-v1", "eval.video_env_kwargs={}"],
                         "SAC needs a continuous (Box) space"),
    "SAC-Flow without noise": ([*SAC, "network.actor=flow", "network.flow={noise_method: flow_sde}"],
                               "SAC-Flow needs flow_noise"),
    "zero Polyak": ([*SAC, "algorithm.tau=0"], "algorithm.tau=0.0 must be in (0, 1]"),
    "two workers per env": ([*SAC, "env.num_workers=2"], "env.num_workers=2 must be in [0, 1]"),
    "hidden layer of width zero": ([*SAC, "network.actor_hidden=[64,0]"], "every entry must be >= 1"),
    "SAC old target key and new": ([*SAC, "eval.target_return=5", "eval.target=6"], "both 'eval.target_return'"),
    # eval
    "pass@k above samples": (["eval", "k=8"], "k=8 is larger than samples=4"),
    "eval of no run": (["eval", "run_dir=/no/such/run"], "run_dir='/no/such/run' is not a folder"),
    "nothing to evaluate": (["eval", "samples=0", "greedy=false"], "nothing to evaluate"),
    "eval limit zero": (["eval", "limit=0"], "limit=0 must be >= 1"),
    # the runtime demo
    "demo zero iterations": (["train", "runtime_demo", "iterations=0"], "iterations=0 must be >= 1"),
}
# Known only once the cluster's inventory is (Ray starts, no worker does).
NEEDS_CLUSTER = {
    "placement beyond the slots": ([*TINY, "placement.actor=7", "cluster.log_to_driver=false"],
                                   "placement for 'actor': CPU slot 7 does not exist (cluster has"),
    "stage processes collocated": ([*GYM, "env.stage_processes=true", "cluster.log_to_driver=false"],
                                   "env.stage_processes=true needs the env on its own resources"),
}


_NOT_THE_ERROR = ("infinirl: config key '", "Token authentication is enabled")


def _expand(arg: str, paths: dict[str, str]) -> str:
    for name, path in paths.items():
        arg = arg.replace(f"<{name}>", path)
    return arg


def _run(args, paths, capsys):
    code = main([_expand(arg, paths) for arg in args])
    err = capsys.readouterr().err
    # Ray's own start-up notice and our renamed-key warnings are not the error.
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith(_NOT_THE_ERROR)]
    return code, lines, err


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_naming_the_fix(case, tmp_path, tiny_llama_dir, capsys, no_workers):
    args, fragment = CASES[case]
    if any("metaworld" in arg for arg in args) or args[1] == "ppo_metaworld_reach":
        pytest.importorskip("metaworld")
    if args[1].startswith("sac") or any("gym:" in arg for arg in args):
        pytest.importorskip("gymnasium")
    code, lines, err = _run(args, _files(tmp_path, tiny_llama_dir), capsys)
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("infinirl: config error: "), err
    assert fragment in lines[0], lines[0]
    assert "Traceback" not in err
    assert not os.path.exists(tmp_path / "out"), "a refused run left an output folder"


# `infinirl validate` runs the runners' driver-side checks too (RunnerSpec.preflight): what train
# refuses from the config and its files, validate refuses with the same line.
VALIDATE_CASES = ("unknown env option", "unknown policy option", "unknown policy option key", "cloning data missing",
                  "unknown video option", "data file missing", "data file malformed", "data rows without the answer",
                  "prompt over the limit", "observation field missing", "discrete actions")


@pytest.mark.parametrize("case", VALIDATE_CASES)
def test_validate_refuses_what_train_refuses(case, tmp_path, tiny_llama_dir, capsys, no_workers):
    args, fragment = CASES[case]
    if any("metaworld" in arg for arg in args) or args[1] == "ppo_metaworld_reach":
        pytest.importorskip("metaworld")
    if args[1].startswith("sac") or any("gym:" in arg for arg in args):
        pytest.importorskip("gymnasium")
    code, lines, err = _run(["validate", *args[1:]], _files(tmp_path, tiny_llama_dir), capsys)
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("infinirl: config error: ") and fragment in lines[0], err
    assert not os.path.exists(tmp_path / "out")


@pytest.mark.parametrize("case", list(NEEDS_CLUSTER))
def test_bad_input_known_from_the_cluster_starts_no_worker(case, tmp_path, tiny_llama_dir, capsys, no_workers):
    pytest.importorskip("gymnasium")
    no_workers["cluster_ok"] = True
    args, fragment = NEEDS_CLUSTER[case]
    code, lines, err = _run(args, _files(tmp_path, tiny_llama_dir), capsys)
    assert code == 2, err
    assert len(lines) == 1 and fragment in lines[0], err
    assert not os.path.exists(tmp_path / "out")


OFT_FIXTURE = Path(__file__).parents[1] / "fixtures" / "vla_oft"
# The shipped OpenVLA-OFT config (bf16 weights) on the tiny published-format checkpoint.
OFT = ["train", "grpo_openvla_oft_libero", "output_dir=<tmp>/out",
       f"policy.kwargs.checkpoint={OFT_FIXTURE / 'openvla_oft'}",
       f"policy.kwargs.architecture={OFT_FIXTURE / 'architecture.json'}",
       "policy.kwargs.unnorm_key=tiny_libero_no_noops", "env.kwargs={image_size: 32}"]


@pytest.fixture
def bf16_kept(monkeypatch):
    """bf16 weights stay bf16 on this CPU (on one without native bf16 they would load as float32)."""
    from infinirl.engines.cpu_dtype import cpu_bf16_is_fast

    monkeypatch.setenv("INFINIRL_CPU_BF16", "1")
    cpu_bf16_is_fast.cache_clear()
    yield
    monkeypatch.delenv("INFINIRL_CPU_BF16")
    cpu_bf16_is_fast.cache_clear()


@pytest.mark.parametrize("dtype", ["bfloat16", "float16"])
def test_a_compiled_update_of_low_precision_weights_is_one_line(dtype, tmp_path, tiny_llama_dir, capsys, no_workers,
                                                                 bf16_kept):
    """The compiled step keeps no float32 master weights: refused by the driver, not by the actor's
    first update after the workers started and the first rollout ran."""
    pytest.importorskip("libero")
    args = [*OFT, f"policy.kwargs.dtype={dtype}", "actor.compile=true"]
    code, lines, err = _run(args, _files(tmp_path, tiny_llama_dir), capsys)
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("infinirl: config error: "), err
    assert (f"actor.compile=true: policy openvla_oft trains {dtype} weights (policy.kwargs.dtype={dtype})"
            in lines[0]), lines[0]
    assert lines[0].endswith("set actor.compile=false or policy.kwargs.dtype=float32"), lines[0]
    assert "Traceback" not in err
    assert not os.path.exists(tmp_path / "out")


def test_there_are_at_least_sixty_distinct_cases():
    assert len(CASES) + len(NEEDS_CLUSTER) >= 60


def test_an_unreachable_cluster_is_one_line_and_exit_code_1(tmp_path, tiny_llama_dir, capsys, no_workers):
    args = [*TINY, "cluster.address=127.0.0.1:1", "cluster.connect_timeout_s=1"]
    code, lines, err = _run(args, _files(tmp_path, tiny_llama_dir), capsys)
    assert code == 1, err
    assert len(lines) == 1 and lines[0].startswith("infinirl: ClusterError: cannot reach the Ray head"), err
    assert "Traceback" not in err
