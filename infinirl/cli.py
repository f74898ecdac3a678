"""`infinirl` command line: train / validate / list, on Hydra configs validated before anything starts."""

from __future__ import annotations

import argparse
import sys

from infinirl.config import ConfigError, available_configs, check_override_keys, compose, to_dataclass


def _build_config(name: str, overrides: list[str]):
    from infinirl.runners import load_runners

    runner_name = compose(name).get("runner")
    if not runner_name:
        raise ConfigError(f"config '{name}' has no 'runner:' key; set one of: {', '.join(load_runners().names())}")
    try:
        spec = load_runners().get(runner_name)
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
    for command, text in (("train", "run a job"), ("validate", "check a config without running it")):
        p = sub.add_parser(command, help=text)
        p.add_argument("config", nargs="?", default="default",
                       help=f"config name (default: default). Available: {', '.join(available_configs())}")
        p.add_argument("overrides", nargs="*", help="key=value overrides, e.g. steps=10 placement.learner=0")
    sub.add_parser("list", help="list configs and runners")
    args = parser.parse_args(argv)

    if args.command == "list":
        from infinirl.runners import load_runners

        print("configs:", ", ".join(available_configs()))
        for name in load_runners().names():
            print(f"runner {name}: {load_runners().get(name).summary}")
        return 0
    try:
        spec, cfg = _build_config(args.config, args.overrides)
    except ConfigError as exc:
        print(f"infinirl: config error: {exc}", file=sys.stderr)
        return 2
    if args.command == "validate":
        print(f"config '{args.config}' is valid (runner {spec.name})")
        return 0
    spec.run(cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
