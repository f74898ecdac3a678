"""Save a :class:`~.vla.VLA` as the folder :func:`~.vla.load_vla` reads (LeRobot's layout).

::

    config.json                                            "type" (the family), LeRobot's fields, and
                                                           "architecture" (every size, so any family loads
                                                           without its variant names) and "instructions"
    model.safetensors                                      our parameter names (the loader takes them as is)
    policy_preprocessor.json                               a normalizer_processor step naming
    policy_preprocessor_step_0_normalizer_processor.safetensors      the state/action statistics
    policy_postprocessor.json                              an unnormalizer_processor step naming
    policy_postprocessor_step_0_unnormalizer_processor.safetensors   the action statistics
    tokenizer/                                             the tokenizer, when it can save itself

The folder is built beside its target and renamed into place: it exists whole or not at all.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

from infinirl.models.vla.config import LEROBOT_FIELDS, VLAConfig
from infinirl.models.vla.normalize import Normalizer
from infinirl.models.vla.processor import ACTION, STATE
from infinirl.utils import write_json_atomic
from infinirl.utils.atomic import replace_directory

__all__ = ["PREPROCESSOR_STATS", "POSTPROCESSOR_STATS", "save_vla", "vla_config_json"]

PREPROCESSOR_STATS = "policy_preprocessor_step_0_normalizer_processor.safetensors"
POSTPROCESSOR_STATS = "policy_postprocessor_step_0_unnormalizer_processor.safetensors"


def features_json(config: VLAConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """LeRobot's ``input_features`` and ``output_features`` of ``config``."""
    resolution = list(config.image_resolution)
    inputs: dict[str, Any] = {key: {"type": "VISUAL", "shape": [3, *resolution]} for key in config.camera_keys}
    inputs[STATE] = {"type": "STATE", "shape": [config.state_dim]}
    return inputs, {ACTION: {"type": "ACTION", "shape": [config.action_dim]}}


def vla_config_json(config: VLAConfig) -> dict[str, Any]:
    """The ``config.json`` :func:`~.config.read_vla_config` reads back into ``config``."""
    inputs, outputs = features_json(config)
    return {"type": config.family, "input_features": inputs, "output_features": outputs,
            **{name: getattr(config, name) for name in LEROBOT_FIELDS},
            "image_resolution": list(config.image_resolution), "empty_cameras": 0,
            "normalization_mapping": dict(config.normalization), "architecture": config.architecture.to_dict(),
            "instructions": dict(config.instructions)}


def _stats(norm: Normalizer) -> dict[str, torch.Tensor]:
    return {f"{feature}.{name}": getattr(norm, buffer).detach().cpu().contiguous()
            for (feature, name), buffer in norm.names.items()}


def _pipeline(name: str, registry_name: str, state_file: str, config: VLAConfig, eps: float,
              features: dict[str, Any]) -> dict[str, Any]:
    step = {"registry_name": registry_name, "config": {"eps": eps, "features": features,
                                                       "norm_map": dict(config.normalization)},
            "state_file": state_file}
    return {"name": name, "steps": [step]}


def write_vla_files(vla, folder: Path) -> None:
    """Every file of the layout into an existing (empty) ``folder``."""
    config = vla.config
    inputs, outputs = features_json(config)
    write_json_atomic(folder / "config.json", vla_config_json(config))
    state = {name: tensor.detach().cpu().contiguous() for name, tensor in vla.model.state_dict().items()}
    save_file(state, str(folder / "model.safetensors"))
    processor = vla.processor
    save_file(_stats(processor.input_norm), str(folder / PREPROCESSOR_STATS))
    save_file(_stats(processor.output_norm), str(folder / POSTPROCESSOR_STATS))
    write_json_atomic(folder / "policy_preprocessor.json",
                      _pipeline("policy_preprocessor", "normalizer_processor", PREPROCESSOR_STATS, config,
                                processor.input_norm.eps, {**inputs, **outputs}))
    write_json_atomic(folder / "policy_postprocessor.json",
                      _pipeline("policy_postprocessor", "unnormalizer_processor", POSTPROCESSOR_STATS, config,
                                processor.output_norm.eps, outputs))
    if hasattr(processor.tokenizer, "save_pretrained"):
        processor.tokenizer.save_pretrained(str(folder / "tokenizer"))


def save_vla(vla, folder: str | Path) -> Path:
    """Write ``vla`` (network, statistics, tokenizer) to ``folder``, replacing what is there."""
    target = Path(folder)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        write_vla_files(vla, tmp)
        tmp.chmod(0o755)
        replace_directory(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target
