"""Configuration: Hydra YAML composed from groups, validated into typed dataclasses up front.

``load_job_config(name, overrides)`` composes ``infinirl/configs/<name>.yaml`` (and its defaults
list) with ``key=value`` overrides, then ``to_dataclass`` converts it *strictly*: an unknown key,
a wrong type or a bad value raises ``ConfigError`` naming the dotted key path, what was given, and
what is accepted, before Ray or any worker starts. Nothing here starts anything.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import sys
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING
from pathlib import Path
from typing import Any, Literal

CONFIG_DIR = Path(__file__).parent / "configs"


class ConfigError(ValueError):
    """A configuration value or key that cannot work; the message says which and how to fix it."""


@dataclasses.dataclass(frozen=True)
class Bounds:
    """Numeric limits of a config field, checked when the config is built (see :func:`bounded`)."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    each: bool = False
    """The field is a list: every element must lie within the limits."""

    def describe(self) -> str:
        low = f"> {self.gt}" if self.gt is not None else f">= {self.ge}" if self.ge is not None else None
        high = f"< {self.lt}" if self.lt is not None else f"<= {self.le}" if self.le is not None else None
        if low and high:
            left = "(" if self.gt is not None else "["
            right = ")" if self.lt is not None else "]"
            lo = self.gt if self.gt is not None else self.ge
            hi = self.lt if self.lt is not None else self.le
            return f"in {left}{lo}, {hi}{right}"
        return low or high or "any number"

    def holds(self, value: float) -> bool:
        if isinstance(value, float) and math.isnan(value):
            return False
        return not ((self.gt is not None and not value > self.gt) or (self.ge is not None and not value >= self.ge)
                    or (self.lt is not None and not value < self.lt) or (self.le is not None and not value <= self.le))


def bounded(default: Any = MISSING, *, default_factory: Any = MISSING, gt: float | None = None,
            ge: float | None = None, lt: float | None = None, le: float | None = None, each: bool = False) -> Any:
    """A dataclass field whose numeric value must lie within the given limits (``None`` values pass).

    The limits live on the field, next to its documentation, and :func:`to_dataclass` checks them
    with the key's dotted path in the error; a config's ``validate()`` keeps only the rules that
    involve several fields."""
    bounds = Bounds(gt=gt, ge=ge, lt=lt, le=le, each=each)
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata={"bounds": bounds})
    return dataclasses.field(default=default, metadata={"bounds": bounds})


def _check_bounds(field: dataclasses.Field, value: Any, path: str) -> None:
    bounds = field.metadata.get("bounds")
    if bounds is None or value is None:
        return
    values = list(value) if bounds.each else [value]
    for item in values:
        if not bounds.holds(item):
            shown = f"{path}={value!r}" if not bounds.each else f"{path}={list(value)!r}: every entry"
            raise ConfigError(f"{shown} must be {bounds.describe()}")


def available_configs() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))


def compose(name: str, overrides: list[str] | None = None, config_dir: Path | None = None,
            complete: bool = False) -> dict:
    """Compose a Hydra config into a plain dict (no Hydra run directory, no logging side effects).
    ``complete``: refuse a value still missing (``???`` in the YAML, not given as an override)."""
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
    missing = sorted(OmegaConf.missing_keys(cfg)) if complete else []
    if missing:  # `???` in a YAML: a value only the user can give (a local checkpoint folder)
        raise ConfigError(f"config '{name}' needs {', '.join(missing)}: set {missing[0]}=<value> on the command line "
                          "(the config's header says what it expects)")
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
    data = upgrade_renamed_keys(cls, data, path)
    unknown = [k for k in data if k not in fields]
    if unknown:
        key = unknown[0]
        near = difflib.get_close_matches(str(key), list(fields), n=1)
        hint = f" Did you mean '{_join(path, near[0])}'?" if near else ""
        raise ConfigError(
            f"unknown config key '{_join(path, key)}'.{hint} Valid keys here: {', '.join(sorted(fields))}"
        )
    kwargs = {name: _convert(hints[name], value, _join(path, name)) for name, value in data.items()}
    for name, value in kwargs.items():
        _check_bounds(fields[name], value, _join(path, name))
    try:
        obj = cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}" if path else str(exc)) from None
    except (TypeError, ValueError) as exc:  # a class's own __post_init__ checks
        raise ConfigError(f"{path or 'config'}: {exc}") from None
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate()
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}" if path and not str(exc).startswith(path) else str(exc)) from None
    return obj


def renamed_keys(cls: type) -> dict[str, str]:
    """``old dotted key -> new dotted key`` of a config class (its ``RENAMED_KEYS``), for keys that
    were renamed and still work, with a warning, until the next minor release."""
    return dict(getattr(cls, "RENAMED_KEYS", {}) or {})


def upgrade_renamed_keys(cls: type, data: dict, path: str = "", warn: bool = True) -> dict:
    """A copy of ``data`` (a raw mapping for ``cls``) with renamed keys moved to their new names.
    ``warn``: tell the user to rename them (not for a config a checkpoint recorded: nobody edits it)."""
    renames = renamed_keys(cls)
    if not renames or not any(old.split(".")[0] in data for old in renames):
        return data
    data = _deep_copy(data)
    for old, new in renames.items():
        value, found = _pop_path(data, old.split("."))
        if not found:
            continue
        if _has_path(data, new.split(".")):
            raise ConfigError(f"both '{_join(path, old)}' and its new name '{_join(path, new)}' are set; "
                              f"keep only '{_join(path, new)}'")
        if warn:
            _warn_renamed(_join(path, old), _join(path, new))
        _set_path(data, new.split("."), value)
    return data


def upgrade_renamed_overrides(cls: type, overrides: list[str]) -> list[str]:
    """``key=value`` overrides with renamed keys replaced by their new names (warning once each)."""
    renames = renamed_keys(cls)
    given = {o.lstrip("+~").partition("=")[0] for o in overrides}
    for old, new in renames.items():
        if old in given and new in given:
            raise ConfigError(f"both '{old}' and its new name '{new}' are set; keep only '{new}'")
    out = []
    for override in overrides:
        prefix = override[: len(override) - len(override.lstrip("+~"))]
        key, sep, value = override[len(prefix):].partition("=")
        if key in renames:
            _warn_renamed(key, renames[key])
            key = renames[key]
        out.append(f"{prefix}{key}{sep}{value}")
    return out


_WARNED: set[str] = set()


def _warn_renamed(old: str, new: str) -> None:
    if old in _WARNED:
        return
    _WARNED.add(old)
    print(f"infinirl: config key '{old}' is now '{new}'; the old name works until release 0.2, please rename it",
          file=sys.stderr, flush=True)


def _deep_copy(data: Any) -> Any:
    return {k: _deep_copy(v) for k, v in data.items()} if isinstance(data, dict) else data


def _pop_path(data: dict, parts: list[str]) -> tuple[Any, bool]:
    node = data
    for part in parts[:-1]:
        node = node.get(part)
        if not isinstance(node, dict):
            return None, False
    if parts[-1] not in node:
        return None, False
    return node.pop(parts[-1]), True


def _has_path(data: dict, parts: list[str]) -> bool:
    node: Any = data
    for part in parts:
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def _set_path(data: dict, parts: list[str], value: Any) -> None:
    node = data
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"config key '{'.'.join(parts)}': '{part}' is not a mapping")
    node[parts[-1]] = value


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


def _convert(tp: Any, value: Any, path: str) -> Any:
    """``value`` as type ``tp`` (checked, never coerced across kinds); errors name ``path``."""
    if tp is Any:
        return value
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return _convert_union(tp, value, path)
    if origin is Literal:
        return _convert_literal(tp, value, path)
    if dataclasses.is_dataclass(tp):
        return to_dataclass(tp, value, path)
    if origin in (list, tuple) or tp in (list, tuple):
        return _convert_sequence(tp, value, path)
    if origin is dict or tp is dict:
        return _convert_mapping(tp, value, path)
    scalar = _SCALARS.get(tp)
    return scalar(value, path) if scalar is not None else value


def _convert_union(tp: Any, value: Any, path: str) -> Any:
    args = typing.get_args(tp)
    if value is None and type(None) in args:
        return None
    errors, same_shape = [], []
    for arg in args:
        if arg is type(None):
            continue
        try:
            return _convert(arg, value, path)
        except ConfigError as exc:
            errors.append(str(exc))
            if _same_shape(arg, value):  # a mapping given for a mapping member: its error is the useful one
                same_shape.append(str(exc))
    if len(errors) == 1 or len(same_shape) == 1:
        raise ConfigError((same_shape or errors)[0])
    raise ConfigError(f"{path}: {value!r} matches none of {tp}")


def _same_shape(tp: Any, value: Any) -> bool:
    origin = typing.get_origin(tp) or tp
    if isinstance(value, Mapping):
        return origin is dict
    if isinstance(value, (list, tuple)):
        return origin in (list, tuple)
    return False


def _convert_literal(tp: Any, value: Any, path: str) -> Any:
    args = typing.get_args(tp)
    if value not in args:
        near = difflib.get_close_matches(str(value), [str(a) for a in args], n=1)
        hint = f" Did you mean '{near[0]}'?" if near else ""
        raise ConfigError(f"{path}={value!r} is not allowed.{hint} Choose one of: {', '.join(map(str, args))}")
    return value


def _convert_sequence(tp: Any, value: Any, path: str) -> Any:
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{path}: expected a list, got {value!r}")
    args = typing.get_args(tp)
    is_tuple = typing.get_origin(tp) is tuple or tp is tuple
    if is_tuple and args and args[-1] is not Ellipsis:  # tuple[float, float]: exactly that many values
        if len(value) != len(args):
            raise ConfigError(f"{path}: expected {len(args)} values, got {list(value)!r}")
        return tuple(_convert(inner, v, f"{path}[{i}]") for i, (inner, v) in enumerate(zip(args, value)))
    inner = args[0] if args else Any
    items = [_convert(inner, v, f"{path}[{i}]") for i, v in enumerate(value)]
    return tuple(items) if is_tuple else items


def _convert_mapping(tp: Any, value: Any, path: str) -> Any:
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: expected a mapping, got {value!r}")
    args = typing.get_args(tp)
    value_type = args[1] if len(args) == 2 else Any
    return {k: _convert(value_type, v, _join(path, k)) for k, v in value.items()}


def _to_bool(value: Any, path: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{path}: expected true/false, got {value!r}")
    return value


def _to_int(value: Any, path: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{path}: expected an integer, got {value!r}")
    return value


def _to_float(value: Any, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{path}: expected a number, got {value!r}")
    return float(value)


def _to_str(value: Any, path: str) -> str:
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)  # e.g. placement `learner: 1` (YAML/CLI read it as an int)
    if not isinstance(value, str):
        raise ConfigError(f"{path}: expected a string, got {value!r}")
    return value


_SCALARS = {bool: _to_bool, int: _to_int, float: _to_float, str: _to_str}


NO_DEFAULT = object()
"""What :func:`plain_default` returns for a key without a default."""


def plain_default(cls: type, dotted: str) -> Any:
    """The plain value (:func:`to_plain`) a dotted key of config class ``cls`` has when nothing sets
    it: its field's default, inside the default of the section that holds it (a section's factory
    may set its own values); :data:`NO_DEFAULT` for a key without one or one ``cls`` lacks."""
    first, *rest = dotted.split(".")
    fields = {f.name: f for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls) else {}
    field = fields.get(first)
    if field is None:
        return NO_DEFAULT
    if field.default is not MISSING:
        value = field.default
    elif field.default_factory is not MISSING:
        value = field.default_factory()
    else:
        return NO_DEFAULT
    value = to_plain(value)
    for part in rest:
        if not isinstance(value, dict) or part not in value:
            return NO_DEFAULT
        value = value[part]
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
