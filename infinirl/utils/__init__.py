"""Small helpers every layer may use (they import nothing else of InfiniRL): atomic file writes
and the process's random-number-generator state."""

from infinirl.utils.atomic import (
    atomic_open,
    atomic_path,
    fsync_directory,
    replace_directory,
    torch_save_atomic,
    write_json_atomic,
    write_text_atomic,
)
from infinirl.utils.rng import capture_rng_state, restore_rng_state, seed_everything

__all__ = [
    "atomic_open",
    "atomic_path",
    "fsync_directory",
    "capture_rng_state",
    "replace_directory",
    "restore_rng_state",
    "seed_everything",
    "torch_save_atomic",
    "write_json_atomic",
    "write_text_atomic",
]
