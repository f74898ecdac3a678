"""Driver-side checks of a model folder, so a bad path fails before any worker loads it."""

from __future__ import annotations

import json
from pathlib import Path

from infinirl.config import ConfigError

__all__ = ["check_model_path", "model_context_length"]


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


def model_context_length(path: str) -> int | None:
    """The model's context length (``max_position_embeddings``, GPT-2's ``n_positions``) from its
    ``config.json``, when that is on disk: a local folder, or the embedded model once converted.
    None otherwise (a hub id, a config without the field): nothing is downloaded or loaded."""
    from infinirl.models.smollm2 import MODEL_NAME, converted_dir

    folder = converted_dir() if path == MODEL_NAME else Path(path).expanduser()
    try:
        config = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(config, dict):
        return None
    for key in ("max_position_embeddings", "n_positions"):
        value = config.get(key)
        if isinstance(value, int) and not isinstance(value, bool) and value > 0:
            return value
    return None
