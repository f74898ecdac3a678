"""`infinirl` command line: train / eval / validate / list, on Hydra configs validated before anything starts."""

from __future__ import annotations

import argparse
import sys

from infinirl.config import ConfigError, available_configs, check_override_keys, compose, to_dataclass


def _runners():
    import infinirl.evaluation.runner  # noqa: F401  (registers runner `eval`)
    from infinirl.runners import load_runners

    return load_runners()


def build_config(name: str, overrides: list[str], command: str = "train"):
    """``(runner spec, typed config)`` for ``infinirl <command> <name> <overrides...>``: override keys
    are checked against the runner's config class, so any of its keys may be set, also one the YAML
    leaves out. Tests use it to run a demo exactly as the command line would."""
    runner_name = compose(name).get("runner")
    if not runner_name:
        raise ConfigError(f"config '{name}' has no 'runner:' key; set one of: {', '.join(_runners().names())}")
    if command == "eval" and runner_name != "eval":
        raise ConfigError(f"config '{name}' is a training config (runner {runner_name}); `infinirl eval` takes an "
                          f"eval config (default: eval) and run_dir=<the run's output_dir> for its checkpoint")
    try:
        spec = _runners().get(runner_name)
    except KeyError as exc:
        raise ConfigError(f"runner: {exc}") from None
    check_override_keys(spec.config_cls, overrides)
    # Keys were checked against the typed config above, so a valid key the YAML leaves at its
    # default may be set too (Hydra's `++` = add or override).
    upserts = [o if o[:1] in "+~" else "++" + o for o in overrides]
    return spec, to_dataclass(spec.config_cls, compose(name, upserts))


def main(argv: list[str] | None = None) -> int:
    import os

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads: see runtime.cluster
    parser = argparse.ArgumentParser(
        prog="infinirl",
        description="InfiniRL: RL post-training for LLMs, VLAs and robot policies, from a laptop CPU to a cluster.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    default_config = {"train": "default", "eval": "eval", "validate": "default"}
    for command, text, example in (
        ("train", "run a job", "steps=10 placement.learner=0"),
        ("eval", "greedy accuracy, pass@1 and pass@k of a model or a training run's checkpoint",
         "run_dir=runs/grpo_chain_sum samples=8 k=[1,8]"),
        ("validate", "check a config without running it", "steps=10"),
    ):
        default = default_config[command]
        p = sub.add_parser(command, help=text)
        p.add_argument("config", nargs="?", default=default,
                       help=f"config name (default: {default}). Available: {', '.join(available_configs())}")
        p.add_argument("overrides", nargs="*", help=f"key=value overrides, e.g. {example}")
    sub.add_parser("list", help="list configs and runners")
    args = parser.parse_args(argv)
    if "=" in (getattr(args, "config", None) or ""):  # `infinirl eval run_dir=...`: no config name given
        args.overrides.insert(0, args.config)
        args.config = default_config[args.command]

    if args.command == "list":
        runners = _runners()
        print("configs:", ", ".join(available_configs()))
        for name in runners.names():
            print(f"runner {name}: {runners.get(name).summary}")
        return 0
    try:
        spec, cfg = build_config(args.config, args.overrides, args.command)
        if args.command == "validate":
            print(f"config '{args.config}' is valid (runner {spec.name})")
            return 0
        # Runners check what only they can (the env task, data files, prompt lengths) in the driver
        # before any worker starts and raise ConfigError: reported like a bad key, no traceback.
        spec.run(cfg)
        return 0
    except ConfigError as exc:
        print(f"infinirl: config error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
