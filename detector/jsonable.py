"""Plain Python types for ``json.dumps`` (strict JSON: no NaN), for every JSON output of newtsim."""

from __future__ import annotations

import math
import os

import numpy as np


def jsonable(o):
    """Plain Python types for json.dumps: numpy scalars/arrays and paths converted, NaN and infinities -> None."""
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist())
    if isinstance(o, (np.bool_, bool)):
        return bool(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        v = float(o)
        return v if math.isfinite(v) else None
    if isinstance(o, os.PathLike):
        return str(o)
    return o
