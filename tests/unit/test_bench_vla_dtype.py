"""benchmarks/vla_dtype.py's dtype check: on a CPU-only host without native bf16 the policy loads
bfloat16 as float32, and a "bf16 vs float32" ratio of two float32 rows would mean nothing; the
benchmark reads the dtype the weights really hold and fails instead."""

import os
import sys

import torch

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import vla_dtype as bench  # noqa: E402


def test_weights_dtype_is_the_dtype_of_most_parameter_elements():
    backbone_and_head = torch.nn.Sequential(torch.nn.Linear(64, 64).to(torch.bfloat16), torch.nn.Linear(4, 1))
    assert bench.weights_dtype(backbone_and_head) == "bfloat16"
    assert bench.weights_dtype(torch.nn.Linear(4, 4)) == "float32"


def test_a_bf16_row_loaded_as_float32_fails_and_says_how_to_keep_bf16():
    assert bench.dtype_failures({"float32": "float32", "bfloat16": "bfloat16"}) == {}
    failed = bench.dtype_failures({"float32": "float32", "bfloat16": "float32"})
    assert list(failed) == ["bfloat16"]
    assert failed["bfloat16"].startswith("its weights are float32") and "INFINIRL_CPU_BF16=1" in failed["bfloat16"]
