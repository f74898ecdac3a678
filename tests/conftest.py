"""Shared pytest setup: skip `gpu` tests without CUDA so the CPU suite stays green and honest; one
Ray instance for the session; the tiny model reasoning tests share; quiet deliberate crashes."""
import os
import re

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (see infinirl.runtime.cluster)

import pytest  # noqa: E402
import torch  # noqa: E402

from infinirl.envs.gymnasium_env import use_headless_gl  # noqa: E402

# MuJoCo binds its GL backend when it is first imported, once per process: choose the off-screen one
# before any test imports it, so a state-only test that runs first (MuJoCo's default is glfw, which
# needs a display) cannot leave a later rendering test (a simulated robot's camera) without GL.
use_headless_gl()

# pyproject's timeout (600 s) bounds every test of the default suite; a learning run of the slow
# tier takes minutes on two cores and more on a busy host, so it gets this much instead.
SLOW_TEST_TIMEOUT_S = 2400


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "slow" in item.keywords and item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(SLOW_TEST_TIMEOUT_S))
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
    as a Hugging Face folder: the model every reasoning test trains, evaluates or refuses. Its 2048
    positions hold the default rollout.max_prompt_length (1024) and a response, as the config checks
    (RoPE's frequencies do not depend on the number, so neither do the weights or any result)."""
    from transformers import AutoTokenizer, LlamaConfig, LlamaForCausalLM

    from infinirl.models.smollm2 import ensure_converted

    tokenizer = AutoTokenizer.from_pretrained(ensure_converted())
    config = LlamaConfig(vocab_size=len(tokenizer), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=2, num_key_value_heads=1, tie_word_embeddings=True,
                         max_position_embeddings=2048, eos_token_id=tokenizer.eos_token_id)
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("tiny-llama")
    LlamaForCausalLM(config).save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    return str(folder)


# Tests kill worker processes on purpose; keep Ray's report of those deaths out of the output.
#
# When a worker process exits unexpectedly, its raylet publishes "A worker died or was killed while
# executing a task by an unexpected system error ... Worker PID: <pid> ... (1) the process was
# killed by the OOM killer ..." to the driver. Every Ray driver runs a thread
# (``ray._private.worker.listen_error_messages``) that prints such messages to stdout through
# ``ray._private.worker.print_to_stdstream``, whatever ``log_to_driver`` says, whenever they
# arrive. A test that kills a rank on purpose declares the process with ``deliberate_deaths(pid)``;
# raylet messages naming one of those pids are dropped, every other message is printed as before.



_expected_pids: set[int] = set()
_WORKER_PID = re.compile(r"Worker PID: (\d+)")


def about_a_deliberate_death(line: str) -> bool:
    """Whether a raylet message reports the death of a process a test killed on purpose."""
    match = _WORKER_PID.search(line)
    return bool(match) and int(match[1]) in _expected_pids


def _install_filter() -> None:
    import ray._private.worker as ray_worker

    original = ray_worker.print_to_stdstream
    if getattr(original, "drops_deliberate_deaths", False):
        return

    def print_to_stdstream(data, ignore_prefix: bool):
        if data.get("pid") == "raylet":
            lines = [line for line in data.get("lines", []) if not about_a_deliberate_death(line)]
            if not lines:
                return
            data = {**data, "lines": lines}
        return original(data, ignore_prefix)

    print_to_stdstream.drops_deliberate_deaths = True
    ray_worker.print_to_stdstream = print_to_stdstream


@pytest.fixture
def deliberate_deaths():
    """Call with the pids of worker processes the test is about to kill or crash."""
    _install_filter()

    def expect(*pids: int) -> None:
        _expected_pids.update(int(pid) for pid in pids if pid)

    return expect
