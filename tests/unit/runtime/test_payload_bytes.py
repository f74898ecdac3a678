"""The path of a channel item is picked by its array bytes, wherever its arrays sit."""

from dataclasses import dataclass

import numpy as np
import torch

from infinirl.runtime.payload import tensor_bytes


@dataclass
class Episode:
    frames: list
    actions: torch.Tensor


def test_numpy_arrays_and_bytes_count_wherever_they_are_nested():
    frame = np.zeros((64, 64, 3), dtype=np.uint8)  # 12288 bytes, a camera frame
    assert tensor_bytes({"camera": [frame, frame], "state": (np.zeros(4, dtype=np.float32),)}) == 2 * 12288 + 16
    assert tensor_bytes(Episode([frame], torch.zeros(8))) == 12288 + 32
    assert tensor_bytes({"jpeg": b"x" * 100, "t": torch.zeros(2, dtype=torch.int64)}) == 116
    assert tensor_bytes(frame) == 12288
    assert tensor_bytes({"reward": 1.0, "text": "abc"}) == 0
