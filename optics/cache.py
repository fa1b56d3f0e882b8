"""On-disk cache of optics results, keyed by a hash of the design, the product and its settings.

Ray-traced products (vignetting maps, PSFs, PST curves) depend only on the design file's content, the
settings and the code's cache version, so a repeated request is answered from
``$NEWTSIM_CACHE_DIR`` (default ``~/.cache/newtsim/optics``). Bump :data:`CACHE_VERSION` when a change to
the tracing code changes results.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

#: 2: AR-coated corrector surfaces, the camera housing behind the lens stack (art's new corrector)
CACHE_VERSION = 2


def cache_dir() -> Path:
    root = os.environ.get("NEWTSIM_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "newtsim" / "optics"


def cache_key(product: str, design, settings: dict) -> str:
    """Hex digest of the design's content (not its name or path), the product and the settings.

    The ``[perturbation]`` table is part of the content when any entry is non-zero (a perturbed design
    gets its own PSF grids, SIP and maps); an all-zero table hashes like a design without one, so the
    nominal design's cached products stay valid."""
    exclude = {"name"}
    pert = getattr(design, "perturbation", None)
    if pert is None or pert.is_zero:
        exclude.add("perturbation")
    payload = {"v": CACHE_VERSION, "product": product, "settings": settings,
               "design": design.model_dump(mode="json", exclude=exclude)}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:20]


def cached_json(product: str, design, settings: dict, compute, use_cache: bool = True,
                read: bool = True) -> tuple[dict, bool]:
    """``(result, from_cache)``: the stored JSON for this key, or ``compute()`` (a JSON-able dict) stored.
    ``read=False`` always computes but still stores (a caller that needs more than the JSON)."""
    path = cache_dir() / f"{product}-{cache_key(product, design, settings)}.json"
    if use_cache and read and path.is_file():
        try:
            return json.loads(path.read_text()), True
        except (OSError, json.JSONDecodeError):
            pass  # a damaged entry is recomputed
    result = compute()
    if use_cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.json")  # one per process: no two writers share it
            tmp.write_text(json.dumps(result))
            tmp.replace(path)
        except OSError:
            pass  # a read-only home must not break a computation
    return result, False


def cached_file(product: str, design, settings: dict, suffix: str, write, use_cache: bool = True) -> Path:
    """Path of the cached file ``<product>-<key><suffix>`` of this design and settings; ``write(path)``
    makes it on first use (written to a temporary name, then renamed: a crash leaves no half file).
    With ``use_cache=False`` it is always rewritten."""
    path = cache_dir() / f"{product}-{cache_key(product, design, settings)}{suffix}"
    if use_cache and path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}{suffix}")
    write(tmp)
    tmp.replace(path)
    return path
