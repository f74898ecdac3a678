"""Which keyword arguments a class or function takes, read off its signature.

Used to refuse an option a constructor does not take before anything is built: env options
(``envs/options.py``), rollout engine options (``engines/registry.py``) and advantage estimator
options (``runners/reasoning_config.py``). Standard library only, so any layer may use it.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

__all__ = ["keyword_names"]


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
