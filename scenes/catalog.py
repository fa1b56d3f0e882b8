"""Catalogue layer of the scenes package (stable import path); the implementation is ``scenes.sky``.

``from scenes.catalog import stars_in_field, star_photon_rate, StarTable, CatalogError``
"""

from .sky import (
    CatalogError,
    StarTable,
    star_electron_rate,
    star_photon_rate,
    stars_in_field,
    teff_from_b_v,
    teff_from_bp_rp,
)

__all__ = ["CatalogError", "StarTable", "star_electron_rate", "star_photon_rate", "stars_in_field",
           "teff_from_b_v", "teff_from_bp_rp"]
