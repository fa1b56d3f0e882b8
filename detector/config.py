"""Validation helper: pydantic models in, one-line user errors out."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from .errors import DetectorError

M = TypeVar("M", bound=BaseModel)


def _expected_from(err: dict) -> str:
    ctx = err.get("ctx") or {}
    kind = err.get("type", "")
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
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        key = f"{prefix}.{loc}" if prefix and loc else (prefix or loc)
        got = err.get("input")
        msg = "unknown key" if err.get("type") == "extra_forbidden" else (
            "missing" if err.get("type") == "missing" else f"invalid value {got!r}")
        raise DetectorError(msg, key=key, expected=_expected_from(err), file=file) from None
