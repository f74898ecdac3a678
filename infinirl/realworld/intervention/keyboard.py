"""Keyboard intervention: keys typed into a terminal take over the robot and steer it.

The device reads a terminal (``path``, e.g. the ``/dev/pts/N`` of a terminal window on the robot's
machine, or an adopted descriptor ``fd``) in raw, non-blocking mode, once per control step:

* ``toggle_key`` (space): take over / hand back;
* ``axis_keys``: one two-character string per action entry, ``"<minus><plus>"``; each press
  adds ``-step`` / ``+step`` to that entry for the present step (a terminal reports presses, not
  releases, so an entry returns to its ``rest`` value on the next step unless the key repeats);
  entries in ``latched_axes`` keep their value until changed (a gripper);
* ``success_key`` (``s``) / ``failure_key`` (``f``): mark the episode.

Keys pressed while the human does not hold control move nothing. Other bytes are ignored. While the
control loop runs an evaluation or a demonstration (:meth:`~InterventionDevice.hold_off`) the toggle
key is refused, and a take-over held when one starts goes back to the policy, both with a warning
in the log (a terminal in raw mode shows nothing else).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import numpy as np

from infinirl.realworld.intervention.device import (
    INTERVENTION_DEVICES,
    HumanInput,
    InterventionDevice,
    hold_off_message,
)
from infinirl.realworld.intervention.fd_reader import NonBlockingReader

__all__ = ["DEFAULT_AXIS_KEYS", "KeyboardDevice"]

logger = logging.getLogger(__name__)

DEFAULT_AXIS_KEYS = ("ad", "xw", "ze", "jl", "ki", "uo", "nm", "gh")
"""Entry 0: a/d, 1: x/w, 2: z/e, 3: j/l, ... (minus key first)."""


def fill(values: Sequence[float] | None, size: int, default: float, what: str) -> np.ndarray:
    """``values`` as a float32 vector of ``size`` entries (``default`` everywhere when None)."""
    if values is None:
        return np.full(size, default, np.float32)
    array = np.asarray(values, np.float32).reshape(-1)
    if array.shape != (size,):
        raise ValueError(f"{what}: needs {size} entries (one per action entry), got {array.shape[0]}")
    return array


@INTERVENTION_DEVICES.register("keyboard")
class KeyboardDevice(InterventionDevice):
    """See the module docstring."""

    def __init__(self, *, action_dim: int, path: str | None = None, fd: int | None = None,
                 axis_keys: Sequence[str] | None = None, toggle_key: str = " ", success_key: str = "s",
                 failure_key: str = "f", step: float = 1.0, rest: Sequence[float] | None = None,
                 latched_axes: Sequence[int] = (), raw: bool = True) -> None:
        super().__init__(action_dim=action_dim)
        axis_keys = tuple(axis_keys if axis_keys is not None else DEFAULT_AXIS_KEYS[:action_dim])
        if len(axis_keys) > action_dim or any(len(pair) != 2 for pair in axis_keys):
            raise ValueError(f"keyboard.axis_keys: at most {action_dim} two-character strings '<minus><plus>', "
                             f"got {list(axis_keys)}")
        self._keys: dict[str, tuple[int, float]] = {}
        for axis, (minus, plus) in enumerate(axis_keys):
            self._keys[minus], self._keys[plus] = (axis, -float(step)), (axis, float(step))
        controls = {toggle_key: "toggle", success_key: "success", failure_key: "failure"}
        clash = sorted(set(controls) & set(self._keys))
        if clash or len(controls) != 3:
            raise ValueError(f"keyboard: keys {clash or list(controls)} are bound twice; give each its own key")
        self._controls: Mapping[str, str] = controls
        self.rest = fill(rest, action_dim, 0.0, "keyboard.rest")
        self.latched_axes = frozenset(int(a) for a in latched_axes)
        self.latched = self.rest.copy()
        self.active = False
        if path is None and fd is None:
            import os
            import sys

            fd = sys.stdin.fileno()
            if not os.isatty(fd):
                raise OSError("keyboard: this process's stdin is not a terminal (a robot worker has none); set the "
                              "device's path option to a terminal, e.g. the /dev/pts/N that `tty` prints in it")
        self.reader = NonBlockingReader(what="keyboard", path=path, fd=fd, raw=raw)

    def poll(self, *, observation=None, policy_action=None) -> HumanInput:
        delta = np.zeros(self.action_dim, np.float32)
        marks: list[str] = []
        for key in self.reader.read_or_lost().decode("latin-1"):
            control = self._controls.get(key)
            if control == "toggle" and self.held_off is not None and not self.active:
                logger.warning("keyboard: take-over refused: %s", hold_off_message(self.held_off))
            elif control == "toggle":
                self.active = not self.active
                delta[:] = 0.0  # presses before a take-over steer nothing
            elif control is not None:
                marks.append(control)
            elif key in self._keys and self.active:
                axis, amount = self._keys[key]
                delta[axis] += amount
        if self.reader.eof:
            # The terminal went away: nobody can hand back any more, so control returns to the policy
            # for good (keys read before the loss still give their marks).
            self.active = False
            self.latched = self.rest.copy()
        if not self.active:
            return HumanInput(active=False, marks=tuple(marks))
        action = np.clip(self.rest + delta, -1.0, 1.0)
        for axis in self.latched_axes:
            self.latched[axis] = np.clip(self.latched[axis] + delta[axis], -1.0, 1.0)
            action[axis] = self.latched[axis]
        return HumanInput(active=True, action=action.astype(np.float32), marks=tuple(marks))

    def hold_off(self, kind: str | None) -> None:
        super().hold_off(kind)
        if kind is not None and self.active:
            self.active = False  # a later toggle takes over anew, once training episodes run again
            logger.warning("keyboard: control goes back to the policy: %s", hold_off_message(kind))

    def close(self) -> None:
        self.reader.close()
