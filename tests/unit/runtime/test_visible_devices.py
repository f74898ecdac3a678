"""Rank device masks name the devices discovery counted: local indices map through the mask the
node's processes inherited; a local instance's num_gpus bounds the devices the inventory lists."""

import os

import pytest

from infinirl.runtime.cluster import capped_accelerators
from infinirl.runtime.inventory import Accelerator
from infinirl.runtime.placement import physical_visible_devices


def test_local_indices_map_through_the_inherited_mask(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,5,6,7")
    inherited = os.environ.get("CUDA_VISIBLE_DEVICES")
    assert physical_visible_devices("CUDA_VISIBLE_DEVICES", "0", inherited) == "4"
    assert physical_visible_devices("CUDA_VISIBLE_DEVICES", "1,3", inherited) == "5,7"
    assert physical_visible_devices("CUDA_VISIBLE_DEVICES", "", inherited) == ""  # a device-less rank sees none
    with pytest.raises(ValueError, match="local device 4.*sees 4 device"):
        physical_visible_devices("CUDA_VISIBLE_DEVICES", "4", inherited)


def test_without_an_inherited_mask_local_indices_are_physical(monkeypatch):
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert physical_visible_devices("CUDA_VISIBLE_DEVICES", "2,3", os.environ.get("CUDA_VISIBLE_DEVICES")) == "2,3"
    assert physical_visible_devices("CUDA_VISIBLE_DEVICES", "0", "GPU-a1, GPU-b2") == "GPU-a1"  # UUIDs too


def test_num_gpus_caps_the_listed_accelerators():
    found = [Accelerator("cuda", i, 1 << 30) for i in (2, 0, 3, 1)]
    assert [a.local_index for a in capped_accelerators(found, 2)] == [0, 1]
    assert len(capped_accelerators(found, None)) == 4
