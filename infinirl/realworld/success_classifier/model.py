"""The success classifier: observation -> probability that the task is done.

An observation is a dict of the robot env's keys (``state``: the float state vector,
``pixels.<camera>``: uint8 ``[H, W, 3]`` frames). :class:`ClassifierSpec` names the keys read and the
architecture, an entry of :data:`CLASSIFIER_ARCHITECTURES`:

* ``mlp``: the vector keys, each standardised by its training mean and std, concatenated, through
  an MLP (ReLU) to one logit;
* ``cnn``: each camera frame through its own small conv stack
  (:class:`~infinirl.models.policies.heads.ConvEncoder`), concatenated with the standardised vector
  keys if any, through the same MLP head.

A saved classifier (:func:`save_classifier`) is one torch file with the spec, the input shapes, the
decision threshold, the weights and the training report, plus ``<path>.json`` with all of it but the
weights, for people to read. :func:`load_classifier` fails in one line naming the file and the fix
when the file is missing, is not a classifier, or reads keys the env does not give.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from infinirl.registry import Registry
from infinirl.utils import torch_save_atomic, write_json_atomic

__all__ = ["CLASSIFIER_ARCHITECTURES", "CLASSIFIER_FORMAT", "ClassifierArchitecture", "ClassifierSpec",
           "SuccessClassifier", "load_classifier", "save_classifier"]

CLASSIFIER_FORMAT = "infinirl.success_classifier.v1"
_RETRAIN = "train one with: infinirl train-classifier <labels_dir> --out {path}"


@dataclass(frozen=True, kw_only=True)
class ClassifierSpec:
    """What a classifier reads and how it is built (see the module docstring)."""

    architecture: str = "mlp"
    obs_keys: tuple[str, ...] = ("state",)
    hidden: tuple[int, ...] = (256, 256)
    """Widths of the MLP head's hidden layers."""
    channels: tuple[int, ...] = (16, 32, 32)
    kernels: tuple[int, ...] = (8, 4, 3)
    strides: tuple[int, ...] = (4, 2, 1)
    image_features: int = 64
    """cnn: features of each camera's conv stack."""

    def __post_init__(self) -> None:
        for name in ("obs_keys", "hidden", "channels", "kernels", "strides"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        CLASSIFIER_ARCHITECTURES.get(self.architecture)  # an unknown name fails listing the registered ones
        if not self.obs_keys:
            raise ValueError("ClassifierSpec.obs_keys: name at least one observation key, e.g. ['state']")
        if any(width < 1 for width in self.hidden):
            raise ValueError(f"ClassifierSpec.hidden: widths must be >= 1, got {list(self.hidden)}")


def is_image(shape: tuple[int, ...]) -> bool:
    return len(shape) == 3


@dataclass(frozen=True, kw_only=True)
class ClassifierArchitecture:
    """``build(spec, shapes) -> nn.Module`` whose ``forward(inputs)`` maps a dict of ``[B, ...]``
    tensors (vector keys already standardised) to ``[B]`` logits."""

    build: Callable[[ClassifierSpec, Mapping[str, tuple[int, ...]]], nn.Module]
    description: str = ""


CLASSIFIER_ARCHITECTURES: Registry[ClassifierArchitecture] = Registry("success classifier architecture")


class FeatureHead(nn.Module):
    """Conv features of the image keys + the vector keys, concatenated, through an MLP to one logit."""

    def __init__(self, spec: ClassifierSpec, shapes: Mapping[str, tuple[int, ...]]) -> None:
        super().__init__()
        from infinirl.models.policies.heads import ConvEncoder
        from infinirl.models.policies.mlp import mlp

        self.image_keys = [key for key in spec.obs_keys if is_image(shapes[key])]
        self.vector_keys = [key for key in spec.obs_keys if not is_image(shapes[key])]
        self.encoders = nn.ModuleList(
            ConvEncoder(shapes[key], channels=spec.channels, kernels=spec.kernels, strides=spec.strides,
                        features=spec.image_features) for key in self.image_keys)
        width = len(self.image_keys) * spec.image_features + sum(math.prod(shapes[k]) for k in self.vector_keys)
        self.head = mlp([width, *spec.hidden, 1], activation=nn.ReLU, out_gain=1.0)

    def forward(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        parts = [encoder(inputs[key]) for key, encoder in zip(self.image_keys, self.encoders)]
        parts += [inputs[key].flatten(1) for key in self.vector_keys]
        return self.head(torch.cat(parts, dim=1)).squeeze(1)


def _mlp(spec: ClassifierSpec, shapes: Mapping[str, tuple[int, ...]]) -> nn.Module:
    images = [key for key in spec.obs_keys if is_image(shapes[key])]
    if images:
        raise ValueError(f"architecture 'mlp' reads vectors; {images} are camera frames: use architecture 'cnn'")
    return FeatureHead(spec, shapes)


def _cnn(spec: ClassifierSpec, shapes: Mapping[str, tuple[int, ...]]) -> nn.Module:
    if not any(is_image(shapes[key]) for key in spec.obs_keys):
        raise ValueError(f"architecture 'cnn' needs a camera frame among obs_keys {list(spec.obs_keys)} (e.g. "
                         "pixels.<camera>); on vectors alone use architecture 'mlp'")
    return FeatureHead(spec, shapes)


CLASSIFIER_ARCHITECTURES.add("mlp", ClassifierArchitecture(build=_mlp, description="MLP on the state vector"))
CLASSIFIER_ARCHITECTURES.add("cnn", ClassifierArchitecture(
    build=_cnn, description="a conv stack per camera frame (+ the state vector) into an MLP"))


class SuccessClassifier(nn.Module):
    """The classifier: standardises the vector keys, runs the architecture's network."""

    def __init__(self, spec: ClassifierSpec, shapes: Mapping[str, tuple[int, ...]], threshold: float = 0.5,
                 mean: Mapping[str, np.ndarray] | None = None, std: Mapping[str, np.ndarray] | None = None) -> None:
        super().__init__()
        missing = [key for key in spec.obs_keys if key not in shapes]
        if missing:
            raise ValueError(f"the labelled observations have no {missing}; they hold {sorted(shapes)}")
        self.spec, self.threshold = spec, float(threshold)
        self.shapes = {key: tuple(int(s) for s in shapes[key]) for key in spec.obs_keys}
        self.net = CLASSIFIER_ARCHITECTURES.get(spec.architecture).build(spec, self.shapes)
        self.vector_keys = [key for key in spec.obs_keys if not is_image(self.shapes[key])]
        for index, key in enumerate(self.vector_keys):
            shape = self.shapes[key]
            centre = np.zeros(shape) if mean is None else mean[key]
            scale = np.ones(shape) if std is None else std[key]
            self.register_buffer(f"mean_{index}", torch.as_tensor(np.asarray(centre, np.float32).reshape(shape)))
            self.register_buffer(f"std_{index}", torch.as_tensor(np.asarray(scale, np.float32).reshape(shape)))

    def forward(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``[B]`` logits of the batch ``inputs`` (key -> ``[B, ...]``)."""
        dtype = next(self.parameters()).dtype
        ready = dict(inputs)
        for index, key in enumerate(self.vector_keys):
            ready[key] = (inputs[key].to(dtype) - getattr(self, f"mean_{index}")) / getattr(self, f"std_{index}")
        return self.net(ready)

    @torch.no_grad()
    def probability(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """``[B]`` success probabilities of a batch of observations (numpy, key -> ``[B, ...]``)."""
        inputs = {key: torch.from_numpy(np.ascontiguousarray(obs[key])) for key in self.spec.obs_keys}
        return torch.sigmoid(self(inputs)).double().numpy()

    def check_inputs(self, shapes: Mapping[str, tuple[int, ...]], path: str) -> None:
        """One-line error naming ``path`` when an observation with these per-row ``shapes`` lacks a
        key the classifier reads, or has another shape."""
        for key, shape in self.shapes.items():
            if key not in shapes:
                raise ValueError(f"success classifier {path} reads {key!r}, which this robot env's observation lacks "
                                 f"(it has {sorted(shapes)}); add it to the env's observations/cameras, or train "
                                 "the classifier on labels recorded with this env's")
            if tuple(shapes[key]) != shape:
                raise ValueError(f"success classifier {path} reads {key!r} of shape {list(shape)}, this robot env "
                                 f"gives {list(shapes[key])}; train it on labels recorded with this env's "
                                 "observations (the same observation sources, cameras and image size)")


def save_classifier(path: str, classifier: SuccessClassifier, report: Mapping[str, Any] | None = None) -> None:
    """``path`` (torch) and ``<path>.json`` (everything but the weights), each written atomically."""
    about = {"format": CLASSIFIER_FORMAT, "spec": asdict(classifier.spec),
             "shapes": {key: list(shape) for key, shape in classifier.shapes.items()},
             "threshold": classifier.threshold, "report": dict(report or {})}
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    torch_save_atomic({**about, "state_dict": classifier.state_dict()}, path)
    write_json_atomic(f"{path}.json", about)


def load_classifier(path: str, shapes: Mapping[str, tuple[int, ...]] | None = None) -> SuccessClassifier:
    """The classifier saved at ``path`` (eval mode); ``shapes``: the per-row shapes of the
    observation it will read, checked against the keys and shapes it was trained on."""
    fix = _RETRAIN.format(path=path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"success classifier {path} does not exist; {fix}")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(f"success classifier {path} cannot be read ({type(exc).__name__}); {fix}") from None
    if not isinstance(saved, dict) or saved.get("format") != CLASSIFIER_FORMAT:
        raise ValueError(f"{path} is not a success classifier file (format {CLASSIFIER_FORMAT}); {fix}")
    try:
        spec = ClassifierSpec(**saved["spec"])
        classifier = SuccessClassifier(spec, {k: tuple(v) for k, v in saved["shapes"].items()},
                                       threshold=saved["threshold"])
        classifier.load_state_dict(saved["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"success classifier {path} does not match this version's classifiers "
                         f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); {fix}") from None
    classifier.report = dict(saved.get("report", {}))
    classifier.eval()
    if shapes is not None:
        classifier.check_inputs(shapes, path)
    return classifier
