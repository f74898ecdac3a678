"""Adam with float32 master weights for low-precision (bf16 / fp16) parameters.

Why: a VLA fine-tuned in full is loaded in bfloat16 to fit, and Adam stepping the bf16 weights in place
loses the update: Adam moves a weight by about ``lr`` a step (5e-6 in the LIBERO configs), while bf16
keeps 8 significant bits, so weights near 0.01 are 6e-5 apart and the step rounds back to the same
weight: the policy never moves. Here each low-precision parameter that receives a gradient gets a float32 copy (the
*master*) in the optimizer's state: Adam steps the master with the gradient cast up, its moments are
float32, and the parameter receives the master rounded back. The master travels in ``state_dict()``
(``state[p]["master"]``) so a resumed run continues from the exact float32 weights, not from their
rounding. Float32 parameters take ``torch.optim.Adam``'s own path, untouched.
"""

from __future__ import annotations

from collections.abc import Iterable
from itertools import chain

import torch

__all__ = ["LOW_PRECISION", "MasterWeightAdam", "adam_for", "low_precision_trainable"]

LOW_PRECISION = (torch.bfloat16, torch.float16)


class MasterWeightAdam(torch.optim.Adam):
    """``torch.optim.Adam`` whose low-precision parameters step through float32 masters (module docstring).

    The optimizer's groups and state stay keyed by the model's own parameters (learning-rate schedules,
    step counts and checkpoints read them as for plain Adam); only inside :meth:`step` are the
    low-precision ones replaced by their masters."""

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        swapped = []  # (group params, index, param, master)
        for group in self.param_groups:
            params = group["params"]
            for index, param in enumerate(params):
                if param.dtype not in LOW_PRECISION or param.grad is None:
                    continue  # float32: Adam's own path; no gradient: Adam skips it anyway
                state = self.state[param]
                master = state.pop("master", None)
                if master is None:
                    master = param.detach().to(torch.float32, copy=True)
                master.grad = param.grad.to(torch.float32)
                # Adam keys its state by the tensor it steps: lend the moments to the master for this step
                self.state[master] = state
                params[index] = master
                swapped.append((params, index, param, master))
        try:
            super().step()
        finally:
            for params, index, param, master in swapped:
                params[index] = param
                state = self.state.pop(master)
                master.grad = None
                state["master"] = master
                self.state[param] = state
                param.copy_(master)
        return loss

    def load_state_dict(self, state_dict: dict) -> None:
        """Torch casts every floating state tensor to its parameter's dtype: restore the low-precision
        parameters' masters and moments in float32 (a checkpoint of plain Adam's bf16 moments is cast up)."""
        super().load_state_dict(state_dict)
        saved_ids = chain.from_iterable(group["params"] for group in state_dict["param_groups"])
        params = chain.from_iterable(group["params"] for group in self.param_groups)
        for saved_id, param in zip(saved_ids, params, strict=True):
            if param.dtype not in LOW_PRECISION or saved_id not in state_dict["state"]:
                continue
            state = self.state[param]
            for key, value in state_dict["state"][saved_id].items():
                if key != "step" and torch.is_tensor(value) and value.is_floating_point():
                    # a copy: a state dict taken from a live optimizer shares its tensors
                    state[key] = value.detach().to(device=param.device, dtype=torch.float32, copy=True)


def low_precision_trainable(params: Iterable[torch.Tensor]) -> list[torch.dtype]:
    """The low-precision dtypes among the trainable ``params`` (sorted by name; empty for a float32 model):
    non-empty is where :func:`adam_for` picks :class:`MasterWeightAdam`. The driver asks it of the policy it
    builds to refuse, before any worker starts, what the actor's optimizer could not do (``actor.compile``)."""
    return sorted({p.dtype for p in params if p.requires_grad and p.dtype in LOW_PRECISION}, key=str)


def adam_for(groups: list[dict], lr: float, eps: float, **options) -> torch.optim.Adam:
    """``torch.optim.Adam`` over the parameter ``groups``, or :class:`MasterWeightAdam` where a trainable
    parameter is low-precision (float32 models keep plain Adam, bit for bit)."""
    low = low_precision_trainable(chain.from_iterable(group["params"] for group in groups))
    return (MasterWeightAdam if low else torch.optim.Adam)(groups, lr=lr, eps=eps, **options)
