"""Prompt rendering and chat-template encoding to token ids."""

import pytest
from tokenizers import Tokenizer, models, pre_tokenizers
from transformers import PreTrainedTokenizerFast

from infinirl.tasks.problem import Problem
from infinirl.tasks.prompts import BOXED_ANSWER_TEMPLATE, build_messages, encode_prompt, encode_prompts, render_prompt

CHATML = (
    "{% for message in messages %}<|im_start|>{{ message['role'] }}\n{{ message['content'] }}<|im_end|>\n"
    "{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)


@pytest.fixture(scope="module")
def tokenizer():
    """A tiny offline word-level tokenizer with a ChatML template (no hub access needed)."""
    words = "<unk> <|im_start|> <|im_end|> system user assistant \n what is 2 + 3 ? be brief .".split(" ")
    vocab = {word: index for index, word in enumerate(dict.fromkeys(words + ["\n"]))}
    backend = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    backend.pre_tokenizer = pre_tokenizers.Sequence(
        [pre_tokenizers.Split(pattern="\n", behavior="isolated"), pre_tokenizers.Split(pattern=" ", behavior="removed")]
    )
    fast = PreTrainedTokenizerFast(tokenizer_object=backend, unk_token="<unk>")
    fast.add_special_tokens({"additional_special_tokens": ["<|im_start|>", "<|im_end|>"]})
    fast.chat_template = CHATML
    return fast


PROBLEM = Problem(uid="p/0", prompt="what is 2 + 3 ?", answer="5", verifier="gsm8k")


def test_render_prompt_keeps_latex_braces():
    assert render_prompt("1+1", BOXED_ANSWER_TEMPLATE) == "1+1\nPut your final answer within \\boxed{}."


def test_messages_with_and_without_system_prompt():
    assert build_messages(PROBLEM) == [{"role": "user", "content": PROBLEM.prompt}]
    assert build_messages(PROBLEM, "be brief .")[0] == {"role": "system", "content": "be brief ."}


def test_encode_prompt_matches_the_rendered_chat_template(tokenizer):
    ids = encode_prompt(PROBLEM, tokenizer)
    rendered = tokenizer.apply_chat_template(build_messages(PROBLEM), add_generation_prompt=True, tokenize=False)
    assert rendered.endswith("<|im_start|>assistant\n")
    assert ids == tokenizer(rendered, add_special_tokens=False)["input_ids"]
    assert all(isinstance(token, int) for token in ids)
    assert "<unk>" not in tokenizer.convert_ids_to_tokens(ids)


def test_system_prompt_is_prepended(tokenizer):
    plain = encode_prompt(PROBLEM, tokenizer)
    with_system = encode_prompt(PROBLEM, tokenizer, system_prompt="be brief .")
    assert len(with_system) > len(plain) and with_system[-len(plain) :] == plain
    assert encode_prompts([PROBLEM, PROBLEM], tokenizer) == [plain, plain]


def test_tokenizer_without_chat_template(tokenizer):
    bare = PreTrainedTokenizerFast(tokenizer_object=tokenizer.backend_tokenizer, unk_token="<unk>")
    with pytest.raises(ValueError, match="use_chat_template=False"):
        encode_prompt(PROBLEM, bare)
    assert encode_prompt(PROBLEM, bare, use_chat_template=False) == bare(PROBLEM.prompt)["input_ids"]
