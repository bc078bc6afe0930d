"""Small helpers for frozen-dataclass configs loaded from YAML with validation and overrides."""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from quasisim.errors import InputError
from quasisim.files import check_input_file

T = TypeVar("T")


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML keeps the last silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                twice = key in seen
            except TypeError:  # an unhashable key: PyYAML's own error follows
                continue
            if twice:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice in one mapping", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep)


def read_yaml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    check_input_file(path, "YAML file")
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)
    except yaml.YAMLError as e:
        raise InputError(path, None, "valid YAML", " ".join(str(e).split())) from None
    except (UnicodeDecodeError, OSError) as e:
        raise InputError(path, None, "a readable UTF-8 YAML file", " ".join(str(e).split())[:160]) from None
    if not isinstance(data, dict):
        raise InputError(path, None, "a YAML mapping at the top level", type(data).__name__)
    return data


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any] | None) -> dict[str, Any]:
    """Return a copy of ``data`` with dotted-key overrides applied (``{"pd.joint.kp": 3.0}``)."""
    out = _deepcopy(data)
    for key, value in (overrides or {}).items():
        cur = out
        parts = key.split(".")
        for p in parts[:-1]:
            cur = cur.setdefault(p, {})
        cur[parts[-1]] = value
    return out


def _deepcopy(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _deepcopy(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_deepcopy(v) for v in d]
    return d


def load(cls: type[T], path: str | Path, overrides: dict[str, Any] | None = None) -> T:
    """``cls`` (a frozen dataclass with a ``path`` field) from the YAML file ``path`` with dotted-key
    ``overrides``, validated (:func:`build`)."""
    return build(cls, {**apply_overrides(read_yaml(path), overrides), "path": str(path)}, path)


def build(cls: type[T], data: dict[str, Any], path: str | Path | None, prefix: str = "") -> T:
    """Construct frozen dataclass ``cls`` from a mapping, checking keys and basic types.

    Unknown keys and missing required keys raise :class:`InputError` naming the field.
    """
    if not isinstance(data, dict):
        raise InputError(path, prefix.rstrip(".") or None, "a mapping", type(data).__name__)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(data) - set(fields)
    if unknown:
        raise InputError(
            path, prefix + sorted(unknown)[0], f"one of the keys {', '.join(sorted(fields))}", "an unknown key"
        )
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise InputError(path, prefix + name, "a value (required key)", "missing")
            continue
        kwargs[name] = _coerce(hints[name], data[name], path, prefix + name)
    return cls(**kwargs)


def _coerce(tp: Any, value: Any, path: str | Path | None, field: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(a, value, path, field)
            except InputError as e:
                errors.append(e)
        raise errors[0]
    if dataclasses.is_dataclass(tp):
        return build(tp, value, path, field + ".")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise InputError(path, field, "a list", repr(value))
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, path, f"{field}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise InputError(path, field, f"a list of {len(args)} values", f"{len(value)} values")
        return tuple(_coerce(a, v, path, f"{field}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if origin is dict:
        if not isinstance(value, dict):
            raise InputError(path, field, "a mapping", repr(value))
        return {str(k): _coerce(args[1], v, path, f"{field}.{k}") for k, v in value.items()}
    if tp is float:
        if isinstance(value, str):  # PyYAML reads 4.0e4 (no sign in the exponent) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(path, field, "a number", repr(value))
        if not math.isfinite(value):
            raise InputError(path, field, "a finite number", repr(value))
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(path, field, "an integer", repr(value))
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise InputError(path, field, "true or false", repr(value))
        return value
    if tp is str:
        if not isinstance(value, str):
            raise InputError(path, field, "a string", repr(value))
        return value
    return value
