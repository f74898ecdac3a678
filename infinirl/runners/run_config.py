"""The run configuration every runner shares: seed, length, output, cadences, loggers, placement, cluster.

A runner's config class derives from :class:`RunConfig` and adds its own sections (model, env,
algorithm, ...). The shared keys mean the same in every runner:

* ``iterations``: how many times the runner's ``step()`` runs (one rollout + one update);
* ``eval.every`` / ``eval.at_start``: held-out evaluation cadence;
* ``save_every`` / ``keep_checkpoints``: checkpoint cadence and retention
  (``<output_dir>/checkpoints/iter_NNNNNN/``);
* ``resume``: continue from the newest checkpoint of ``output_dir``;
* ``placement``: component -> devices or CPU slots; a key may name several components
  (``"actor,rollout": "0"``), and components a config leaves out keep the runner's defaults;
  ``auto``: the scheduler picks the placement (docs/scheduler.md), and ``auto`` as one component's
  spec lets it place that component only.

Numeric limits are declared on the fields (:func:`~infinirl.config.bounded`); a subclass's
``check()`` holds only the rules that involve several fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from infinirl.config import ConfigError, bounded
from infinirl.runtime import ClusterConfig

__all__ = ["AUTO_PLACEMENT", "EvalSchedule", "RunConfig", "expand_placement", "validate_placement"]

AUTO_PLACEMENT = "auto"
"""``placement: auto``: the scheduler profiles the config and runs the placement it predicts fastest."""


@dataclass(kw_only=True)
class EvalSchedule:
    """When the held-out evaluation runs; each runner's eval section adds what it evaluates."""

    every: int = bounded(5, ge=0)
    """Evaluate every N iterations (and after the last); 0 = only after the last."""
    at_start: bool = True
    """Also evaluate the initial policy (iteration 0): the baseline the summary's eval_before reports."""


@dataclass(kw_only=True)
class RunConfig:
    """Keys shared by every runner (see the module docstring)."""

    RUNNER: ClassVar[str] = ""
    """The registered runner this config class belongs to."""
    DEFAULT_PLACEMENT: ClassVar[dict[str, str]] = {}
    """Where each required component goes unless the config says otherwise."""
    OPTIONAL_COMPONENTS: ClassVar[dict[str, str]] = {}
    """Components a run may launch besides the required ones -> the component whose placement
    they take when the config gives none (e.g. a critic on the actor's devices)."""
    RENAMED_KEYS: ClassVar[dict[str, str]] = {}
    """Old key -> new key; the old one still works, with a warning, until release 0.2."""
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = ()
    """Keys (or key prefixes) of this runner, besides the shared ones, whose change on resume takes
    effect as intended (throughput settings that do not change what is learned)."""

    runner: str = ""
    seed: int = bounded(0, ge=0)
    iterations: int = bounded(20, ge=1)
    """Iterations of the runner's step (one rollout and one update each)."""
    output_dir: str = "runs/run"
    """Metrics, TensorBoard, curves, checkpoints and the resolved config go here."""
    save_every: int = bounded(0, ge=0)
    """Checkpoint every N iterations (0 = only at the end)."""
    keep_checkpoints: int = bounded(0, ge=0)
    """Newest checkpoints kept on disk; 0 = keep all."""
    resume: bool = True
    """Continue from the newest checkpoint in output_dir if there is one (a config that changed in a
    way the checkpoint cannot honour is refused, naming the keys)."""
    loggers: list[str] = field(default_factory=lambda: ["tensorboard"])
    """Metric sinks besides metrics.jsonl: tensorboard, wandb, swanlab."""
    eval: EvalSchedule = field(default_factory=EvalSchedule)
    placement: dict[str, str] | str = field(default_factory=dict,
                                            metadata={"merge_override": lambda value: expand_placement(value)})
    """Component -> devices or CPU slots (see infinirl.runtime.placement); "a,b" keys place several.
    ``auto``: the placement the scheduler predicts fastest, chosen when the run starts; ``auto`` as one
    component's spec (``placement.learner=auto``): the scheduler places that one, the others stay.
    A mapping given on the command line (``placement={critic: 1}``) merges over the config's by
    component, like ``placement.critic=1``; ``placement=auto`` replaces it."""
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    def __post_init__(self) -> None:
        if not self.runner:
            self.runner = self.RUNNER
        if isinstance(self.placement, dict):  # "auto" is resolved when the run starts; another string fails validate
            self.placement = {**expand_placement(self.DEFAULT_PLACEMENT), **expand_placement(self.placement)}

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        """Shared rules, then the runner's cross-field rules (:meth:`check`)."""
        from infinirl.runners.loggers import LOGGERS, require_logger

        if self.runner != self.RUNNER:
            raise ConfigError(f"runner={self.runner!r}: this config is for the {self.RUNNER!r} runner; to run another "
                              "runner pick one of its configs (`infinirl list`)")
        for name in self.loggers:
            if name not in LOGGERS:
                raise ConfigError(f"loggers: unknown logger {name!r}; choose from {', '.join(LOGGERS.names())}")
            try:
                require_logger(name)
            except ImportError as exc:
                raise ConfigError(f"loggers: {exc}, or remove {name!r} from loggers") from None
        self._validate_placement()
        self.check()

    def check(self) -> None:
        """Rules that involve several fields of the runner's own sections; raise ConfigError."""

    def _validate_placement(self) -> None:
        if self.placement == AUTO_PLACEMENT:
            return
        known = [*self.DEFAULT_PLACEMENT, *self.OPTIONAL_COMPONENTS]
        if isinstance(self.placement, dict):  # an "auto" entry still names a known component
            validate_placement({c: "0" if spec == AUTO_PLACEMENT else spec for c, spec in self.placement.items()},
                               known, self.RUNNER)
            return
        validate_placement(self.placement, known, self.RUNNER)

    # ------------------------------------------------------------------ derived
    @property
    def auto_placement(self) -> bool:
        """``placement: auto``, or ``auto`` for some components (``placement.learner=auto``): the run
        resolves those when it starts (``run_support``), the others stay where they are given."""
        if isinstance(self.placement, dict):
            return AUTO_PLACEMENT in self.placement.values()
        return self.placement == AUTO_PLACEMENT

    def pinned_placement(self) -> dict[str, str]:
        """Under :attr:`auto_placement`, the launched components the config places itself (the
        scheduler searches only the others); all of them otherwise."""
        if not isinstance(self.placement, dict):
            return {}
        return {name: spec for name, spec in self.placement_spec().items() if spec != AUTO_PLACEMENT}

    def components(self) -> list[str]:
        """The components this run launches (required ones, then optional ones it uses)."""
        return list(self.DEFAULT_PLACEMENT)

    def placement_spec(self) -> dict[str, str]:
        """One placement entry per launched component (optional ones fall back as declared)."""
        entries = dict(self.placement)
        for name, fallback in self.OPTIONAL_COMPONENTS.items():
            entries.setdefault(name, entries[fallback])
        return {name: entries[name] for name in self.components()}

    def data_files(self) -> dict[str, str]:
        """``label -> path`` of the data files and folders this run reads whose contents decide what it
        trains on (rows, demonstrations, a checkpoint it starts from); each is recorded in every
        checkpoint (a file by size and sha256, a folder by a digest of its files), and a resume over
        other contents is refused (:mod:`infinirl.runners.run_inputs`). The label names the config key."""
        return {}

    def resume_may_change(self, key: str) -> bool:
        """Whether a change of ``key`` (dotted) between a checkpoint and this config takes effect on resume."""
        shared = ("iterations", "output_dir", "resume", "save_every", "keep_checkpoints", "loggers", "eval",
                  "placement", "cluster")
        return any(key == p or key.startswith(p + ".") for p in (*shared, *self.RESUME_MAY_CHANGE))

    def resume_refusal_hint(self, key: str) -> str:
        """Why a change of ``key`` is refused on resume where the general reason does not say it, and what to do."""
        return ""


def validate_placement(placement: dict[str, str], known, runner: str) -> None:
    """Every entry names a component of ``runner`` and parses as a placement spec."""
    from infinirl.runtime.placement import PlacementError, parse_spec

    if not isinstance(placement, dict):
        raise ConfigError(f"placement={placement!r}: give a mapping of component -> devices (e.g. {{actor: '0'}}) "
                          f"or '{AUTO_PLACEMENT}' for the scheduler's choice")
    for component, spec in placement.items():
        if component not in known:
            raise ConfigError(f"placement.{component}: the {runner} runner has no such component; "
                              f"its components are {', '.join(known)}")
        try:
            parse_spec(spec, component)
        except PlacementError as exc:
            raise ConfigError(f"placement.{component}: {exc}") from None


def expand_placement(placement: dict[str, Any]) -> dict[str, str]:
    """``{"actor,rollout": "0"}`` -> ``{"actor": "0", "rollout": "0"}``; a component named twice is an error."""
    entries: dict[str, str] = {}
    for key, spec in (placement or {}).items():
        for name in (part.strip() for part in str(key).split(",")):
            if not name:
                raise ConfigError(f"placement key {key!r} has an empty component name")
            if name in entries:
                raise ConfigError(f"placement gives {name!r} twice; give each component one entry")
            entries[name] = str(spec)
    return entries
