"""Where embodied workers compute: the placement's device under ``auto``, the CPU under ``cpu``."""

import pytest
import torch

from infinirl.components.embodied_policy import compute_device, module_device


def test_auto_follows_the_placement_and_cpu_overrides_it():
    assert compute_device("cpu", "auto") == torch.device("cpu")
    assert compute_device("cuda", "auto") == torch.device("cuda")
    assert compute_device("cuda", "cpu") == torch.device("cpu")
    assert compute_device("cpu", "cpu") == torch.device("cpu")


def test_an_unknown_setting_is_named_with_the_choices():
    with pytest.raises(ValueError, match=r"device='gpu'.*\['auto', 'cpu'\]"):
        compute_device("cuda", "gpu")


def test_module_device_reads_parameters_then_buffers():
    assert module_device(torch.nn.Linear(2, 2)) == torch.device("cpu")
    assert module_device(torch.nn.Identity()) == torch.device("cpu")
    with_buffer = torch.nn.Module()
    with_buffer.register_buffer("stat", torch.zeros(1, dtype=torch.float64))
    assert module_device(with_buffer) == torch.device("cpu")
