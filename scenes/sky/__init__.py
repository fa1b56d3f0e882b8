"""The sky's stars: catalogues (built-in Gaia DR3, Gaia archive, user tables), faint-star model, photometry.

Entry points: :func:`stars_in_field` (a :class:`StarTable` for a field and epoch) and
:func:`star_photon_rate` / :func:`star_electron_rate` (blackbody photometry normalised to Gaia G).
docs/scenes_catalog.md describes the sources, models, equations, references, licences and checks.
"""

from .catalog import stars_in_field
from .colours import teff_from_b_v, teff_from_bp_rp
from .starcounts import (
    bs80_integral_counts_v,
    expected_synthetic_count,
    field_model,
    synthetic_stars,
)
from .starflux import (
    gaia_g_passband,
    photon_flux_density,
    star_electron_rate,
    star_photon_rate,
)
from .table import CatalogError, StarTable

__all__ = [
    "CatalogError", "StarTable", "bs80_integral_counts_v", "expected_synthetic_count", "field_model",
    "gaia_g_passband", "photon_flux_density", "star_electron_rate", "star_photon_rate", "stars_in_field",
    "synthetic_stars", "teff_from_b_v", "teff_from_bp_rp",
]
