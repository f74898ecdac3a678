"""File loaders, presets, data-dir resolution and the resumable epoch iterator."""

import json
from collections import Counter

import pytest

from infinirl.tasks.datasets import (
    DATA_DIR_ENV,
    EpochBatchIterator,
    data_dir,
    load_preset,
    load_problems,
    preset_path,
    read_rows,
)
from infinirl.tasks.prompts import NUMBER_ANSWER_TEMPLATE
from infinirl.tasks.verifiers import safe_score


@pytest.fixture
def gsm8k_like(tmp_path):
    path = tmp_path / "mini.jsonl"
    rows = [
        {"question": "What is 2 + 3?", "answer": "2 + 3 = 5\n#### 5", "level": 1},
        {"question": "What is 1000 * 2?", "answer": "...\n#### 2,000", "level": 2},
    ]
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n\n")
    return path


def test_jsonl_loader_applies_extractor_template_and_metadata(gsm8k_like):
    problems = load_problems(
        gsm8k_like,
        prompt_key="question",
        answer_key="answer",
        verifier="gsm8k",
        answer_extractor="gsm8k",
        metadata_keys=["level"],
    )
    assert [p.answer for p in problems] == ["5", "2000"]
    assert [p.uid for p in problems] == ["mini/0", "mini/1"]
    assert problems[0].prompt == NUMBER_ANSWER_TEMPLATE.replace("{question}", "What is 2 + 3?")
    assert problems[1].metadata == {"question": "What is 1000 * 2?", "level": 2}
    assert safe_score("#### 2,000", problems[1]).correct


def test_custom_extractor_and_template(gsm8k_like):
    problems = load_problems(
        gsm8k_like,
        prompt_key="question",
        answer_key="answer",
        verifier="gsm8k",
        answer_extractor=lambda text: text.split()[-1],
        prompt_template="Q: {question} A:",
        limit=1,
    )
    assert len(problems) == 1
    assert problems[0].prompt == "Q: What is 2 + 3? A:" and problems[0].answer == "5"


def test_missing_file_names_the_path(tmp_path):
    missing = tmp_path / "nope.jsonl"
    with pytest.raises(FileNotFoundError, match="nope.jsonl"):
        load_problems(missing, prompt_key="q", answer_key="a", verifier="gsm8k")


def test_absent_key_names_the_key_and_shows_the_row_keys(gsm8k_like):
    with pytest.raises(KeyError) as raised:
        load_problems(gsm8k_like, prompt_key="prompt", answer_key="answer", verifier="gsm8k")
    message = str(raised.value)
    assert "'prompt'" in message and "['answer', 'level', 'question']" in message


def test_bad_json_line_is_reported_with_its_line_number(tmp_path):
    path = tmp_path / "bad.jsonl"
    path.write_text('{"a": 1}\n{oops\n')
    with pytest.raises(ValueError, match="bad.jsonl:2"):
        read_rows(path)


def test_unsupported_suffix_lists_supported_ones(tmp_path):
    path = tmp_path / "data.csv"
    path.write_text("a,b\n")
    with pytest.raises(ValueError, match=r"\.jsonl"):
        read_rows(path)


def test_parquet_loader(tmp_path):
    parquet = pytest.importorskip("pyarrow.parquet", reason="pyarrow not installed (optional, Parquet only)")
    import pyarrow

    path = tmp_path / "mini.parquet"
    parquet.write_table(pyarrow.table({"problem": ["1+1?"], "solution": ["2"]}), path)
    problems = load_problems(path, prompt_key="problem", answer_key="solution", verifier="math")
    assert problems[0].answer == "2" and problems[0].uid == "mini/0"


def test_template_without_placeholder_is_rejected(gsm8k_like):
    with pytest.raises(ValueError, match="no \\{question\\} placeholder"):
        load_problems(gsm8k_like, prompt_key="question", answer_key="answer", verifier="gsm8k",
                      prompt_template="Solve it.")


def test_data_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(DATA_DIR_ENV, str(tmp_path))
    assert data_dir() == tmp_path
    assert preset_path("gsm8k", "train") == tmp_path / "gsm8k" / "train.jsonl"
    monkeypatch.delenv(DATA_DIR_ENV)
    assert data_dir().parts[-2:] == ("shared", "data")


def test_preset_errors(tmp_path):
    with pytest.raises(ValueError, match="no split 'train'; available: \\['test'\\]"):
        preset_path("math500", "train")
    with pytest.raises(KeyError, match="gsm8k"):
        preset_path("gsm9k", "test")
    with pytest.raises(FileNotFoundError, match=str(tmp_path)):
        load_preset("gsm8k", "test", root=tmp_path)


def _require_preset(name, split):
    path = preset_path(name, split)
    if not path.is_file():
        pytest.skip(f"{path} not found; set {DATA_DIR_ENV} to the shared data directory to run this")


def test_gsm8k_preset_reads_the_shared_data():
    _require_preset("gsm8k", "test")
    problems = load_preset("gsm8k", "test")
    assert len(problems) == 1319
    assert problems[0].answer == "18" and problems[0].verifier == "gsm8k"
    assert all(safe_score(f"#### {p.answer}", p).correct for p in problems)


def test_math500_preset_reads_the_shared_data():
    _require_preset("math500", "test")
    problems = load_preset("math500", "test", limit=20)
    assert len(problems) == 20 and problems[0].verifier == "math"
    assert "\\boxed{}" in problems[0].prompt and "level" in problems[0].metadata


# --- EpochBatchIterator ------------------------------------------------------------------------


def test_each_epoch_visits_every_item_once_in_a_fresh_order():
    iterator = EpochBatchIterator(list(range(10)), seed=7)
    first, second = iterator.next_batch(10), iterator.next_batch(10)
    assert sorted(first) == sorted(second) == list(range(10))
    assert first != second
    assert iterator.epoch == 1


def test_batches_cross_epoch_boundaries_with_fixed_size():
    iterator = EpochBatchIterator(list(range(5)), seed=0)
    batches = [iterator.next_batch(3) for _ in range(5)]  # 15 items = 3 epochs
    assert all(len(b) == 3 for b in batches)
    assert Counter(x for b in batches for x in b) == Counter({i: 3 for i in range(5)})


def test_unshuffled_iteration_is_in_order():
    assert EpochBatchIterator("abc", shuffle=False).next_batch(5) == list("abcab")


def test_epoch_iterator_resume_continues_exactly():
    iterator = EpochBatchIterator(list(range(23)), seed=3)
    for _ in range(10):
        iterator.next_batch(4)
    state = iterator.state_dict()
    expected = [iterator.next_batch(4) for _ in range(5)]
    restored = EpochBatchIterator(list(range(23)), seed=3)
    restored.load_state_dict(state)
    assert [restored.next_batch(4) for _ in range(5)] == expected


def test_epoch_iterator_refuses_a_mismatched_checkpoint():
    from infinirl.config import ConfigError

    state = EpochBatchIterator(list(range(5)), seed=1).state_dict()
    # one line naming the fix, as the command line prints a config error (resume refuses changed data
    # files before any worker starts; this is what a checkpoint recorded without their digests meets)
    with pytest.raises(ConfigError, match=r"seed=1 over 5 items.*start over with resume=false"):
        EpochBatchIterator(list(range(6)), seed=1).load_state_dict(state)


def test_epoch_iterator_argument_errors():
    with pytest.raises(ValueError, match="empty"):
        EpochBatchIterator([])
    with pytest.raises(ValueError, match="positive"):
        EpochBatchIterator([1]).next_batch(0)
