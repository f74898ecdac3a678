"""Shared pytest setup: skip `gpu` tests without CUDA so the CPU suite stays green and honest."""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (see infinirl.runtime.cluster)

import pytest  # noqa: E402
import torch  # noqa: E402


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip_gpu = pytest.mark.skip(reason="needs CUDA (run on a GPU machine: pytest -m gpu)")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip_gpu)


@pytest.fixture(scope="session")
def ray_cluster():
    """One local Ray instance for the whole session (starting Ray costs seconds)."""
    from infinirl.runtime import Cluster

    cluster = Cluster(num_cpus=2, log_to_driver=False).start()
    yield cluster
    cluster.shutdown()


def ship_by_value(module_name: str) -> None:
    """Let Ray workers unpickle classes defined in a test module (not importable from workers)."""
    import sys

    import ray.cloudpickle

    ray.cloudpickle.register_pickle_by_value(sys.modules[module_name])


@pytest.fixture(scope="session")
def tiny_llama_dir(tmp_path_factory):
    """A randomly initialised 2-layer Llama with SmolLM2's tokenizer (chat template included), saved
    as a Hugging Face folder: the model every reasoning test trains, evaluates or refuses."""
    from transformers import AutoTokenizer, LlamaConfig, LlamaForCausalLM

    from infinirl.models.smollm2 import ensure_converted

    tokenizer = AutoTokenizer.from_pretrained(ensure_converted())
    config = LlamaConfig(vocab_size=len(tokenizer), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=2, num_key_value_heads=1, tie_word_embeddings=True,
                         max_position_embeddings=512, eos_token_id=tokenizer.eos_token_id)
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("tiny-llama")
    LlamaForCausalLM(config).save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    return str(folder)
