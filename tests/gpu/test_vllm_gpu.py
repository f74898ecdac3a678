"""The vLLM engine's sleep mode on a real GPU (vLLM's CUDA build): weights loaded while the engine
sleeps survive its wake-up. Skipped without CUDA (conftest.py) or without vLLM.

Each engine runs in a rollout rank of its own (a Ray actor on GPU 0), as the runner runs it: vLLM's
in-process engine is one per process, and each sleep level needs a fresh one.
"""

import pytest

from infinirl.engines.base import SamplingParams
from infinirl.engines.vllm_engine import vllm_available
from infinirl.runtime import WeightSource, Worker, WorkerGroup, place, sync_weights
from tests.conftest import ship_by_value

pytestmark = pytest.mark.gpu

if not vllm_available():
    pytest.skip("vLLM is not installed (its CUDA build: pip install vllm; see docs/vllm.md)",
                allow_module_level=True)

from infinirl.components.rollout import RolloutWorker  # noqa: E402
from infinirl.engines.hf_generate import HFGenerateEngine  # noqa: E402
from infinirl.models.hf_causal_lm import tiny_causal_lm  # noqa: E402

ship_by_value(__name__)

PROMPTS = [[5, 6, 7, 8, 9, 10, 11], [20, 21], [30, 31, 32, 33]]
GREEDY = SamplingParams(max_new_tokens=10, greedy=True)


def _tiny(seed: int):
    return tiny_causal_lm(tokenizer="byte", seed=seed, hidden=64, heads=2, kv_heads=1)


class TinyTrainer(Worker, WeightSource):
    """Serves model B's weights to ``sync_weights`` (on CPU: the rollout has the GPU)."""

    def __init__(self, seed: int):
        self.model, _ = _tiny(seed)

    def weights_for_sync(self):
        return self.model.state_dict().items()


@pytest.fixture(scope="module")
def model_a_dir(tmp_path_factory):
    model, tokenizer = _tiny(0)
    folder = tmp_path_factory.mktemp("tiny_a")
    model.save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    return str(folder)


@pytest.mark.parametrize("sleep_level", [1, 2])
def test_weights_loaded_while_asleep_survive_reload(ray_cluster, model_a_dir, sleep_level):
    """offload -> load model B -> reload -> greedy output is model B's (transformers on CPU). The
    load wakes only the weights; reload must then wake only the KV cache, not map the weights again
    over the new load."""
    options = {"max_model_len": 256, "eos_token_ids": [], "sleep_level": sleep_level,
               "gpu_memory_utilization": 0.3}
    plan = place(ray_cluster.refresh(), {"rollout": "0"})
    rollout = WorkerGroup.launch(RolloutWorker, "rollout", placement=plan.ranks("rollout"),
                                 args=(model_a_dir, "float32", 8, 0, "vllm", options))
    trainer = WorkerGroup.launch(TinyTrainer, "actor", num_ranks=1, args=(1,))
    try:
        model_a, tokenizer = _tiny(0)
        model_b, _ = _tiny(1)
        expected_a = [r.response_ids for r in HFGenerateEngine(model_a, tokenizer, eos_token_ids=[])
                      .generate(PROMPTS, GREEDY)]
        expected_b = [r.response_ids for r in HFGenerateEngine(model_b, tokenizer, eos_token_ids=[])
                      .generate(PROMPTS, GREEDY)]
        assert expected_a != expected_b
        assert [r.response_ids for r in rollout.generate(PROMPTS, GREEDY).wait(timeout=300)[0]] == expected_a

        rollout.offload().wait(timeout=300)
        sync_weights(trainer, rollout, version=3)
        rollout.reload().wait(timeout=300)
        rollout.reload().wait(timeout=300)  # idempotent: nothing left asleep
        results = rollout.generate(PROMPTS, GREEDY).wait(timeout=300)[0]
        assert [r.response_ids for r in results] == expected_b
        assert all(r.weight_version == 3 for r in results)
    finally:
        trainer.shutdown()
        rollout.shutdown()


def test_a_fixed_kv_cache_starts_beside_a_trainer_holding_memory(ray_cluster, model_a_dir):
    """With kv_cache_bytes set, vLLM still refuses to start unless gpu_memory_utilization x the GPU
    is free; the engine passes its own 0.3 rather than leaving vLLM's default (~0.9), which a
    collocated trainer holding a fifth of the GPU would fail."""
    import torch

    total = torch.cuda.get_device_properties(0).total_memory
    held = torch.empty(int(total * 0.2), dtype=torch.uint8, device="cuda")  # the trainer's share
    options = {"max_model_len": 256, "eos_token_ids": [], "kv_cache_bytes": 64 << 20, "gpu_memory_utilization": 0.3}
    plan = place(ray_cluster.refresh(), {"rollout": "0"})
    rollout = WorkerGroup.launch(RolloutWorker, "rollout", placement=plan.ranks("rollout"),
                                 args=(model_a_dir, "float32", 8, 0, "vllm", options))
    try:
        model_a, tokenizer = _tiny(0)
        expected = [r.response_ids for r in HFGenerateEngine(model_a, tokenizer, eos_token_ids=[])
                    .generate(PROMPTS, GREEDY)]
        assert [r.response_ids for r in rollout.generate(PROMPTS, GREEDY).wait(timeout=300)[0]] == expected
    finally:
        rollout.shutdown()
        del held
