"""What every inference engine checks and defaults before generating (``engines.generate_inputs``),
shared by the transformers and the vLLM engine."""

from types import SimpleNamespace

import numpy as np
import pytest

from infinirl.engines.base import SamplingParams
from infinirl.engines.generate_inputs import default_eos_ids, stop_token_ids, validate_prompts

SAMPLING = SamplingParams(max_new_tokens=4)


@pytest.mark.parametrize("prompts, error, match", [
    ([[1, 2], []], ValueError, "prompt 1 is empty"),
    ([[1, "a"]], TypeError, "prompt 0 must be a list of token ids .* 'a'; tokenize first"),
    ([[1, 10]], ValueError, r"prompt 0 has token id 10 outside the model's vocabulary \[0, 10\)"),
    ([[-1, 3]], ValueError, "prompt 0 has token id -1 outside"),
    ([[1] * 7], ValueError, r"prompt 0 \(7 tokens\) \+ max_new_tokens=4 = 11 exceeds the engine's max_model_len=10; "
                            "shorten the prompt or lower max_new_tokens"),
])
def test_bad_prompts_are_refused_naming_the_prompt_and_the_fix(prompts, error, match):
    with pytest.raises(error, match=match):
        validate_prompts(prompts, SAMPLING, vocab_size=10, max_length=10, max_length_name="the engine's max_model_len")


def test_good_prompts_pass_and_no_length_limit_means_none():
    validate_prompts([[0, 9], [np.int64(3)]], SAMPLING, vocab_size=10, max_length=6, max_length_name="limit")
    validate_prompts([[1] * 500], SAMPLING, vocab_size=10, max_length=None, max_length_name="limit")


def test_default_eos_ids_take_the_generation_config_then_the_tokenizer_once_each():
    tokenizer = SimpleNamespace(eos_token_id=2)
    assert default_eos_ids(None, [2, 7], tokenizer) == (2, 7)
    assert default_eos_ids(None, 7, tokenizer) == (7, 2)
    assert default_eos_ids(None, None, None) == ()
    assert default_eos_ids([], 7, tokenizer) == ()  # explicit (even empty) wins
    assert default_eos_ids([5, 5], None, tokenizer) == (5, 5)


def test_stop_ids_are_the_request_s_then_eos_unless_ignored():
    assert stop_token_ids(SamplingParams(stop_token_ids=(4, 2)), (2, 9)) == [4, 2, 9]
    assert stop_token_ids(SamplingParams(stop_token_ids=(4,), ignore_eos=True), (2, 9)) == [4]
