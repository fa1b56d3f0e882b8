"""Validation helper: pydantic models in, one-line user errors out."""

from __future__ import annotations

import math
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from .errors import DetectorError

M = TypeVar("M", bound=BaseModel)


#: strict-mode errors that mean a coercion the lax mode would have made silently: ``true`` or ``"2"`` for a
#: number, ``"yes"`` or ``1`` for a boolean, ``2.5`` for an integer, ``true`` for a literal such as ``1``
_COERCIONS = {"int_type", "float_type", "bool_type", "literal_error", "int_from_float"}
#: parts of an error location that name a member of a union, not a key
_SCHEMA_TAGS = {"int", "float", "str", "bool", "none", "list", "dict", "tuple"}


def _is_coercion(err: dict) -> bool:
    got = err.get("input")
    kind = err.get("type", "")
    if kind not in _COERCIONS:
        return False
    if kind == "literal_error":
        return isinstance(got, bool)
    if kind == "bool_type":  # 1, "yes", "true": only true and false are booleans
        return not isinstance(got, bool)
    return isinstance(got, (bool, str)) or (kind in ("int_type", "int_from_float") and isinstance(got, float))


def _nonfinite(data: Any, loc: tuple = ()) -> tuple[tuple, float] | None:
    """The first NaN or infinite number in ``data`` (nested tables and arrays) and where it is."""
    if isinstance(data, float) and not math.isfinite(data):
        return loc, data
    if isinstance(data, dict):
        items = data.items()
    elif isinstance(data, (list, tuple)):
        items = enumerate(data)
    else:
        return None
    for k, v in items:
        found = _nonfinite(v, (*loc, k))
        if found is not None:
            return found
    return None


def _expected_from(err: dict) -> str:
    ctx = err.get("ctx") or {}
    kind = err.get("type", "")
    got = err.get("input")
    if kind in ("int_type", "float_type", "int_from_float") and isinstance(got, (bool, str, float)):
        what = "an integer" if kind != "float_type" else "a number"
        why = {bool: "true/false", str: "text", float: "a decimal number"}[type(got)]
        return f"{what}, not {why}"
    if kind == "bool_type":
        return "true or false (unquoted)"
    if kind in ("dict_type", "model_type", "model_attributes_type", "dataclass_type"):
        return "a table"
    if kind in ("list_type", "tuple_type", "set_type"):
        return "an array"
    if kind == "string_type":
        return "text in quotes"
    if "ge" in ctx:
        return f">= {ctx['ge']}"
    if "gt" in ctx:
        return f"> {ctx['gt']}"
    if "le" in ctx:
        return f"<= {ctx['le']}"
    if "lt" in ctx:
        return f"< {ctx['lt']}"
    if "expected" in ctx:
        return str(ctx["expected"])
    if kind == "extra_forbidden":
        return "one of the documented keys"
    if kind == "missing":
        return "a value"
    return err.get("msg", "a valid value").replace("Input should be ", "")


def validate(model: type[M], data: Any, *, prefix: str = "", file: str | None = None) -> M:
    """Validate ``data`` against ``model``; raise :class:`DetectorError` naming the first bad key.

    Parameters
    ----------
    model : pydantic model class
    data : mapping
    prefix : str
        Dotted prefix of the table in the scene file (``"effects.prnu"``), used in the message.
    file : str, optional
        The scene file, used in the message.

    Strict about types (no silent coercion: ``true`` or ``"2"`` where a number is expected, ``"yes"`` for a
    boolean, ``2.5`` for an integer are refused; an integer for a number is fine) and about finiteness (NaN
    and infinities are refused wherever they appear: "expected a finite number").
    """
    bad = _nonfinite(data)
    if bad is not None:
        loc, value = bad
        raise DetectorError(f"invalid value {value!r}", key=_key(prefix, loc), expected="a finite number",
                            file=file)
    try:
        model.model_validate(data, strict=True)
    except ValidationError as exc:
        coerced = [e for e in exc.errors() if _is_coercion(e)]
        if coerced:
            raise _error(coerced[0], prefix, file) from None
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise _error(exc.errors()[0], prefix, file) from None


def _key(prefix: str, loc) -> str:
    loc = ".".join(str(p) for p in loc if not (isinstance(p, str) and (p in _SCHEMA_TAGS or "[" in p)))
    return f"{prefix}.{loc}" if prefix and loc else (prefix or loc)


def _error(err: dict, prefix: str, file: str | None) -> DetectorError:
    """One validation error as the one-line user error: file, key, what was wrong, what was expected."""
    key = _key(prefix, err["loc"])
    got = err.get("input")
    kind = err.get("type")
    if kind == "extra_forbidden":
        return DetectorError("unknown key", key=key, expected=_expected_from(err), file=file)
    if kind == "missing":
        return DetectorError("missing", key=key, expected=_expected_from(err), file=file)
    if kind in ("value_error", "assertion_error"):  # a validator's own sentence, without pydantic's prefix
        text = err.get("msg", "")
        for head in ("Value error, ", "Assertion failed, "):
            text = text.removeprefix(head)
        if isinstance(got, dict):  # a check across a table's keys: the sentence says what is wrong
            return DetectorError(text, key=key, file=file)
        return DetectorError(f"invalid value {got!r}", key=key, expected=text, file=file)
    shown = "a table" if isinstance(got, dict) else repr(got)
    return DetectorError(f"invalid value {shown}", key=key, expected=_expected_from(err), file=file)
