"""Row bands for the calibration-frame analysis: frames read band by band, regular subsamples gathered band
by band, per-pixel maps kept on disk (issue 12: characterize a full 14192 x 10640 IMX411 set in bounded memory).

Three small pieces, used by :mod:`detector.characterize`:

* :class:`FitsRows`: a 2-D FITS image whose rows are read on demand (``rows(a, b)``, BZERO/BSCALE applied)
  through astropy's ``section`` on a file opened with ``memmap=False``: only the requested rows are read
  from disk. (A memory map would do the same I/O, but its pages count in the process's resident set until
  unmapped, so a pass over seven 300 MB frames would show 2 GB more peak RSS.)
* :class:`Sampler`: the regular subsample of :func:`detector.stats.subsample` (every k-th value of the
  flattened image or of a rectangle of it, ``k = ceil(n / max_n)``) gathered band by band: the same values,
  in the same order, as ``subsample(full_array)``, so every robust statistic of the whole-frame code is
  reproduced exactly.
* :class:`BandStore`: a float32 (or float64) image kept in a temporary raw file, written and read back by
  rows (the per-pixel maps of the camera twin; ``np.asarray(store)`` loads it for small frames and tests).

Band height: :func:`band_rows` gives ``BAND_PIXELS // width`` rows (at least 16): a frame of at most
``BAND_PIXELS`` pixels is one band, so small frames (the SBIG STL-1001E, the tests) go through the very same
arithmetic as before; the 14192-pixel-wide IMX411 has 591-row bands.
"""

from __future__ import annotations

import math
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
from astropy.io import fits

from .errors import DetectorError
from .stats import MAX_STAT_PIXELS

#: pixels per band [pixels]: 8 Mpixel = 64 MB per float64 temporary
BAND_PIXELS = 8_388_608


def band_rows(shape: tuple[int, int], band_pixels: int | None = None) -> int:
    """Rows per band for an image of ``shape`` (rows, cols): ``band_pixels // cols``, at least 16."""
    bp = BAND_PIXELS if band_pixels is None else int(band_pixels)
    return int(min(shape[0], max(16, bp // max(shape[1], 1))))


def bands(shape: tuple[int, int], rows: int):
    """``(r0, r1)`` of consecutive row bands covering ``shape[0]`` rows."""
    for r0 in range(0, shape[0], rows):
        yield r0, min(shape[0], r0 + rows)


class FitsRows:
    """The first 2-D image of a FITS file, read by rows.

    Parameters
    ----------
    path : str or Path
    role : str
        "bias", "dark" or "flat", for messages.

    Attributes: ``path``, ``header`` (the image HDU's cards over the primary's), ``shape`` (rows, cols),
    ``dtype`` (stored type after scaling: the integer type for BZERO-shifted unsigned data, else float).
    """

    def __init__(self, path, role: str = "frame"):
        self.path = str(path)
        p = Path(path)
        what = f"{role} file"
        if not p.is_file():
            raise DetectorError(f"{what} not found", file=self.path, expected="an existing FITS file")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", fits.verify.VerifyWarning)
                warnings.filterwarnings("error", message=".*truncated.*")
                self._hdul = fits.open(p, memmap=False, lazy_load_hdus=True)
                self._hdu, self.header = self._find(what)
                self.shape = self._shape()
                # touch the last row: a truncated file fails here, not in the middle of a pass
                last = self._read(self.shape[0] - 1, self.shape[0])
                self.dtype = last.dtype
        except DetectorError:
            self.close()
            raise
        except Warning as exc:
            self.close()
            raise DetectorError(f"{what} is truncated ({exc})", file=self.path,
                                expected="a complete FITS file") from None
        except MemoryError:
            self.close()
            raise
        except Exception as exc:  # noqa: BLE001 -- astropy raises OSError/ValueError/TypeError/IndexError
            self.close()
            raise DetectorError(f"{what} cannot be read as FITS ({type(exc).__name__}: {exc})", file=self.path,
                                expected="a complete FITS file") from None

    def _find(self, what):
        for hdu in self._hdul:
            if hdu.is_image or isinstance(hdu, fits.CompImageHDU):
                shp = tuple(int(hdu.header.get(f"NAXIS{i}", 0)) for i in range(int(hdu.header.get("NAXIS", 0)), 0, -1))
                if shp and all(s > 0 for s in shp) and len([s for s in shp if s > 1]) == 2:
                    header = self._hdul[0].header.copy()
                    if hdu is not self._hdul[0]:
                        header.extend(hdu.header, update=True)
                    return hdu, header
        raise DetectorError(f"no 2-D image in the {what}", file=self.path, expected="a 2-D image HDU")

    def _shape(self):
        h = self._hdu.header
        shp = [int(h[f"NAXIS{i}"]) for i in range(int(h["NAXIS"]), 0, -1)]
        self._full = tuple(shp)
        two = [s for s in shp if s > 1]
        return int(two[0]), int(two[1])

    def _read(self, a: int, b: int) -> np.ndarray:
        # rows a:b of the 2-D image inside a possibly higher-dimensional HDU with singleton axes
        idx = []
        seen = 0
        for s in self._full:
            if s == 1:
                idx.append(0)
            else:
                idx.append(slice(a, b) if seen == 0 else slice(None))
                seen += 1
        return np.asarray(self._hdu.section[tuple(idx)])

    def rows(self, a: int, b: int) -> np.ndarray:
        """Rows ``a:b`` as stored (scaled), not converted."""
        try:
            return self._read(a, b)
        except MemoryError:
            raise
        except Exception as exc:  # noqa: BLE001 -- a damaged file: one line naming it
            raise DetectorError(f"file cannot be read at rows {a}:{b} ({type(exc).__name__}: {exc})",
                                file=self.path, expected="a complete FITS file") from None

    def close(self) -> None:
        h = getattr(self, "_hdul", None)
        if h is not None:
            h.close()
            self._hdul = None


class Sampler:
    """The regular subsample of a rectangle of an image, gathered band by band.

    ``Sampler(shape, max_n)`` reproduces ``subsample(image, max_n)``; with ``region=(y0, y1, x0, x1)`` it
    reproduces ``subsample(image[y0:y1, x0:x1], max_n)``. :meth:`take` returns the sampled values of a band
    (rows ``r0:r0 + len(band)`` of the full-width image), in order; concatenating them over the bands gives
    the subsample.
    """

    def __init__(self, shape: tuple[int, int], max_n: int = MAX_STAT_PIXELS, region: tuple | None = None):
        h, w = shape
        self.y0, self.y1, self.x0, self.x1 = region if region is not None else (0, h, 0, w)
        self.rw = self.x1 - self.x0
        n = (self.y1 - self.y0) * self.rw
        self.step = math.ceil(n / max_n) if n > max_n else 1
        self.n = n

    def take(self, r0: int, band: np.ndarray) -> np.ndarray:
        r1 = r0 + band.shape[0]
        a, b = max(r0, self.y0), min(r1, self.y1)
        if a >= b:
            return band[:0, 0].copy()
        sub = band[a - r0:b - r0, self.x0:self.x1]
        if self.step == 1:
            return sub.ravel().copy()
        first = (a - self.y0) * self.rw  # flat index (in the region) of the band's first value
        start = (-first) % self.step
        if sub.flags.c_contiguous:
            return sub.ravel()[start::self.step].copy()
        k = np.arange(start, sub.shape[0] * self.rw, self.step)  # no copy of the whole region
        return sub[k // self.rw, k % self.rw]


class Gather:
    """Accumulates the pieces :meth:`Sampler.take` returns (one list per name); ``get(name)`` concatenates."""

    def __init__(self):
        self.parts: dict[str, list] = {}

    def add(self, name: str, values: np.ndarray) -> None:
        self.parts.setdefault(name, []).append(values)

    def get(self, name: str) -> np.ndarray:
        p = self.parts.get(name, [])
        return np.concatenate(p) if p else np.zeros(0)


class BandStore:
    """A 2-D image in a temporary raw file (native byte order), written and read by rows.

    Parameters
    ----------
    shape : (rows, cols)
    dtype : numpy dtype (float32 for the maps, float64 for intermediate values)
    folder : where the temporary file goes (default: the system's temporary folder)

    ``np.asarray(store)`` reads the whole image (small frames, tests); :meth:`close` deletes the file.
    """

    def __init__(self, shape, dtype=np.float32, folder=None):
        self.shape = (int(shape[0]), int(shape[1]))
        self.dtype = np.dtype(dtype)
        fd, self.path = tempfile.mkstemp(prefix="newtsim_band_", suffix=".raw", dir=folder)
        self._f = os.fdopen(fd, "w+b")
        try:  # unlinked at once (POSIX): the space comes back when the file is closed, even if killed
            os.unlink(self.path)
            self._unlinked = True
        except OSError:
            self._unlinked = False
        self._f.truncate(self.shape[0] * self.shape[1] * self.dtype.itemsize)
        self.ndim = 2
        self.size = self.shape[0] * self.shape[1]

    def write(self, r0: int, band: np.ndarray) -> None:
        band = np.ascontiguousarray(band, dtype=self.dtype)
        self._f.seek(r0 * self.shape[1] * self.dtype.itemsize)
        self._f.write(band.tobytes())

    def rows(self, a: int, b: int) -> np.ndarray:
        a, b = max(0, a), min(self.shape[0], b)
        self._f.seek(a * self.shape[1] * self.dtype.itemsize)
        n = (b - a) * self.shape[1]
        out = np.frombuffer(self._f.read(n * self.dtype.itemsize), dtype=self.dtype, count=n)
        return out.reshape(b - a, self.shape[1]).copy()

    def __array__(self, dtype=None, copy=None):
        a = self.rows(0, self.shape[0])
        return a if dtype is None else a.astype(dtype)

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None
            if not self._unlinked:
                try:
                    os.unlink(self.path)
                except OSError:
                    pass

    def __del__(self):
        try:
            self.close()
        except OSError:  # interpreter shutdown: the file may already be gone
            pass


class ArrayRows:
    """An in-memory 2-D array with the ``rows(a, b)`` interface of :class:`FitsRows` and :class:`BandStore`."""

    def __init__(self, a: np.ndarray):
        self.a = np.asarray(a)
        self.shape = self.a.shape
        self.dtype = self.a.dtype

    def rows(self, a: int, b: int) -> np.ndarray:
        return self.a[max(0, a):min(self.shape[0], b)]


def as_rows(x):
    """A ``rows(a, b)`` source: stores and readers as they are, arrays wrapped in :class:`ArrayRows`."""
    return x if hasattr(x, "rows") else ArrayRows(x)


def halo_rows(sigma_px: float, truncate: float = 4.0) -> int:
    """Rows either side that a Gaussian filter of ``sigma_px`` reaches (scipy's radius ``int(truncate sigma + 0.5)``)."""
    return int(truncate * float(sigma_px) + 0.5)
