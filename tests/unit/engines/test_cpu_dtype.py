"""bf16 requested on a CPU without native bf16 becomes float32, for the trainer and the rollout."""

import warnings

import pytest
import torch

from infinirl.engines import cpu_dtype
from infinirl.engines.distributed import compute_dtype
from infinirl.engines.registry import ROLLOUT_ENGINES, build_rollout_engine


@pytest.fixture
def native_bf16(monkeypatch):
    """Pretend the CPU has (True) or lacks (False) native bf16."""
    def set_to(value: bool):
        monkeypatch.setattr(cpu_dtype, "cpu_bf16_is_fast", lambda: value)
        cpu_dtype._warn_once.cache_clear()
    return set_to


def test_without_native_bf16_bfloat16_becomes_float32_with_one_warning(native_bf16):
    native_bf16(False)
    with pytest.warns(UserWarning, match="INFINIRL_CPU_BF16=1"):
        assert cpu_dtype.resolve_cpu_dtype("bfloat16") == "float32"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once per process, not per call
        assert cpu_dtype.resolve_cpu_dtype("bf16") == "float32"
    assert cpu_dtype.resolve_cpu_dtype("float32") == "float32"
    assert compute_dtype("bfloat16", torch.device("cpu")) == torch.float32
    assert compute_dtype("float32", torch.device("cpu")) == torch.float32


def test_with_native_bf16_bfloat16_is_kept(native_bf16):
    native_bf16(True)
    assert cpu_dtype.resolve_cpu_dtype("bfloat16") == "bfloat16"
    assert compute_dtype("bfloat16", torch.device("cpu")) == torch.bfloat16


def test_the_rollout_engine_gets_the_resolved_dtype_on_cpu_only(native_bf16, monkeypatch):
    native_bf16(False)
    seen = []
    monkeypatch.setitem(ROLLOUT_ENGINES._entries, "probe", lambda *args: seen.append(args[1]))
    with pytest.warns(UserWarning):
        build_rollout_engine("probe", "model", "bfloat16", "cpu", 8)
    build_rollout_engine("probe", "model", "bfloat16", "cuda", 8)
    assert seen == ["float32", "bfloat16"]


def test_the_override_keeps_bf16(monkeypatch):
    monkeypatch.setenv("INFINIRL_CPU_BF16", "1")
    cpu_dtype.cpu_bf16_is_fast.cache_clear()
    try:
        assert cpu_dtype.cpu_bf16_is_fast()
    finally:
        monkeypatch.delenv("INFINIRL_CPU_BF16")
        cpu_dtype.cpu_bf16_is_fast.cache_clear()


def test_policy_weights_keep_bf16_where_a_gpu_will_compute_them(native_bf16, monkeypatch):
    native_bf16(False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert cpu_dtype.resolve_weights_dtype("bfloat16") is torch.bfloat16
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.warns(UserWarning, match="INFINIRL_CPU_BF16=1"):
        assert cpu_dtype.resolve_weights_dtype("bfloat16") is torch.float32
    assert cpu_dtype.resolve_weights_dtype("float32") is torch.float32
    native_bf16(True)
    assert cpu_dtype.resolve_weights_dtype("bfloat16") is torch.bfloat16
    with pytest.raises(ValueError, match="policy.kwargs.dtype: unknown dtype 'bfloat17'; use one of"):
        cpu_dtype.resolve_weights_dtype("bfloat17")


def test_a_vla_policy_asked_for_bf16_on_a_cpu_without_it_loads_float32(native_bf16, tmp_path_factory):
    from tests.unit.models.test_vla_steered import policy, tiny_checkpoint

    checkpoint = tiny_checkpoint(tmp_path_factory)
    native_bf16(False)
    with pytest.warns(UserWarning, match="INFINIRL_CPU_BF16=1"):
        slow_cpu = policy(checkpoint, name="pi0_smollm2_residual", dtype="bfloat16")
    assert {p.dtype for p in slow_cpu.vla.parameters()} == {torch.float32}
    native_bf16(True)
    fast_cpu = policy(checkpoint, name="pi0_smollm2_residual", dtype="bfloat16")
    assert {p.dtype for p in fast_cpu.vla.parameters()} == {torch.bfloat16}
