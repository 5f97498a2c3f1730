"""Strict YAML configuration: files merged in order, then converted to frozen dataclasses.

One loader serves every process (the bridge may not import ``agent``; the station composes the
agent's parameter dataclasses with the robot model defined here). Rules:

* Files are deep-merged left to right: mappings merge key by key, any other value replaces.
* Every leaf remembers the file it came from, so an error names that file, the key path and what
  was expected: ``config/ekf.yaml: ekf.sigma_phi: expected a number in [0, 0.5], got 'abc'``.
* Unknown keys, missing keys, wrong types, non-finite numbers and out-of-range values are errors.
* Ranges are declared on the dataclass field: ``field(metadata=bounds(0.0, 1.0))``.

Supported field types: bool, int, float, str, ``Literal[...]``, ``Optional[T]``, ``tuple[T, ...]``,
``tuple[T1, T2]``, ``list[T]``, ``dict[str, T]`` and nested dataclasses.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.resources
import math
import sys
import typing
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Tuple, TypeVar, Union

import yaml

T = TypeVar("T")



def _config_dir() -> Path:
    """The shipped defaults: the repository's ``config/``, packaged in the wheel as ``nao_core.defaults``.

    A source checkout or an editable install reads ``config/`` next to the package; an installed
    wheel reads its package data through ``importlib.resources``.
    """
    source = Path(__file__).resolve().parent.parent / "config"
    if source.is_dir():
        return source
    return Path(str(importlib.resources.files("nao_core") / "defaults"))


CONFIG_DIR = _config_dir()


class ConfigError(ValueError):
    """A configuration value is wrong; the message names the file, the key path and the rule."""


def bounds(lo: Optional[float] = None, hi: Optional[float] = None) -> dict:
    """Field metadata declaring an inclusive numeric range (applies to each element of tuples)."""
    return {"bounds": (lo, hi)}


class _NoAliasLoader(yaml.SafeLoader):
    """SafeLoader that refuses anchors/aliases: a hand-written config never needs them, and alias
    expansion lets a tiny file grow exponentially ("billion laughs")."""

    def compose_node(self, parent, index):  # type: ignore[no-untyped-def]
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(None, None, "aliases are not allowed in configuration files",
                                              self.peek_event().start_mark)
        return super().compose_node(parent, index)


def read_yaml(path: Path, what: str = "a mapping") -> dict:
    """The top-level mapping of a YAML file (empty file: ``{}``); aliases refused; ConfigError names
    the file. ``what`` names the expected top level in the error (e.g. "a mapping of sections")."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        data = yaml.load(text, Loader=_NoAliasLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: nesting too deep") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected {what} at the top level, got {type(data).__name__}")
    return data


def _merge(base: dict, origin: dict, update: Mapping, source: str, prefix: Tuple[str, ...] = ()) -> None:
    """Deep-merge ``update`` into ``base``; record in ``origin`` which file set each key path."""
    for key, value in update.items():
        path = prefix + (str(key),)
        origin[path] = source
        if isinstance(value, Mapping) and isinstance(base.get(key), dict):
            _merge(base[key], origin, value, source, path)
        else:
            base[key] = copy.deepcopy(value)
            if isinstance(value, Mapping):
                _record(origin, value, source, path)


def _record(origin: dict, value: Mapping, source: str, prefix: Tuple[str, ...]) -> None:
    for key, sub in value.items():
        origin[prefix + (str(key),)] = source
        if isinstance(sub, Mapping):
            _record(origin, sub, source, prefix + (str(key),))


class _Converter:
    def __init__(self, origin: dict, default_source: str):
        self.origin = origin
        self.default_source = default_source

    def fail(self, path: Tuple[str, ...], message: str) -> ConfigError:
        source = self.default_source
        for cut in range(len(path), 0, -1):
            if path[:cut] in self.origin:
                source = self.origin[path[:cut]]
                break
        return ConfigError(f"{source}: {'.'.join(path) or '<top>'}: {message}")

    def dataclass(self, cls: type, data: Any, path: Tuple[str, ...]) -> Any:
        if not isinstance(data, Mapping):
            raise self.fail(path, f"expected a mapping for {cls.__name__}, got {_show(data)}")
        hints = typing.get_type_hints(cls)
        fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
        unknown = sorted(set(map(str, data)) - set(fields))
        if unknown:
            raise self.fail(path + (unknown[0],), f"unknown key; expected one of {sorted(fields)}")
        kwargs = {}
        for name, field in fields.items():
            if name not in data:
                if field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING:
                    continue
                raise self.fail(path + (name,), "missing required key")
            kwargs[name] = self.value(hints[name], data[name], path + (name,), field.metadata)
        try:
            return cls(**kwargs)
        except (ValueError, TypeError) as exc:  # __post_init__ cross-field checks
            raise self.fail(path, str(exc)) from None

    def value(self, tp: Any, data: Any, path: Tuple[str, ...], meta: Mapping) -> Any:
        origin, args = typing.get_origin(tp), typing.get_args(tp)
        if dataclasses.is_dataclass(tp):
            return self.dataclass(tp, data, path)
        if origin is Union:
            if data is None and type(None) in args:
                return None
            inner = [a for a in args if a is not type(None)]
            for arm in inner[:-1]:  # first arm that accepts the value wins
                try:
                    return self.value(arm, data, path, meta)
                except ConfigError:
                    pass
            return self.value(inner[-1], data, path, meta)
        if origin is typing.Literal:
            if data not in args:
                raise self.fail(path, f"expected one of {list(args)}, got {_show(data)}")
            return data
        if tp is bool:
            if not isinstance(data, bool):
                raise self.fail(path, f"expected true or false, got {_show(data)}")
            return data
        if tp in (int, float):
            return self.number(tp, data, path, meta)
        if tp is str:
            if not isinstance(data, str):
                raise self.fail(path, f"expected a string, got {_show(data)}")
            return data
        if origin in (tuple, list):
            if not isinstance(data, (list, tuple)):
                raise self.fail(path, f"expected a list, got {_show(data)}")
            if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
                if len(data) != len(args):
                    raise self.fail(path, f"expected a list of {len(args)} items, got {len(data)}")
                items = [self.value(a, d, path + (f"[{i}]",), meta) for i, (a, d) in enumerate(zip(args, data))]
            else:
                item_tp = args[0] if args else Any
                items = [self.value(item_tp, d, path + (f"[{i}]",), meta) for i, d in enumerate(data)]
            return tuple(items) if origin is tuple else items
        if origin is dict:
            if not isinstance(data, Mapping):
                raise self.fail(path, f"expected a mapping, got {_show(data)}")
            return {str(k): self.value(args[1], v, path + (str(k),), meta) for k, v in data.items()}
        if tp is Any:
            return data
        raise TypeError(f"config loader: unsupported field type {tp!r} at {'.'.join(path)}")

    def number(self, tp: type, data: Any, path: Tuple[str, ...], meta: Mapping) -> Any:
        lo, hi = meta.get("bounds", (None, None))
        rng = f" in [{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
        kind = "an integer" if tp is int else "a number"
        ok_type = isinstance(data, int) if tp is int else isinstance(data, (int, float))
        if isinstance(data, bool) or not ok_type:
            raise self.fail(path, f"expected {kind}{rng}, got {_show(data)}")
        if not math.isfinite(data) or (lo is not None and data < lo) or (hi is not None and data > hi):
            raise self.fail(path, f"expected {kind}{rng}, got {_show(data)}")
        return tp(data)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def load(cls: type[T], files: Iterable[Union[str, Path]], section: Optional[str] = None) -> T:
    """Merge YAML ``files`` in order and convert the result (or its ``section``) to ``cls``.

    Raises ConfigError with the file, the key path and the expectation on any problem.
    """
    merged: dict = {}
    origin: dict = {}
    paths = [Path(f) for f in files]
    for path in paths:
        _merge(merged, origin, read_yaml(path), str(path))
    conv = _Converter(origin, str(paths[-1]) if paths else "<config>")
    if section is not None and section not in merged:
        raise ConfigError(f"{paths[-1] if paths else '<config>'}: {section}: missing required section")
    data, prefix = (merged, ()) if section is None else (merged[section], (section,))
    try:
        return conv.dataclass(cls, data, prefix)
    except RecursionError:
        raise ConfigError(f"{conv.default_source}: nesting too deep") from None


def from_mapping(cls: type[T], data: Mapping, source: str = "<mapping>") -> T:
    """Convert an in-memory mapping (e.g. a decoded ``info`` reply) with the same strict rules."""
    conv = _Converter({}, source)
    return conv.dataclass(cls, data, ())


def main_error(exc: ConfigError) -> int:
    """Print a configuration error for a CLI and return its exit code (2), never a traceback."""
    print(f"configuration error: {exc}", file=sys.stderr)
    return 2
