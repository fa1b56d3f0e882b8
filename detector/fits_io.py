"""FITS writing and reading: streamed, atomic, astropy/DS9/AstroImageJ-readable.

The primary HDU is written band by band as the chain produces it (the 151-Mpixel IMX411 frame never has to
sit in memory twice), into a temporary file in the target folder that is renamed only once complete:
nothing is ever half-written. Unsigned 16-bit frames use the FITS convention BITPIX = 16, BZERO = 32768.
Truth tables and images follow as extensions.
"""

from __future__ import annotations

import io
import os
import tempfile
import warnings
from pathlib import Path
from typing import Iterable

import numpy as np
from astropy.io import fits

from .errors import DetectorError

BLOCK = 2880

_BITPIX = {np.dtype(np.uint16): (16, 32768), np.dtype(np.int16): (16, None), np.dtype(np.uint32): (32, 2 ** 31),
           np.dtype(np.int32): (32, None), np.dtype(np.float32): (-32, None), np.dtype(np.float64): (-64, None)}


def _to_disk(arr: np.ndarray) -> bytes:
    """Big-endian bytes of a band in its FITS representation (unsigned shifted by BZERO)."""
    dt = arr.dtype
    if dt == np.uint16:
        return (arr ^ np.uint16(0x8000)).view(np.int16).astype(">i2").tobytes()
    if dt == np.uint32:
        return (arr ^ np.uint32(0x80000000)).view(np.int32).astype(">i4").tobytes()
    return arr.astype(dt.newbyteorder(">")).tobytes()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def primary_header(shape: tuple[int, int], dtype, cards: fits.Header | dict | None = None) -> fits.Header:
    """A primary header for an image of ``shape`` (rows, cols) and ``dtype``, plus ``cards``."""
    bitpix, bzero = _BITPIX[np.dtype(dtype)]
    h = fits.Header()
    h["SIMPLE"] = True
    h["BITPIX"] = bitpix
    h["NAXIS"] = 2
    h["NAXIS1"] = shape[1]
    h["NAXIS2"] = shape[0]
    h["EXTEND"] = True
    if bzero is not None:
        h["BSCALE"] = 1
        h["BZERO"] = bzero
    if cards is not None:
        items = cards.cards if isinstance(cards, fits.Header) else cards.items()
        for card in items:
            key, val, *com = card if isinstance(card, tuple) else (card.keyword, card.value, card.comment)
            if key in ("COMMENT", "HISTORY"):
                h.add_comment(val) if key == "COMMENT" else h.add_history(val)
            else:
                h[key] = (val, com[0]) if com and com[0] else val
    return h


def _extension_bytes(hdus: list) -> bytes:
    """Serialized extension HDUs (an empty primary is written to a buffer and its block dropped)."""
    if not hdus:
        return b""
    buf = io.BytesIO()
    fits.HDUList([fits.PrimaryHDU(), *hdus]).writeto(buf)
    raw = buf.getvalue()
    assert len(fits.PrimaryHDU().header.tostring()) == BLOCK
    return raw[BLOCK:]


def table_hdu(name: str, table: np.ndarray) -> fits.BinTableHDU:
    hdu = fits.BinTableHDU(data=table, name=name)
    return hdu


def write_streamed(path: str | os.PathLike, header: fits.Header, bands: Iterable[tuple[int, int, np.ndarray]],
                   shape: tuple[int, int], dtype, extensions: list | None = None) -> Path:
    """Write a FITS file whose primary image arrives as ``(row0, row1, band)`` in order; atomic.

    Parameters
    ----------
    path : output file
    header : the primary header (from :func:`primary_header`)
    bands : iterator of (first row, end row, array of those rows)
    shape, dtype : of the whole image
    extensions : HDUs appended after the image (truth tables, expected electrons ...)
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise DetectorError(f"output folder {folder} does not exist", key="output", expected="an existing folder")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(header.tostring().encode("ascii"))
            expected_row = 0
            nbytes = 0
            for r0, r1, band in bands:
                if r0 != expected_row or band.shape != (r1 - r0, shape[1]) or band.dtype != np.dtype(dtype):
                    raise RuntimeError(f"band rows {r0}:{r1} {band.shape} {band.dtype} out of order or shape")
                raw = _to_disk(band)
                f.write(raw)
                nbytes += len(raw)
                expected_row = r1
            if expected_row != shape[0]:
                raise RuntimeError(f"image ended at row {expected_row} of {shape[0]}")
            f.write(b"\0" * (-nbytes % BLOCK))
            f.write(_extension_bytes(list(extensions or [])))
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the file the user's usual mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_image(path, image: np.ndarray, cards=None, extensions: list | None = None) -> Path:
    """Write a whole in-memory image (atomic)."""
    header = primary_header(image.shape, image.dtype, cards)
    return write_streamed(path, header, [(0, image.shape[0], image)], image.shape, image.dtype, extensions)


def read_image(path: str | os.PathLike, *, key: str | None = None, role: str = "",
               dtype=np.float64) -> tuple[np.ndarray, fits.Header]:
    """Read the first 2-D image of a FITS file (primary or, for tile-compressed files, an extension).

    Parameters
    ----------
    key : the scene/CLI key the file came from, for messages
    role : what the file is ("bias", "dark" ...), for messages
    dtype : type of the returned data (BZERO/BSCALE applied); ``None`` keeps the stored type

    Returns the data and its header: the image HDU's cards over the primary's (a compressed image keeps
    EXPTIME and friends in the primary). Raises :class:`DetectorError` naming the file for a missing,
    corrupt, truncated or non-image file.
    """
    p = Path(path)
    what = f"{role} file" if role else "file"
    if p.is_dir():
        raise DetectorError(f"{what} is a directory", key=key, file=str(p), expected="a FITS file")
    if p.exists() and not p.is_file():
        raise DetectorError(f"{what} is not a regular file", key=key, file=str(p), expected="a FITS file")
    if not p.is_file():
        raise DetectorError(f"{what} not found", key=key, file=str(p), expected="an existing FITS file")
    try:
        with warnings.catch_warnings():
            # non-standard cards are common in camera files: not our user's problem; truncation is
            warnings.simplefilter("ignore", fits.verify.VerifyWarning)
            warnings.filterwarnings("error", message=".*truncated.*")
            data, header = _first_image(p, what)
    except DetectorError:
        raise
    except Warning as exc:
        raise DetectorError(f"{what} is truncated ({exc})", key=key, file=str(p),
                            expected="a complete FITS file") from None
    except Exception as exc:  # astropy raises OSError/ValueError/TypeError for damaged files
        raise DetectorError(f"{what} cannot be read as FITS ({type(exc).__name__}: {exc})", key=key,
                            file=str(p), expected="a complete FITS file") from None
    return (data if dtype is None else data.astype(dtype, copy=False)), header


def _first_image(p: Path, what: str) -> tuple[np.ndarray, fits.Header]:
    """The first HDU holding a 2-D image (singleton axes dropped), with the primary's cards beneath its own."""
    with fits.open(p, memmap=False) as hdul:
        for hdu in hdul:
            if hdu.is_image or isinstance(hdu, fits.CompImageHDU):
                data = hdu.data
                if data is not None and np.squeeze(data).ndim == 2:
                    header = hdul[0].header.copy()
                    if hdu is not hdul[0]:
                        header.extend(hdu.header, update=True)
                    return np.asarray(np.squeeze(data)), header
    raise DetectorError(f"no 2-D image in the {what}", file=str(p), expected="a 2-D image HDU")
