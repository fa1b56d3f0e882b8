"""Reading a measured frame the way a scene says (``[measured]``: HDU, trim section; ``[mask]``: masked pixels).

Compare and diagnose read the frame through :func:`read_measured`: the image HDU (``[measured] hdu``, default
the first image), cut to ``[measured] trim`` (a raw frame's light-sensitive pixels, without its prescan and
overscan), with the pixels of ``[mask] file`` (and of a mask given on the command line) set to NaN, which the
comparison leaves out of the fit and every statistic (docs/reliability.md).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from detector.errors import DetectorError

_NUMERIC = re.compile(r"^(CRVAL|CRPIX|CDELT|CROTA|CD\d_|PC\d_|PV\d_|A_|B_|AP_|BP_|EQUINOX|EPOCH|LONPOLE|LATPOLE|"
                      r"A_ORDER|B_ORDER|AP_ORDER|BP_ORDER|CD\d|PC\d)")


def clean_header(header):
    """A copy of ``header`` with numbers written as strings turned into numbers (WCS keywords), and
    ``-SIP`` added to a TAN CTYPE when the header carries SIP polynomials (``A_ORDER``): astropy then reads
    the polynomials without its multi-line notice about inconsistent SIP information."""
    h = header.copy()
    for card in list(h.keys()):
        if _NUMERIC.match(card) and isinstance(h[card], str):
            v = _number(h[card])
            if v is not None:
                h[card] = v
    if "A_ORDER" in h:
        for k in ("CTYPE1", "CTYPE2"):
            c = str(h.get(k, ""))
            if c.endswith("-TAN"):
                h[k] = c + "-SIP"
    return h



def _number(v):
    try:
        f = float(str(v).strip().replace("D", "E"))
    except ValueError:
        return None
    return f if np.isfinite(f) else None


def measured_wcs(header):
    """The celestial ``astropy.wcs.WCS`` of a measured header (:func:`clean_header`), warnings silenced; None
    when it has no usable WCS."""
    from astropy.wcs import WCS

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return WCS(clean_header(header), relax=True).celestial
    except Exception:  # noqa: BLE001  (a broken WCS is reported as absent)
        return None


_SECTION = re.compile(r"^\s*\[\s*(\d+)\s*:\s*(\d+)\s*,\s*(\d+)\s*:\s*(\d+)\s*\]\s*$")


def parse_section(text: str) -> tuple[slice, slice]:
    """A FITS/IRAF section ``"[x1:x2,y1:y2]"`` (1-based, inclusive) as numpy slices ``(rows, cols)``.

    Raises ValueError naming the form expected."""
    m = _SECTION.match(str(text))
    if not m:
        raise ValueError(f"{text!r}: expected a FITS section '[x1:x2,y1:y2]' (1-based, inclusive)")
    x1, x2, y1, y2 = (int(v) for v in m.groups())
    if x1 < 1 or y1 < 1 or x2 < x1 or y2 < y1:
        raise ValueError(f"{text!r}: expected 1 <= x1 <= x2 and 1 <= y1 <= y2")
    return slice(y1 - 1, y2), slice(x1 - 1, x2)


def section_text(rows: slice, cols: slice) -> str:
    """The FITS section of numpy slices (inverse of :func:`parse_section`)."""
    return f"[{cols.start + 1}:{cols.stop},{rows.start + 1}:{rows.stop}]"


def read_hdu(path, hdu=None, *, role: str = "measured", key: str | None = None, dtype=np.float64):
    """The image of HDU ``hdu`` (index or EXTNAME; None: the first image, :func:`detector.fits_io.read_image`)
    as ``dtype`` and its header (the primary's cards under the HDU's)."""
    from detector.fits_io import read_image

    if hdu is None:
        return read_image(path, key=key, role=role, dtype=dtype)
    from astropy.io import fits

    p = Path(path)
    if not p.is_file():
        raise DetectorError(f"{role} file not found", key=key, file=str(p), expected="an existing FITS file")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with fits.open(p, memmap=False) as hdul:
            try:
                h = hdul[hdu]
            except (KeyError, IndexError):
                raise DetectorError(f"no HDU {hdu!r}", key=key, file=str(p),
                                    expected=f"an HDU index 0..{len(hdul) - 1} or an EXTNAME") from None
            if h.data is None or h.data.ndim != 2:
                raise DetectorError(f"HDU {hdu!r} holds no 2-D image", key=key, file=str(p), expected="an image HDU")
            header = hdul[0].header.copy()
            for card in h.header.cards:
                if card.keyword not in ("", "COMMENT", "HISTORY"):
                    header[card.keyword] = (card.value, card.comment)
            data = np.asarray(h.data, dtype=dtype)
    return data, header


def read_mask(path, shape: tuple[int, int], hdu=None, *, key: str = "mask.file") -> np.ndarray:
    """A mask FITS (non-zero = masked) as a boolean array of ``shape``; a wrong size is an error naming the file."""
    m, _ = read_hdu(path, hdu, role="mask", key=key, dtype=np.float64)
    if m.shape != tuple(shape):
        raise DetectorError(f"mask is {m.shape[1]}x{m.shape[0]} pixels", key=key, file=str(path),
                            expected=f"{shape[1]}x{shape[0]} as the measured frame (after [measured] trim)")
    return np.isfinite(m) & (m != 0) | ~np.isfinite(m)


def read_measured(path, scene=None, *, extra_mask: str | None = None, dtype=np.float32,
                  key: str = "MEASURED") -> tuple[np.ndarray, object, dict]:
    """The measured frame as the scene reads it: its ``[measured]`` HDU and trim section, its ``[mask]`` (and
    ``extra_mask``, a mask file given on the command line) as NaN. Returns (data, header, notes) with
    ``notes["masked_pixels"]`` the count of pixels the masks removed and ``notes["trim"]`` the section."""
    meas = getattr(scene, "measured", None)
    data, header = read_hdu(path, getattr(meas, "hdu", None), role="measured", key=key, dtype=np.float64)
    notes: dict = {"masked_pixels": 0, "trim": None}
    if meas is not None and meas.trim:
        rows, cols = parse_section(meas.trim)
        if rows.stop > data.shape[0] or cols.stop > data.shape[1]:
            raise DetectorError(f"trim section {meas.trim} lies outside the {data.shape[1]}x{data.shape[0]} frame",
                                key="measured.trim", file=str(path), expected="a section inside the frame")
        data = data[rows, cols]
        notes["trim"] = meas.trim
    masks = []
    mcfg = getattr(scene, "mask", None)
    if mcfg is not None:
        for f in [mcfg.file] if isinstance(mcfg.file, str) else mcfg.file:
            masks.append(read_mask(f, data.shape, mcfg.hdu))
    if extra_mask is not None:
        masks.append(read_mask(extra_mask, data.shape, key="--mask"))
    if masks:
        m = np.logical_or.reduce(masks)
        notes["masked_pixels"] = int(m.sum())
        data = np.where(m, np.nan, data)
        notes["mask"] = m
    return data.astype(dtype, copy=False), header, notes


def with_mask(scene, mask_path: str | None):
    """``scene`` with the mask file ``mask_path`` (a command line's ``--mask``, relative to the working
    directory) added to its ``[mask]`` (the union of the two is masked); ``scene`` itself when None."""
    if mask_path is None:
        return scene
    import os

    from .scene import MaskCfg, check_scene

    p = os.path.abspath(os.path.expanduser(mask_path))
    if not os.path.isfile(p):
        raise DetectorError("mask file not found", key="--mask", file=p, expected="a FITS image, non-zero = masked")
    old = scene.mask
    files = [] if old is None else ([old.file] if isinstance(old.file, str) else list(old.file))
    scene.mask = MaskCfg(file=[*files, p], hdu=None if old is None else old.hdu)
    check_scene(scene)
    return scene


def scene_mask(scene, shape: tuple[int, int]) -> np.ndarray | None:
    """The union of the scene's ``[mask]`` files over a frame of ``shape`` (None without a mask)."""
    mcfg = getattr(scene, "mask", None)
    if mcfg is None:
        return None
    files = [mcfg.file] if isinstance(mcfg.file, str) else mcfg.file
    return np.logical_or.reduce([read_mask(f, shape, mcfg.hdu) for f in files])
