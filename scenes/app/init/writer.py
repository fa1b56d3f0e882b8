"""The scene TOML with each value's source as a comment, and the files it names beside it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import tomli_w


def scene_text(scene: dict, sources: dict, header_lines=()) -> str:
    """TOML of ``scene`` with ``# source`` after every key whose dotted name is in ``sources``."""
    text = tomli_w.dumps(scene)
    out, table = [], ""
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("[") and not s.startswith("[[") or s.startswith("[["):
            table = s.strip("[]").strip()
        elif " = " in line and not line.startswith(" "):
            key = line.split(" = ", 1)[0].strip()
            dotted = f"{table}.{key}" if table else key
            if dotted in sources:
                comment = sources[dotted].replace("\n", " ")
                line = f"{line}  # {comment}"
        out.append(line)
    head = ["# written by `newtsim init`: every value's source (measured | header | assumed) follows it as a comment"]
    head += [f"# {h}" for h in header_lines]
    return "\n".join(head + out) + "\n"


def write_file(kind: str, payload, path: Path) -> None:
    path = Path(path)
    if kind == "csv":
        path.write_text(payload)
    elif kind == "toml":
        path.write_text(tomli_w.dumps(payload))
    elif kind == "fits":
        from astropy.io import fits

        arrays = payload if isinstance(payload, (list, tuple)) else [payload]
        hdus = [fits.PrimaryHDU(np.asarray(arrays[0]))] + [fits.ImageHDU(np.asarray(a)) for a in arrays[1:]]
        fits.HDUList(hdus).writeto(path, overwrite=True)
    elif kind == "json":
        path.write_text(json.dumps(payload, indent=1, default=str))
    else:
        raise ValueError(kind)
