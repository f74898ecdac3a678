"""Task sources: a training run's held-out problems, and evaluating only those with ``from_run``."""

import json

import pytest

from infinirl.config import ConfigError
from infinirl.tasks.config import TaskConfig
from infinirl.tasks.problem import normalize_question
from infinirl.tasks.sources import eval_problems, training_problems, verifier_for


def test_reasoning_gym_eval_of_a_run_is_its_held_out_set_whatever_the_limit():
    task = TaskConfig()
    _, held_out = training_problems(task, seed=0)
    assert len(held_out) == task.eval_size
    assert eval_problems(task, "test", 200, from_run=True) == held_out
    assert eval_problems(task, "test", 10, from_run=True) == held_out[:10]
    assert len(eval_problems(task, "test", 100)) == 100  # not a run's task: as many as asked for


def write_rows(path, questions):
    path.write_text("".join(json.dumps({"question": q, "answer": str(i)}) + "\n" for i, q in enumerate(questions)))
    return path


def test_data_file_training_excludes_held_out_questions_by_text(tmp_path):
    # "What is 1+1?" is held out (row 1) and repeats further down, differing in case and spacing only.
    questions = ["What is 0+0?", "What is 1+1?", "What is 2+2?", "What is 3+3?", "what is  1+1?", "What is 4+4?"]
    task = TaskConfig(source="dataset", name=str(write_rows(tmp_path / "rows.jsonl", questions)), verifier="math",
                      eval_size=2)
    stream, held_out = training_problems(task, seed=0)
    held_out_keys = {normalize_question(p.metadata["question"]) for p in held_out}
    assert held_out_keys == {"what is 0+0?", "what is 1+1?"}
    trained = {normalize_question(p.metadata["question"]) for p in stream.next_batch(12)}
    assert trained == {"what is 2+2?", "what is 3+3?", "what is 4+4?"}


def test_data_file_with_nothing_left_to_train_on_is_refused(tmp_path):
    path = write_rows(tmp_path / "rows.jsonl", ["Q a", "Q b", "q  a", "Q B"])
    with pytest.raises(ConfigError, match="leaves none to train on"):
        training_problems(TaskConfig(source="dataset", name=str(path), verifier="math", eval_size=2), seed=0)


TOY = "infinirl.tasks.toy_rewards:response_length"


@pytest.mark.parametrize("task", [
    TaskConfig(eval_size=4),
    TaskConfig(eval_size=4, verifier=TOY),
    TaskConfig(source="dataset", name="gsm8k", eval_size=4),
    TaskConfig(source="dataset", name="gsm8k", eval_size=4, verifier="math"),
    TaskConfig(source="dataset", name="gsm8k", eval_size=4, verifier=TOY),
    TaskConfig(source="fictional_kb", name="fictional_kb", config={}, eval_size=4),
    TaskConfig(source="fictional_kb", name="fictional_kb", config={}, eval_size=4, verifier=TOY),
    TaskConfig(source="code", name="functions", config={}, eval_size=2),
], ids=["gym", "gym-user-function", "gsm8k-preset", "gsm8k-preset-math", "gsm8k-preset-user-function",
        "kb", "kb-user-function", "code"])
def test_problems_name_the_verifier_their_source_scores_with(task, tmp_path, monkeypatch):
    # The reward worker scores each problem by the verifier it names: the source's choice, and
    # task.verifier where the user set one.
    if task.name == "gsm8k":  # a preset reads INFINIRL_DATA_DIR: give it GSM8K-shaped files of its own
        from infinirl.tasks.datasets import DATA_DIR_ENV

        for split in ("train", "test"):
            rows = [{"question": f"{split} question {i}?", "answer": f"Work.\n#### {i}"} for i in range(12)]
            path = tmp_path / "gsm8k" / f"{split}.jsonl"
            path.parent.mkdir(exist_ok=True)
            path.write_text("".join(json.dumps(row) + "\n" for row in rows))
        monkeypatch.setenv(DATA_DIR_ENV, str(tmp_path))
    stream, held_out = training_problems(task, seed=0)
    expected = verifier_for(task, "test")
    assert expected != "reasoning_gym" or task.source == "reasoning_gym"
    assert expected == task.verifier or task.verifier == "reasoning_gym"
    assert {p.verifier for p in held_out + stream.next_batch(2) + eval_problems(task, "test", 2)} == {expected}


def test_held_out_rows_of_a_data_file_ask_each_question_once(tmp_path):
    # Rows 0-3 are held out; row 2 repeats row 0's question (case and spacing aside).
    questions = ["What is 0+0?", "What is 1+1?", "what is  0+0?", "What is 3+3?", "What is 4+4?", "What is 5+5?"]
    task = TaskConfig(source="dataset", name=str(write_rows(tmp_path / "rows.jsonl", questions)), verifier="math",
                      eval_size=4)
    _, held_out = training_problems(task, seed=0)
    assert [p.metadata["question"] for p in held_out] == ["What is 0+0?", "What is 1+1?", "What is 3+3?"]
    assert [p.answer for p in held_out] == ["0", "1", "3"]  # the first row of a question is kept
    assert eval_problems(task, "test", None, from_run=True) == held_out


def test_a_few_shot_example_showing_a_held_out_question_is_refused(tmp_path):
    questions = ["What is 0+0?", "What is 1+1?", "What is 2+2?", "What is 3+3?"]
    path = str(write_rows(tmp_path / "rows.jsonl", questions))
    leaking = [{"user": "What is 2+2?", "assistant": "#### 4"}, {"user": "Solve: what is 1+1?", "assistant": "#### 2"}]
    task = TaskConfig(source="dataset", name=path, verifier="math", eval_size=2, few_shot=leaking)
    with pytest.raises(ConfigError, match=r"task.few_shot\[1\] shows the question 'what is 1\+1\?'"):
        training_problems(task, seed=0)
    with pytest.raises(ConfigError, match=r"task.few_shot\[1\]"):
        eval_problems(task, "test", None, from_run=True)
    # An example from the training rows is fine.
    training_problems(TaskConfig(source="dataset", name=path, verifier="math", eval_size=2, few_shot=leaking[:1]),
                      seed=0)


@pytest.mark.parametrize(("task", "expected"), [
    (TaskConfig(source="dataset", name="gsm8k"), "marker"),
    (TaskConfig(source="dataset", name="math500"), "boxed"),
    (TaskConfig(source="dataset", name="rows.jsonl"), "marker"),
    (TaskConfig(source="fictional_kb", name="fictional_kb", config={}), "tagged"),
    (TaskConfig(), None),
    (TaskConfig(answer_format="tagged"), "tagged"),
    (TaskConfig(source="dataset", name="math500", answer_format="marker"), "marker"),
], ids=["gsm8k", "math500", "data-file", "kb", "gym", "gym-set", "math500-set"])
def test_the_answer_format_is_the_tasks_or_its_sources(task, expected):
    from infinirl.tasks.sources import answer_format_for

    assert answer_format_for(task) == expected


def test_a_format_bonus_without_an_answer_format_or_with_a_bad_one_is_refused():
    with pytest.raises(ConfigError, match="task.format_bonus=0.1 needs task.answer_format"):
        TaskConfig(format_bonus=0.1).validate()
    with pytest.raises(ConfigError, match="task.answer_format='bold' is not an answer extractor"):
        TaskConfig(answer_format="bold").validate()
    TaskConfig(format_bonus=0.1, answer_format="tagged").validate()
    TaskConfig(source="dataset", name="gsm8k", verifier="gsm8k", format_bonus=0.1).validate()
