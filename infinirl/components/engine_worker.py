"""What every component that owns a training engine (actor, critic) exposes the same way.

The runner checkpoints, offloads and compares weights of these components without knowing which
one it talks to; the delegations live here once instead of in each component.
"""

from __future__ import annotations

import hashlib

import torch

from infinirl.runtime import Worker


class EngineWorker(Worker):
    """A Worker with ``self.engine`` (an FSDP train engine): checkpoint, offload, weight digest."""

    engine: object

    def weights_digest(self) -> str:
        """SHA-256 over the full weights (all ranks take part): resume tests compare these."""
        return engine_digest(self.engine)

    def save_checkpoint(self, path: str) -> None:
        self.engine.save_checkpoint(path)

    def load_checkpoint(self, path: str) -> None:
        self.engine.load_checkpoint(path)

    def offload(self) -> None:
        self.engine.offload()

    def reload(self) -> None:
        self.engine.reload()


def engine_digest(engine) -> str:
    """SHA-256 over an engine's full weights, in sync order (names and bytes)."""
    digest = hashlib.sha256()
    for name, tensor in engine.state_dict_for_sync():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()
