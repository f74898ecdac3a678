"""`infinirl` command line: train / eval / validate / list, on Hydra configs validated before anything starts;
`demos` records demonstration datasets; `plan` ranks placements by predicted step time;
`train-classifier` trains a success classifier on human success labels."""

from __future__ import annotations

import argparse
import sys

from infinirl.config import (
    ConfigError,
    available_configs,
    check_override_keys,
    compose,
    to_dataclass,
    upgrade_renamed_overrides,
)

_DEFAULT_CONFIG = {"train": "default", "eval": "eval", "validate": "default", "plan": "default"}


def _runners():
    from infinirl.runners import load_runners

    return load_runners()


def build_config(name: str, overrides: list[str], command: str = "train"):
    """``(runner spec, typed config)`` for ``infinirl <command> <name> <overrides...>``: override keys
    are checked against the runner's config class, so any of its keys may be set, also one the YAML
    leaves out. Tests use it to run a demo exactly as the command line would."""
    base = compose(name)
    runner_name = base.get("runner")
    if not runner_name:
        raise ConfigError(f"config '{name}' has no 'runner:' key; set one of: {', '.join(_runners().names())}")
    if command == "eval" and runner_name != "eval":
        raise ConfigError(f"config '{name}' is a training config (runner {runner_name}); `infinirl eval` takes an "
                          f"eval config (default: eval) and run_dir=<the run's output_dir> for its checkpoint")
    try:
        spec = _runners().get(runner_name)
    except KeyError as exc:
        raise ConfigError(f"runner: {exc}") from None
    for override in overrides:
        if "=" not in override and not override.startswith("~"):
            raise ConfigError(f"override {override!r} has no '=': write key=value (e.g. iterations=10)")
    overrides = upgrade_renamed_overrides(spec.config_cls, overrides)
    _refuse_runner_change(name, runner_name, overrides)
    check_override_keys(spec.config_cls, overrides)
    composed = compose(name, hydra_overrides(base, overrides, spec.config_cls), complete=True)
    return spec, to_dataclass(spec.config_cls, composed)


def _refuse_runner_change(name: str, runner_name: str, overrides: list[str]) -> None:
    for override in overrides:
        key, _, value = override.lstrip("+~").partition("=")
        if key == "runner" and value != runner_name:
            raise ConfigError(f"runner={value}: config '{name}' is for the {runner_name!r} runner and its keys are "
                              f"that runner's; pick a config of the runner you want (`infinirl list`) instead of "
                              "overriding runner")


def hydra_overrides(base: dict, overrides: list[str], cls: type | None = None) -> list[str]:
    """Our ``key=value`` overrides in Hydra's grammar.

    Keys were checked against the typed config, so a valid key the YAML leaves out may be set too
    (Hydra's ``++``: add or override). A mapping value given for a key the YAML sets depends on
    what the key is in ``cls`` (the runner's config class):

    * a typed section (a dataclass, optional or not: ``env``, ``actor.lora``): merged, entry by
      entry, as if each were given as ``key.entry=value`` (``env={num_envs: 4}`` keeps the YAML's
      ``env.name``); a section the YAML leaves unset (``null``) is set to the mapping;
    * a field whose metadata names a ``merge_override`` normaliser (``placement``): the two
      mappings are normalised (``"actor,rollout"`` keys expanded) and merged by entry;
    * a free-form mapping (``eval.env_kwargs``, ``policy.kwargs``) or a key under one: the value
      replaces the YAML's mapping (``eval.env_kwargs={}`` clears it), as a user reading
      ``key=value`` expects."""
    out = []
    for override in overrides:
        if override[:1] in "+~":
            out.append(override)
            continue
        key, _, value = override.partition("=")
        current = _value_at(base, key)
        if not value.strip().startswith("{") or not isinstance(current, dict):
            out.append("++" + override)
            continue
        kind, field = _mapping_kind(cls, key)
        if kind == "section":
            entries = _parsed_mapping(override)
            out += hydra_overrides(base, [f"{key}.{name}={_hydra_value(item)}" for name, item in entries.items()],
                                   cls)
        elif kind == "merge":
            normalise = field.metadata["merge_override"]
            merged = {**normalise(current), **normalise(_plain(_parsed_mapping(override)))}
            out += [f"~{key}", f"+{key}={_hydra_value(merged)}"]
        else:
            out += [f"~{key}", f"+{key}={value}"]
    return out


def _mapping_kind(cls: type | None, dotted: str) -> tuple[str, object]:
    """How a mapping override of ``dotted`` applies: ``section`` (a dataclass: merged by entry),
    ``merge`` (a field with a ``merge_override`` normaliser) or ``replace`` (a free-form mapping,
    or a key under one, or no class to look in)."""
    import dataclasses
    import typing

    node, field = cls, None
    for part in dotted.split("."):
        node = _dataclass_of(node)
        if node is None:
            return "replace", None
        fields = {f.name: f for f in dataclasses.fields(node)}
        if part not in fields:
            return "replace", None
        field = fields[part]
        node = typing.get_type_hints(node)[part]
    if _dataclass_of(node) is not None:
        return "section", field
    if field is not None and "merge_override" in field.metadata:
        return "merge", field
    return "replace", field


def _dataclass_of(tp) -> type | None:
    """``tp`` if it is a dataclass, the dataclass of ``Optional[dataclass]``, else None."""
    import dataclasses
    import types
    import typing

    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        members = [arg for arg in typing.get_args(tp) if arg is not type(None)]
        if len(members) == 1:
            return _dataclass_of(members[0])
    return None


def _parsed_mapping(override: str) -> dict:
    """The mapping of ``key={...}`` as Hydra parses it, quoted strings kept quoted for re-writing."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        value = OverridesParser.create().parse_override(override)._value
    except HydraException as exc:
        raise ConfigError(f"override {override!r}: {exc}") from None
    if not isinstance(value, dict):
        raise ConfigError(f"override {override!r}: expected a mapping {{key: value, ...}}")
    return value


def _hydra_value(value) -> str:
    """A parsed value (or plain data) written back in Hydra's grammar; strings stay strings."""
    from hydra.core.override_parser.types import Override, Quote, QuotedString

    if isinstance(value, str):  # plain data (the merged placement): quoted, so "0" stays a string
        value = QuotedString(text=value, quote=Quote.single)
    elif isinstance(value, dict):
        return "{" + ",".join(f"{_hydra_key(k)}:{_hydra_value(v)}" for k, v in value.items()) + "}"
    elif isinstance(value, list):
        return "[" + ",".join(_hydra_value(v) for v in value) + "]"
    return Override._get_value_element_as_str(value)


def _hydra_key(key) -> str:
    from hydra.core.override_parser.types import Override

    return Override._get_value_element_as_str(str(key))  # keys are never quoted; a comma is escaped


def _plain(value):
    """Hydra's parsed value with its quoted strings as plain strings."""
    from hydra.core.override_parser.types import QuotedString

    if isinstance(value, QuotedString):
        return value.text
    if isinstance(value, dict):
        return {_plain(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def _value_at(tree: dict, dotted: str):
    """The value at ``dotted`` in ``tree``; None where it is absent."""
    node = tree
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _configs_for(command: str) -> list[str]:
    """Config names ``command`` accepts: eval configs for ``eval``, training configs otherwise."""
    names = available_configs()
    if command == "validate":
        return names
    wants_eval = command == "eval"
    return [n for n in names if (compose(n).get("runner") == "eval") == wants_eval]


def main(argv: list[str] | None = None) -> int:
    import os

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads: see runtime.cluster
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser(argv).parse_args(argv)
    if "=" in (getattr(args, "config", None) or ""):  # `infinirl eval run_dir=...`: no config name given
        args.overrides.insert(0, args.config)
        args.config = _DEFAULT_CONFIG[args.command]
    if args.command == "record":
        from infinirl.results import record_run

        try:
            print(record_run(args.source, args.to, args.title))
        except (FileNotFoundError, ValueError) as exc:
            print(f"infinirl: record: {exc}", file=sys.stderr)
            return 2
        return 0
    if args.command == "demos":
        from infinirl.data.demos import demos_command

        return demos_command(args)
    if args.command == "train-classifier":
        from infinirl.realworld.success_classifier.command import train_classifier_command

        return train_classifier_command(args)
    if args.command == "robots":
        from infinirl.realworld.discovery import robots_command

        return robots_command(args.overrides, args.address, args.kinds)
    if args.command == "list":
        runners = _runners()
        print("configs:", ", ".join(available_configs()))
        for name in runners.names():
            print(f"runner {name}: {runners.get(name).summary}")
        return 0
    return _run_config_command(args)


def _run_config_command(args: argparse.Namespace) -> int:
    """``train``, ``eval``, ``validate`` and ``plan``: bad config and cluster failures as one line."""
    try:
        spec, cfg = build_config(args.config, args.overrides, args.command)
        if args.command == "validate":
            if spec.preflight is not None:  # what `train` checks in the driver before the cluster starts
                spec.preflight(cfg)
            print(f"config '{args.config}' is valid (runner {spec.name})")
            return 0
        if args.command == "plan":
            from infinirl.scheduler.auto import plan_command

            return plan_command(cfg, args)
        # Runners check what only they can (the env task, data files, prompt lengths, the resume
        # point) in the driver before any worker starts and raise ConfigError: reported like a bad
        # key, one line, no traceback.
        spec.run(cfg)
        return 0
    except ConfigError as exc:
        print(f"infinirl: config error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except Exception as exc:
        from infinirl.runtime.errors import ClusterError  # here: importing the runtime starts Ray's modules

        if not isinstance(exc, ClusterError):
            raise
        # Ray not started or joined, a node lost: the message says what to do
        print(f"infinirl: ClusterError: {one_line(str(exc))}", file=sys.stderr)
        return 1


def one_line(message: str) -> str:
    """A message on one line (Hydra's parse errors span several), so the error reads as one line."""
    return " ".join(part.strip() for part in message.splitlines() if part.strip())


def _parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="infinirl",
        description="InfiniRL: RL post-training for LLMs, VLAs and robot policies, from a laptop CPU to a cluster.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for command, text, example in (
        ("train", "run a job", "iterations=10 placement.actor=0"),
        ("eval", "greedy accuracy, pass@1 and pass@k of a model or a training run's checkpoint",
         "run_dir=runs/grpo_chain_sum samples=8 k=[1,8]"),
        ("validate", "check a config (and the files and env it names) without running it", "iterations=10"),
    ):
        default = _DEFAULT_CONFIG[command]
        p = sub.add_parser(command, help=text)
        # Only `--help` shows the names, and sorting them by runner composes every config: do it then only.
        names = _configs_for(command) if {"-h", "--help"} & set(argv) else available_configs()
        p.add_argument("config", nargs="?", default=default,
                       help=f"config name (default: {default}). Available: {', '.join(names)}")
        p.add_argument("overrides", nargs="*", help=f"key=value overrides, e.g. {example}")
    plan = sub.add_parser("plan", help="rank placements by predicted step time, from a short measured profile "
                                       "(docs/scheduler.md); placement=auto runs the first")
    plan.add_argument("config", nargs="?", default=_DEFAULT_CONFIG["plan"], help="config name (default: default)")
    plan.add_argument("overrides", nargs="*", help="key=value overrides, e.g. env.num_envs=32")
    plan.add_argument("--top", type=int, default=20, help="candidates shown (default 20)")
    plan.add_argument("--refresh", action="store_true", help="profile again even if a cached profile matches")
    plan.add_argument("--profile-iterations", type=int, default=4,
                      help="iterations of each probe run (the first is warm-up; default 4)")
    plan.add_argument("--profile-rounds", type=int, default=1,
                      help="run every probe this many times, interleaved, so a drifting load shifts all alike")
    plan.add_argument("--gpus", type=int, default=None,
                      help="plan for a simulated cluster of this many GPUs instead (the measured profile scaled)")
    plan.add_argument("--gpus-per-node", type=int, default=8, help="simulated GPUs per node (default 8)")
    plan.add_argument("--speedup", type=float, default=1.0,
                      help="a simulated GPU is this many times faster than the profiled device (default 1)")
    sub.add_parser("list", help="list configs and runners")
    robots = sub.add_parser("robots", help="the robots each node of the cluster reaches (robot:N of placements)")
    robots.add_argument("overrides", nargs="*", help="where to look, kind.option=value: sim_sawyer.instances=2, "
                                                     "so101_feetech.ports=[/dev/ttyACM0]")
    robots.add_argument("--address", default=None, help="join this Ray cluster (default: a local one)")
    robots.add_argument("--kinds", action="store_true", help="list the registered driver kinds and exit")
    record = sub.add_parser("record", help="append a finished run's summary (or a benchmark's JSON file) to the "
                                           "results file, with its command, host and date")
    record.add_argument("source", help="a run's output_dir (its summary.json), a JSON file, or a "
                        "benchmark's saved output (its last line is the JSON)")
    record.add_argument("--to", default="docs/results.md", help="the results file (default: docs/results.md)")
    record.add_argument("--title", default=None, help="the entry's title (default: the run's)")
    demos = sub.add_parser("demos", help="record scripted-expert demonstrations as a LeRobotDataset (v3.0) for "
                                         "behaviour cloning (docs/datasets.md)")
    demos.add_argument("source", help="where the experts come from: metaworld")
    demos.add_argument("--tasks", required=True, help="comma-separated task names or a benchmark, e.g. "
                                                      "reach-v3,push-v3 or MT10")
    demos.add_argument("--episodes-per-task", type=int, required=True, help="successful episodes to keep per task")
    demos.add_argument("--out", required=True, help="the dataset folder to create")
    demos.add_argument("--image-size", type=int, default=64, help="camera frames are SIZE x SIZE (even; default 64)")
    demos.add_argument("--camera", default="corner", help="the camera recorded (default: corner)")
    demos.add_argument("--seed", type=int, default=0, help="seeds the task layouts and the action noise")
    demos.add_argument("--noise-std", type=float, default=0.0,
                       help="Gaussian noise added to the expert's actions, for more varied states (default 0)")
    demos.add_argument("--instructions", choices=["env", "natural"], default="env",
                       help="task strings: the env's own instruction (what a policy sees when evaluated) or the "
                            "Meta-World paper's sentence (MT10 tasks)")
    demos.add_argument("--overwrite", action="store_true", help="replace an existing dataset at --out")
    demos.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_train_classifier(sub)
    return parser


def _add_train_classifier(sub) -> None:
    p = sub.add_parser("train-classifier", help="train a success classifier on the success labels of marked "
                                                "episodes, the reward of real-world RL (docs/realworld.md)")
    p.add_argument("labels_dir", help="the labels folder (<output_dir>/success_labels of a run with "
                                      "interventions.labels=true)")
    p.add_argument("--out", required=True, help="the classifier file to write (and <out>.json)")
    p.add_argument("--arch", default="mlp", help="architecture: mlp (state vector) or cnn (camera frames; default mlp)")
    p.add_argument("--keys", default=None, help="comma-separated observation keys, e.g. state or pixels.corner,state "
                                                "(default: state for mlp, every camera for cnn)")
    p.add_argument("--hidden", default="256,256", help="hidden widths of the MLP head (default 256,256)")
    p.add_argument("--steps", type=int, default=2000, help="training steps (default 2000)")
    p.add_argument("--batch-size", type=int, default=64, help="rows per step, half successes (default 64)")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    p.add_argument("--val-fraction", type=float, default=0.2,
                   help="share of episodes held out for validation (default 0.2; 0: none)")
    p.add_argument("--threshold", type=float, default=0.5,
                   help="probability at or above which a success is predicted (default 0.5)")
    p.add_argument("--seed", type=int, default=0, help="seeds the split, the weights and the batches")


if __name__ == "__main__":
    sys.exit(main())
