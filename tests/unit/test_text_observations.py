"""Text observation fields (a VLA's instruction) reach the policy at acting and at the update."""

import numpy as np
import torch

from infinirl.algorithms.embodied_ppo import _rows
from infinirl.components.embodied_actor import _to_tensor
from infinirl.components.embodied_rollout import array_obs
from infinirl.models.policies.base import prepare_obs


def test_instructions_travel_as_string_arrays_and_reach_the_policy_as_text():
    obs = array_obs({"state": np.zeros((2, 3), np.float32), "instruction": ["open the drawer", "push the block"]})
    assert obs["instruction"].dtype.kind == "U"
    stacked = {k: np.stack([v, v]).reshape(4, *v.shape[1:]) for k, v in obs.items()}  # two steps, as recorded
    batch = _to_tensor({"obs": stacked})["obs"]
    assert isinstance(batch["state"], torch.Tensor) and isinstance(batch["instruction"], np.ndarray)
    mini = _rows(batch, torch.tensor([3, 0]))
    assert mini["instruction"].tolist() == ["push the block", "open the drawer"]
    assert prepare_obs(mini)["instruction"] == ["push the block", "open the drawer"]
