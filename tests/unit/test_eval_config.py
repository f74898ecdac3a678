"""`infinirl eval` config: a training run's folder resolves to its checkpoint, model, actor and
task; bad input is a config error naming the key, before any worker starts."""

import json

import pytest

from infinirl.cli import main
from infinirl.config import ConfigError, to_dataclass, to_plain
from infinirl.evaluation.config import EvalConfig
from infinirl.runners.reasoning_config import ReasoningConfig
from infinirl.tasks.datasets import preset_path


def fake_run(root, steps=(2, 4)):
    """A run folder as the reasoning runner leaves it: config.json and checkpoints/step_N/actor/."""
    run = ReasoningConfig(output_dir=str(root))
    run.actor.lora = {"r": 4, "alpha": 8.0}
    run.rollout.max_new_tokens = 17
    run.rollout.stop_strings = ["\n\n"]
    run.task.name, run.task.eval_size = "basic_arithmetic", 5
    root.mkdir(parents=True, exist_ok=True)
    (root / "config.json").write_text(json.dumps(to_plain(run)))
    for step in steps:
        (root / "checkpoints" / f"step_{step:06d}" / "actor").mkdir(parents=True)
    (root / "checkpoints" / "step_000009.tmp" / "actor").mkdir(parents=True)  # unfinished save: ignored
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

def test_a_runs_data_file_contributes_only_its_held_out_rows(tmp_path):
    from infinirl.evaluation.runner import load_problems

    data = tmp_path / "rows.jsonl"
    data.write_text("".join(json.dumps({"question": f"{i}+1?", "answer": str(i + 1)}) + "\n" for i in range(10)))
    run = fake_run(tmp_path / "run")
    raw = json.loads((run / "config.json").read_text())
    raw["task"].update(source="dataset", name=str(data), verifier="math", eval_size=3)
    (run / "config.json").write_text(json.dumps(raw))
    plan = to_dataclass(EvalConfig, {"run_dir": str(run)}).resolve()
    assert [p.uid for p in load_problems(plan, "test", None)] == ["rows/0", "rows/1", "rows/2"]
    own = to_dataclass(EvalConfig, {"run_dir": str(run), "task": {**raw["task"]}}).resolve()
    assert len(load_problems(own, "test", None)) == 10  # a task given explicitly: the whole file


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
