"""Training a success classifier from a labels folder, and the metrics it is judged by.

Each step draws a class-balanced batch from the training episodes (:func:`~.labels.balanced_batch`)
and takes an Adam step on the binary cross-entropy of its logits. The report gives, on the training
and the held-out validation rows, the confusion counts and accuracy, precision, recall and balanced
accuracy at the decision threshold: a success is rare among the observations, so accuracy alone
rewards a classifier that never predicts one, and balanced accuracy (the mean of the two classes'
recalls) does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from infinirl.realworld.success_classifier.labels import LabelledEpisodes, balanced_batch, split_episodes
from infinirl.realworld.success_classifier.model import ClassifierSpec, SuccessClassifier, is_image

__all__ = ["TrainSpec", "classification_metrics", "predict", "train_classifier"]

_CHUNK = 1024  # rows per inference batch: bounds the memory of camera frames


@dataclass(frozen=True, kw_only=True)
class TrainSpec:
    steps: int = 2000
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 0.0
    val_fraction: float = 0.2
    """Share of the episodes held out (separately of those with and without a success)."""
    threshold: float = 0.5
    """A probability at or above it predicts success (saved with the classifier)."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch_size < 2:
            raise ValueError(f"TrainSpec: steps must be >= 1 and batch_size >= 2, got {self.steps}, {self.batch_size}")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"TrainSpec.threshold must be in (0, 1), got {self.threshold}")


def classification_metrics(predicted: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """Confusion counts, accuracy, precision, recall and balanced accuracy of boolean predictions;
    a ratio with nothing to count (precision with no predicted success) is NaN."""
    predicted, truth = np.asarray(predicted, bool), np.asarray(labels).astype(bool)
    tp, fp = int(np.sum(predicted & truth)), int(np.sum(predicted & ~truth))
    tn, fn = int(np.sum(~predicted & ~truth)), int(np.sum(~predicted & truth))

    def ratio(num: int, den: int) -> float:
        return num / den if den else float("nan")

    recalls = [ratio(tp, tp + fn), ratio(tn, tn + fp)]
    present = [r for r in recalls if r == r]
    return {"rows": float(len(truth)), "tp": float(tp), "fp": float(fp), "tn": float(tn), "fn": float(fn),
            "accuracy": ratio(tp + tn, len(truth)), "precision": ratio(tp, tp + fp), "recall": recalls[0],
            "balanced_accuracy": float(np.mean(present)) if present else float("nan")}


def predict(classifier: SuccessClassifier, obs: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """Success probabilities of ``rows`` of ``obs``."""
    out = [classifier.probability({key: obs[key][rows[i:i + _CHUNK]] for key in classifier.spec.obs_keys})
           for i in range(0, len(rows), _CHUNK)]
    return np.concatenate(out) if out else np.zeros(0)


def _check_classes(data: LabelledEpisodes, train: np.ndarray, val: np.ndarray, val_fraction: float) -> None:
    successes = int(np.sum(data.labels == 1))
    if successes == 0 or successes == len(data.labels):
        only = "no success (every label is 0)" if successes == 0 else "only successes (every label is 1)"
        raise ValueError(f"labels in {data.folder} hold {only} over {len(data.files)} episodes; a classifier needs "
                         "both: mark successes and failures (success and failure marks of the intervention device)")
    if val_fraction > 0 and len(set(data.labels[val].tolist())) < 2:
        with_success = len(np.unique(data.episode[data.labels == 1]))
        raise ValueError(f"labels in {data.folder}: {with_success} of {len(data.files)} episodes hold a success, too "
                         "few to hold out both classes; record more marked episodes, or train without a validation "
                         "split (val_fraction 0)")
    if len(set(data.labels[train].tolist())) < 2:
        raise ValueError(f"labels in {data.folder}: the training episodes hold one class only; record more "
                         "marked episodes of each outcome")


def _standardisation(data: LabelledEpisodes, spec: ClassifierSpec, rows: np.ndarray):
    mean, std = {}, {}
    for key in spec.obs_keys:
        if is_image(data.shapes[key]):
            continue
        values = data.obs[key][rows].astype(np.float64)
        mean[key] = values.mean(axis=0)
        spread = values.std(axis=0)
        std[key] = np.where(spread > 1e-6, spread, 1.0)  # a constant entry is left as it is
    return mean, std


def train_classifier(data: LabelledEpisodes, spec: ClassifierSpec,
                     train: TrainSpec | None = None) -> tuple[SuccessClassifier, dict]:
    """The trained classifier (eval mode) and its report (counts and metrics on both splits)."""
    train = train or TrainSpec()
    train_rows, val_rows = split_episodes(data, train.val_fraction, train.seed)
    _check_classes(data, train_rows, val_rows, train.val_fraction)
    mean, std = _standardisation(data, spec, train_rows)
    with torch.random.fork_rng(devices=[]):  # seeded weights without touching the caller's generator
        torch.manual_seed(train.seed)
        classifier = SuccessClassifier(spec, data.shapes, threshold=train.threshold, mean=mean, std=std)
    optimizer = torch.optim.Adam(classifier.parameters(), lr=train.lr, weight_decay=train.weight_decay)
    loss_fn = torch.nn.BCEWithLogitsLoss()
    rng = np.random.default_rng([train.seed, 0xBA7C])
    tensors = {key: torch.from_numpy(np.ascontiguousarray(data.obs[key])) for key in spec.obs_keys}
    labels = torch.from_numpy(data.labels.astype(np.float32))
    classifier.train()
    for _ in range(train.steps):
        batch = torch.from_numpy(balanced_batch(data.labels, train_rows, train.batch_size, rng))
        loss = loss_fn(classifier({key: value[batch] for key, value in tensors.items()}), labels[batch])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    classifier.eval()
    report = {"labels_dir": data.folder, "episodes": len(data.files), "observations": len(data.labels),
              "successes": int(np.sum(data.labels == 1)), "obs_keys": list(spec.obs_keys), "steps": train.steps,
              "threshold": train.threshold, "final_loss": float(loss.detach())}
    for name, rows in (("train", train_rows), ("validation", val_rows)):
        if len(rows):
            predicted = predict(classifier, data.obs, rows) >= train.threshold
            report[name] = classification_metrics(predicted, data.labels[rows])
    return classifier, report
