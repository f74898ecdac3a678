"""Checkpoints of an FSDP2 trainer: model and optimizer as DCP shards, plus a small per-rank file.

Layout of a checkpoint directory:

* ``model_optim/``: DCP shards of model + optimizer, which reshard to any world size;
* ``engine_rank{r}.pt``: per-rank trainer state (schedule, step, RNG; the RNG differs per rank).

Written atomically: everything goes to ``<path>.tmp`` and rank 0 renames it into place only after
all ranks finished, so ``path`` is either the old checkpoint or the complete new one.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import torch
import torch.distributed.checkpoint as dcp
from torch import nn
from torch.distributed.checkpoint.state_dict import (
    get_model_state_dict,
    get_optimizer_state_dict,
    set_model_state_dict,
    set_optimizer_state_dict,
)

from infinirl.engines.distributed import barrier
from infinirl.utils import replace_directory

__all__ = ["DCP_DIR", "ENGINE_STATE", "load_model_and_optimizer", "read_engine_state", "save_sharded_checkpoint",
           "write_engine_state"]

DCP_DIR = "model_optim"
ENGINE_STATE = "engine_rank{rank}.pt"


def save_sharded_checkpoint(path: str | Path, model: nn.Module, optimizer: torch.optim.Optimizer,
                            engine_state: Callable[[], dict], rank: int, device: torch.device) -> None:
    """Write ``model`` + ``optimizer`` (DCP) and ``engine_state()`` (this rank's file) to ``path``.

    ``engine_state()`` is called after the shards are written; its dict gains
    ``has_optimizer_state`` (an optimizer that never stepped is not saved: reading its state
    would initialise it). On an error the temporary directory is removed. With several nodes
    ``path`` must be on a shared filesystem (every rank writes its own shards). Collective.
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    if rank == 0:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
    barrier(device)
    try:
        has_optimizer_state = bool(optimizer.state)
        state = {"model": get_model_state_dict(model)}
        if has_optimizer_state:
            state["optimizer"] = get_optimizer_state_dict(model, optimizer)
        dcp.save(state, checkpoint_id=str(tmp / DCP_DIR))
        write_engine_state({**engine_state(), "has_optimizer_state": has_optimizer_state},
                           tmp / ENGINE_STATE.format(rank=rank))
        barrier(device)
        if rank == 0:
            replace_directory(tmp, path)
        barrier(device)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_engine_state(state: dict, file: Path) -> None:
    """One rank's trainer state (inside the temporary directory, so no rename of its own)."""
    torch.save(state, file)


def read_engine_state(path: str | Path, rank: int) -> dict:
    """This rank's trainer state from a :func:`save_sharded_checkpoint` directory, or rank 0's when
    the checkpoint came from fewer ranks (its RNG state is then reused)."""
    path = Path(path)
    if not (path / DCP_DIR).is_dir():
        raise FileNotFoundError(f"load_checkpoint: {path} is not an engine checkpoint (no {DCP_DIR}/)")
    engine_file = path / ENGINE_STATE.format(rank=rank)
    if not engine_file.exists():
        engine_file = path / ENGINE_STATE.format(rank=0)
    return torch.load(engine_file, weights_only=False)  # our own file: RNG tuples


def load_model_and_optimizer(path: str | Path, model: nn.Module, optimizer: torch.optim.Optimizer,
                             has_optimizer_state: bool) -> None:
    """Load the DCP shards into ``model`` (and ``optimizer``), resharding to this world size. Collective."""
    state = {"model": get_model_state_dict(model)}
    if has_optimizer_state:
        state["optimizer"] = get_optimizer_state_dict(model, optimizer)
    dcp.load(state, checkpoint_id=str(Path(path) / DCP_DIR))
    set_model_state_dict(model, state["model"])
    if has_optimizer_state:
        set_optimizer_state_dict(model, optimizer, state["optimizer"])
