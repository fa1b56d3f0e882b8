"""Gaia DR3 from the ESA Gaia archive (astroquery), cached on disk so a repeated field needs no network.

The query (ADQL, run with ``astroquery.gaia.GaiaClass.launch_job_async``) selects the cone, padded by
``PM_PAD_DEG`` so that stars moving into the field by the requested epoch are included, and the magnitude
limit::

    SELECT source_id, ra, dec, pmra, pmdec, parallax, ref_epoch, phot_g_mean_mag, bp_rp
    FROM gaiadr3.gaia_source
    WHERE 1 = CONTAINS(POINT('ICRS', ra, dec), CIRCLE('ICRS', <ra>, <dec>, <radius + pad>))
      AND phot_g_mean_mag <= <mag_limit>

The result is written as a FITS table ``<cache_dir>/gaia-<hash>.fits`` where ``<hash>`` is the first 16 hex
digits of the SHA-256 of the query text (centre rounded to 1e-6 deg, radius and limit to 1e-4), so the same
field always maps to the same file; :func:`gaia_cache_path` gives it. The cache is read before anything
else; astroquery is imported only on a cache miss (importing ``astroquery.gaia`` already contacts the
archive). The default cache directory is ``~/.cache/newtsim/gaia``, or ``$NEWTSIM_CACHE_DIR/gaia``.

Gaia DR3 positions are at ``ref_epoch`` = J2016.0; they are propagated to the requested epoch with the
linear space motion of ``scenes.sky.astrometry``. Stars without astrometry (2-parameter solutions) have NaN
proper motion and stay at their catalogue position. Gaia DR3 is complete to G ~ 20.7 (``GAIA_ARCHIVE_LIMIT_G``)
and misses some stars brighter than G ~ 3 (saturation).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from .astrometry import in_cone, propagate
from .colours import teff_from_bp_rp
from .table import CatalogError, StarTable

GAIA_TABLE = "gaiadr3.gaia_source"
GAIA_ARCHIVE_LIMIT_G = 20.7
PM_PAD_DEG = 0.05  # 180 arcsec: Barnard's star moves this far in 17 years


def default_cache_dir() -> Path:
    """``$NEWTSIM_CACHE_DIR/gaia`` when that variable is set (as for the optics cache), else ``~/.cache/newtsim/gaia``."""
    root = os.environ.get("NEWTSIM_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "newtsim") / "gaia"


def gaia_query(ra_deg: float, dec_deg: float, radius_deg: float, mag_limit: float) -> str:
    """The ADQL query for a cone (padded for proper motion) and a G limit."""
    return ("SELECT source_id, ra, dec, pmra, pmdec, parallax, ref_epoch, phot_g_mean_mag, bp_rp "
            f"FROM {GAIA_TABLE} "
            f"WHERE 1 = CONTAINS(POINT('ICRS', ra, dec), CIRCLE('ICRS', {ra_deg % 360.0:.6f}, {dec_deg:.6f}, "
            f"{radius_deg + PM_PAD_DEG:.4f})) AND phot_g_mean_mag <= {mag_limit:.4f}")


def gaia_cache_path(ra_deg: float, dec_deg: float, radius_deg: float, mag_limit: float,
                    cache_dir: str | Path | None = None) -> Path:
    """The cache file of a field: ``<cache_dir>/gaia-<sha256(query)[:16]>.fits``."""
    key = hashlib.sha256(gaia_query(ra_deg, dec_deg, radius_deg, mag_limit).encode()).hexdigest()[:16]
    return Path(cache_dir if cache_dir is not None else default_cache_dir()) / f"gaia-{key}.fits"


def _column(table, name: str, file: str) -> np.ndarray:
    lower = {c.lower(): c for c in table.colnames}
    if name not in lower:
        raise CatalogError(f"cached Gaia table has no column '{name}'", file=file,
                           expected="columns source_id, ra, dec, pmra, pmdec, ref_epoch, phot_g_mean_mag, bp_rp")
    col = table[lower[name]]
    return np.ma.filled(np.ma.asarray(col, dtype=float), np.nan) if name != "source_id" else \
        np.ma.filled(np.ma.asarray(col), 0).astype(np.int64)


def fetch_gaia(ra_deg: float, dec_deg: float, radius_deg: float, mag_limit: float, path: Path):
    """Run the archive query and write the cache file (network needed); returns the astropy Table."""
    query = gaia_query(ra_deg, dec_deg, radius_deg, mag_limit)
    try:
        from astroquery.gaia import GaiaClass

        gaia = GaiaClass(show_server_messages=False)
        table = gaia.launch_job_async(query).get_results()
    except ImportError:
        raise CatalogError("catalog 'gaia' needs the astroquery package and network access", file=str(path),
                           expected="pip install astroquery, or catalog='builtin'") from None
    except Exception as exc:  # noqa: BLE001 -- network, HTTP, TAP or SSL errors: one clear message
        raise CatalogError(f"Gaia archive query failed ({type(exc).__name__}: {exc}); no cached result at "
                           f"{path}", key="sky.catalog",
                           expected="network access to the Gaia archive once (the result is then cached), "
                                    "or catalog='builtin' (offline)") from None
    table.meta["QUERY"] = query
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.fits")
    table.write(tmp, format="fits", overwrite=True)
    os.replace(tmp, path)
    return table


def gaia_archive_stars(ra_deg: float, dec_deg: float, radius_deg: float, mag_limit: float, epoch_jyear: float,
                       cache_dir: str | Path | None = None) -> StarTable:
    """Gaia DR3 stars in a cone at ``epoch_jyear`` from the cache, else from the archive (then cached).

    Parameters
    ----------
    ra_deg, dec_deg, radius_deg : float
        Cone centre and radius [deg].
    mag_limit : float
        Faintest G [mag].
    epoch_jyear : float
        Epoch of the returned positions [Julian year].
    cache_dir : path, optional
        Cache directory (default :func:`default_cache_dir`).

    Returns
    -------
    StarTable
        ``source = 'gaia-archive'``.
    """
    from astropy.table import Table

    path = gaia_cache_path(ra_deg, dec_deg, radius_deg, mag_limit, cache_dir)
    if path.is_file():
        try:
            table = Table.read(path, format="fits")
        except (OSError, ValueError) as exc:
            raise CatalogError(f"cannot read the cached Gaia table ({exc})", file=str(path),
                               expected="a FITS table; delete it to query the archive again") from None
        origin = "cache"
    else:
        table = fetch_gaia(ra_deg, dec_deg, radius_deg, mag_limit, path)
        origin = "archive"
    file = str(path)
    sid = _column(table, "source_id", file)
    ra, dec = _column(table, "ra", file), _column(table, "dec", file)
    pmra, pmdec = _column(table, "pmra", file), _column(table, "pmdec", file)
    ref = _column(table, "ref_epoch", file)
    ref = np.where(np.isfinite(ref), ref, 2016.0)
    mag, bp_rp = _column(table, "phot_g_mean_mag", file), _column(table, "bp_rp", file)
    ra_t, dec_t = propagate(ra, dec, pmra, pmdec, ref, epoch_jyear)
    keep = in_cone(ra_t, dec_t, ra_deg, dec_deg, radius_deg) & (mag <= mag_limit)
    n = len(sid)
    out = StarTable(ra_t, dec_t, mag, bp_rp, teff_from_bp_rp(bp_rp), np.full(n, "gaia-archive"), sid, pmra, pmdec,
                    epoch_jyear=epoch_jyear,
                    meta={"catalog": f"Gaia DR3 archive ({GAIA_TABLE})", "cache_file": file, "origin": origin})
    return out[keep]
