"""Seeds (thesis Annex IV; DESIGN.md convention 2).

Two independent roots:

* the **hardware seed** fixes everything that belongs to the physical chip (PRNU/DSNU maps, hot, dead
  and column defects, amplifier gains): the same every frame, like the real camera;
* the **frame seed** drives everything that changes from frame to frame (shot noise, read noise, row
  noise, cosmic rays).

Each consumer gets its own stream through ``SeedSequence(root, spawn_key=(stream, index))``, where
``stream`` is a stable number derived from the effect name and ``index`` the row band. Streams are
therefore independent of the number of threads, of the processing order and of which other effects are
switched on: same seeds, same bytes.
"""

from __future__ import annotations

import zlib

import numpy as np

#: Rows per random-number band, in sensor rows. Dense hardware maps are drawn per band of the *full*
#: sensor width, so a region of interest sees exactly the pixels of the full frame.
BAND_ROWS = 240


def stream_id(name: str) -> int:
    """A stable 32-bit stream number for a name (CRC-32, not Python's salted ``hash``)."""
    return zlib.crc32(name.encode("utf-8"))


def generator(root_seed: int, name: str, *index: int) -> np.random.Generator:
    """An independent PCG64 generator for (root seed, stream name, indices)."""
    ss = np.random.SeedSequence(int(root_seed), spawn_key=(stream_id(name), *map(int, index)))
    return np.random.Generator(np.random.PCG64(ss))


def fresh_seed() -> int:
    """A new frame seed from the OS entropy pool (recorded in the FITS header so the frame can be re-made)."""
    return int(np.random.SeedSequence().entropy % (2 ** 63))
