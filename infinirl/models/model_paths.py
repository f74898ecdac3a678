"""Driver-side checks of a model folder, so a bad path fails before any worker loads it."""

from __future__ import annotations

import json
from pathlib import Path

from infinirl.config import ConfigError

__all__ = ["check_model_path"]


def check_model_path(path: str, key: str) -> None:
    """Raise ConfigError naming ``key`` unless ``path`` is the embedded model, a hub id, or a folder
    whose ``config.json`` is JSON naming a model type this transformers knows."""
    from infinirl.models.smollm2 import MODEL_NAME

    looks_like_hub_id = path.count("/") == 1 and not path.startswith((".", "/", "~"))
    if path == MODEL_NAME or (looks_like_hub_id and not Path(path).exists()):
        return
    folder = Path(path).expanduser()
    if not folder.is_dir():
        raise ConfigError(f"{key}={path!r} is not a folder; pass a local Hugging Face model folder or the "
                          f"embedded default '{MODEL_NAME}'")
    config_file = folder / "config.json"
    if not config_file.is_file():
        raise ConfigError(f"{key}={path!r} has no config.json; pass the folder a Hugging Face model was saved to "
                          "(save_pretrained writes config.json beside the weights)")
    try:
        config = json.loads(config_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{key}={path!r}: {config_file} is not valid JSON ({exc}); re-save the model") from None
    model_type = config.get("model_type") if isinstance(config, dict) else None
    from transformers import CONFIG_MAPPING

    if model_type not in CONFIG_MAPPING:
        raise ConfigError(f"{key}={path!r}: {config_file} names model_type {model_type!r}, which this transformers "
                          "version does not know; upgrade transformers or pass a supported model")
