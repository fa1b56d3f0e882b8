"""User star tables (CSV or FITS) as a catalogue: ``[sky] catalog = "my_stars.csv"``.

Columns (case-insensitive; the first name found is used):

==============  ==========================================================  ========
quantity        accepted names                                              unit
==============  ==========================================================  ========
RA (required)   ra_deg, ra, raj2000, ra_icrs                                deg
Dec (required)  dec_deg, dec, dej2000, de_icrs, decj2000                    deg
G (required)    mag_g, phot_g_mean_mag, gmag, g, mag                        mag
pm RA           pmra, pmra_mas_yr  (mu_alpha* = mu_alpha cos dec)           mas/yr
pm Dec          pmdec, pmdec_mas_yr                                         mas/yr
epoch           ref_epoch, epoch, epoch_jyear  (needed with pmra/pmdec)     Julian yr
colour          bp_rp                                                       mag
temperature     teff_k, teff                                                K
identifier      source_id, id                                               integer
==============  ==========================================================  ========

Teff comes from ``teff_k`` if given, else from ``bp_rp`` (``scenes.sky.colours``), else the fallback
temperature. Rows outside the cone or fainter than the limit are dropped. The table is taken as complete:
no synthetic stars are added to it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .astrometry import in_cone, propagate
from .colours import teff_from_bp_rp
from .table import CatalogError, StarTable

ALIASES = {
    "ra": ("ra_deg", "ra", "raj2000", "ra_icrs"),
    "dec": ("dec_deg", "dec", "dej2000", "de_icrs", "decj2000"),
    "mag": ("mag_g", "phot_g_mean_mag", "gmag", "g", "mag"),
    "pmra": ("pmra", "pmra_mas_yr"),
    "pmdec": ("pmdec", "pmdec_mas_yr"),
    "epoch": ("ref_epoch", "epoch", "epoch_jyear"),
    "bp_rp": ("bp_rp",),
    "teff": ("teff_k", "teff"),
    "id": ("source_id", "id"),
}
CSV_SUFFIXES = (".csv", ".ecsv", ".txt", ".dat")
FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz")


def read_user_table(path: str | Path):
    """Read a CSV/ECSV or FITS table with astropy; errors name the file."""
    from astropy.table import Table

    p = Path(path).expanduser()
    file = str(path)
    name = p.name.lower()
    if not p.is_file():
        raise CatalogError("star catalogue file not found", key="sky.catalog", file=file,
                           expected="'builtin', 'gaia' or the path of a CSV/FITS star table")
    if name.endswith(FITS_SUFFIXES):
        fmt = "fits"
    elif name.endswith(".ecsv"):
        fmt = "ascii.ecsv"
    elif name.endswith(CSV_SUFFIXES):
        fmt = "ascii.csv"
    else:
        raise CatalogError(f"unknown star table format '{p.suffix or p.name}'", key="sky.catalog", file=file,
                           expected="a .csv/.ecsv or .fits/.fit table")
    try:
        table = Table.read(p, format=fmt, **({"comment": "#"} if fmt == "ascii.csv" else {}))
    except Exception as exc:  # noqa: BLE001 -- astropy raises many types for malformed files
        raise CatalogError(f"cannot read the star table ({type(exc).__name__}: {exc})", key="sky.catalog",
                           file=file, expected=f"a valid {'FITS' if fmt == 'fits' else 'CSV'} table") from None
    return table


def _find(table, quantity: str) -> str | None:
    lower = {c.lower(): c for c in table.colnames}
    for alias in ALIASES[quantity]:
        if alias in lower:
            return lower[alias]
    return None


def _floats(table, col: str, file: str) -> np.ndarray:
    try:
        return np.ma.filled(np.ma.asarray(table[col], dtype=float), np.nan)
    except (TypeError, ValueError):
        raise CatalogError(f"column '{col}' is not numeric", key="sky.catalog", file=file,
                           expected="numbers") from None


def user_stars(path: str | Path, ra_deg: float, dec_deg: float, radius_deg: float, mag_limit: float,
               epoch_jyear: float) -> StarTable:
    """Stars of a user CSV/FITS table within a cone, at ``epoch_jyear`` (``source = 'user'``).

    Parameters
    ----------
    path : path
        The table (columns in the module docstring).
    ra_deg, dec_deg, radius_deg : float
        Cone centre and radius [deg].
    mag_limit : float
        Faintest G kept [mag].
    epoch_jyear : float
        Epoch of the returned positions [Julian year]; proper motions are applied from ``ref_epoch``.
    """
    file = str(path)
    table = read_user_table(path)
    cols = {}
    for quantity in ("ra", "dec", "mag"):
        cols[quantity] = _find(table, quantity)
        if cols[quantity] is None:
            raise CatalogError(f"missing column for {quantity.upper() if quantity != 'mag' else 'G magnitude'}",
                               key="sky.catalog", file=file,
                               expected="one of " + ", ".join(ALIASES[quantity]) +
                                        f" (columns found: {', '.join(table.colnames) or 'none'})")
    ra = _floats(table, cols["ra"], file)
    dec = _floats(table, cols["dec"], file)
    mag = _floats(table, cols["mag"], file)
    n = len(ra)
    bad = ~(np.isfinite(ra) & np.isfinite(dec) & np.isfinite(mag)) | (np.abs(dec) > 90)
    if bad.any():
        row = int(np.nonzero(bad)[0][0]) + 1
        raise CatalogError(f"row {row}: RA, Dec and G must be finite numbers with |Dec| <= 90", key="sky.catalog",
                           file=file, expected=f"valid values in columns {cols['ra']}, {cols['dec']}, {cols['mag']}")
    pm_cols = (_find(table, "pmra"), _find(table, "pmdec"))
    if any(pm_cols) and not all(pm_cols):
        raise CatalogError("proper motion needs both pmra and pmdec", key="sky.catalog", file=file,
                           expected="columns pmra and pmdec [mas/yr]")
    pmra = _floats(table, pm_cols[0], file) if pm_cols[0] else np.full(n, np.nan)
    pmdec = _floats(table, pm_cols[1], file) if pm_cols[1] else np.full(n, np.nan)
    epoch_col = _find(table, "epoch")
    if pm_cols[0] and epoch_col is None:
        raise CatalogError("proper motions given without their reference epoch", key="sky.catalog", file=file,
                           expected="a column " + " or ".join(ALIASES["epoch"]) + " [Julian year, e.g. 2016.0]")
    ref = _floats(table, epoch_col, file) if epoch_col else np.full(n, epoch_jyear)
    ref = np.where(np.isfinite(ref), ref, epoch_jyear)
    bp_rp_col, teff_col, id_col = _find(table, "bp_rp"), _find(table, "teff"), _find(table, "id")
    bp_rp = _floats(table, bp_rp_col, file) if bp_rp_col else np.full(n, np.nan)
    teff = _floats(table, teff_col, file) if teff_col else np.full(n, np.nan)
    if np.any(teff[np.isfinite(teff)] <= 0):
        raise CatalogError(f"column '{teff_col}' has non-positive temperatures", key="sky.catalog", file=file,
                           expected="Teff in kelvin > 0")
    teff = np.where(np.isfinite(teff), teff, teff_from_bp_rp(bp_rp))
    if id_col:
        try:
            sid = np.asarray(table[id_col], dtype=np.int64)
        except (TypeError, ValueError):
            sid = np.arange(n, dtype=np.int64)
    else:
        sid = np.arange(n, dtype=np.int64)
    ra_t, dec_t = propagate(ra, dec, pmra, pmdec, ref, epoch_jyear)
    keep = in_cone(ra_t, dec_t, ra_deg, dec_deg, radius_deg) & (mag <= mag_limit)
    out = StarTable(ra_t, dec_t, mag, bp_rp, teff, np.full(n, "user"), sid, pmra, pmdec, epoch_jyear=epoch_jyear,
                    meta={"catalog": f"user table {file}", "rows_in_file": n})
    return out[keep]
