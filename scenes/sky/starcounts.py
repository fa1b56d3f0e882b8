"""Faint-star population: a Bahcall-Soneira Galaxy model in Gaia G, and a seeded, tiled sampler.

Physics
-------
The number of stars per square degree and per magnitude towards galactic coordinates (l, b) is the
fundamental equation of stellar statistics (Bahcall & Soneira 1980, ApJS 44, 73):

    A(m) dm = omega * sum_c  integral phi_c(M) rho_c(r, M) / rho_c(sun) r^2 dr,   M = m - 5 log10(r / 10 pc) - a(r)

with the structure of Bahcall & Soneira (1980, "BS80"):

* disk: rho = exp(-(R - R0) / h) exp(-|z| / H(M_V)), R0 = 8 kpc, h = 3.5 kpc, H = 90 pc for M_V <= 2.3
  rising linearly to 325 pc at M_V >= 5.1 (dwarfs) and H = 250 pc for giants;
* disk luminosity function (BS80, fitted to Wielen's function): phi(M) = n* 10^(beta (M - M*)) /
  [1 + 10^(-(alpha - beta) delta (M - M*))]^(1/delta), n* = 4.03e-3 pc^-3 mag^-1, M* = +1.28, alpha = 0.74,
  beta = 0.04, 1/delta = 3.40, for -7 <= M_V <= 16; the fraction of giants is 0.8 for M_V <= 1.5, falling
  linearly to 0 at M_V = 3 (red clump and giant branch);
* spheroid: de Vaucouleurs law rho ~ exp(-7.669 (a/r_e)^(1/4)) (a/r_e)^(-7/8), r_e = 2.67 kpc, axis ratio
  0.8, local spheroid/disk density 1/400 (BS80: 1/800-1/500); its luminosity function is the disk one for
  M_V >= 3.5 (main sequence below the turn-off) and half of it brighter (giant branch and horizontal
  branch). These two spheroid numbers were set so that the spheroid term reproduces the spheroid part of
  BS80's analytic fit (eq. B1, below) at the galactic pole within 25 % for V = 14-22;
* extinction (BS80): a_V(r) = 0.15 mag csc|b| [1 - exp(-r sin|b| / 100 pc)], i.e. a 100-pc dust
  layer, 1.5 mag/kpc in the plane, 0.15 mag towards the poles.

The model is evaluated directly in Gaia G: each component maps M_V to G - V and BP-RP with the mean dwarf
sequence of Pecaut & Mamajek (2013) (``scenes.sky.colours``) or, for giants, BP-RP = 1.2 with the G - V
relation of Riello et al. (2021); A_G = 0.884 A_V and E(BP-RP) = 0.432 A_V (R_G = 2.740, R_BP - R_RP =
1.339, R_V = 3.1: Casagrande & VandenBerg 2018, MNRAS 479, L102). Each synthetic star's colour is therefore
that of its own absolute magnitude, population and reddening.

Checks (docs/scenes_catalog.md has the numbers): the model reproduces BS80's analytic fit (eq. B1,
:func:`bs80_integral_counts_v`, valid for |b| >= 20 deg) within ~20 % for V = 12-20 at |b| = 20-90 deg, and
the Gaia DR3 counts of the built-in catalogue to G = 10 within ~25 % in every latitude band, the galactic
plane included.

Sampler
-------
The sky is cut into fixed tiles (declination bands of ``TILE_DEG``, each split in right ascension into
near-square cells). Every tile and every 1-mag slab of G has its own random stream,
``SeedSequence([seed, band, cell, slab, MODEL_VERSION])``: a star's existence does not depend on the field
asked for or on the magnitude limit, so overlapping or dithered fields, or a deeper limit, see the same
faint stars. Within a tile the count is Poisson with the model's mean at the tile centre, positions are
uniform on the sphere, G is drawn from the differential counts (0.05-mag bins, uniform inside a bin) and
the colour from the model's distance/population mix at that G.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .astrometry import angular_distance_deg, in_cone, to_galactic
from .colours import (
    GIANT_BP_RP,
    dwarf_colours_from_mv,
    g_minus_v_from_bp_rp,
    teff_from_bp_rp,
)
from .table import StarTable

MODEL_VERSION = 1
TILE_DEG = 0.5
G_BIN = 0.05  # magnitude resolution of the model's differential counts
SYNTHETIC_ID_BASE = -(10 ** 12)

# --- Galaxy model parameters (module docstring) -------------------------------------------------------
R0_KPC = 8.0
DISK_SCALE_LENGTH_KPC = 3.5
GIANT_SCALE_HEIGHT_KPC = 0.250
SPHEROID_RE_KPC = 2.67
SPHEROID_AXIS_RATIO = 0.8
SPHEROID_NORM = 1.0 / 400.0
SPHEROID_TURNOFF_MV = 3.5
SPHEROID_GIANT_FRACTION = 0.5
EXT_POLE_MAG = 0.15
DUST_SCALE_HEIGHT_KPC = 0.100
A_G_PER_A_V = 0.884
E_BPRP_PER_A_V = 0.432
MV_MIN, MV_MAX = -7.0, 16.0

_R_KPC = np.logspace(-3.0, 2.0, 241)  # 1 pc .. 100 kpc
_DLNR = np.log(_R_KPC[1] / _R_KPC[0])
_DEG2_SR = (np.pi / 180.0) ** 2


def disk_luminosity_function(mv) -> np.ndarray:
    """BS80 disk luminosity function phi(M_V) [stars pc^-3 mag^-1] (BS80, fitted to Wielen's data)."""
    m = np.asarray(mv, dtype=float)
    n_star, m_star, alpha, beta, inv_delta = 4.03e-3, 1.28, 0.74, 0.04, 3.40
    x = m - m_star
    phi = n_star * 10 ** (beta * x) / (1 + 10 ** (-(alpha - beta) / inv_delta * x)) ** inv_delta
    return np.where((m >= MV_MIN) & (m <= MV_MAX), phi, 0.0)


def dwarf_scale_height_kpc(mv) -> np.ndarray:
    """BS80 disk scale height of main-sequence stars [kpc]: 90 pc (M_V <= 2.3) to 325 pc (M_V >= 5.1)."""
    return np.interp(mv, [2.3, 5.1], [0.090, 0.325])


def giant_fraction(mv) -> np.ndarray:
    """Fraction of disk stars of absolute magnitude M_V that are giants (0.8 up to M_V = 1.5, 0 from 3)."""
    return np.interp(mv, [1.5, 3.0], [0.8, 0.0])


@dataclass(frozen=True)
class _Component:
    """A population tabulated on a uniform grid of absolute magnitude in the band (G or V).

    ``lf[k]`` is the number of stars pc^-3 per magnitude *in the band* at ``m0 + k * dm`` (the luminosity
    function times dM_V/dM_band), ``mv`` the matching M_V, ``bp_rp0`` the intrinsic colour.
    """

    name: str
    m0: float
    dm: float
    mv: np.ndarray
    bp_rp0: np.ndarray
    lf: np.ndarray
    disk: bool
    giant: bool


_DM_TAB = 0.005


def _tabulate(name, mv, m_band, bp_rp0, lf, disk, giant) -> _Component:
    """Resample a population (monotonic M_V -> M_band) on a uniform M_band grid."""
    grid = np.arange(m_band[0], m_band[-1], _DM_TAB)
    mv_g = np.interp(grid, m_band, mv)
    jac = np.interp(grid, m_band, np.gradient(mv, m_band))  # dM_V / dM_band
    return _Component(name, float(grid[0]), _DM_TAB, mv_g, np.interp(grid, m_band, bp_rp0),
                      np.interp(grid, m_band, lf) * jac, disk, giant)


def _components(band: str) -> tuple[_Component, ...]:
    mv = np.arange(MV_MIN, MV_MAX + 1e-9, 0.01)
    phi = disk_luminosity_function(mv)
    fg = giant_fraction(mv)
    g_v_dwarf, c_dwarf = dwarf_colours_from_mv(mv)
    g_v_giant = float(g_minus_v_from_bp_rp(GIANT_BP_RP))
    giant = mv <= 3.0
    sd = mv >= SPHEROID_TURNOFF_MV
    sg = mv < SPHEROID_TURNOFF_MV
    if band == "G":
        m_dwarf, m_giant = mv + g_v_dwarf, mv + g_v_giant
    else:
        m_dwarf, m_giant = mv, mv
    c_giant = np.full(mv.shape, GIANT_BP_RP)
    return (
        _tabulate("disk dwarfs", mv, m_dwarf, c_dwarf, phi * (1 - fg), True, False),
        _tabulate("disk giants", mv[giant], m_giant[giant], c_giant[giant], (phi * fg)[giant], True, True),
        _tabulate("spheroid dwarfs", mv[sd], m_dwarf[sd], c_dwarf[sd], SPHEROID_NORM * phi[sd], False, False),
        _tabulate("spheroid giants", mv[sg], m_giant[sg], c_giant[sg],
                  SPHEROID_NORM * SPHEROID_GIANT_FRACTION * phi[sg], False, True),
    )


_COMPONENTS = {"G": _components("G"), "V": _components("V")}


def extinction_v(r_kpc, b_deg) -> np.ndarray:
    """BS80 extinction a_V(r) [mag] to distance ``r_kpc`` at latitude ``b_deg`` (100-pc dust layer)."""
    r = np.asarray(r_kpc, dtype=float)
    sb = abs(np.sin(np.radians(b_deg)))
    if sb < 1e-6:
        return EXT_POLE_MAG * r / DUST_SCALE_HEIGHT_KPC
    return EXT_POLE_MAG / sb * -np.expm1(-r * sb / DUST_SCALE_HEIGHT_KPC)


def _geometry(l_deg: float, b_deg: float):
    lr, br = np.radians(l_deg), np.radians(b_deg)
    r = _R_KPC
    x = R0_KPC - r * np.cos(br) * np.cos(lr)
    y = -r * np.cos(br) * np.sin(lr)
    z = r * np.sin(br)
    big_r = np.hypot(x, y)
    disk_radial = np.exp(-(big_r - R0_KPC) / DISK_SCALE_LENGTH_KPC)

    def devauc(a):
        s = np.maximum(a, 1e-3) / SPHEROID_RE_KPC
        return np.exp(-7.669 * s ** 0.25) / s ** 0.875

    sph = devauc(np.sqrt(big_r ** 2 + (z / SPHEROID_AXIS_RATIO) ** 2)) / devauc(np.array(R0_KPC))
    vol_pc3 = _DEG2_SR * (r * 1e3) ** 3 * _DLNR  # per deg^2 per ln-r step
    a_v = extinction_v(r, b_deg)
    mu = 5 * np.log10(r * 100.0)
    return np.abs(z), disk_radial, sph, vol_pc3, a_v, mu


@dataclass
class FieldModel:
    """The model's stars towards one direction, tabulated on (distance, G) for one population each.

    ``weight[c][i, j]`` is the expected number of stars per square degree of component ``c`` at distance
    ``_R_KPC[i]`` with G in the bin ``g_edges[j] .. g_edges[j+1]``; ``bp_rp[c][i, j]`` their observed colour.
    """

    l_deg: float
    b_deg: float
    g_edges: np.ndarray
    weight: list  # of (n_r, n_g) arrays
    bp_rp: list

    @property
    def per_bin(self) -> np.ndarray:
        """Expected stars per square degree in each G bin."""
        return sum(w.sum(axis=0) for w in self.weight)

    def integral(self, g_max: float) -> float:
        """Stars per square degree with G <= g_max (linear inside a bin)."""
        cum = np.concatenate([[0.0], np.cumsum(self.per_bin)])
        return float(np.interp(g_max, self.g_edges, cum))


def field_model(l_deg: float, b_deg: float, g_min: float, g_max: float, band: str = "G") -> FieldModel:
    """Tabulate the Galaxy model towards (l, b) for ``g_min <= m < g_max`` in 0.05-mag bins.

    Parameters
    ----------
    l_deg, b_deg : float
        Galactic longitude and latitude [deg].
    g_min, g_max : float
        Magnitude range [mag]; bins are aligned on multiples of 0.05 mag.
    band : {"G", "V"}
        Gaia G (default) or Johnson V (for the comparison with BS80's fit, which is in V).

    Returns
    -------
    FieldModel
    """
    lo = np.floor(g_min / G_BIN + 1e-9) * G_BIN
    hi = np.ceil(g_max / G_BIN - 1e-9) * G_BIN
    edges = np.round(np.arange(lo, hi + G_BIN / 2, G_BIN), 6)
    centres = 0.5 * (edges[1:] + edges[:-1])
    absz, disk_radial, sph, vol, a_v, mu = _geometry(l_deg, b_deg)
    a_band = a_v * (A_G_PER_A_V if band == "G" else 1.0)
    e_col = E_BPRP_PER_A_V * a_v
    weights, colours = [], []
    for comp in _COMPONENTS[band]:
        m_abs = centres[None, :] - mu[:, None] - a_band[:, None]  # (n_r, n_g) absolute magnitude in the band
        k = np.rint((m_abs - comp.m0) / comp.dm).astype(np.int64)
        inside = (k >= 0) & (k < len(comp.lf))
        k = np.clip(k, 0, len(comp.lf) - 1)
        if comp.disk:
            h = GIANT_SCALE_HEIGHT_KPC if comp.giant else dwarf_scale_height_kpc(comp.mv[k])
            dens = disk_radial[:, None] * np.exp(-absz[:, None] / h)
        else:
            dens = sph[:, None]
        weights.append(np.where(inside, vol[:, None] * dens * comp.lf[k] * G_BIN, 0.0))
        colours.append(comp.bp_rp0[k] + e_col[:, None])
    return FieldModel(float(l_deg), float(b_deg), edges, weights, colours)


def bs80_integral_counts_v(v_mag, l_deg, b_deg) -> np.ndarray:
    """Stars per square degree brighter than V: Bahcall & Soneira (1980) analytic fit, Appendix B, eq. (B1).

    ``N = C1 10^(beta (m - m*)) / [1 + 10^(alpha (m - m*))]^delta / [sin b (1 - mu cot b cos l)]^(3 - 5 gamma)
    + C2 10^(eta (m - m+)) / [1 + 10^(kappa (m - m+))]^lambda / (1 - cos b cos l)^sigma`` with C1 = 925,
    alpha = -0.132, beta = 0.035, delta = 3.0, m* = 15.75, C2 = 1050, kappa = -0.180, eta = 0.087,
    lambda = 2.5, m+ = 17.5, sigma = 1.45 - 0.20 cos b cos l, mu and gamma linear in m between V = 12 and
    20. Valid for |b| >= 20 deg and 4 <= V <= 22 (15 % accuracy with respect to the full model); the first
    term is the disk, the second the spheroid. Used here as the reference the Galaxy model is checked
    against, not for sampling.
    """
    m = np.asarray(v_mag, dtype=float)
    lr, br = np.radians(l_deg), np.radians(np.abs(b_deg))
    mu = np.clip(0.0075 * (m - 12.0) + 0.03, 0.03, 0.09)
    gamma = np.clip(0.04 * (12.0 - m) + 0.36, 0.04, 0.36)
    sigma = 1.45 - 0.20 * np.cos(br) * np.cos(lr)
    disk = (925.0 * 10 ** (0.035 * (m - 15.75)) / (1 + 10 ** (-0.132 * (m - 15.75))) ** 3.0
            / (np.sin(br) * (1 - mu / np.tan(br) * np.cos(lr))) ** (3 - 5 * gamma))
    spheroid = (1050.0 * 10 ** (0.087 * (m - 17.5)) / (1 + 10 ** (-0.180 * (m - 17.5))) ** 2.5
                / (1 - np.cos(br) * np.cos(lr)) ** sigma)
    return disk + spheroid


# --- tiles ----------------------------------------------------------------------------------------------

def _n_bands() -> int:
    return round(180.0 / TILE_DEG)


def _band_cells(band: int) -> int:
    dec_lo = -90.0 + band * TILE_DEG
    dec_mid = dec_lo + TILE_DEG / 2
    return max(1, int(np.ceil(360.0 * np.cos(np.radians(dec_mid)) / TILE_DEG)))


@dataclass(frozen=True)
class Tile:
    """A fixed sky cell: declination band ``band`` (of ``TILE_DEG``), right-ascension cell ``cell``."""

    band: int
    cell: int

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(ra_lo, ra_hi, dec_lo, dec_hi) [deg]."""
        n = _band_cells(self.band)
        dec_lo = -90.0 + self.band * TILE_DEG
        return self.cell * 360.0 / n, (self.cell + 1) * 360.0 / n, dec_lo, dec_lo + TILE_DEG

    @property
    def area_deg2(self) -> float:
        ra_lo, ra_hi, dec_lo, dec_hi = self.bounds
        return float(np.radians(ra_hi - ra_lo) * (np.sin(np.radians(dec_hi)) - np.sin(np.radians(dec_lo)))
                     / _DEG2_SR)

    @property
    def centre(self) -> tuple[float, float]:
        ra_lo, ra_hi, dec_lo, dec_hi = self.bounds
        s = 0.5 * (np.sin(np.radians(dec_lo)) + np.sin(np.radians(dec_hi)))
        return 0.5 * (ra_lo + ra_hi), float(np.degrees(np.arcsin(s)))


def tiles_in_cone(ra_deg: float, dec_deg: float, radius_deg: float) -> list[Tile]:
    """Every tile that may overlap the cone (conservative: tile centres within radius + one tile diagonal)."""
    out = []
    margin = TILE_DEG * 1.5
    for band in range(_n_bands()):
        dec_lo = -90.0 + band * TILE_DEG
        if dec_lo > dec_deg + radius_deg + TILE_DEG or dec_lo + TILE_DEG < dec_deg - radius_deg - TILE_DEG:
            continue
        n = _band_cells(band)
        ra_c = (np.arange(n) + 0.5) * 360.0 / n
        dec_c = dec_lo + TILE_DEG / 2
        width = 360.0 / n * np.cos(np.radians(dec_c))  # angular width of a cell [deg]
        d = angular_distance_deg(ra_deg, dec_deg, ra_c, dec_c)
        for cell in np.nonzero(d <= radius_deg + margin + width)[0]:
            out.append(Tile(band, int(cell)))
    return out


def _slab_range(g_lo: float, g_hi: float) -> range:
    return range(int(np.floor(g_lo)), int(np.ceil(g_hi)))


def tile_stars(tile: Tile, g_lo: float, g_hi: float, seed: int = 0,
               model: FieldModel | None = None) -> dict[str, np.ndarray]:
    """Draw the synthetic stars of one tile with ``g_lo < G <= g_hi``.

    Each whole 1-mag slab overlapping (g_lo, g_hi] is drawn from its own stream and then cut, so the stars
    of a tile do not depend on the limits asked for.

    Returns
    -------
    dict
        ``ra_deg, dec_deg, mag_g, bp_rp, source_id`` arrays.
    """
    slabs = _slab_range(g_lo, g_hi)
    if model is None:
        ra_c, dec_c = tile.centre
        l_c, b_c = to_galactic(ra_c, dec_c)
        model = field_model(float(l_c), float(b_c), slabs.start, slabs.stop)
    ra_lo, ra_hi, dec_lo, dec_hi = tile.bounds
    area = tile.area_deg2
    centres = 0.5 * (model.g_edges[1:] + model.g_edges[:-1])
    per_bin = model.per_bin
    out = {k: [] for k in ("ra_deg", "dec_deg", "mag_g", "bp_rp", "source_id")}
    stacked_w = np.concatenate(model.weight, axis=0)  # (n_comp * n_r, n_g)
    stacked_c = np.concatenate(model.bp_rp, axis=0)
    s_lo, s_hi = np.sin(np.radians(dec_lo)), np.sin(np.radians(dec_hi))
    for slab in slabs:
        bins = np.nonzero((centres > slab) & (centres < slab + 1))[0]
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), tile.band, tile.cell, slab + 100,
                                                            MODEL_VERSION]))
        counts = rng.poisson(per_bin[bins] * area)
        n = int(counts.sum())
        if n == 0:
            continue
        b = np.repeat(bins, counts)
        g = model.g_edges[b] + rng.random(n) * G_BIN
        # colour: (population, distance) drawn in proportion to the model's weight in the star's G bin
        colour = np.empty(n)
        u = rng.random(n)
        start = 0
        for j, c in zip(bins, counts):
            if c:
                cdf = np.cumsum(stacked_w[:, j])
                k = np.minimum(np.searchsorted(cdf, u[start:start + c] * cdf[-1], side="right"), len(cdf) - 1)
                colour[start:start + c] = stacked_c[k, j]
                start += c
        ra = ra_lo + rng.random(n) * (ra_hi - ra_lo)
        dec = np.degrees(np.arcsin(s_lo + rng.random(n) * (s_hi - s_lo)))
        keep = (g > g_lo) & (g <= g_hi)
        sid = SYNTHETIC_ID_BASE - ((tile.band * 100000 + tile.cell) * 40 + slab) * 10 ** 6 - np.arange(n)
        for key, val in zip(out, (ra, dec, g, colour, sid)):
            out[key].append(val[keep])
    return {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in out.items()}


def synthetic_stars(ra_deg: float, dec_deg: float, radius_deg: float, g_lo: float, g_hi: float,
                    epoch_jyear: float, seed: int = 0) -> StarTable:
    """Synthetic faint stars with ``g_lo < G <= g_hi`` in a cone (``source = 'synthetic'``).

    Parameters
    ----------
    ra_deg, dec_deg, radius_deg : float
        Cone centre and radius [deg].
    g_lo, g_hi : float
        Gaia G range [mag] (``g_lo`` is the completeness limit of the real catalogue used with it).
    epoch_jyear : float
        Epoch stamped on the table (synthetic stars do not move).
    seed : int
        User seed (>= 0), combined with each tile's indices; the same seed gives the same sky.
    """
    meta = {"model": f"Bahcall-Soneira Galaxy model in G (scenes.sky.starcounts v{MODEL_VERSION})",
            "tile_deg": TILE_DEG, "seed": int(seed), "g_range": (float(g_lo), float(g_hi))}
    if g_hi <= g_lo:
        return StarTable.empty(epoch_jyear, meta)
    parts = []
    for tile in tiles_in_cone(ra_deg, dec_deg, radius_deg):
        s = tile_stars(tile, g_lo, g_hi, int(seed))
        sel = in_cone(s["ra_deg"], s["dec_deg"], ra_deg, dec_deg, radius_deg)
        parts.append({k: v[sel] for k, v in s.items()})
    cols = {k: np.concatenate([p[k] for p in parts]) if parts else np.zeros(0) for k in
            ("ra_deg", "dec_deg", "mag_g", "bp_rp", "source_id")}
    n = len(cols["ra_deg"])
    nan = np.full(n, np.nan)
    return StarTable(cols["ra_deg"], cols["dec_deg"], cols["mag_g"], cols["bp_rp"], teff_from_bp_rp(cols["bp_rp"]),
                     np.full(n, "synthetic"), cols["source_id"].astype(np.int64), nan, nan.copy(),
                     epoch_jyear=epoch_jyear, meta=meta)


def expected_synthetic_count(ra_deg: float, dec_deg: float, radius_deg: float, g_lo: float, g_hi: float,
                             oversample: int = 24) -> float:
    """Model mean number of synthetic stars in a cone (tile densities times tile/cone overlap areas).

    The overlap is measured on an ``oversample`` x ``oversample`` equal-area sub-grid of each tile.
    """
    total = 0.0
    f = (np.arange(oversample) + 0.5) / oversample
    for tile in tiles_in_cone(ra_deg, dec_deg, radius_deg):
        ra_lo, ra_hi, dec_lo, dec_hi = tile.bounds
        s_lo, s_hi = np.sin(np.radians(dec_lo)), np.sin(np.radians(dec_hi))
        ra_g, s_g = np.meshgrid(ra_lo + f * (ra_hi - ra_lo), s_lo + f * (s_hi - s_lo))
        frac = in_cone(ra_g.ravel(), np.degrees(np.arcsin(s_g.ravel())), ra_deg, dec_deg, radius_deg).mean()
        if frac == 0:
            continue
        l_c, b_c = to_galactic(*tile.centre)
        m = field_model(float(l_c), float(b_c), np.floor(g_lo), np.ceil(g_hi))
        total += (m.integral(g_hi) - m.integral(g_lo)) * tile.area_deg2 * frac
    return total
