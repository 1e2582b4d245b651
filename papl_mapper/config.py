"""Typed configuration: nested dataclasses, loaded from TOML, overridden with `key.sub=value`.

Each stage owns its config dataclass (with a docstring per field); pipelines nest them.
`load_config` merges defaults <- TOML file <- overrides and validates every key and type.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from papl_mapper.errors import ConfigError

C = TypeVar("C")


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Convert a TOML value or an override string to the annotated field type."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None or (isinstance(value, str) and value.lower() in ("none", "null")):
            if type(None) in args:
                return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"config key {key!r}: {value!r} fits none of {annotation}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"config key {key!r}: {value!r} is not one of {list(args)}")
        return value
    if origin in (tuple, list):
        if isinstance(value, str):
            value = [v for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key {key!r}: expected a list, got {value!r}")
        item_type = args[0] if args else Any
        items = [_coerce(v, item_type, key) for v in value]
        return tuple(items) if origin is tuple else items
    if annotation is Any:
        return value
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on"):
            return True
        if isinstance(value, str) and value.lower() in ("false", "0", "no", "off"):
            return False
        raise ConfigError(f"config key {key!r}: expected true or false, got {value!r}")
    if annotation in (int, float):
        if isinstance(value, bool):
            raise ConfigError(f"config key {key!r}: expected a number, got {value!r}")
        try:
            out = annotation(value)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"config key {key!r}: expected {annotation.__name__}, got {value!r}") from exc
        if annotation is int and isinstance(value, float) and not value.is_integer():
            raise ConfigError(f"config key {key!r}: expected an integer, got {value!r}")
        return _check_number(out, key)
    if annotation is str:
        return str(value)
    if annotation is Path:
        return Path(value)
    return value


def _check_number(value: float, key: str) -> float:
    """Every numeric setting is finite and non-negative (none has a negative default or meaning), and a
    standard deviation (`*sigma*`) is positive: NaN, infinity or -1 would run on and give a garbage map."""
    if not math.isfinite(value):
        raise ConfigError(f"config key {key!r}: {value!r} is not a finite number")
    if value < 0:
        raise ConfigError(f"config key {key!r}: {value!r} is negative; every setting is positive or 0")
    if "sigma" in key.rsplit(".", 1)[-1] and value == 0:
        raise ConfigError(f"config key {key!r}: a standard deviation must be > 0, got {value!r}")
    return value


def _merge(obj: Any, data: dict[str, Any], prefix: str, renamed_keys: dict[str, str] | None = None) -> Any:
    """`obj` updated by `data`; `renamed_keys` (the top-level class's RENAMED, by full dotted key)
    names where a setting of older config files lives now."""
    if renamed_keys is None:
        renamed_keys = getattr(type(obj), "RENAMED", {})
    hints = typing.get_type_hints(type(obj))
    fields = {f.name: f for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in data.items():
        full = f"{prefix}{key}"
        if key not in fields:
            renamed = renamed_keys.get(full)
            if renamed:
                raise ConfigError(f"config key {full!r} is now {renamed!r}")
            raise ConfigError(f"unknown config key {full!r}; known: {sorted(fields)}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ConfigError(f"config key {full!r} is a section; give a table")
            changes[key] = _merge(current, value, full + ".", renamed_keys)
        else:
            changes[key] = _coerce(value, hints[key], full)
    return dataclasses.replace(obj, **changes) if changes else obj


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """Turn ['a.b=1', 'c=x'] into a nested dict of strings (coerced later against the types)."""
    nested: dict[str, Any] = {}
    for pair in pairs:
        if "=" not in pair:
            raise ConfigError(f"--set {pair!r}: expected key=value")
        key, value = pair.split("=", 1)
        parts = key.strip().split(".")
        node = nested
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {pair!r}: {part!r} is not a section")
        node[parts[-1]] = value.strip()
    return nested


def load_config(cls: type[C], path: Path | None = None, overrides: list[str] = ()) -> C:
    """Defaults of `cls`, updated by the TOML file at `path`, then by `key=value` overrides."""
    config = cls()
    if path is not None:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError as exc:
            raise ConfigError(f"{path}: config file not found") from exc
        except IsADirectoryError as exc:
            raise ConfigError(f"{path}: is a folder; give a TOML config file") from exc
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read the config file ({exc.strerror or exc})") from exc
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from exc
        config = _merge(config, data, "")
    if overrides:
        config = _merge(config, parse_overrides(list(overrides)), "")
    return config


def config_to_dict(config: Any) -> dict[str, Any]:
    """A plain dict of a (nested) config dataclass, with paths as strings and None dropped (TOML)."""

    def clean(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items() if x is not None}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        if isinstance(v, Path):
            return str(v)
        return v

    return clean(dataclasses.asdict(config))


def dump_toml(data: dict[str, Any]) -> str:
    """Serialise a nested dict of scalars and lists to TOML (enough for our configs)."""

    def scalar(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(scalar(x) for x in v) + "]"
        # JSON's escapes are TOML's (\n, \", \uXXXX): a newline in a value cannot start a new key
        return json.dumps(str(v), ensure_ascii=False).replace("\x7f", "\\u007f")

    lines: list[str] = []

    def emit(table: dict[str, Any], name: str) -> None:
        plain = {k: v for k, v in table.items() if not isinstance(v, dict)}
        nested = {k: v for k, v in table.items() if isinstance(v, dict)}
        if name and plain:
            lines.append(f"[{name}]")
        for k, v in plain.items():
            lines.append(f"{k} = {scalar(v)}")
        if plain:
            lines.append("")
        for k, v in nested.items():
            emit(v, f"{name}.{k}" if name else k)

    emit(data, "")
    return "\n".join(lines).rstrip() + "\n"
