"""JSON schemas generated from dataclasses, and a validator for the subset generated.

The wire messages (runtime/aefabmap_runtime/core/records/messages.py) are dataclasses; their schemas are derived
from the field type hints, so a field added to a record is in its schema at once.
Supported hints: int, float, bool, str, ``X | None`` (nullable), ``dict[str, X]``,
``list[X]``, and nested dataclasses. Field metadata may carry ``description`` and ``enum``.
A field without a default is required.

:func:`validate` checks a decoded JSON document against such a schema (keywords: type,
properties, required, additionalProperties, items, enum) and returns the first error as
one line, or None; it exists so that readers need no third-party validator.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any

_SCALARS = {int: "integer", float: "number", bool: "boolean", str: "string"}


def schema_for_dataclass(cls: type, *, title: str | None = None, description: str | None = None) -> dict:
    """JSON schema (draft 2020-12 subset) of a dataclass's fields, in field order."""
    hints = typing.get_type_hints(cls)
    props: dict[str, dict] = {}
    required: list[str] = []
    for f in dataclasses.fields(cls):
        prop = _schema_for_type(hints[f.name])
        if "enum" in f.metadata:
            allowed = list(f.metadata["enum"])
            if _nullable(prop):
                allowed.append(None)
            prop["enum"] = allowed
        if "description" in f.metadata:
            prop["description"] = f.metadata["description"]
        props[f.name] = prop
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            required.append(f.name)
    schema: dict[str, Any] = {}
    if title is not None:
        schema["title"] = title
    if description is not None:
        schema["description"] = description
    schema.update({"type": "object", "properties": props, "required": required})
    return schema


def _nullable(prop: dict) -> bool:
    t = prop.get("type")
    return isinstance(t, list) and "null" in t


def _schema_for_type(hint: Any) -> dict:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        if len(inner) != 1 or len(args) != 2:
            raise TypeError(f"only `X | None` unions are supported, got {hint!r}")
        prop = _schema_for_type(inner[0])
        t = prop["type"]
        prop["type"] = [*t, "null"] if isinstance(t, list) else [t, "null"]
        return prop
    if hint in _SCALARS:
        return {"type": _SCALARS[hint]}
    if origin is dict:
        if args[0] is not str:
            raise TypeError(f"JSON object keys are strings, got {hint!r}")
        return {"type": "object", "additionalProperties": _schema_for_type(args[1])}
    if origin is list:
        return {"type": "array", "items": _schema_for_type(args[0])}
    if dataclasses.is_dataclass(hint):
        return schema_for_dataclass(hint)
    raise TypeError(f"no JSON schema for type {hint!r}")


def _type_ok(value: Any, name: str) -> bool:
    if name == "null":
        return value is None
    if name == "boolean":
        return isinstance(value, bool)
    if name == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if name == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if name == "string":
        return isinstance(value, str)
    if name == "object":
        return isinstance(value, dict)
    if name == "array":
        return isinstance(value, list)
    return False


def _kind(value: Any) -> str:
    for name in ("null", "boolean", "integer", "number", "string", "object", "array"):
        if _type_ok(value, name):
            return name
    return type(value).__name__


def validate(doc: Any, schema: dict, path: str = "") -> str | None:
    """The first way ``doc`` breaks ``schema`` as one line ("field 'x': ..."), or None."""
    where = f"field {path!r}: " if path else ""
    t = schema.get("type")
    if t is not None:
        allowed = t if isinstance(t, list) else [t]
        if not any(_type_ok(doc, name) for name in allowed):
            return f"{where}expected {' or '.join(allowed)}, got {_kind(doc)}"
    if "enum" in schema and doc not in schema["enum"]:
        return f"{where}{doc!r} is not one of {schema['enum']}"
    if isinstance(doc, dict):
        for name in schema.get("required", ()):
            if name not in doc:
                return f"{where}missing required field {_join(path, name)!r}"
        props = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        for key, value in doc.items():
            sub = props.get(key, extra if isinstance(extra, dict) else None)
            if extra is False and key not in props:
                return f"{where}unexpected field {_join(path, key)!r}"
            if sub is not None and (err := validate(value, sub, _join(path, key))):
                return err
    elif isinstance(doc, list) and "items" in schema:
        for i, value in enumerate(doc):
            if err := validate(value, schema["items"], f"{path}[{i}]"):
                return err
    return None


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else str(key)
