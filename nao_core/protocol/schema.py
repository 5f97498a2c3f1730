"""JSON Schema (draft 2020-12) of a protocol message, derived from its dataclass.

The dataclass is the single source of truth: the strict decoder converts with the same field
types and ``bounds`` metadata (``nao_core.config.from_mapping``), so schema and decoder agree.
The station registers these schemas in MCAP (encoding ``jsonschema``) and logs the bytes received.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Dict, Mapping, Union

DRAFT = "https://json-schema.org/draft/2020-12/schema"


def message_schema(cls: type, version: int) -> Dict[str, Any]:
    """The schema of a message class: its fields plus the ``v`` and ``type`` envelope fields."""
    body = _object(cls)
    body["properties"] = {"v": {"const": version}, "type": {"const": cls.TYPE}, **body["properties"]}
    body["required"] = ["v", "type", *body["required"]]
    return {"$schema": DRAFT, "$id": f"nao-active-recon/{cls.TYPE}", "title": cls.__name__, **body}


def record_schema(cls: type, name: str) -> Dict[str, Any]:
    """The schema of a plain dataclass record (no message envelope), e.g. a station log record."""
    return {"$schema": DRAFT, "$id": f"nao-active-recon/{name}", "title": name, **_object(cls)}


def _object(cls: type) -> Dict[str, Any]:
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.init]
    return {
        "type": "object",
        "properties": {f.name: _schema(hints[f.name], f.metadata) for f in fields},
        "required": [f.name for f in fields if _required(f)],
        "additionalProperties": False,
    }


def _required(f: dataclasses.Field) -> bool:
    return f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING


def _schema(tp: Any, meta: Mapping) -> Dict[str, Any]:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _object(tp)
    if origin is Union:
        inner = [a for a in args if a is not type(None)]
        arms = [_schema(a, meta) for a in inner] + ([{"type": "null"}] if type(None) in args else [])
        return arms[0] if len(arms) == 1 else {"anyOf": arms}
    if origin is typing.Literal:
        return {"enum": list(args)}
    if tp is bool:
        return {"type": "boolean"}
    if tp in (int, float):
        out: Dict[str, Any] = {"type": "integer" if tp is int else "number"}
        lo, hi = meta.get("bounds", (None, None))
        if lo is not None:
            out["minimum"] = lo
        if hi is not None:
            out["maximum"] = hi
        return out
    if tp is str:
        return {"type": "string"}
    if origin in (tuple, list):
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            items = [_schema(a, meta) for a in args]
            if all(item == items[0] for item in items):
                return {"type": "array", "items": items[0], "minItems": len(items), "maxItems": len(items)}
            return {"type": "array", "prefixItems": items, "items": False, "minItems": len(items)}
        return {"type": "array", "items": _schema(args[0], meta) if args else {}}
    if origin is dict:
        return {"type": "object", "additionalProperties": _schema(args[1], meta)}
    if tp is Any:
        return {}
    raise TypeError(f"protocol schema: unsupported field type {tp!r}")
