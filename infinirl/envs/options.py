"""Which keyword options an env family takes, read off signatures where it can be.

A simulator option that a family does not take would otherwise surface only when an env is built
with it, which for evaluation options is after training. :class:`EnvOptions` says, per family and task,
which names are accepted, so :func:`~infinirl.envs.registry.check_env_kwargs` can refuse a bad
option in the driver, before any worker starts. Families read them off their factory's fields or
off the simulator's constructor (:func:`keyword_names`), so the list cannot drift from the code.

Only the standard library is imported here: this module is loaded by every env worker.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

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


def keyword_names(target: Callable[..., Any], skip: tuple[str, ...] = ()) -> tuple[frozenset[str], bool]:
    """The names ``target`` (a class or a function) takes by keyword, and whether it takes others.

    A class's ``**kwargs`` is followed into the next ``__init__`` of its method resolution order,
    the usual ``super().__init__(..., **kwargs)`` (gymnasium's MuJoCo tasks hand ``width`` and
    ``height`` to ``MujocoEnv`` that way). From such a parent only parameters with a default or
    keyword-only ones count: the ones without are those the subclass fills in positionally.
    ``**kwargs`` that leads nowhere readable (a plain function, or up to ``object``) means "takes
    others": True as the second value.
    """
    if not isinstance(target, type):
        names, open_ended = _parameters(target, forwarded=False)
        return frozenset(names) - set(skip), open_ended
    names: set[str] = set()
    forwarded = False
    for klass in target.__mro__:
        init = vars(klass).get("__init__")
        if init is None:
            continue
        if klass is object:
            return frozenset(names) - set(skip), True
        found, open_ended = _parameters(init, forwarded)
        names |= found
        if not open_ended:
            return frozenset(names) - set(skip), False
        forwarded = True
    return frozenset(names) - set(skip), True


def _parameters(function: Callable[..., Any], forwarded: bool) -> tuple[set[str], bool]:
    try:
        signature = inspect.signature(function)
    except (TypeError, ValueError):  # a builtin without a readable signature: anything may pass
        return set(), True
    names, open_ended = set(), False
    for name, parameter in signature.parameters.items():
        if parameter.kind is parameter.VAR_KEYWORD:
            open_ended = True
        elif parameter.kind is parameter.KEYWORD_ONLY or (
            parameter.kind is parameter.POSITIONAL_OR_KEYWORD
            and name != "self"
            and (not forwarded or parameter.default is not parameter.empty)
        ):
            names.add(name)
    return names, open_ended
