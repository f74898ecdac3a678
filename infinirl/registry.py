"""A small name -> object registry, shared by every pluggable family in InfiniRL.

RLinf picks advantages, losses, models and envs through if/elif chains over config strings, so
adding one means editing a dispatcher far from the new code. Here a new entry is one decorated
definition in one file. The class is generic on purpose: ``envs``,
``models`` and ``robots`` reuse it, and out-of-tree plugins can register through entry points.

A misspelt name fails with every registered name listed (and the closest match suggested), because
the person reading that error is usually editing a YAML file and needs the valid spellings.
"""

from __future__ import annotations

import difflib
import types
from collections.abc import Callable, Iterator
from importlib import metadata
from typing import Generic, TypeVar

T = TypeVar("T")

__all__ = ["Registry", "UnknownNameError"]


class UnknownNameError(KeyError, ValueError):
    """A name that no entry of the registry answers to.

    Subclasses both ``KeyError`` (a failed lookup) and ``ValueError`` (a bad config value), so
    callers may catch whichever matches how they think about it.
    """

    def __str__(self) -> str:  # KeyError would print the message wrapped in quotes
        return str(self.args[0]) if self.args else ""


class Registry(Generic[T]):
    """Maps names to objects of one kind (functions, classes, small spec objects).

    Args:
        kind: what the entries are, in words; it begins every error message
            (``"advantage estimator"`` gives ``unknown advantage estimator 'x'; registered: ...``).
        entry_point_group: optional ``importlib.metadata`` entry-point group. Installed packages
            that declare entry points in it are loaded, once, the first time a name is missing, so
            a plugin registers itself just by being installed.
    """

    def __init__(self, kind: str, entry_point_group: str | None = None) -> None:
        self.kind = kind
        self._entries: dict[str, T] = {}
        self._entry_point_group = entry_point_group
        self._entry_points_loaded = entry_point_group is None

    def register(self, name: str) -> Callable[[T], T]:
        """Decorator form of :meth:`add`: ``@REG.register("grpo")`` above a definition."""

        def decorate(obj: T) -> T:
            self.add(name, obj)
            return obj

        return decorate

    def add(self, name: str, obj: T) -> None:
        """Register ``obj`` under ``name``; registering a taken name is an error, never a silent
        overwrite (two plugins fighting over one name would otherwise depend on import order)."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"{self.kind} names must be non-empty strings, got {name!r}")
        if name in self._entries and self._entries[name] is not obj:
            raise ValueError(
                f"{self.kind} {name!r} is already registered ({self._entries[name]!r})"
            )
        self._entries[name] = obj

    def get(self, name: str) -> T:
        """The entry registered as ``name``; :class:`UnknownNameError` listing all names if none."""
        if name not in self._entries:
            self._load_entry_points()
        try:
            return self._entries[name]
        except (KeyError, TypeError):
            raise UnknownNameError(self._unknown_message(name)) from None

    def names(self) -> list[str]:
        """Registered names, sorted."""
        self._load_entry_points()
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        self._load_entry_points()
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, names={sorted(self._entries)})"

    def _unknown_message(self, name: object) -> str:
        names = self.names()
        message = f"unknown {self.kind} {name!r}; registered: {', '.join(names) or '(none)'}"
        close = difflib.get_close_matches(str(name), names, n=1) if names else []
        if close:
            message += f"; did you mean {close[0]!r}?"
        return message

    def _load_entry_points(self) -> None:
        if self._entry_points_loaded:
            return
        self._entry_points_loaded = True
        for entry_point in metadata.entry_points(group=self._entry_point_group):
            # Loading imports the plugin module, whose decorators call ``register`` on us. A plugin
            # may instead expose the object itself; then the entry point's name is its name.
            loaded = entry_point.load()
            if entry_point.name not in self._entries and not isinstance(loaded, types.ModuleType):
                self.add(entry_point.name, loaded)


# The algorithm families. Entries are added by the modules that define them (advantages.py, ...).
