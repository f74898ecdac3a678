"""Reasoning tasks: problems from files or generators, prompts as token ids, verifiable rewards.

- `Problem` / `ProblemSource`: the record and the resumable stream interface (`problem.py`).
- Files and presets (`gsm8k`, `math500`), `EpochBatchIterator` (`datasets.py`).
- reasoning-gym eval sets and held-out-safe train streams (`reasoning_gym_tasks.py`).
- Instruction templates and chat-template encoding (`prompts.py`).
- Answer extraction (`answers.py`) and verifiers with `safe_score` (`verifiers.py`).
"""

# Imported for their registrations: task sources (code, fictional_kb) and verifiers (code_tests, exact_match).
from infinirl.tasks import code_tasks, exact_match, fictional_kb  # noqa: F401
from infinirl.tasks.answers import ANSWER_EXTRACTORS, extract_answer_auto, parse_number
from infinirl.tasks.datasets import (
    DATA_DIR_ENV,
    DATASET_PRESETS,
    EpochBatchIterator,
    data_dir,
    load_preset,
    load_problems,
)
from infinirl.tasks.problem import Problem, ProblemSource, normalize_question
from infinirl.tasks.prompts import (
    BOXED_ANSWER_TEMPLATE,
    NUMBER_ANSWER_TEMPLATE,
    encode_prompt,
    encode_prompts,
    render_prompt,
)
from infinirl.tasks.reasoning_gym_tasks import (
    DEFAULT_EVAL_SEED,
    ReasoningGymStream,
    ReasoningGymTask,
    build_eval_set,
)
from infinirl.tasks.verifiers import (
    VERIFIERS,
    RewardResult,
    build_verifier,
    get_verifier,
    safe_score,
    score_responses,
    summarize_rewards,
)

__all__ = [
    "ANSWER_EXTRACTORS",
    "BOXED_ANSWER_TEMPLATE",
    "DATASET_PRESETS",
    "DATA_DIR_ENV",
    "DEFAULT_EVAL_SEED",
    "EpochBatchIterator",
    "NUMBER_ANSWER_TEMPLATE",
    "Problem",
    "ProblemSource",
    "ReasoningGymStream",
    "ReasoningGymTask",
    "RewardResult",
    "VERIFIERS",
    "build_eval_set",
    "build_verifier",
    "data_dir",
    "encode_prompt",
    "encode_prompts",
    "extract_answer_auto",
    "get_verifier",
    "load_preset",
    "load_problems",
    "normalize_question",
    "parse_number",
    "render_prompt",
    "safe_score",
    "score_responses",
    "summarize_rewards",
]
