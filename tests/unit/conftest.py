"""The unit tier starts no Ray: a test that needs a cluster belongs in tests/integration."""

import pytest


@pytest.fixture(autouse=True)
def _no_ray(monkeypatch):
    import ray

    def refuse(*args, **kwargs):
        raise AssertionError("unit tests run without Ray; move a test that starts a cluster to tests/integration")

    monkeypatch.setattr(ray, "init", refuse)


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny models gain nothing from threads, and on a shared CPU every extra thread's
    synchronisation costs far more than its share of the arithmetic: such a module runs on one."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def tiny_byte_llama():
    """A tiny random Llama and the offline byte-level tokenizer (no hub, deterministic everywhere)."""
    from infinirl.models.hf_causal_lm import tiny_causal_lm

    return tiny_causal_lm(tokenizer="byte", seed=0)
