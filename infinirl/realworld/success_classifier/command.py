"""``infinirl train-classifier <labels_dir> --out <path>``: train a success classifier on a labels
folder, print its validation metrics, save it. Bad input (a missing or empty folder, labels of one
class only, too few episodes to hold out) is reported in one line."""

from __future__ import annotations

import argparse
import sys

from infinirl.realworld.success_classifier.labels import load_labels
from infinirl.realworld.success_classifier.model import ClassifierSpec, save_classifier
from infinirl.realworld.success_classifier.train import TrainSpec, train_classifier

__all__ = ["default_keys", "format_metrics", "train_classifier_command"]


def default_keys(architecture: str, held: list[str]) -> list[str]:
    """The observation keys read when none are named: ``cnn`` every camera frame, others the state."""
    if architecture == "cnn":
        return sorted(key for key in held if key.startswith("pixels.")) or ["pixels.<camera>"]
    return ["state"]


def format_metrics(metrics: dict) -> str:
    names = ("accuracy", "balanced_accuracy", "precision", "recall")
    counts = ", ".join(f"{key} {int(metrics[key])}" for key in ("tp", "fp", "tn", "fn"))
    return ", ".join(f"{name} {metrics[name]:.3f}" for name in names) + f" ({counts})"


def _ints(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in text.split(",") if part.strip())


def _run(args: argparse.Namespace) -> None:
    keys = [key for key in (args.keys or "").split(",") if key]
    if keys:
        data = load_labels(args.labels_dir, keys)
    elif args.arch == "cnn":
        data = load_labels(args.labels_dir)
        keys = default_keys("cnn", list(data.obs))
        data = load_labels(args.labels_dir, keys)
    else:
        keys = default_keys(args.arch, [])
        data = load_labels(args.labels_dir, keys)
    spec = ClassifierSpec(architecture=args.arch, obs_keys=tuple(keys), hidden=_ints(args.hidden))
    train = TrainSpec(steps=args.steps, batch_size=args.batch_size, lr=args.lr, val_fraction=args.val_fraction,
                      threshold=args.threshold, seed=args.seed)
    classifier, report = train_classifier(data, spec, train)
    print(f"success classifier ({args.arch} on {', '.join(keys)}): {report['observations']} observations of "
          f"{report['episodes']} episodes, {report['successes']} successes")
    for split in ("train", "validation"):
        if split in report:
            print(f"  {split}: {format_metrics(report[split])}")
    save_classifier(args.out, classifier, report)
    print(f"saved {args.out} (and {args.out}.json); the robot env's reward: rewards {{classifier: 1.0}}, "
          f"reward_options {{classifier: {{path: {args.out}}}}}")


def train_classifier_command(args: argparse.Namespace) -> int:
    try:
        _run(args)
    except (FileNotFoundError, ValueError) as exc:
        print(f"infinirl: train-classifier: {exc}", file=sys.stderr)
        return 2
    return 0
