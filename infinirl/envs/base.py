"""The vectorised environment contract shared by every simulator adapter.

Two layers, so a new simulator needs only the small one:

* :class:`SubEnv` is ONE simulator instance (one robot, one scene). An adapter (MetaWorld,
  gymnasium, ...) implements only this: reset to a seed or a fixed state, step one action, say what
  its actions and observations look like.
* :class:`Env` is what components and runners use: ``num_envs`` sub-environments stepped together,
  observations batched with a leading env dimension, automatic reset with the final observation
  kept, episode statistics and crash recovery. :class:`infinirl.envs.vector.VectorEnv` builds an
  :class:`Env` from any :class:`SubEnv` factory, so that logic exists once (RLinf has a copy of it
  in each of its eight env wrappers).

Observations are dicts. Array entries have a leading env dimension; the conventional keys are
``state`` (full low-dimensional state, float32), ``proprio`` (robot joint/end-effector state,
float32), ``rgb`` (uint8 camera image, height x width x 3) and ``instruction`` (a list of ``num_envs``
language strings). Only numpy is used here, so this module imports in any process cheaply.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = [
    "ActionSpace",
    "collate_obs",
    "copy_obs",
    "obs_row",
    "set_obs_rows",
    "ArraySpec",
    "Env",
    "EnvCrashError",
    "Obs",
    "ObservationSpec",
    "StepResult",
    "SubEnv",
    "SubEnvFactory",
    "SubStep",
    "step_takes_observe",
]

Obs = dict[str, Any]
"""One observation: ``{"state": array, "rgb": array, "instruction": str | list[str], ...}``."""

STRING_DTYPE = "str"
"""The ``ArraySpec.dtype`` of text fields (``instruction``): batched as a Python list, not an array."""


class EnvCrashError(RuntimeError):
    """A sub-environment failed in a way that restarting it cannot fix (its factory or its reset
    keeps raising, or it crashed more often than ``max_restarts``). The message carries the
    original traceback, so the root cause is visible where the run stops."""


def collate_obs(rows: Sequence[Obs]) -> Obs:
    """Per-env observations -> one batched dict: arrays stacked on a new leading env axis, text
    fields (``instruction``) kept as a list of strings."""
    batched: Obs = {}
    for key, first in rows[0].items():
        values = [row[key] for row in rows]
        batched[key] = values if isinstance(first, str) else np.stack(values)
    return batched


def copy_obs(obs: Obs) -> Obs:
    """A batched observation that shares no buffer with ``obs`` (safe to keep across steps)."""
    return {key: list(value) if isinstance(value, list) else value.copy() for key, value in obs.items()}


def obs_row(obs: Obs, index: int) -> Obs:
    """Env ``index``'s observation out of a batched one (no env dimension)."""
    return {key: value[index] for key, value in obs.items()}


def set_obs_rows(obs: Obs, indices: Sequence[int], rows: Obs) -> None:
    """Write the batched ``rows`` into ``obs`` at env ``indices``, in place."""
    for key, value in rows.items():
        target = obs[key]
        if isinstance(target, list):
            for position, index in enumerate(indices):
                target[index] = value[position]
        else:
            target[list(indices)] = value


@dataclass(frozen=True)
class ArraySpec:
    """Shape and dtype of one observation field for ONE env (no leading env dimension).

    ``dtype`` is a numpy dtype name (``"float32"``, ``"uint8"``) or ``"str"`` for text fields.
    """

    shape: tuple[int, ...]
    dtype: str

    @property
    def is_text(self) -> bool:
        return self.dtype == STRING_DTYPE


ObservationSpec = Mapping[str, ArraySpec]
"""Field name -> :class:`ArraySpec`, e.g. ``{"state": ArraySpec((39,), "float32")}``."""


@dataclass(frozen=True, eq=False)
class ActionSpace:
    """The actions ONE env accepts: a box (``low``/``high`` per dimension) or ``num_choices``
    discrete actions (then ``shape`` is ``()`` and actions are integers ``0..num_choices-1``).

    Policies size their heads from this; the vectoriser checks batched actions against it so that
    a wrong shape fails at the call with the expected shape named, not deep inside a simulator.
    """

    shape: tuple[int, ...]
    low: np.ndarray
    high: np.ndarray
    dtype: str = "float32"
    num_choices: int | None = None

    @classmethod
    def box(cls, low: Any, high: Any, dtype: str = "float32") -> ActionSpace:
        """A continuous space; ``low`` and ``high`` are arrays of the action's shape."""
        low_array = np.asarray(low, dtype=dtype)
        high_array = np.asarray(high, dtype=dtype)
        if low_array.shape != high_array.shape:
            raise ValueError(f"low {low_array.shape} and high {high_array.shape} differ in shape")
        return cls(tuple(low_array.shape), low_array, high_array, dtype)

    @classmethod
    def discrete(cls, num_choices: int) -> ActionSpace:
        """``num_choices`` integer actions, ``0 .. num_choices - 1``."""
        return cls((), np.asarray(0), np.asarray(num_choices - 1), "int64", num_choices)

    @property
    def is_discrete(self) -> bool:
        return self.num_choices is not None

    def __eq__(self, other: object) -> bool:  # the generated one would compare arrays ambiguously
        if not isinstance(other, ActionSpace):
            return NotImplemented
        return (
            (self.shape, self.dtype, self.num_choices) == (other.shape, other.dtype, other.num_choices)
            and np.array_equal(self.low, other.low)
            and np.array_equal(self.high, other.high)
        )

    __hash__ = None  # mutable-array fields: not hashable

    def chunked(self, chunk_size: int) -> ActionSpace:
        """The space of ``chunk_size`` consecutive actions, shape ``(chunk_size, *shape)``."""
        repeat = (chunk_size,) + (1,) * len(self.shape)
        return ActionSpace(
            (chunk_size, *self.shape),
            np.tile(self.low, repeat),
            np.tile(self.high, repeat),
            self.dtype,
            self.num_choices,
        )

    def sample(self, num_envs: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """Uniformly random actions for ``num_envs`` envs (smoke tests, random baselines)."""
        rng = rng or np.random.default_rng()
        if self.is_discrete:
            return rng.integers(0, self.num_choices, size=(num_envs, *self.shape))
        return rng.uniform(self.low, self.high, size=(num_envs, *self.shape)).astype(self.dtype)

    def validate(self, actions: Any, num_envs: int) -> np.ndarray:
        """``actions`` as a numpy array of shape ``(num_envs, *shape)``, or a ``ValueError`` that
        names the expected and the received shape. Torch tensors are accepted (moved to CPU)."""
        if hasattr(actions, "detach"):  # a torch tensor, without importing torch here
            actions = actions.detach().cpu().numpy()
        array = np.asarray(actions)
        expected = (num_envs, *self.shape)
        if array.shape != expected:
            raise ValueError(
                f"expected actions of shape {expected} (num_envs={num_envs}, action shape "
                f"{self.shape}), got {array.shape}"
            )
        if self.is_discrete and not np.issubdtype(array.dtype, np.integer):
            raise ValueError(f"expected integer actions in [0, {self.num_choices}), got {array.dtype}")
        return array


@dataclass
class SubStep:
    """What one :class:`SubEnv` returns from ``step``: per-env scalars, not batched."""

    obs: Obs
    reward: float
    terminated: bool
    truncated: bool
    success: bool = False


@dataclass
class StepResult:
    """One step of ``num_envs`` envs; every array has the env dimension first.

    ``info`` always holds (arrays of length ``num_envs``):

    * ``success``: the simulator's task-success flag at this step;
    * ``final_obs`` / ``final_obs_mask``: an episode that ended at this step was reset at once
      (``obs`` is then the first observation of the next episode; with ``step(...,
      autoreset=False)`` it is not, and ``obs`` repeats the last one); its last observation is kept in
      ``final_obs``, valid where ``final_obs_mask`` (= ``terminated | truncated``) is true, so
      truncated episodes can still be bootstrapped from a value of their last state;
    * ``episode_return`` / ``episode_length`` / ``episode_success`` (success at any step of the
      episode): statistics of the episode that ended, valid where ``final_obs_mask``;
    * ``restarted``: the sub-env crashed and was rebuilt; its episode is reported truncated and
      ``restart_errors`` maps its index to the traceback text.
    """

    obs: Obs
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def done(self) -> np.ndarray:
        """Episode ended by either way (the next ``obs`` belongs to a new episode)."""
        return self.terminated | self.truncated


@runtime_checkable
class SubEnv(Protocol):
    """One simulator instance; adapters implement this, :class:`VectorEnv` batches it.

    ``reset`` gets either a ``seed`` (a fresh random episode, reproducible from the seed) or a
    ``state_id`` (one of a fixed set of initial states, so several envs can start identically, as
    embodied GRPO needs). Simulators without a table of initial states treat a state id as a seed.
    Observations carry no env dimension; ``instruction`` is a plain string.

    An adapter whose observations have a costly part (camera frames) may give ``step`` a keyword
    ``observe: bool = True``: with ``observe=False`` nobody will read the step's observation (an
    inner step of an action chunk), so it may repeat the previous frame instead of rendering, except
    on a step that ends the episode (its final observation is kept). Physics, reward and state must
    not depend on it. :func:`step_takes_observe` tells whether an env's ``step`` takes it.
    """

    action_space: ActionSpace
    observation_spec: ObservationSpec

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs: ...

    def step(self, action: np.ndarray) -> SubStep: ...

    def render(self) -> np.ndarray: ...

    def close(self) -> None: ...


SubEnvFactory = Callable[[int], SubEnv]
"""Builds the sub-env with the given global index; must be picklable (a module-level class or a
``functools.partial`` of one) because worker processes call it."""


def step_takes_observe(env: object) -> bool:
    """Whether ``env.step`` takes the ``observe`` keyword (skip what nobody will read)."""
    try:
        return "observe" in inspect.signature(env.step).parameters
    except (TypeError, ValueError):  # a step without a readable signature: assume not
        return False


@runtime_checkable
class Env(Protocol):
    """The vectorised environment components and runners program against.

    ``step(actions, env_mask=None)``: where ``env_mask`` is false the env is not stepped; its row
    repeats its current observation with zero reward and no episode end (action chunking uses
    this to stop an env whose episode ended within a chunk). ``autoreset=False``: an episode that
    ends is not restarted and that env may not be stepped again before ``reset`` (for a last step
    whose next observation is not used). An env may also take ``step(..., observe=False)`` for a
    step whose observation nobody reads (:class:`~infinirl.envs.vector.VectorEnv` does; see
    :class:`SubEnv`). ``open_episodes()``: the return so far and the steps so
    far of each env's running episode (``{"return": [num_envs], "length": [num_envs]}``), for
    reporting progress on episodes longer than a collection. ``offload``/``reload`` release and
    restore device memory for simulators that hold some; CPU simulators make them no-ops.
    """

    num_envs: int
    action_space: ActionSpace
    observation_spec: ObservationSpec

    def reset(
        self, seeds: int | Sequence[int] | None = None, state_ids: Sequence[int] | None = None
    ) -> Obs: ...

    def step(self, actions: Any, env_mask: np.ndarray | None = None, autoreset: bool = True) -> StepResult: ...

    def render(self) -> np.ndarray: ...

    def open_episodes(self) -> dict[str, np.ndarray]: ...

    def offload(self) -> None: ...

    def reload(self) -> None: ...

    def close(self) -> None: ...
