"""vLLM's completions as GenerationResults, the temperatures vLLM would change, and the reload API
the weight sync needs: plain functions, tested without vLLM (a completion here is a plain object
with the fields of vLLM's ``CompletionOutput`` that the conversion reads)."""

from types import SimpleNamespace

import pytest

from infinirl.engines.base import SamplingParams
from infinirl.engines.vllm_process import check_reload_api
from infinirl.engines.vllm_requests import to_generation_result, vllm_sampling_params


def completion(token_ids, finish_reason, stop_reason=None):
    """The fields of a vLLM ``CompletionOutput`` that ``to_generation_result`` reads."""
    logprobs = [{token: SimpleNamespace(logprob=-0.5)} for token in token_ids]
    return SimpleNamespace(token_ids=token_ids, logprobs=logprobs, finish_reason=finish_reason,
                           stop_reason=stop_reason)


def test_a_stop_id_sampled_as_the_last_allowed_token_is_a_stop():
    # Older vLLM V1 checks the token cap before the stop ids and reports such a response as
    # "length"; it ended on a stop id all the same, as HFGenerateEngine reports it.
    result = to_generation_result([1, 2], 0, 0, completion([7, 8, 2], "length"), 4, stop_ids={2})
    assert result.finish_reason == "stop" and result.response_ids == [7, 8, 2] and result.weight_version == 4


def test_a_response_cut_at_the_cap_stays_length():
    result = to_generation_result([1], 0, 0, completion([7, 8, 9], "length"), 0, stop_ids={2})
    assert result.finish_reason == "length"
    assert to_generation_result([1], 0, 0, completion([7, 8, 2], "length"), 0).finish_reason == "length"


def test_stop_strings_and_refused_finish_reasons():
    result = to_generation_result([1], 2, 1, completion([7, 8], "stop", stop_reason="\n"), 0, stop_ids={2})
    assert result.finish_reason == "stop" and result.extra == {"stop_string": "\n"}
    assert (result.prompt_index, result.sample_index, result.response_logprobs) == (2, 1, [-0.5, -0.5])
    with pytest.raises(RuntimeError, match="finished with 'abort'"):
        to_generation_result([1], 0, 0, completion([7], "abort"), 0, stop_ids={2})


@pytest.mark.parametrize("temperature", [0.001, 0.0099])
def test_temperatures_vllm_would_raise_to_its_floor_are_refused(temperature):
    # vLLM raises 0 < T < 0.01 to 0.01 with a warning: the log-probs would follow 0.01 while the
    # trainer scores at T. Refused before vLLM is imported (it is not installed here).
    with pytest.raises(ValueError, match=rf"temperature={temperature}.*0\.01"):
        vllm_sampling_params(SamplingParams(temperature=temperature), 1, [], 0)


def test_reload_api_check_names_the_missing_arguments_and_the_version():
    check_reload_api(["weights_iterator", "is_checkpoint_format"], "0.32.0")
    with pytest.raises(RuntimeError, match=r"vLLM 0\.9\.0.*is_checkpoint_format.*install vLLM 0\.32\.0"):
        check_reload_api(["weights_iterator", "process_weights_after_loading"], "0.9.0")
    with pytest.raises(RuntimeError, match=r"no reload_weights"):
        check_reload_api(None, "0.8.0")
