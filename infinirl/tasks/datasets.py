"""File-backed problem sets (JSONL, Parquet), named presets, and a resumable batch iterator.

Data is never bundled: presets resolve under a data directory given by ``INFINIRL_DATA_DIR``
(default ``<repo>/../shared/data``), so a clone without the data still imports and trains on
generated tasks; only loading a preset fails, with a message saying where it looked.
"""

from __future__ import annotations

import json
import os
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from infinirl.registry import Registry
from infinirl.tasks.answers import extract_after_marker
from infinirl.tasks.problem import Problem
from infinirl.tasks.prompts import BOXED_ANSWER_TEMPLATE, NUMBER_ANSWER_TEMPLATE, render_prompt

DATA_DIR_ENV = "INFINIRL_DATA_DIR"
_REPO_ROOT = Path(__file__).resolve().parents[2]

Row = dict[str, Any]
GoldExtractor = Callable[[str], str]


def data_dir() -> Path:
    """Where supplied datasets live: ``$INFINIRL_DATA_DIR`` or ``<repo>/../shared/data``."""
    configured = os.environ.get(DATA_DIR_ENV)
    return Path(configured) if configured else _REPO_ROOT.parent / "shared" / "data"


# --- reading rows ------------------------------------------------------------------------------

ROW_READERS: Registry[Callable[[Path], list[Row]]] = Registry("row reader")


@ROW_READERS.register(".jsonl")
def read_jsonl(path: Path) -> list[Row]:
    """One JSON object per non-empty line; a bad line is reported with its line number."""
    rows = []
    with open(path, encoding="utf-8") as handle:
        for line_number, line in enumerate(handle, start=1):
            if not line.strip():
                continue
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError as error:
                raise ValueError(f"{path}:{line_number}: not valid JSON ({error})") from None
    return rows


@ROW_READERS.register(".parquet")
def read_parquet(path: Path) -> list[Row]:
    """Rows of a Parquet file; needs ``pyarrow``, imported lazily since only this reader uses it."""
    try:
        import pyarrow.parquet as parquet
    except ImportError:
        raise ImportError(
            f"reading {path} needs pyarrow, which is not installed; run `pip install pyarrow` "
            "or convert the file to JSONL."
        ) from None
    return parquet.read_table(path).to_pylist()


def read_rows(path: str | Path) -> list[Row]:
    """Rows of a data file, reader chosen by suffix."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"data file {path} does not exist; check the path (presets read from "
            f"${DATA_DIR_ENV}, currently {data_dir()})."
        )
    if path.suffix not in ROW_READERS:
        raise ValueError(
            f"cannot read {path}: unsupported suffix {path.suffix!r}; "
            f"supported: {ROW_READERS.names()}"
        )
    return ROW_READERS.get(path.suffix)(path)


# --- ground-truth answer extraction ------------------------------------------------------------

GOLD_EXTRACTORS: Registry[GoldExtractor] = Registry("gold answer extractor")
GOLD_EXTRACTORS.add("identity", lambda text: text.strip())


@GOLD_EXTRACTORS.register("gsm8k")
def extract_gsm8k_gold(solution: str) -> str:
    """``"...worked solution...\\n#### 1,234"`` -> ``"1234"``."""
    final = extract_after_marker(solution)
    if final is None:
        raise ValueError(f"GSM8K solution has no '#### <answer>' line: {solution[-80:]!r}")
    return final.replace(",", "")


# --- problems from files -----------------------------------------------------------------------


def _require_key(row: Row, key: str, path: Path, row_index: int) -> Any:
    if key not in row:
        raise KeyError(
            f"{path} row {row_index} has no key {key!r}; its keys are {sorted(row)}. "
            "Set prompt_key/answer_key to one of them."
        )
    return row[key]


def load_problems(
    path: str | Path,
    *,
    prompt_key: str,
    answer_key: str,
    verifier: str,
    answer_extractor: str | GoldExtractor = "identity",
    prompt_template: str = NUMBER_ANSWER_TEMPLATE,
    uid_prefix: str | None = None,
    metadata_keys: Sequence[str] = (),
    limit: int | None = None,
) -> list[Problem]:
    """Read a JSONL/Parquet file into Problems.

    Args:
        prompt_key / answer_key: row fields holding the question and the ground truth.
        verifier: verifier name stored on every problem (see `verifiers.py`).
        answer_extractor: registry name (``"identity"``, ``"gsm8k"``) or a function turning the
            answer field into the bare answer string.
        prompt_template: instruction wrapped around the question; must match the verifier's
            expected answer format (see `prompts.py`).
        uid_prefix: uids are ``f"{uid_prefix}/{row_index}"``; defaults to the file stem.
        metadata_keys: extra row fields copied into ``Problem.metadata`` (e.g. ``level``).
        limit: keep only the first ``limit`` rows (quick evals).
    """
    path = Path(path)
    rows = read_rows(path)[:limit]
    extract = (
        GOLD_EXTRACTORS.get(answer_extractor)
        if isinstance(answer_extractor, str)
        else answer_extractor
    )
    prefix = uid_prefix if uid_prefix is not None else path.stem
    problems = []
    for index, row in enumerate(rows):
        question = str(_require_key(row, prompt_key, path, index))
        answer = extract(str(_require_key(row, answer_key, path, index)))
        metadata = {key: _require_key(row, key, path, index) for key in metadata_keys}
        problems.append(
            Problem(
                uid=f"{prefix}/{index}",
                prompt=render_prompt(question, prompt_template),
                answer=answer,
                verifier=verifier,
                metadata={"question": question, **metadata},
            )
        )
    return problems


# --- named presets -----------------------------------------------------------------------------


@dataclass(frozen=True)
class DatasetPreset:
    """How to read one supplied dataset: ``<data_dir>/<folder>/<split>.jsonl`` plus its fields."""

    folder: str
    splits: tuple[str, ...]
    prompt_key: str
    answer_key: str
    verifier: str
    answer_extractor: str
    prompt_template: str
    answer_format: str
    """The answer extractor matching ``prompt_template``'s instruction (what a format bonus checks)."""
    metadata_keys: tuple[str, ...] = ()


DATASET_PRESETS: Registry[DatasetPreset] = Registry("dataset preset")
DATASET_PRESETS.add(
    "gsm8k",
    DatasetPreset(
        folder="gsm8k",
        splits=("train", "test"),
        prompt_key="question",
        answer_key="answer",
        verifier="gsm8k",
        answer_extractor="gsm8k",
        prompt_template=NUMBER_ANSWER_TEMPLATE,
        answer_format="marker",
    ),
)
DATASET_PRESETS.add(
    "math500",
    DatasetPreset(
        folder="math500",
        splits=("test",),
        prompt_key="problem",
        answer_key="answer",
        verifier="math",
        answer_extractor="identity",
        prompt_template=BOXED_ANSWER_TEMPLATE,
        answer_format="boxed",
        metadata_keys=("subject", "level", "unique_id"),
    ),
)


def preset_path(name: str, split: str, root: str | Path | None = None) -> Path:
    """File a preset reads for ``split``; raises if the split does not exist for that preset."""
    preset = DATASET_PRESETS.get(name)
    if split not in preset.splits:
        raise ValueError(
            f"dataset preset {name!r} has no split {split!r}; available: {list(preset.splits)}"
        )
    return Path(root if root is not None else data_dir()) / preset.folder / f"{split}.jsonl"


def load_preset(
    name: str,
    split: str = "test",
    *,
    root: str | Path | None = None,
    prompt_template: str | None = None,
    limit: int | None = None,
    verifier: str | None = None,
) -> list[Problem]:
    """Problems of a named preset (``gsm8k``, ``math500``) from the data directory; each names
    ``verifier`` (default: the preset's own), so a configured ``task.verifier`` is the one that scores."""
    preset = DATASET_PRESETS.get(name)
    return load_problems(
        preset_path(name, split, root),
        prompt_key=preset.prompt_key,
        answer_key=preset.answer_key,
        verifier=verifier or preset.verifier,
        answer_extractor=preset.answer_extractor,
        prompt_template=prompt_template if prompt_template is not None else preset.prompt_template,
        uid_prefix=f"{name}/{split}",
        metadata_keys=preset.metadata_keys,
        limit=limit,
    )


# --- resumable batches -------------------------------------------------------------------------

T = TypeVar("T")


class EpochBatchIterator(Generic[T]):
    """Endless batches over a fixed dataset: every epoch is a fresh seeded permutation.

    Batches always have ``batch_size`` items; a batch that reaches the end of an epoch continues
    into the next epoch's permutation, so no item is dropped and shapes stay fixed. The position
    is just ``(epoch, offset)`` and the permutation is a pure function of ``(seed, epoch)``, which
    is why `state_dict` is two integers and restoring it continues exactly.
    """

    def __init__(self, items: Sequence[T], seed: int = 0, shuffle: bool = True):
        if len(items) == 0:
            raise ValueError("EpochBatchIterator needs at least one item; the dataset is empty.")
        self.items = items
        self.seed = seed
        self.shuffle = shuffle
        self.epoch = 0
        self.offset = 0
        self._order = self._permutation(0)

    def _permutation(self, epoch: int) -> list[int]:
        order = list(range(len(self.items)))
        if self.shuffle:
            random.Random(f"{self.seed}/{epoch}").shuffle(order)
        return order

    def next_batch(self, batch_size: int) -> list[T]:
        if batch_size <= 0:
            raise ValueError(f"batch_size must be positive, got {batch_size}")
        batch = []
        while len(batch) < batch_size:
            if self.offset == len(self._order):
                self.epoch += 1
                self.offset = 0
                self._order = self._permutation(self.epoch)
            take = min(batch_size - len(batch), len(self._order) - self.offset)
            batch.extend(self.items[i] for i in self._order[self.offset : self.offset + take])
            self.offset += take
        return batch

    def state_dict(self) -> dict[str, Any]:
        return {
            "epoch": self.epoch,
            "offset": self.offset,
            "seed": self.seed,
            "size": len(self.items),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["seed"] != self.seed or state["size"] != len(self.items):
            from infinirl.config import ConfigError  # reported as one line, like every config error

            raise ConfigError(
                f"cannot resume: checkpoint was taken with seed={state['seed']} over "
                f"{state['size']} items, this iterator has seed={self.seed} over "
                f"{len(self.items)}; resume with the same dataset and seed, or start over with resume=false."
            )
        self.epoch = state["epoch"]
        self.offset = state["offset"]
        self._order = self._permutation(self.epoch)
