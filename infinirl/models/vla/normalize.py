"""LeRobot's state/action normalisation, read from the processor files saved with a checkpoint.

LeRobot saves its processor pipelines next to the weights: ``policy_preprocessor.json`` lists the
steps, and its ``normalizer_processor`` step names a ``.safetensors`` file of statistics keyed
``"<feature>.<stat>"`` (``observation.state.mean``, ``action.q01``, ...); the postprocessor's
``unnormalizer_processor`` step does the same for the actions the policy returns. The modes
(``MEAN_STD``, ``MIN_MAX``, ``QUANTILES``, ``QUANTILE10``, ``IDENTITY``) map each feature type to
``[-1, 1]``-ish values with LeRobot's formulas (``eps`` guards zero spans, as there).

Unlike LeRobot, which passes a feature through unchanged when its statistics are absent, a
missing statistic is an error here: a policy fed raw joint angles where it was trained on
normalised ones fails silently.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import load_file
from torch import nn

__all__ = ["MODE_STATS", "Normalizer", "read_normalizer"]

MODE_STATS = {"MEAN_STD": ("mean", "std"), "MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"),
              "QUANTILE10": ("q10", "q90"), "IDENTITY": ()}


class Normalizer(nn.Module):
    """Normalise / unnormalise named features (``observation.state``, ``action``).

    Args:
        modes: feature -> mode (one of :data:`MODE_STATS`).
        stats: feature -> stat name -> tensor; each mode's statistics must be there.
        eps: LeRobot's guard (added to ``std``; replaces a zero span for the ranges).
        source: where the statistics came from, for error messages.
    """

    def __init__(self, modes: dict[str, str], stats: dict[str, dict[str, torch.Tensor]], eps: float = 1e-8,
                 source: str = "the stats given"):
        super().__init__()
        self.modes, self.eps, self.names = dict(modes), float(eps), {}
        for feature, mode in self.modes.items():
            if mode not in MODE_STATS:
                raise ValueError(f"{source}: {feature} uses normalisation {mode!r}; known: {sorted(MODE_STATS)}")
            needed = MODE_STATS[mode]
            have = stats.get(feature, {})
            absent = [name for name in needed if name not in have]
            if absent:
                raise ValueError(
                    f"normalisation stats {', '.join(f'{feature}.{name}' for name in absent)} ({mode}) are missing "
                    f"from {source}: keep LeRobot's processor files with the checkpoint, or pass "
                    f"stats={{'{feature}': {{{', '.join(repr(n) for n in needed)}: ...}}}}")
            for name in needed:
                buffer = f"{feature.replace('.', '__')}__{name}"
                self.register_buffer(buffer, torch.as_tensor(have[name], dtype=torch.float32).clone())
                self.names[(feature, name)] = buffer

    def _stat(self, feature: str, name: str, like: torch.Tensor) -> torch.Tensor:
        return getattr(self, self.names[(feature, name)]).to(device=like.device, dtype=like.dtype)

    def _span(self, feature: str, low: str, high: str, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lo, hi = self._stat(feature, low, like), self._stat(feature, high, like)
        span = hi - lo
        return lo, torch.where(span == 0, torch.full_like(span, self.eps), span)

    def normalize(self, feature: str, x: torch.Tensor) -> torch.Tensor:
        mode = self.modes.get(feature, "IDENTITY")
        if mode == "IDENTITY":
            return x
        if mode == "MEAN_STD":
            return (x - self._stat(feature, "mean", x)) / (self._stat(feature, "std", x) + self.eps)
        lo, span = self._span(feature, *MODE_STATS[mode], x)
        return 2 * (x - lo) / span - 1

    def unnormalize(self, feature: str, x: torch.Tensor) -> torch.Tensor:
        mode = self.modes.get(feature, "IDENTITY")
        if mode == "IDENTITY":
            return x
        if mode == "MEAN_STD":
            return x * self._stat(feature, "std", x) + self._stat(feature, "mean", x)
        lo, span = self._span(feature, *MODE_STATS[mode], x)
        return (x + 1) * span / 2 + lo


def _find_step(folder: Path, pipeline: str, registry_name: str) -> dict:
    path = folder / f"{pipeline}.json"
    if not path.is_file():
        raise FileNotFoundError(f"no {path.name} in {folder}: the normalisation stats live in LeRobot's processor "
                                f"files saved with the checkpoint; save them, or pass stats=...")
    steps = json.loads(path.read_text()).get("steps", [])
    for step in steps:
        if step.get("registry_name") == registry_name:
            return step
    raise ValueError(f"{path} has no '{registry_name}' step: cannot tell how to normalise; pass stats=...")


def read_normalizer(folder: str | Path, features: dict[str, str], pipeline: str = "policy_preprocessor",
                    registry_name: str = "normalizer_processor",
                    stats: dict[str, dict[str, torch.Tensor]] | None = None) -> Normalizer:
    """The :class:`Normalizer` of a saved LeRobot pipeline step, for ``features`` (feature ->
    feature type, e.g. ``{"observation.state": "STATE"}``). ``stats`` replaces the file's statistics
    (feature by feature); the modes still come from the step's ``norm_map``."""
    folder = Path(folder)
    step = _find_step(folder, pipeline, registry_name)
    config = step.get("config", {})
    norm_map = config.get("norm_map", {})
    loaded: dict[str, dict[str, torch.Tensor]] = {}
    source = f"{folder / (pipeline + '.json')}"
    if "state_file" in step:
        state_path = folder / step["state_file"]
        if not state_path.is_file():
            raise FileNotFoundError(f"{source} names {step['state_file']}, which is not in {folder}: the "
                                    f"normalisation stats are missing; copy it there or pass stats=...")
        source = str(state_path)
        for flat, tensor in load_file(str(state_path)).items():
            feature, name = flat.rsplit(".", 1)
            loaded.setdefault(feature, {})[name] = tensor
    for feature, values in (stats or {}).items():
        loaded[feature] = {name: torch.as_tensor(value) for name, value in values.items()}
        source = "the stats given" if stats else source
    modes = {feature: norm_map.get(kind, "IDENTITY") for feature, kind in features.items()}
    return Normalizer(modes, loaded, eps=config.get("eps", 1e-8), source=source)
