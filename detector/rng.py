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


#: deviates per block of :func:`standard_normal_f32` (the block's float64 and float32 temporaries, ~200 kB, stay
#: in the cache between the passes over them)
NORMAL_BLOCK = 1 << 15
_TWO_PI_F32 = np.float32(2.0 * np.pi)


def standard_normal_f32(rng: np.random.Generator, shape) -> np.ndarray:
    """Standard-normal float32 deviates by the Box-Muller transform (Box & Muller 1958, Ann. Math. Stat. 29, 610).

    For independent uniforms u1, u2 on [0, 1), ``r = sqrt(-2 ln(1 - u1))`` and ``theta = 2 pi u2`` give two
    independent standard normals ``r cos(theta)`` and ``r sin(theta)``: an exact transform, so the deviates are
    N(0, 1) as much as ``rng.standard_normal(shape, dtype=np.float32)``'s, about three times faster (numpy's
    float32 ziggurat costs ~8 ns a deviate on these machines, this ~2.5 ns). ``u1`` is a float64 uniform (53
    bits: ``r`` reaches sqrt(2 ln 2^53) = 8.57, beyond which the normal holds 1e-17 of its mass); ``u2`` a
    float32 uniform (24 bits: the angle's grid is 2 pi / 2^24, float32's own resolution of an angle near 2 pi);
    ``ln(1 - u1)`` in float64, the rest in float32. Each block of :data:`NORMAL_BLOCK` deviates takes its
    first half from the cosines and its second half from the sines of the same radii and angles (a block of k
    deviates draws ceil(k / 2) of each uniform, u1's first); the deviates of a call are the blocks in C order.
    Not the same numbers as ``rng.standard_normal``: same generator state, same deviates (numpy's vectorised ln,
    cos and sin: their last bit may depend on the CPU's instruction set).
    """
    out = np.empty(shape, dtype=np.float32)
    flat = out.reshape(-1)
    n = flat.size
    half = (min(n, NORMAL_BLOCK) + 1) // 2
    u = np.empty(half)
    r = np.empty(half, dtype=np.float32)
    th = np.empty(half, dtype=np.float32)
    for i in range(0, n, NORMAL_BLOCK):
        k = min(NORMAL_BLOCK, n - i)
        h = (k + 1) // 2
        a, rr, t = u[:h], r[:h], th[:h]
        rng.random(out=a)
        np.subtract(1.0, a, out=a)  # (0, 1]: ln stays finite
        np.log(a, out=a)
        np.multiply(a, -2.0, out=rr, casting="same_kind")  # -2 ln(1 - u1) rounded to float32
        np.sqrt(rr, out=rr)
        rng.random(out=t, dtype=np.float32)
        t *= _TWO_PI_F32
        o = flat[i:i + k]
        np.cos(t, out=o[:h])
        o[:h] *= rr
        if k > h:
            np.sin(t[:k - h], out=o[h:])
            o[h:] *= rr[:k - h]
    return out
