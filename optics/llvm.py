"""Start Mitsuba's llvm (CPU) variant safely.

drjit JIT-compiles its kernels with the system's LLVM. LLVM 15 and 16 abort the whole process (SIGABRT,
no Python exception) at the first ray intersection and LLVM 14 is refused, so before ``mi.set_variant``
we find an LLVM 17 or newer library and pin it through ``DRJIT_LIBLLVM_PATH``.

Only entry points (the CLI, benchmarks, examples) and one test fixture call :func:`init_mitsuba`;
library modules never set a variant at import (DESIGN.md convention 6).
"""

from __future__ import annotations

import glob
import os
import re

from .design import OpticsError

MIN_LLVM = 17
DEFAULT_VARIANT = "llvm_ad_mono"
INSTALL_HINT = ("install LLVM 17 or newer (Debian/Ubuntu: `apt install libllvm19`) or point "
                "DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= 17")
_SEARCH = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
)


def llvm_major(path: str) -> int | None:
    """LLVM major version read from a library file name (``libLLVM-19.so``, ``libLLVM.so.19.1``)."""
    name = os.path.basename(path)
    m = re.match(r"libLLVM[-.]?(?:so\.)?(\d+)", name)
    if m:
        return int(m.group(1))
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_llvm(min_version: int = MIN_LLVM) -> str:
    """Path of the newest LLVM shared library of version ``>= min_version``.

    ``DRJIT_LIBLLVM_PATH``, when set, is checked (not replaced): a version below ``min_version`` raises.
    """
    pinned = os.environ.get("DRJIT_LIBLLVM_PATH")
    if pinned:
        v = llvm_major(pinned)
        if not os.path.exists(pinned):
            raise OpticsError(f"DRJIT_LIBLLVM_PATH={pinned}: no such file; {INSTALL_HINT}")
        if v is not None and v < min_version:
            raise OpticsError(f"DRJIT_LIBLLVM_PATH={pinned} is LLVM {v}; Mitsuba's llvm variant needs "
                              f">= {min_version} (LLVM 15/16 abort the process); {INSTALL_HINT}")
        return pinned
    found = []
    for pattern in _SEARCH:
        for path in glob.glob(pattern):
            v = llvm_major(path)
            if v is not None and v >= min_version and not path.endswith(".a"):
                found.append((v, len(path), path))
    if not found:
        seen = sorted({llvm_major(p) for pat in _SEARCH for p in glob.glob(pat)} - {None})
        raise OpticsError(f"no LLVM >= {min_version} found (found: {seen or 'none'}); {INSTALL_HINT}")
    return max(found, key=lambda t: (t[0], -t[1]))[2]


def init_mitsuba(variant: str = DEFAULT_VARIANT):
    """Pin an LLVM >= 17, select ``variant`` and return the ``mitsuba`` module.

    Entry points only. Raises :class:`OpticsError` (never a SIGABRT) when no suitable LLVM exists.
    """
    if variant.startswith("llvm"):
        os.environ["DRJIT_LIBLLVM_PATH"] = find_llvm()
    try:
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise OpticsError(f"Mitsuba 3 is not installed ({exc}); run `pip install 'newtsim[optics]'`") from None
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi
