"""Typed configuration: dataclasses loaded from YAML, with ``--set a.b=value`` overrides.

Every key is checked against the dataclass fields and every value against the field's type, so a
typo or a malformed value fails before any work starts, with the offending key in the message.
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import yaml

from mapless.errors import MaplessError
from mapless.files import write_text

T = TypeVar("T")


class ConfigError(MaplessError):
    pass


def _not_a_mapping(key: str, value: Any) -> str:
    return f"config key {key!r}: expected a mapping, got a {type(value).__name__} ({value!r})"


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if annotation is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg, key)
            except ConfigError as error:
                errors.append(str(error).removeprefix(f"config key {key!r}: "))
        raise ConfigError(f"config key {key!r}: {value!r} matches none of {annotation} ({'; '.join(errors)})")
    if dataclasses.is_dataclass(annotation):
        if not isinstance(value, dict):
            raise ConfigError(_not_a_mapping(key, value))
        return from_dict(annotation, value, prefix=f"{key}.")
    if origin in (tuple, list):
        if isinstance(value, str):
            value = [v for v in value.strip("[]()").split(",") if v.strip()]
        if not isinstance(value, list | tuple):
            raise ConfigError(f"config key {key!r}: expected a list, got {value!r}")
        item = args[0] if args else Any
        items = [_coerce(v, item, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict or annotation is dict:
        if not isinstance(value, dict):
            raise ConfigError(_not_a_mapping(key, value))
        return dict(value)
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"config key {key!r}: {value!r} is not one of {list(args)}")
        return value
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0"):
            return value.lower() in ("true", "yes", "1")
        raise ConfigError(f"config key {key!r}: expected true/false, got {value!r}")
    if annotation in (int, float):
        if isinstance(value, bool):
            raise ConfigError(f"config key {key!r}: expected a number, got {value!r}")
        try:
            number = (
                float(value)
                if annotation is float
                else int(str(value), 0)
                if isinstance(value, str)
                else value
            )
        except (TypeError, ValueError):  # float([1]) is a TypeError
            raise ConfigError(f"config key {key!r}: expected {annotation.__name__}, got {value!r}") from None
        if annotation is int and (not isinstance(number, int) or isinstance(number, float)):
            if isinstance(number, float) and number.is_integer():
                return int(number)
            raise ConfigError(f"config key {key!r}: expected an integer, got {value!r}")
        return annotation(number)
    if annotation is str:
        if not isinstance(value, str | int | float):
            raise ConfigError(f"config key {key!r}: expected a string, got {value!r}")
        return str(value)
    return value


def from_dict(cls: type[T], data: dict, prefix: str = "") -> T:
    """Build dataclass ``cls`` from a (nested) mapping, rejecting unknown keys."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = set(data) - set(fields)
    if unknown:
        key = sorted(unknown, key=str)[0]  # YAML keys may be numbers or None as well as strings
        raise ConfigError(
            f"unknown config key {f'{prefix}{key}'!r}; valid keys here: {', '.join(sorted(fields))}"
        )
    kwargs = {name: _coerce(value, hints[name], f"{prefix}{name}") for name, value in data.items()}
    try:
        return cls(**kwargs)
    except MaplessError as error:
        raise ConfigError(f"{error}") from error
    except (TypeError, ValueError) as error:
        raise ConfigError(f"config {prefix or cls.__name__}: {error}") from error


def to_dict(config: Any) -> dict:
    def convert(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {f.name: convert(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, tuple | list):
            return [convert(v) for v in value]
        return value

    return convert(config)


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """``["train.lr=3e-4", "model.name=savn"]`` applied onto a nested dict (values parsed as YAML)."""
    data = dict(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like key=value")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw
        node = data
        parts = key.strip().split(".")
        for part in parts[:-1]:
            child = node.get(part)
            node[part] = dict(child) if isinstance(child, dict) else {}
            node = node[part]
        node[parts[-1]] = value
    return data


def move_keys(data: dict, moves: list[tuple[str, str]]) -> dict:
    """``data`` (not modified) with the value at each ``old`` dotted path of ``moves`` moved to its
    ``new`` path; a path ``data`` lacks is skipped, and a section emptied by the moves is dropped."""
    out = copy.deepcopy(data)
    emptied = set()
    for old, new in moves:
        *sections, key = old.split(".")
        node = out
        if not all(isinstance(node := node.get(s), dict) for s in sections) or key not in node:
            continue
        value = node.pop(key)
        if sections and not node:
            emptied.add(tuple(sections))
        *sections, key = new.split(".")
        node = out
        for section in sections:
            node = node.setdefault(section, {})
        node[key] = value
    for sections in sorted(emptied, key=len, reverse=True):
        *parents, last = sections
        node = out
        for section in parents:
            node = node[section]
        if not node[last]:
            del node[last]
    return out


def merge_mappings(base: dict, top: dict) -> dict:
    """``top`` read over ``base`` key by key, nested mappings included (neither is modified): the one
    rule by which every layer of a config is read over the one below it (docs/guide/configuration.md)."""
    out = dict(base)
    for key, value in top.items():
        nested = isinstance(value, dict) and isinstance(out.get(key), dict)
        out[key] = merge_mappings(out[key], value) if nested else value
    return out


#: One layer of a config: where it comes from (a file, ``--set``, a recipe) and its mapping.
Layer = tuple[str, dict]


def merge_layers(layers: list[Layer]) -> tuple[dict, dict[str, str]]:
    """The layers read one over the other by :func:`merge_mappings`, lowest first, and the source
    of each leaf of the result (``"train.model.name": "budgets/small.yaml"``)."""
    out: dict = {}
    sources: dict[str, str] = {}
    for label, mapping in layers:
        out = merge_mappings(out, mapping)
        _record_sources(sources, mapping, label, "")
    return out, sources


def _record_sources(sources: dict[str, str], mapping: dict, label: str, prefix: str) -> None:
    for key, value in mapping.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            sources.pop(path, None)  # a mapping over a plain value replaces it
            _record_sources(sources, value, label, f"{path}.")
            continue
        for inner in [k for k in sources if k.startswith(f"{path}.")]:
            del sources[inner]
        sources[path] = label


def source_of(sources: dict[str, str], path: str, default: str = "default") -> str:
    """The layer that set ``path`` (or the nearest mapping above it), else ``default``."""
    parts = path.split(".")
    for end in range(len(parts), 0, -1):
        found = sources.get(".".join(parts[:end]))
        if found is not None:
            return found
    return default


def leaves(data: dict, prefix: str = "") -> dict[str, Any]:
    """``{"a.b": value}`` for every value of a nested mapping that is not itself a non-empty mapping."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, dict) and value:
            out.update(leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def format_sources(data: dict, sources: dict[str, str], default: str = "default") -> str:
    """Each leaf of ``data`` as ``key: value  # layer`` (``--print-config``), one a line."""
    lines = []
    for path, value in leaves(data).items():
        shown = yaml.safe_dump(value, default_flow_style=True, width=10_000).strip()
        shown = shown.removesuffix("\n...").strip()
        lines.append(f"{path}: {shown}  # {source_of(sources, path, default)}")
    return "\n".join(lines)


def read_extending(
    path: Path, label: Callable[[Path], str] = str, _chain: tuple[Path, ...] = ()
) -> list[Layer]:
    """The config file at ``path`` as layers: the file its ``extends: OTHER`` names (a file beside
    it; ``.yaml`` may be left out: a budget says ``extends: small``), itself read the same way,
    then the file. ``label`` names each file's layer. A chain that comes back to a file, by real
    path (``..``, a link or another spelling of the folder), is refused."""
    data = read_mapping(path)
    base = data.pop("extends", None)
    if base is None:
        return [(label(path), data)]
    chain = (*_chain, path.resolve())
    name = str(base)
    base_path = path.parent / (name if name.endswith((".yaml", ".yml")) else f"{name}.yaml")
    if not base_path.is_file():
        raise ConfigError(f"{path}: 'extends: {base}' names no file beside it")
    if base_path.resolve() in chain:
        circle = " -> ".join(p.stem for p in (*chain, base_path.resolve()))
        raise ConfigError(f"{path}: config files cannot extend in a circle ({circle})")
    return [*read_extending(base_path, label, chain), (label(path), data)]


def section(data: dict, key: str, where: str = "", prefix: str = "") -> dict:
    """``data[key]``, a nested mapping of a config (missing or empty: ``{}``), or a ConfigError naming
    the key (after ``prefix``, the mapping's own key) and the type it must have; ``where`` (a file)
    starts the message."""
    value = data.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"{where + ': ' if where else ''}{_not_a_mapping(prefix + str(key), value)}")
    return value


def read_mapping(path: str | Path) -> dict:
    """The top-level mapping of a YAML config file, or a ConfigError saying why there is none."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except OSError as error:
        raise ConfigError(f"cannot read config {path}: {error}") from error
    except UnicodeDecodeError as error:
        raise ConfigError(f"config {path} is not UTF-8 text: {error}") from error
    except yaml.YAMLError as error:
        raise ConfigError(f"config {path} is not valid YAML: {error}") from error
    except RecursionError:  # PyYAML parses nesting recursively
        raise ConfigError(f"config {path} is nested too deeply to be a config") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config {path} must be a mapping at the top level")
    return data


def load_config(cls: type[T], path: str | Path | None = None, overrides: list[str] | None = None) -> T:
    data = read_mapping(path) if path is not None else {}
    return from_dict(cls, apply_overrides(data, overrides or []))


def save_config(config: Any, path: str | Path, comment: str = "") -> None:
    """``config`` as YAML; ``comment`` goes above it as ``#`` lines, which loading ignores (the file
    stays a config that ``load_config`` and ``mapless train`` read)."""
    header = "".join(f"# {line}\n" for line in comment.splitlines())
    write_text(path, header + yaml.safe_dump(to_dict(config), sort_keys=False))
