"""The compiled optimizer step lives in :mod:`infinirl.engines.compiled_step`; these names stay
importable from here for existing callers."""

from infinirl.engines.compiled_step import (
    CompiledAdamStep,
    adam_,
    adam_corrections,
    clip_by_total_norm,
    inductor_options,
)

__all__ = ["CompiledAdamStep", "adam_", "adam_corrections", "clip_by_total_norm", "inductor_options"]
