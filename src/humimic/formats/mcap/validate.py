"""A compiled checker for the JSON Schema subset of :data:`~.schemas.SCHEMAS`.

The ``jsonschema`` package costs 3 ms per message here; these closures check a message in one
pass, and name the failing field's dotted path.
"""

from __future__ import annotations

from typing import Any

from humimic.formats.mcap.schemas import SCHEMAS

Checker = Any  # Callable[[object, str], str | None]: value, path -> error or None


def compile_schema(schema: dict[str, Any]) -> Checker:
    """A fast checker for the JSON Schema subset humimic's schemas use.

    Supported keywords: ``type`` (object, array, number, integer, string, boolean),
    ``properties``, ``required``, ``items``, ``additionalProperties`` (a schema). Others are
    ignored. The checker returns ``None`` or a message that starts with the failing field's
    dotted path. Arrays of numbers are checked in one pass (they dominate the messages).
    """
    kind = schema.get("type")
    props = {k: compile_schema(v) for k, v in schema.get("properties", {}).items()}
    required = list(schema.get("required", []))
    items = compile_schema(schema["items"]) if isinstance(schema.get("items"), dict) else None
    addl = schema.get("additionalProperties")
    addl_check = compile_schema(addl) if isinstance(addl, dict) else None
    numeric_items = (
        isinstance(schema.get("items"), dict) and schema["items"].get("type") == "number"
    )

    def where(path: str) -> str:
        return path or "(message)"

    def check(value: object, path: str = "") -> str | None:
        if kind == "object":
            if not isinstance(value, dict):
                return f"{where(path)}: expected an object, got {type(value).__name__}"
            for k in required:
                if k not in value:
                    return f"{where(path + '.' + k if path else k)}: required field missing"
            for k, v in value.items():
                sub = f"{path}.{k}" if path else k
                c = props.get(k, addl_check)
                if c is not None:
                    err = c(v, sub)
                    if err:
                        return err
            return None
        if kind == "array":
            if not isinstance(value, list):
                return f"{where(path)}: expected an array, got {type(value).__name__}"
            if numeric_items:
                for i, x in enumerate(value):
                    if type(x) not in (int, float):
                        return f"{path}.{i}: expected a number, got {x!r}"
                return None
            if items is not None:
                for i, x in enumerate(value):
                    err = items(x, f"{path}.{i}")
                    if err:
                        return err
            return None
        if kind == "number":
            if type(value) not in (int, float):
                return f"{where(path)}: expected a number, got {value!r}"
        elif kind == "integer":
            if type(value) is not int:
                return f"{where(path)}: expected an integer, got {value!r}"
        elif kind == "string":
            if not isinstance(value, str):
                return f"{where(path)}: expected a string, got {value!r}"
        elif kind == "boolean" and not isinstance(value, bool):
            return f"{where(path)}: expected true or false, got {value!r}"
        return None

    return check


VALIDATORS: dict[str, Checker] = {name: compile_schema(s) for name, s in SCHEMAS.items()}
"""Schema name -> its compiled checker, for every schema in :data:`SCHEMAS`."""
