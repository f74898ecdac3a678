"""Which keyword options an env family takes, read off signatures where it can be.

A simulator option that a family does not take would otherwise surface only when an env is built
with it, which for evaluation options is after training. :class:`EnvOptions` says, per family and task,
which names are accepted, so :func:`~infinirl.envs.registry.check_env_kwargs` can refuse a bad
option in the driver, before any worker starts. Families read them off their factory's fields or
off the simulator's constructor (:func:`~infinirl.utils.signatures.keyword_names`, re-exported
here), so the list cannot drift from the code.

Little is imported here (the standard library, and ``infinirl.utils``, which brings numpy): this
module is loaded by every env worker.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from infinirl.utils.signatures import keyword_names

__all__ = ["EnvOptions", "keyword_names"]


@dataclass(frozen=True, kw_only=True)
class EnvOptions:
    """The keyword options one env family takes for one task.

    ``names``: the accepted names. ``passes_others``: other names are passed on to a callee whose
    options cannot be read (a constructor taking ``**kwargs`` it does not forward to a parent), so
    they cannot be refused ahead of time. ``reserved``: names the adapter sets itself, each with
    the reason, refused even when ``passes_others``. ``choices``: the allowed values of options
    that take one of a few (``obs_mode``).
    """

    names: frozenset[str]
    passes_others: bool = False
    reserved: Mapping[str, str] = field(default_factory=dict)
    choices: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)
