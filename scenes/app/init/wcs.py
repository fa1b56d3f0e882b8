"""A header's WCS, in any common form, as the scene's pointing, roll, plate scale, parity and SIP.

Forms read: TAN, TAN-SIP (with or without the ``-SIP`` suffix on CTYPE when ``A_ORDER`` is present), TPV (PV
polynomials, wcslib), the CD matrix or PC + CDELT (or CROTA2 + CDELT), values written as strings. The
header's mapping pixel -> sky is sampled over the frame and re-expressed in the scene's own convention
(:func:`scenes.projection.tan_wcs`: optical axis at the frame centre, CD = s [[p cos r, -p sin r],
[sin r, cos r]], Calabretta & Greisen 2002, eq. 1), the rest of the mapping as SIP polynomials (Shupe et al.
2005) fitted to the sampled points by least squares, in unbinned sensor pixels about the axis.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from scenes.measured import clean_header

from .header import number  # noqa: F401


def has_wcs(header) -> bool:
    return all(k in header for k in ("CTYPE1", "CTYPE2", "CRVAL1", "CRVAL2")) or "CD1_1" in header and "CRVAL1" in header


def header_wcs(header):
    """``astropy.wcs.WCS`` of the cleaned header (celestial part), warnings silenced."""
    from astropy.wcs import WCS

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WCS(clean_header(header), relax=True).celestial


def _tangent(ra0: float, dec0: float, ra, dec) -> tuple[np.ndarray, np.ndarray]:
    """Gnomonic projection [deg] of (ra, dec) about (ra0, dec0) (Calabretta & Greisen 2002, eq. 54)."""
    a0, d0 = math.radians(ra0), math.radians(dec0)
    a, d = np.radians(ra), np.radians(dec)
    cosc = math.sin(d0) * np.sin(d) + math.cos(d0) * np.cos(d) * np.cos(a - a0)
    xi = np.cos(d) * np.sin(a - a0) / cosc
    eta = (math.cos(d0) * np.sin(d) - math.sin(d0) * np.cos(d) * np.cos(a - a0)) / cosc
    return np.degrees(xi), np.degrees(eta)


def _design(u, v, order: int) -> tuple[np.ndarray, list[tuple[int, int]]]:
    terms = [(p, q) for p in range(order + 1) for q in range(order + 1 - p) if p + q >= 1]
    return np.stack([u ** p * v ** q for p, q in terms], axis=1), terms


def scene_geometry(header, shape: tuple[int, int], binning: int = 1, sip_order: int = 3,
                   min_shift_px: float = 0.05, n: int = 25) -> dict:
    """Pointing, roll, scale, parity and SIP of the scene whose optical axis is the frame centre.

    Returns ``ra_deg, dec_deg`` (sky at the frame centre), ``roll_deg``, ``scale_arcsec`` (per output pixel),
    ``parity`` (sign of det CD), ``sip`` (a ``[telescope.sip]`` table in unbinned sensor pixels, or None when
    the largest departure from the pure TAN mapping is below ``min_shift_px``), ``max_distortion_px`` and
    ``fit_rms_px`` (the polynomial's residual against the header's mapping), ``ctype``, ``form``."""
    h, w = shape
    wcs = header_wcs(header)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ra_c, dec_c = (float(v) for v in wcs.all_pix2world([[cx, cy]], 0)[0])
        xs = np.linspace(-0.5, w - 0.5, n)
        ys = np.linspace(-0.5, h - 0.5, n)
        X, Y = np.meshgrid(xs, ys)
        ra, dec = wcs.all_pix2world(X.ravel(), Y.ravel(), 0)
    xi, eta = _tangent(ra_c, dec_c, ra, dec)
    u, v = X.ravel() - cx, Y.ravel() - cy
    order = max(1, sip_order)
    M, terms = _design(u, v, order)
    cxi, *_ = np.linalg.lstsq(M, xi, rcond=None)
    ceta, *_ = np.linalg.lstsq(M, eta, rcond=None)
    J = np.array([[cxi[terms.index((1, 0))], cxi[terms.index((0, 1))]],
                  [ceta[terms.index((1, 0))], ceta[terms.index((0, 1))]]])
    det = float(np.linalg.det(J))
    parity = 1 if det > 0 else -1
    scale = math.sqrt(abs(det)) * 3600.0
    roll = math.degrees(math.atan2(J[1, 0], J[1, 1]))
    s = scale / 3600.0
    c, si = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    cd = np.array([[parity * s * c, -parity * s * si], [s * si, s * c]])
    # ideal offsets in the scene's pixels, and their departure from the pixel offsets
    ideal = np.linalg.solve(cd, np.stack([xi, eta]))
    da, db = ideal[0] - u, ideal[1] - v
    ca, *_ = np.linalg.lstsq(M, da, rcond=None)
    cb, *_ = np.linalg.lstsq(M, db, rcond=None)
    fit_rms = float(np.sqrt(np.mean((M @ ca - da) ** 2 + (M @ cb - db) ** 2)))
    shift = float(np.max(np.hypot(da, db)))
    ctype = [str(header.get("CTYPE1", "")), str(header.get("CTYPE2", ""))]
    form = ("TPV" if "TPV" in ctype[0] else "TAN-SIP" if ("A_ORDER" in header or "SIP" in ctype[0]) else
            ctype[0][5:].strip("-") or "TAN")
    matrix = "CD" if "CD1_1" in header else "PC+CDELT" if "PC1_1" in header else "CROTA+CDELT" if "CROTA2" in header else "CDELT"
    sip = None
    if shift >= min_shift_px:
        b = float(binning)
        sip = {"order": order}
        r_max = math.hypot(w, h) / 2
        for (p, q), a_, b_ in zip(terms, ca, cb):
            k = b ** (p + q - 1)  # output (binned) pixels -> unbinned sensor pixels: A_pq / b^(p+q-1)
            # a term that moves no pixel of the frame by 1e-4 px is left out (fit noise of a pure TAN)
            if abs(a_) * r_max ** (p + q) > 1e-4:
                sip[f"a_{p}_{q}"] = float(f"{a_ / k:.10g}")
            if abs(b_) * r_max ** (p + q) > 1e-4:
                sip[f"b_{p}_{q}"] = float(f"{b_ / k:.10g}")
        used = [int(key.split("_")[1]) + int(key.split("_")[2]) for key in sip if key[:2] in ("a_", "b_")]
        sip["order"] = max(used, default=1)
        sip["reverse_order"] = min(sip["order"] + 2, 9)
    return {"ra_deg": ra_c % 360.0, "dec_deg": dec_c, "roll_deg": roll, "scale_arcsec": scale, "parity": parity,
            "sip": sip, "max_distortion_px": shift, "fit_rms_px": fit_rms, "ctype": ctype, "form": form,
            "matrix": matrix, "crpix": [float(v) for v in wcs.wcs.crpix]}
