"""`infinirl eval` config: a training run's folder resolves to its checkpoint, model, actor and
task; bad input is a config error naming the key, before any worker starts."""

import json
import os
from pathlib import Path

import pytest

from infinirl.agents.loop import AgentConfig
from infinirl.cli import build_config, main
from infinirl.config import ConfigError, to_dataclass, to_plain
from infinirl.engines.vllm_process import vllm_available
from infinirl.evaluation.config import EvalConfig
from infinirl.runners.checkpoints import Checkpoints
from infinirl.runners.reasoning_config import ReasoningConfig
from infinirl.tasks.datasets import preset_path


def fake_run(root, steps=(2, 4), agent=None):
    """A run folder as the reasoning runner leaves it: config.json and checkpoints/step_N/ with
    actor/ and runner_state.json (step_N folders predate manifests)."""
    run = ReasoningConfig(output_dir=str(root))
    run.actor.lora = {"r": 4, "alpha": 8.0}
    run.rollout.max_new_tokens = 17
    run.rollout.stop_strings = ["\n\n"]
    run.task.name, run.task.eval_size = "basic_arithmetic", 5
    if agent is not None:  # the tools the agent offers are named to the model
        run.task.system_prompt = "Write <calculator>expression</calculator> to compute."
    root.mkdir(parents=True, exist_ok=True)
    raw = to_plain(run)
    raw["rollout"]["agent"] = agent
    (root / "config.json").write_text(json.dumps(raw))
    for step in steps:
        (root / "checkpoints" / f"step_{step:06d}" / "actor").mkdir(parents=True)
        (root / "checkpoints" / f"step_{step:06d}" / "runner_state.json").write_text(json.dumps({"step": step}))
    (root / "checkpoints" / "step_000009.tmp" / "actor").mkdir(parents=True)  # unfinished save: ignored
    return root


def committed_run(root, steps=(2, 4)):
    """A run folder whose checkpoints were written as the loop writes them: iter_N with a manifest."""
    fake_run(root, steps=())
    folders = Checkpoints(str(root))
    for step in steps:
        tmp = folders.begin(step)
        os.makedirs(os.path.join(tmp, "actor"))
        with open(os.path.join(tmp, "actor", "weights.distcp"), "w") as handle:
            handle.write("w" * 100)
        folders.commit(tmp, step, {"iteration": step})
    return root


def test_run_dir_resolves_to_latest_checkpoint_and_the_runs_settings(tmp_path):
    run = fake_run(tmp_path / "run")
    plan = to_dataclass(EvalConfig, {"run_dir": str(run)}).resolve()
    assert plan.checkpoint == run / "checkpoints" / "step_000004" and plan.step == 4
    assert plan.actor.lora.r == 4 and plan.model_path == "smollm2-135m-instruct"
    assert plan.task.name == "basic_arithmetic" and plan.task.eval_size == 5 and plan.verifier == "reasoning_gym"
    assert plan.max_new_tokens == 17 and plan.stop_strings == ["\n\n"]
    assert plan.output == run / "eval" / "basic_arithmetic-step_000004.json"

    for given in ("2", "step_000002", str(run / "checkpoints" / "step_000002")):
        plan = to_dataclass(EvalConfig, {"run_dir": str(run), "checkpoint": given, "max_new_tokens": 9}).resolve()
        assert plan.step == 2 and plan.max_new_tokens == 9
    plan = to_dataclass(EvalConfig, {"checkpoint": str(run / "checkpoints" / "step_000002")}).resolve()
    assert plan.run_dir == run.resolve() and plan.actor.lora.r == 4  # run folder found from the checkpoint



def test_initial_checkpoint_is_the_runs_starting_model_in_the_runs_setting(tmp_path):
    """checkpoint=initial: the baseline a run is compared against, i.e. its model.path untrained,
    with the run's task, budget and agent, and no actor to load."""
    run = fake_run(tmp_path / "run", steps=())
    plan = to_dataclass(EvalConfig, {"run_dir": str(run), "checkpoint": "initial"}).resolve()
    assert plan.checkpoint is None and plan.step == 0 and plan.run_dir == run
    assert plan.model_path == "smollm2-135m-instruct" and plan.task.name == "basic_arithmetic"
    assert plan.max_new_tokens == 17 and plan.stop_strings == ["\n\n"]
    assert plan.output == run / "eval" / "basic_arithmetic-initial.json"
    cfg = to_dataclass(EvalConfig, {"run_dir": str(run), "checkpoint": "initial", "placement": {"rollout": "0",
                                                                                              "reward": "0"}})
    cfg.validate()  # no actor placed: nothing to load
    with pytest.raises(ConfigError, match="checkpoint='initial' needs run_dir"):
        to_dataclass(EvalConfig, {"checkpoint": "initial"}).resolve()

def test_a_runs_data_file_contributes_only_its_held_out_rows(tmp_path, capsys, monkeypatch):
    from infinirl.evaluation.runner import load_problems

    data = tmp_path / "rows.jsonl"
    data.write_text("".join(json.dumps({"question": f"{i}+1?", "answer": str(i + 1)}) + "\n" for i in range(10)))
    run = fake_run(tmp_path / "run")
    raw = json.loads((run / "config.json").read_text())
    raw["task"].update(source="dataset", name=str(data), verifier="math", eval_size=3)
    (run / "config.json").write_text(json.dumps(raw))
    plan = to_dataclass(EvalConfig, {"run_dir": str(run)}).resolve()
    held_out = ["rows/0", "rows/1", "rows/2"]
    assert [p.uid for p in load_problems(plan, "test", None)] == held_out
    # The run's task stated again, only its prompt changed (the file named by another path): still
    # the run's data, so still only its held-out rows, and results of their own.
    monkeypatch.chdir(tmp_path)
    restated = {**raw["task"], "name": "rows.jsonl", "system_prompt": "Think step by step."}
    own = to_dataclass(EvalConfig, {"run_dir": str(run), "task": restated}).resolve()
    assert own.task_from_run and [p.uid for p in load_problems(own, "test", None)] == held_out
    assert own.output != plan.output and own.output.parent == plan.output.parent
    assert [p.uid for p in load_problems(own, "test", 8)] == held_out  # limit is capped at eval_size ...
    assert "limit=8 is capped at the run's task.eval_size=3" in capsys.readouterr().out  # ... and says so
    other = to_dataclass(EvalConfig, {"run_dir": str(run), "task": {**raw["task"], "eval_size": 6}}).resolve()
    assert not other.task_from_run and len(load_problems(other, "test", None)) == 10  # another split: the file


def test_a_runs_generator_task_stated_again_is_its_held_out_set(tmp_path, capsys):
    from infinirl.evaluation.runner import load_problems

    run = fake_run(tmp_path / "run")
    task = {**json.loads((run / "config.json").read_text())["task"], "system_prompt": "Answer with a number."}
    plan = to_dataclass(EvalConfig, {"run_dir": str(run), "task": task, "limit": 50}).resolve()
    assert plan.task_from_run and plan.task.system_prompt == "Answer with a number."
    assert len(load_problems(plan, "test", 50)) == 5  # the run's eval_size, not the generator's next 45
    assert "capped at the run's task.eval_size=5" in capsys.readouterr().out


def test_default_output_names_tell_result_changing_settings_apart(tmp_path):
    run = fake_run(tmp_path / "run")

    def output(**raw):
        return to_dataclass(EvalConfig, {"run_dir": str(run), **raw}).resolve().output.name

    default = "basic_arithmetic-step_000004.json"
    assert output() == default  # defaults keep the documented name
    assert output(max_new_tokens=17, stop_strings=["\n\n"], progress=False, num_threads=2) == default
    changed = {"limit": 3, "samples": 8, "temperature": 0.7, "max_new_tokens": 64, "split": "train",
               "greedy": False, "seed": 1, "rollout": {"max_batch_size": 8}, "model": {"rollout_dtype": "bfloat16"}}
    names = {key: output(**{key: value}) for key, value in changed.items()}
    # (an environment that needs nothing named in the prompt: the task here names no tool)
    names["agent"] = output(rollout={"agent": {"env": "infinirl.agents.toy_envs:EchoEnv", "max_turns": 2}})
    assert output(single_turn=True, rollout={"agent": {"max_turns": 2}}) == default  # the run has no agent
    for key, name in names.items():
        assert name.startswith("basic_arithmetic-step_000004-") and name != default, key
    assert len(set(names.values())) == len(names)  # every setting gives results of their own
    assert output(limit=3) == names["limit"]  # the same settings: the same name, run after run
    assert output(samples=0) == output(samples=0, temperature=0.5, k=[1, 8])  # greedy only: sampling is unused
    base = to_dataclass(EvalConfig, {}).resolve().output
    assert str(base) == "runs/eval/chain_sum-smollm2-135m-instruct.json"
    assert to_dataclass(EvalConfig, {"limit": 2}).resolve().output.name.startswith("chain_sum-smollm2-135m-instruct-")


def test_a_damaged_or_unfinished_checkpoint_is_refused_before_workers_start(tmp_path, capsys):
    run = committed_run(tmp_path / "run")
    plan = to_dataclass(EvalConfig, {"run_dir": str(run)}).resolve()
    assert plan.checkpoint == run / "checkpoints" / "iter_000004" and plan.step == 4
    os.truncate(run / "checkpoints" / "iter_000004" / "actor" / "weights.distcp", 10)
    with pytest.raises(ConfigError, match=r"iter_000004/actor/weights.distcp is truncated or altered \(10 bytes, "
                                          r"written with 100\); evaluate another checkpoint with checkpoint="
                                          r".*iter_000002, iter_000004"):
        to_dataclass(EvalConfig, {"run_dir": str(run)})
    assert to_dataclass(EvalConfig, {"run_dir": str(run), "checkpoint": "2"}).resolve().step == 2
    (run / "checkpoints" / "iter_000002" / "runner_state.json").unlink()
    with pytest.raises(ConfigError, match="iter_000002/runner_state.json is missing"):
        to_dataclass(EvalConfig, {"run_dir": str(run), "checkpoint": "iter_000002"})
    unfinished = Checkpoints(str(run)).begin(6)
    os.makedirs(os.path.join(unfinished, "actor"))
    for given in ("iter_000006.tmp", unfinished):
        with pytest.raises(ConfigError, match=r"iter_000006.tmp is a save that never finished"):
            to_dataclass(EvalConfig, {"run_dir": str(run), "checkpoint": given})
        with pytest.raises(ConfigError, match=r"iter_000006.tmp is a save that never finished"):
            to_dataclass(EvalConfig, {"checkpoint": str(run / "checkpoints" / "iter_000006.tmp")})
    assert main(["eval", f"run_dir={run}", "checkpoint=iter_000006.tmp"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "pick a finished one" in err


def test_one_agent_key_given_keeps_the_rest_of_the_runs_agent(tmp_path):
    agent = {"env": "tools", "env_options": {"call_format": "hermes", "max_calls_per_turn": 2}, "max_turns": 3,
             "schedule": "lockstep"}
    run = fake_run(tmp_path / "run", agent=agent)
    assert to_plain(to_dataclass(EvalConfig, {"run_dir": str(run)}).resolve().agent) == {**to_plain(AgentConfig()),
                                                                                         **agent}
    _, cfg = build_config("eval", [f"run_dir={run}", "rollout.agent.max_turns=2",
                                   "rollout.agent.env_options.max_calls_per_turn=1"], "eval")
    plan = cfg.resolve()
    assert plan.agent.max_turns == 2 and plan.agent.schedule == "lockstep" and plan.agent.env == "tools"
    assert plan.output.name.startswith("basic_arithmetic-step_000004-")
    single = to_dataclass(EvalConfig, {"run_dir": str(run), "single_turn": True}).resolve()
    assert single.agent is None and single.output.name not in (plan.output.name, "basic_arithmetic-step_000004.json")
    assert plan.agent.env_options == {"call_format": "hermes", "max_calls_per_turn": 1}
    named = {"system_prompt": "Write <calculator>expression</calculator> to compute."}
    plain = to_dataclass(EvalConfig, {"rollout": {"agent": {"max_turns": 2}}, "task": named}).resolve()
    assert plain.agent.env_options == {}
    with pytest.raises(ConfigError, match="never name the tool"):  # the model would never hear of the calculator
        to_dataclass(EvalConfig, {"rollout": {"agent": {"max_turns": 2}}})
    with pytest.raises(ConfigError, match="unknown config key 'rollout.agent.max_trns'"):
        to_dataclass(EvalConfig, {"run_dir": str(run), "rollout": {"agent": {"max_trns": 2}}})
    with pytest.raises(ConfigError, match="rollout.agent.max_turns=0 must be >= 1"):
        to_dataclass(EvalConfig, {"run_dir": str(run), "rollout": {"agent": {"max_turns": 0}}})


def test_greedy_only_needs_no_k():
    from infinirl.evaluation.runner import sampling_passes

    cfg = to_dataclass(EvalConfig, {"samples": 0})  # k keeps its default [1, 4]: not used without samples
    assert list(sampling_passes(cfg, cfg.resolve())) == ["greedy"]
    with pytest.raises(ConfigError, match="k=8 is larger than samples=4"):
        to_dataclass(EvalConfig, {"samples": 4, "k": 8})


def test_k_may_be_one_number():
    assert to_dataclass(EvalConfig, {"samples": 8, "k": 8}).ks == [8]


def test_base_model_eval_needs_no_run():
    plan = to_dataclass(EvalConfig, {}).resolve()
    assert plan.checkpoint is None and plan.actor is None and plan.max_new_tokens == 256
    assert plan.task.source == "reasoning_gym" and str(plan.output).startswith("runs/eval/chain_sum-")


@pytest.mark.skipif(not preset_path("gsm8k", "test").is_file(), reason="GSM8K data not present (INFINIRL_DATA_DIR)")
def test_dataset_preset_brings_its_verifier():
    cfg = to_dataclass(EvalConfig, {"task": {"source": "dataset", "name": "gsm8k"}, "limit": 3})
    plan = cfg.resolve()
    assert plan.verifier == "gsm8k" and plan.output.name.startswith("gsm8k-test-")
    from infinirl.evaluation.runner import load_problems

    problems = load_problems(plan, cfg.split, cfg.limit)
    assert len(problems) == 3 and problems[0].verifier == "gsm8k"


def test_cli_rejects_bad_input_naming_the_key(tmp_path, capsys):
    def error_of(*overrides):
        assert main(["eval", *overrides]) == 2
        return capsys.readouterr().err

    assert "k=8 is larger than samples=4" in error_of("k=8")
    assert "k=3 is larger than samples=2" in error_of("samples=2", "k=[1,3]")
    assert "task.name='gsm9k' is neither a dataset preset" in error_of("task.source=dataset", "task.name=gsm9k")
    assert "split='dev'" in error_of("task.source=dataset", "task.name=math500", "split=dev")
    assert "run_dir=" in error_of(f"run_dir={tmp_path / 'missing'}")
    run = fake_run(tmp_path / "run")
    err = error_of(f"run_dir={run}", "checkpoint=7")
    assert "checkpoint='7'" in err and "step_000002, step_000004" in err
    assert "checkpoint=latest" in error_of(f"run_dir={fake_run(tmp_path / 'fresh', steps=())}")
    (tmp_path / "noconfig" / "checkpoints" / "step_000001" / "actor").mkdir(parents=True)
    (tmp_path / "noconfig" / "checkpoints" / "step_000001" / "runner_state.json").write_text("{}")
    assert "has no config.json" in error_of(f"run_dir={tmp_path / 'noconfig'}")
    assert "unknown config key 'task.nme'" in error_of("task.nme=gsm8k")
    assert "is a training config" in error_of("grpo_chain_sum")


def test_bad_dataset_rows_fail_before_workers_start(tmp_path, capsys):
    data = tmp_path / "problems.jsonl"
    data.write_text(json.dumps({"q": "1+1?", "a": "2"}) + "\n")
    assert main(["eval", "task.source=dataset", f"task.name={data}", "task.verifier=gsm8k"]) == 2
    err = capsys.readouterr().err
    assert "no key 'question'" in err and "prompt_key" in err
    assert main(["eval", "task.source=dataset", f"task.name={data}"]) == 2
    assert "task.verifier=reasoning_gym cannot score" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="samples=0 and greedy=false"):
        to_dataclass(EvalConfig, {"samples": 0, "k": [], "greedy": False})


@pytest.mark.skipif(vllm_available(), reason="vLLM is installed here")
def test_the_vllm_engine_without_vllm_installed_is_a_config_error():
    with pytest.raises(ConfigError, match=r"rollout.engine=vllm: vLLM is not installed"):
        to_dataclass(EvalConfig, {"rollout": {"engine": "vllm"}})


def test_a_vllm_engine_gets_a_context_length_holding_the_longest_prompt():
    from infinirl.evaluation.runner import rollout_engine_options
    from infinirl.models.hf_causal_lm import byte_level_tokenizer
    from infinirl.tasks.problem import Problem
    from infinirl.tasks.prompts import encode_prompts

    cfg = to_dataclass(EvalConfig, {"max_new_tokens": 32})
    plan = cfg.resolve()
    tokenizer = byte_level_tokenizer()
    problems = [Problem(uid=str(i), prompt="What is 1 + 1?" * (i + 1), answer="2", verifier="math") for i in range(3)]
    longest = max(len(ids) for ids in encode_prompts(problems, tokenizer, plan.task.system_prompt))
    assert rollout_engine_options(cfg, plan, problems, tokenizer) == {}  # the hf engine: as given
    cfg.rollout.engine = "vllm"  # after validation: vLLM need not be installed to build the options
    assert rollout_engine_options(cfg, plan, problems, tokenizer) == {"max_model_len": longest + 32}
    cfg.rollout.engine_options = {"max_model_len": longest + 31}
    with pytest.raises(ConfigError, match=rf"max_model_len={longest + 31} is shorter .*the longest prompt={longest} "
                                          rf"\+ max_new_tokens=32 = {longest + 32} tokens"):
        rollout_engine_options(cfg, plan, problems, tokenizer)


def data_run(root, data, state_inputs):
    """A run on the data file ``data`` whose checkpoint iter_000002 recorded ``state_inputs``."""
    fake_run(root, steps=())
    raw = json.loads((root / "config.json").read_text())
    raw["task"].update(source="dataset", name=str(data), verifier="math", eval_size=3)
    (root / "config.json").write_text(json.dumps(raw))
    folders = Checkpoints(str(root))
    tmp = folders.begin(2)
    os.makedirs(os.path.join(tmp, "actor"))
    folders.commit(tmp, 2, {"iteration": 2, "inputs": state_inputs})
    return root, raw["task"]


def test_a_runs_data_file_changed_since_its_checkpoint_is_refused(tmp_path):
    """The held-out rows of a run's own data file are its first task.eval_size: on an edited file
    they may be rows the checkpoint trained on, so the evaluation is refused, naming the file."""
    from infinirl.evaluation.runner import check_run_data, preflight
    from infinirl.runners.run_inputs import file_digest

    data = tmp_path / "rows.jsonl"
    rows = [{"question": f"{i}+1?", "answer": str(i + 1)} for i in range(10)]
    data.write_text("".join(json.dumps(row) + "\n" for row in rows))
    run, task = data_run(tmp_path / "run", data, {"data": {"task.name": file_digest(data)}})
    check_run_data(to_dataclass(EvalConfig, {"run_dir": str(run)}).resolve())  # the same rows: evaluated
    data.write_text("".join(json.dumps(row) + "\n" for row in rows[::-1]))
    with pytest.raises(ConfigError, match=rf"^run_dir: task.name {data} is not the file .*iter_000002 trained on "
                                          r"\(.* bytes, sha256 [0-9a-f]{12}; now .*\); its held-out rows would not "
                                          r"be the ones the run held out") as error:
        preflight(to_dataclass(EvalConfig, {"run_dir": str(run)}))
    assert "\n" not in str(error.value)
    # Other data from the same file (another held-out size) is not the run's: evaluated as it is.
    check_run_data(to_dataclass(EvalConfig, {"run_dir": str(run), "task": {**task, "eval_size": 6}}).resolve())


def test_validate_loads_the_problems_and_the_tokenizer_and_checks_the_context(tmp_path, tiny_llama_dir, capsys):
    """What `infinirl eval` refuses before its workers start, validate refuses too."""
    def error_of(*overrides):
        assert main(["validate", "eval", f"model.path={tiny_llama_dir}", *overrides]) == 2
        err = capsys.readouterr().err
        assert err.startswith("infinirl: config error: ") and err.count("\n") == 1, err
        return err

    rows = tmp_path / "rows.jsonl"
    rows.write_text(json.dumps({"question": "1+1?", "answer": "2"}) + "\n")
    (tmp_path / "empty.jsonl").write_text("")
    (tmp_path / "no_answer.jsonl").write_text(json.dumps({"question": "1+1?"}) + "\n")
    dataset = ["task.source=dataset", "task.verifier=math"]
    assert main(["validate", "eval", f"model.path={tiny_llama_dir}", *dataset, f"task.name={rows}"]) == 0
    assert "has no rows" in error_of(*dataset, f"task.name={tmp_path / 'empty.jsonl'}")
    assert "no key 'answer'" in error_of(*dataset, f"task.name={tmp_path / 'no_answer.jsonl'}")
    assert "unknown" in error_of("task.name=basic_arithmetc").lower()
    err = error_of(*dataset, f"task.name={rows}", "max_new_tokens=2040")
    assert "max_new_tokens=2040: prompt 'rows/0' is" in err and "more than the model's context (2048" in err
    no_tokenizer = tmp_path / "no_tokenizer"
    no_tokenizer.mkdir()
    (no_tokenizer / "config.json").write_text((Path(tiny_llama_dir) / "config.json").read_text())
    assert main(["validate", "eval", f"model.path={no_tokenizer}", *dataset, f"task.name={rows}"]) == 2
    assert f"model.path={no_tokenizer}: no tokenizer loads from it" in capsys.readouterr().err
