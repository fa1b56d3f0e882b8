"""The C allocator's handling of frame-sized arrays during a diagnosis (glibc only; elsewhere nothing is changed).

A diagnosis of a 2048 x 2048 frame allocates and frees thousands of frame-sized temporaries (a padded frame's
spectrum, a transformed image, a template stack: 16-130 MB each). glibc's ``malloc`` serves a request above its
mmap threshold (dynamic, at most 32 MiB on 64-bit systems) with a fresh ``mmap`` and returns it with ``munmap``
on ``free``, and trims free memory at the top of its heap above the trim threshold: the next such array is then
new memory again, whose pages the kernel faults in and zeroes one by one. On the 2-core development machine that
was 1.6 million page faults and 24 s of system time in one diagnosis of the 2048 x 2048 benchmark
(``benchmarks/bench_diagnose.py``). With both thresholds raised (:data:`MMAP_THRESHOLD_BYTES`,
:data:`TRIM_THRESHOLD_BYTES`) the freed memory is reused: 0.26 million faults and 7 s of system time. The price
is memory held free between uses: the peak resident memory varies more from run to run (the two fitting threads'
interleaving), by up to a few hundred MB above the default's. Only where memory comes from changes, never a
number.

The thresholds are ``mallopt(3)`` parameters (``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``; glibc manual, "Malloc
Tunable Parameters"). glibc has no call that reads them back: on leaving, they are set to the values its
dynamic rule reaches once a frame-sized array has been freed (the largest mmap threshold, 32 MiB, and twice
that to trim), and the free memory is handed back to the system (``malloc_trim(3)``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import platform
import threading

#: ``mallopt`` parameter numbers (glibc ``malloc.h``)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: during a diagnosis, arrays up to this size come from (and return to) the heap [bytes]: above the largest
#: temporaries of a 2048 x 2048 diagnosis (a stack of three float64 frames, 100 MB)
MMAP_THRESHOLD_BYTES = 256 << 20
#: during a diagnosis, free memory at the top of the heap is kept up to this size [bytes]: twice the mmap
#: threshold, as glibc's own dynamic rule keeps it
TRIM_THRESHOLD_BYTES = 512 << 20
#: on leaving: the thresholds glibc's dynamic rule reaches once a frame-sized array is freed [bytes]
#: (``DEFAULT_MMAP_THRESHOLD_MAX`` on 64-bit systems, and twice that to trim)
MMAP_THRESHOLD_AFTER = 32 << 20
TRIM_THRESHOLD_AFTER = 64 << 20

_LOCK = threading.Lock()
_DEPTH = [0]  # nested or concurrent holders of the raised thresholds


@functools.lru_cache(maxsize=1)
def _glibc():
    """The C library when it is glibc (with ``mallopt`` and ``malloc_trim``), else None."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        libc.malloc_trim.argtypes, libc.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
    except (OSError, AttributeError):
        return None
    return libc


def reuse_freed_memory(fn):
    """Run ``fn`` with glibc's mmap and trim thresholds raised (module docstring): frame-sized arrays freed
    during the call are reused, not returned to the system and faulted in again. Nested and concurrent calls
    share one raise; the last to leave sets the thresholds back and trims the heap. Elsewhere than glibc,
    ``fn`` runs as it is."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        libc = _glibc()
        if libc is None:
            return fn(*args, **kwargs)
        with _LOCK:
            if _DEPTH[0] == 0:
                libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
                libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
            _DEPTH[0] += 1
        try:
            return fn(*args, **kwargs)
        finally:
            with _LOCK:
                _DEPTH[0] -= 1
                if _DEPTH[0] == 0:
                    libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_AFTER)
                    libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_AFTER)
                    libc.malloc_trim(0)
    return wrapper
