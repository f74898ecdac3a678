"""Which of a sleeping vLLM engine's memory pools get woken (runs without vLLM: the bookkeeping
is plain Python; tests/gpu/test_vllm_gpu.py runs the same sequences on vLLM's sleep mode)."""

from infinirl.engines.vllm_engine import SleepPools


def test_reload_after_a_load_while_asleep_wakes_only_the_kv_cache():
    # offload -> load_weights (wakes the weights to load into them) -> reload: the weights hold the
    # new load by then, and waking them again would map them over it.
    pools = SleepPools()
    pools.sleep()
    assert pools.wake("weights") == ["weights"]
    assert pools.wake("weights") == []  # a second load while offloaded wakes nothing more
    assert pools.wake() == ["kv_cache"]
    assert pools.wake() == []  # reload twice: nothing left to wake


def test_reload_without_a_load_wakes_every_pool_by_name():
    pools = SleepPools()
    pools.sleep()
    assert pools.wake() == ["weights", "kv_cache"]


def test_nothing_is_woken_before_a_sleep():
    pools = SleepPools()
    assert pools.wake("weights") == [] and pools.wake() == []
    pools.sleep()
    pools.wake()
    pools.sleep()  # a second offload after a reload puts both to sleep again
    assert pools.wake("weights") == ["weights"] and pools.wake() == ["kv_cache"]
