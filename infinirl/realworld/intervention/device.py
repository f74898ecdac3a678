"""The intervention device interface: how a person (or a simulated one) takes over a learning robot.

Every device (keyboard, gamepad, the run's web page, the scripted simulated human) answers one
question per control step, :meth:`InterventionDevice.poll`: does the human hold control now, and if
so which action do they command? It also delivers the episode marks the human gave since the last
poll (``"success"`` / ``"failure"``), which become the episode's human reward.

Only training episodes are the human's: evaluation episodes measure the policy alone and scripted
demonstrations record their script, so for those the control loop calls :meth:`InterventionDevice.hold_off`
with the episode's kind, and ``hold_off(None)`` when the next training episode starts. The loop goes
on polling meanwhile (a device sees the time pass, and a mark given while the robot resets still
reaches the training episode that ended) but never executes a human's action then; a device refuses a
take-over while held off and says so to its human (:func:`hold_off_message`), rather than accept one
that would steer nothing.

Actions are in the policy's action space (the :class:`~infinirl.realworld.robot_env.RobotEnv`'s
normalised ``[-1, 1]^action_dim``), so an intervened step is stored exactly like a policy step,
with the human's action in place of the policy's and a flag saying who acted.

Devices are registered by name in :data:`INTERVENTION_DEVICES` (entry-point group
``infinirl.intervention_devices``), built by keyword: ``INTERVENTION_DEVICES.get(name)(action_dim=...,
**options)``.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from infinirl.registry import Registry

__all__ = ["EPISODE_MARKS", "HOLD_OFF_KINDS", "INTERVENTION_DEVICES", "HumanInput", "InterventionDevice",
           "hold_off_message"]

EPISODE_MARKS = ("success", "failure")

HOLD_OFF_KINDS = {
    "evaluation": "an evaluation episode is running: the policy is measured alone",
    "demonstration": "a scripted demonstration is running",
}
"""The episode kinds the human stays out of, and what a device tells its human about each."""


def hold_off_message(kind: str) -> str:
    """Why a take-over is refused while episodes of ``kind`` run, and when control opens again."""
    running = HOLD_OFF_KINDS.get(kind) or f"a {kind} episode is running"
    return f"{running}; take-over is refused until the next training episode starts"


@dataclass(frozen=True, kw_only=True)
class HumanInput:
    """What the human did since the last poll.

    ``active``: the human holds control for this step. ``action``: their action (``[-1, 1]``,
    ``action_dim`` entries) when active, else ``None``. ``marks``: episode marks given since the
    last poll, each one of :data:`EPISODE_MARKS`, oldest first.
    """

    active: bool
    action: np.ndarray | None = None
    marks: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        if self.active and self.action is None:
            raise ValueError("HumanInput.active needs an action")
        unknown = [m for m in self.marks if m not in EPISODE_MARKS]
        if unknown:
            raise ValueError(f"HumanInput.marks: unknown mark(s) {unknown}; known: {list(EPISODE_MARKS)}")


class InterventionDevice(abc.ABC):
    """One source of human input for one robot."""

    held_off: str | None = None
    """The kind of the episodes running while the human must stay out (a key of
    :data:`HOLD_OFF_KINDS`), or None during training; set by :meth:`hold_off`."""

    def __init__(self, *, action_dim: int) -> None:
        if action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {action_dim}")
        self.action_dim = action_dim

    @abc.abstractmethod
    def poll(self, *, observation: Mapping[str, np.ndarray] | None = None,
             policy_action: np.ndarray | None = None) -> HumanInput:
        """The human's input for the step about to be taken.

        ``observation`` is the env's current observation and ``policy_action`` what the policy
        proposes; a person does not need them, a simulated human (which decides from the state) and
        the web page (which shows the proposal) do.
        """

    def show(self, frames: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> None:  # noqa: B027
        """Offer the latest camera frames (uint8 ``H x W x 3`` by camera name) and status to a device
        that displays them; devices without a screen ignore it."""

    def bind(self, env: Any) -> None:  # noqa: B027
        """Offer the :class:`~infinirl.realworld.robot_env.RobotEnv` the device serves, before the first
        episode; a device that decides from the robot's state (the simulated human) reads it, others
        ignore it."""

    def reset(self) -> None:  # noqa: B027
        """A new training episode starts (a device with per-episode state clears it)."""

    def hold_off(self, kind: str | None) -> None:
        """From now on the control loop runs episodes of ``kind`` (``"evaluation"``,
        ``"demonstration"``), in which it executes no human action, until ``hold_off(None)`` (before
        the next training episode's reset). A device that holds a take-over gives it back and refuses
        new ones meanwhile, telling its human :func:`hold_off_message`. Overrides call this one."""
        self.held_off = kind

    def close(self) -> None:  # noqa: B027
        """Release what the device holds (threads, sockets, file handles)."""

    def __enter__(self) -> InterventionDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


INTERVENTION_DEVICES: Registry[type[InterventionDevice]] = Registry(
    "intervention device", entry_point_group="infinirl.intervention_devices")
