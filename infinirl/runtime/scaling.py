"""Online scaling: when a running job changes how many ranks a component has, and who asks.

Two sources decide a component's rank count between iterations; the job applies it with
:meth:`~infinirl.runtime.worker.WorkerGroup.resize` and rebalances its own links:

* a **command**: a JSON file ``{"env": 2}`` that the run loop polls (:class:`ScaleCommands`). It
  is consumed once read: renamed to ``<name>.applied`` (or ``<name>.rejected`` with the reason
  printed when it names an unknown component or a bad count);
* a **policy** on the measured busy ratio of the component's ranks (1 - its bubble ratio, the
  fraction of the collection window its ranks spent working; :class:`BusyRatioPolicy`), with
  hysteresis: it grows the component only after ``patience`` consecutive iterations at or above
  ``grow_above`` (it is the bottleneck), shrinks it only after ``patience`` at or below
  ``shrink_below`` (it idles), and never inside the band between the two, so a ratio that hovers
  around one threshold does not flap. A ratio measured on another rank count (an asynchronous
  run's work collected before the last resize) is ignored.

Pure logic and file handling only: nothing here starts or stops a process.
"""

from __future__ import annotations

import json
import os
from collections.abc import Collection
from dataclasses import dataclass

__all__ = ["BusyRatioPolicy", "ScaleCommands", "ScalingConfig", "parse_scale_command"]


@dataclass(kw_only=True)
class ScalingConfig:
    """Online scaling of a runner's scalable component (the embodied runner's: ``env``)."""

    commands: bool = True
    """Poll the command file between iterations."""
    command_file: str = ""
    """The command file; empty: ``scale.json`` in the run's output_dir. Write it atomically
    (write another name, then rename), e.g. ``echo '{"env": 2}' > o/s.tmp && mv o/s.tmp o/scale.json``."""
    auto: bool = False
    """Scale on the measured busy ratio (see grow_above / shrink_below / patience)."""
    min_ranks: int = 1
    max_ranks: int = 2
    grow_above: float = 0.9
    """Add a rank after ``patience`` iterations with the component busy at least this fraction of the time."""
    shrink_below: float = 0.3
    """Remove a rank after ``patience`` iterations with the component busy at most this fraction."""
    patience: int = 3
    """Consecutive iterations a signal must hold before the policy acts (and after it acted)."""

    def check(self) -> None:
        """Raise ValueError naming the key when the policy's settings contradict each other."""
        if not 1 <= self.min_ranks <= self.max_ranks:
            raise ValueError(f"scaling.min_ranks={self.min_ranks} and scaling.max_ranks={self.max_ranks} need "
                             "1 <= min_ranks <= max_ranks")
        if not 0.0 <= self.shrink_below < self.grow_above <= 1.0:
            raise ValueError(f"scaling.shrink_below={self.shrink_below} must be below scaling.grow_above="
                             f"{self.grow_above}, both in [0, 1]: the gap between them is the hysteresis band")
        if self.patience < 1:
            raise ValueError(f"scaling.patience={self.patience} must be >= 1")


class BusyRatioPolicy:
    """Rank count of one component from its busy ratio per iteration, with hysteresis (module doc)."""

    def __init__(self, config: ScalingConfig):
        config.check()
        self.config = config
        self._high = 0
        self._low = 0

    def decide(self, ranks: int, busy_ratio: float, measured_ranks: int | None = None) -> int:
        """The rank count for the next iteration, given this iteration's ``busy_ratio`` at ``ranks``.

        ``measured_ranks``: how many ranks the ratio was measured with, where that may differ from
        ``ranks``. An asynchronous run trains on work collected ahead, so after a resize the next
        iterations still report the old layout's ratio, which says nothing about the new one: such
        a ratio is ignored (neither counted nor breaking a streak), and the policy waits for fresh
        evidence of the layout it would change."""
        if measured_ranks is not None and measured_ranks != ranks:
            return ranks
        cfg = self.config
        self._high = self._high + 1 if busy_ratio >= cfg.grow_above else 0
        self._low = self._low + 1 if busy_ratio <= cfg.shrink_below else 0
        wanted = ranks
        if self._high >= cfg.patience and ranks < cfg.max_ranks:
            wanted = ranks + 1
        elif self._low >= cfg.patience and ranks > cfg.min_ranks:
            wanted = ranks - 1
        if wanted != ranks:  # a change restarts the count: the next one needs fresh evidence
            self._high = self._low = 0
        return wanted


def parse_scale_command(text: str, components: Collection[str], where: str) -> dict[str, int]:
    """``'{"env": 2}'`` -> ``{"env": 2}``; ValueError naming ``where`` and the fix otherwise."""
    try:
        command = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}: not JSON ({exc.msg}); write e.g. {{\"env\": 2}}") from None
    if not isinstance(command, dict) or not command:
        raise ValueError(f"{where}: expected an object of component -> ranks, e.g. {{\"env\": 2}}")
    for name, count in command.items():
        if name not in components:
            raise ValueError(f"{where}: {name!r} cannot be scaled; scalable: {', '.join(components)}")
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ValueError(f"{where}: {name} needs a whole number of ranks >= 1, got {count!r}")
    return dict(command)


class ScaleCommands:
    """The command file a run loop polls: each command is read once, then renamed aside."""

    def __init__(self, path: str, components: Collection[str]):
        self.path = path
        self.components = tuple(components)

    def poll(self) -> dict[str, int]:
        """The pending command (``{}`` if none). A command that cannot be applied is renamed to
        ``.rejected`` and its one-line reason printed; the run goes on."""
        try:
            with open(self.path) as handle:
                text = handle.read()
        except FileNotFoundError:
            return {}
        try:
            command = parse_scale_command(text, self.components, self.path)
        except ValueError as exc:
            os.replace(self.path, self.path + ".rejected")
            print(f"scaling command rejected: {exc}", flush=True)
            return {}
        os.replace(self.path, self.path + ".applied")
        return command

    def reject(self, reason: str) -> None:
        """A parsed command the job cannot apply (e.g. a count its layout does not allow)."""
        if os.path.exists(self.path + ".applied"):
            os.replace(self.path + ".applied", self.path + ".rejected")
        print(f"scaling command rejected: {self.path}: {reason}", flush=True)
