"""Gamepad intervention through the Linux joystick API (``/dev/input/jsN``).

The kernel's joystick driver delivers 8-byte ``struct js_event`` records (``linux/joystick.h``):
``u32 time`` (ms), ``s16 value``, ``u8 type`` (``JS_EVENT_BUTTON`` 1, ``JS_EVENT_AXIS`` 2, or'ed
with ``JS_EVENT_INIT`` 0x80 for the synthetic events that report the initial state on open), ``u8
number``. Axis values span -32767..32767. The device reads every waiting record once per control
step (non-blocking; a partial record waits for its remaining bytes) and keeps the pad's state:

* ``axes``: the joystick axis feeding each action entry (``None`` or missing: the entry's
  ``rest`` value); ``invert``: entries whose sign flips (a stick's y axis reads positive down);
  ``deadzone``: smaller magnitudes read 0;
* ``takeover_button``: the human holds control while it is down (a dead-man switch), or with
  ``takeover_toggle`` each press toggles control;
* ``success_button`` / ``failure_button``: a press marks the episode.

While the control loop runs an evaluation or a demonstration (:meth:`~InterventionDevice.hold_off`)
the take-over button is refused (logged once): a toggled take-over goes back to the policy and
toggles nothing meanwhile; a held dead-man button steers nothing until a training episode starts
(then, still held, it takes control).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Sequence

import numpy as np

from infinirl.realworld.intervention.device import (
    INTERVENTION_DEVICES,
    HumanInput,
    InterventionDevice,
    hold_off_message,
)
from infinirl.realworld.intervention.fd_reader import NonBlockingReader
from infinirl.realworld.intervention.keyboard import fill

__all__ = ["JS_EVENT", "JS_EVENT_AXIS", "JS_EVENT_BUTTON", "JS_EVENT_INIT", "GamepadDevice", "js_event"]

JS_EVENT = struct.Struct("=IhBB")
JS_EVENT_BUTTON = 0x01
JS_EVENT_AXIS = 0x02
JS_EVENT_INIT = 0x80
AXIS_MAX = 32767.0

logger = logging.getLogger(__name__)


def js_event(*, time_ms: int, value: int, type: int, number: int) -> bytes:  # noqa: A002 - the kernel's field name
    """One ``struct js_event`` record as the kernel writes it."""
    return JS_EVENT.pack(time_ms & 0xFFFFFFFF, value, type, number)


@INTERVENTION_DEVICES.register("gamepad")
class GamepadDevice(InterventionDevice):
    """See the module docstring."""

    def __init__(self, *, action_dim: int, path: str | None = "/dev/input/js0", fd: int | None = None,
                 axes: Sequence[int | None] | None = None, invert: Sequence[int] = (), deadzone: float = 0.1,
                 takeover_button: int = 5, takeover_toggle: bool = False, success_button: int = 0,
                 failure_button: int = 1, rest: Sequence[float] | None = None) -> None:
        super().__init__(action_dim=action_dim)
        axes = list(axes if axes is not None else range(action_dim))
        if len(axes) > action_dim:
            raise ValueError(f"gamepad.axes: at most {action_dim} entries (one per action entry), got {len(axes)}")
        self.axes = axes + [None] * (action_dim - len(axes))
        self.sign = np.ones(action_dim, np.float32)
        self.sign[list(invert)] = -1.0
        if not 0.0 <= deadzone < 1.0:
            raise ValueError(f"gamepad.deadzone must be in [0, 1), got {deadzone}")
        self.deadzone = float(deadzone)
        self.takeover_button, self.takeover_toggle = int(takeover_button), bool(takeover_toggle)
        self.mark_buttons = {int(success_button): "success", int(failure_button): "failure"}
        self.rest = fill(rest, action_dim, 0.0, "gamepad.rest")
        self.axis_values: dict[int, float] = {}
        self.buttons: dict[int, bool] = {}
        self.toggled = False
        self._refusal_logged = False
        self._pending = b""
        if fd is not None:
            path = None
        self.reader = NonBlockingReader(what="gamepad", path=path, fd=fd)

    def _events(self) -> list[tuple[int, int, int, int]]:
        data = self._pending + self.reader.read_or_lost()
        whole = len(data) - len(data) % JS_EVENT.size
        self._pending = data[whole:]
        return list(JS_EVENT.iter_unpack(data[:whole]))

    def poll(self, *, observation=None, policy_action=None) -> HumanInput:
        marks: list[str] = []
        refused = False  # a take-over press while held off
        for _time, value, kind, number in self._events():
            initial = bool(kind & JS_EVENT_INIT)
            kind &= ~JS_EVENT_INIT
            if kind == JS_EVENT_AXIS:
                self.axis_values[number] = max(-1.0, value / AXIS_MAX)
            elif kind == JS_EVENT_BUTTON:
                pressed = value != 0
                was = self.buttons.get(number, False)
                self.buttons[number] = pressed
                if initial or not pressed or was:
                    continue  # only a fresh press counts (the initial state on open is no press)
                if number == self.takeover_button and self.held_off is not None:
                    refused = True
                elif number == self.takeover_button and self.takeover_toggle:
                    self.toggled = not self.toggled
                elif number in self.mark_buttons:
                    marks.append(self.mark_buttons[number])
        if self.reader.eof:
            # The pad was unplugged: its last state (a held dead-man button, a deflected stick) is
            # stale and no release will ever arrive, so control returns to the policy for good.
            self.buttons.clear()
            self.axis_values.clear()
            self.toggled = False
            self._pending = b""
        active = self.toggled if self.takeover_toggle else self.buttons.get(self.takeover_button, False)
        if self.held_off is not None:
            if (refused or active) and not self._refusal_logged:
                self._refusal_logged = True
                logger.warning("gamepad: take-over refused: %s", hold_off_message(self.held_off))
            active = False
        if not active:
            return HumanInput(active=False, marks=tuple(marks))
        return HumanInput(active=True, action=self.action(), marks=tuple(marks))

    def hold_off(self, kind: str | None) -> None:
        super().hold_off(kind)
        self._refusal_logged = False
        if kind is not None and self.toggled:
            self.toggled = False  # a later press takes over anew, once training episodes run again
            logger.warning("gamepad: control goes back to the policy: %s", hold_off_message(kind))

    def action(self) -> np.ndarray:
        """The action the pad's present state commands."""
        action = self.rest.copy()
        for entry, axis in enumerate(self.axes):
            if axis is None:
                continue
            value = self.axis_values.get(int(axis), 0.0)
            action[entry] = 0.0 if abs(value) < self.deadzone else value * self.sign[entry]
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def close(self) -> None:
        self.reader.close()
