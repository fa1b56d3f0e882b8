"""The checked reading of a number from an ``[[objects]]`` table, shared by the object and light-curve
parsers (its own module so that neither parser imports the other)."""

from __future__ import annotations

import math

from .errors import ObjectError


def number(table: dict, name: str, prefix: str, file, lo=-math.inf, hi=math.inf, *, lo_open=False,
           default=None, required=False):
    """``table[name]`` as a float in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``); ``default`` when absent,
    or an :class:`ObjectError` naming ``prefix.name`` when ``required``."""
    if name not in table:
        if required:
            raise ObjectError("missing", key=f"{prefix}.{name}", file=file, expected=f"a number in [{lo}, {hi}]")
        return default
    v = table[name]
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    ok = ok and (v > lo if lo_open else v >= lo) and v <= hi
    if not ok:
        interval = f"({lo}, {hi}]" if lo_open else f"[{lo}, {hi}]"
        raise ObjectError(f"{v!r}", key=f"{prefix}.{name}", file=file, expected=f"a number in {interval}")
    return float(v)
