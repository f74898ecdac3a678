"""Configuration: Hydra YAML composed from groups, validated into typed dataclasses up front.

``load_job_config(name, overrides)`` composes ``infinirl/configs/<name>.yaml`` (and its defaults
list) with ``key=value`` overrides, then ``to_dataclass`` converts it *strictly*: an unknown key,
a wrong type or a bad value raises ``ConfigError`` naming the dotted key path, what was given, and
what is accepted, before Ray or any worker starts. Nothing here starts anything.
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from pathlib import Path
from typing import Any, Literal

CONFIG_DIR = Path(__file__).parent / "configs"


class ConfigError(ValueError):
    """A configuration value or key that cannot work; the message says which and how to fix it."""


def available_configs() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))


def compose(name: str, overrides: list[str] | None = None, config_dir: Path | None = None) -> dict:
    """Compose a Hydra config into a plain dict (no Hydra run directory, no logging side effects)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    config_dir = Path(config_dir or CONFIG_DIR)
    if not (config_dir / f"{name}.yaml").exists():
        names = sorted(p.stem for p in config_dir.glob("*.yaml"))
        near = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean '{near[0]}'?" if near else ""
        raise ConfigError(f"no config named '{name}' in {config_dir}.{hint} Available: {', '.join(names)}")
    try:
        with initialize_config_dir(config_dir=str(config_dir.resolve()), version_base=None):
            cfg = hydra_compose(config_name=name, overrides=list(overrides or []))
    except HydraException as exc:
        raise ConfigError(f"config '{name}' with overrides {overrides}: {exc}") from None
    return OmegaConf.to_container(cfg, resolve=True)


def check_override_keys(cls: type, overrides: list[str]) -> None:
    """Reject ``key=value`` overrides whose key the config class lacks, with a did-you-mean.

    Hydra would also refuse them, but with a message about its own ``+key`` syntax; the user needs
    to know which keys exist. Keys under free-form mappings (``placement.*``) are not checked.
    """
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        node: Any = cls
        walked = []
        for part in key.split("."):
            if not (isinstance(node, type) and dataclasses.is_dataclass(node)):
                break
            fields = {f.name: f for f in dataclasses.fields(node)}
            if part not in fields:
                near = difflib.get_close_matches(part, list(fields), n=1)
                prefix = ".".join(walked)
                hint = f" Did you mean '{_join(prefix, near[0])}'?" if near else ""
                raise ConfigError(
                    f"unknown config key '{key}' in override '{override}'.{hint} "
                    f"Valid keys{' under ' + prefix if prefix else ''}: {', '.join(sorted(fields))}"
                )
            walked.append(part)
            node = typing.get_type_hints(node)[part]


def to_dataclass(cls: type, data: Any, path: str = "") -> Any:
    """Build dataclass ``cls`` from a mapping, checking every key and type; errors name the key path."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'config'}: expected a mapping for {cls.__name__}, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    hints = typing.get_type_hints(cls)
    unknown = [k for k in data if k not in fields]
    if unknown:
        key = unknown[0]
        near = difflib.get_close_matches(str(key), list(fields), n=1)
        hint = f" Did you mean '{_join(path, near[0])}'?" if near else ""
        raise ConfigError(
            f"unknown config key '{_join(path, key)}'.{hint} Valid keys here: {', '.join(sorted(fields))}"
        )
    kwargs = {name: _convert(hints[name], value, _join(path, name)) for name, value in data.items()}
    try:
        obj = cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"{path or 'config'}: {exc}") from None
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate()
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}" if path and not str(exc).startswith(path) else str(exc)) from None
    return obj


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


def _convert(tp: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, path)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{path}: {value!r} matches none of {tp}")
    if origin is Literal:
        if value not in args:
            near = difflib.get_close_matches(str(value), [str(a) for a in args], n=1)
            hint = f" Did you mean '{near[0]}'?" if near else ""
            raise ConfigError(f"{path}={value!r} is not allowed.{hint} Choose one of: {', '.join(map(str, args))}")
        return value
    if dataclasses.is_dataclass(tp):
        return to_dataclass(tp, value, path)
    if origin in (list, tuple) or tp in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {value!r}")
        inner = args[0] if args else Any
        items = [_convert(inner, v, f"{path}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if (origin is tuple or tp is tuple) else items
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping, got {value!r}")
        vt = args[1] if len(args) == 2 else Any
        return {k: _convert(vt, v, _join(path, k)) for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if isinstance(value, int) and not isinstance(value, bool):
            return str(value)  # e.g. placement `learner: 1` (YAML/CLI read it as an int)
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {value!r}")
        return value
    return value


def to_plain(obj: Any) -> Any:
    """Dataclass tree -> plain dict (for logging the resolved config next to the run)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_plain(v) for k, v in obj.items()}
    return obj
