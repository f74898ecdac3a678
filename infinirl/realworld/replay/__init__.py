"""A persistent, cache-aware replay store for real-world RL (docs/realworld.md#persistent-replay-buffer)."""

from infinirl.realworld.replay.cache import ByteLRU
from infinirl.realworld.replay.log import ReplayCorruptionError
from infinirl.realworld.replay.sampler import SamplingSpec, TransitionSampler
from infinirl.realworld.replay.spec import EpisodeSpec
from infinirl.realworld.replay.store import ReplayStore, StoreOptions

__all__ = ["ByteLRU", "EpisodeSpec", "ReplayCorruptionError", "ReplayStore", "SamplingSpec", "StoreOptions",
           "TransitionSampler"]
