"""Prompt templates and chat-template encoding: text in, prompt token ids out.

The instruction and the verifier's answer extraction are one contract. The default asks for the
final answer after ``####``: a short marker (few prompt tokens matter on a CPU-bound trainer),
the GSM8K convention small instruct models have seen, and trivially parsed by
`answers.extract_after_marker`. LaTeX answers (MATH) use ``\\boxed{}`` instead because
math-verify reads boxes natively and LaTeX after a bare marker is ambiguous.

Templates use the single placeholder ``{question}``, substituted with `str.replace` rather than
`str.format`, so LaTeX braces in a template (``\\boxed{}``) need no escaping.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from infinirl.tasks.problem import Problem

QUESTION_PLACEHOLDER = "{question}"

# Default for numeric answers (GSM8K, reasoning-gym arithmetic); pairs with the "marker"/"auto"
# answer extractors.
NUMBER_ANSWER_TEMPLATE = "{question}\nGive the final answer after '####'."
# Default for LaTeX answers (MATH-500); pairs with the "math" verifier.
BOXED_ANSWER_TEMPLATE = "{question}\nPut your final answer within \\boxed{}."
# Leave the question untouched (the dataset already carries its instruction).
RAW_TEMPLATE = QUESTION_PLACEHOLDER


def render_prompt(question: str, template: str = NUMBER_ANSWER_TEMPLATE) -> str:
    """Insert ``question`` into ``template`` at ``{question}``."""
    if QUESTION_PLACEHOLDER not in template:
        raise ValueError(
            f"prompt template {template!r} has no {QUESTION_PLACEHOLDER} placeholder; "
            f"add it where the question text belongs, e.g. {NUMBER_ANSWER_TEMPLATE!r}."
        )
    return template.replace(QUESTION_PLACEHOLDER, question)


def build_messages(problem: Problem, system_prompt: str | None = None,
                   few_shot: Sequence[Mapping[str, str]] = ()) -> list[dict[str, str]]:
    """Chat messages for one problem.

    ``system_prompt=None`` sends no system turn, so the tokenizer's chat template decides (some,
    like SmolLM2's, insert their own default system message); pass a string to control it.
    ``few_shot`` examples (``{"user": ..., "assistant": ...}``) come first, as earlier turns.
    """
    messages = [] if system_prompt is None else [{"role": "system", "content": system_prompt}]
    for example in few_shot:
        messages += [{"role": "user", "content": example["user"]},
                     {"role": "assistant", "content": example["assistant"]}]
    messages.append({"role": "user", "content": problem.prompt})
    return messages


def encode_prompt(
    problem: Problem,
    tokenizer: Any,
    system_prompt: str | None = None,
    use_chat_template: bool = True,
    few_shot: Sequence[Mapping[str, str]] = (),
) -> list[int]:
    """Prompt token ids for ``problem``, ending where the assistant's reply begins.

    This is the only place prompt text becomes tokens; rollout, reward and trainer pass these ids
    on unchanged (never decode and re-tokenize: the log-probs must be of the exact tokens sampled).
    """
    if not use_chat_template:
        return list(tokenizer(problem.prompt, add_special_tokens=True)["input_ids"])
    if not getattr(tokenizer, "chat_template", None):
        raise ValueError(
            f"tokenizer {type(tokenizer).__name__} has no chat template; set "
            "tokenizer.chat_template, or pass use_chat_template=False to encode the raw prompt."
        )
    encoded = tokenizer.apply_chat_template(
        build_messages(problem, system_prompt, few_shot), add_generation_prompt=True, tokenize=True
    )
    # transformers >= 5 returns a BatchEncoding here; older versions a plain list of ids.
    ids = encoded["input_ids"] if hasattr(encoded, "keys") else encoded
    return [int(token) for token in ids]


def encode_prompts(
    problems: Sequence[Problem],
    tokenizer: Any,
    system_prompt: str | None = None,
    use_chat_template: bool = True,
    few_shot: Sequence[Mapping[str, str]] = (),
) -> list[list[int]]:
    """`encode_prompt` for each problem (unpadded; packing pads later)."""
    return [encode_prompt(p, tokenizer, system_prompt, use_chat_template, few_shot) for p in problems]
