"""Charge-transfer inefficiency (CTI) of a CCD: trap species that capture charge from the packets moving
through them and release it later, into the packets that follow (a trail behind every source).

Model: the Charge Distortion Model CDM03 (Short et al. 2013, MNRAS 430, 3078, eqs. 2-6; the algorithm
Pyxel and the Gaia/Euclid pipelines use) with instant capture and the volume-driven well fill of ArCTIc
(Massey et al. 2014, MNRAS 439, 887, eq. 22):

* a packet of ``n`` electrons reaches ``rho_k (n / w)^beta`` traps of species ``k`` per pixel (``w`` the
  well depth, ``beta`` the well-fill power); empty traps within its reach capture at once;
* a filled trap releases with probability ``1 - exp(-t_d / tau_k)`` per transfer dwell ``t_d``, into the
  packet in its pixel at that time;
* a packet at row ``j`` crosses ``j + 1`` pixels on its way to the serial register; all pixels it crosses
  are represented by one trap pool of ``(j + 1) rho_k`` traps whose occupancy is carried from one packet to
  the next (CDM03's "representative pixel": exact when every pixel below a packet has seen the same packets,
  e.g. a uniform sky; the test compares it with a trap-by-trap simulation of a column).

Traps start empty at the first row of the read-out window and are filled by whatever passes: a sky
background fills them, so a star on a bright sky loses less (the trail depends on the signal and the
background). Charge is conserved: what the image loses is still in the traps at the end of the read-out
(it goes into the overscan). Each row is one vectorised step over all columns (and species): a full
ML11002 frame (4008 x 2672) takes well under a second.

Serial CTI is the same model along the rows (the serial register at column 0, ``x + 1`` transfers).

Dose model: trap densities grow linearly with the displacement damage, i.e. with the 10-MeV-equivalent
proton fluence ``Phi_10`` (NIEL scaling; Srour, Marshall & Marshall 2003, IEEE TNS 50, 653; Massey et al.
2014 measure a linear growth of the HST ACS trap densities with time in orbit)::

    rho_total = kappa A_px Phi_10

with ``A_px`` the pixel area [um^2] and ``kappa`` the damage factor. The fluence integrates the proton
environments of :mod:`detector.cosmics` (South Atlantic Anomaly for ``saa_fraction`` of the time, the
galactic cosmic rays of low Earth orbit otherwise), slowed down through ``shielding_mm_al`` of aluminium
(:func:`detector.cosmics.residual_energy_mev`) and weighted by the NIEL of silicon relative to 10 MeV
(:func:`niel_ratio`). The default ``kappa = 1e-12`` traps um^-2 per (p cm^-2) is an order-of-magnitude
value (HST ACS: ~0.2 traps per 15 um pixel per year, Massey et al. 2014, for ~1e9 p cm^-2 per year behind
HST's shielding, our own estimate): calibrate it on your own CCD. The ML11002 (KAI-11002, an interline CCD
on the ground) has no measured trap densities in the literature; on the ground its CTI is negligible, so
the effect is off unless switched on, and its default species are HST ACS's (Massey et al. 2014: release
times 0.74, 7.70 and 37.0 parallel transfers, relative densities 0.17, 0.45, 0.38, beta = 0.478) scaled to
0.1 traps per pixel in total.

CMOS sensors have no charge transfer: switching ``cti`` on for a CMOS preset is refused with one error.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field, model_validator

from ..errors import DetectorError
from ..signatures import LinearSignature, Variant
from .base import Effect, EffectParams, Stage, Tile, register_effect

#: HST ACS species (Massey et al. 2014): release times in parallel transfers and relative densities
ACS_RELEASE_TRANSFERS = (0.74, 7.70, 37.0)
ACS_RELATIVE_DENSITY = (0.17, 0.45, 0.38)
#: ML11002 parallel dwell: one row read serially at 8 MHz (4008 pixels) [s]
ML11002_PARALLEL_TRANSFER_S = 4008 / 8e6


def cti_transfer(image_e: np.ndarray, density_per_px, release_time_s, transfer_s: float, beta: float,
                 well_e: float, first_transfers: int = 1, return_trapped: bool = False):
    """Apply CTI along axis 0 (the read-out moves charge towards row 0); a new float64 array [e-].

    Parameters
    ----------
    image_e : 2-D array [e-]
        Charge per pixel; row 0 is read first.
    density_per_px : sequence of float [traps per pixel]
        Trap density of each species.
    release_time_s : sequence of float [s]
        Release time constant of each species.
    transfer_s : float [s]
        Dwell time per transfer.
    beta : float [1]
        Well-fill power: a packet of n e- reaches ``rho (n / well_e)^beta`` traps (Massey et al. 2014).
    well_e : float [e-]
        Well depth of the volume-driven fill.
    first_transfers : int
        Transfers of the packet in row 0 (its absolute row + 1 for a window).
    return_trapped : bool
        Also return the charge [e-] left in the traps per column (what goes into the overscan).

    Algorithm (per row ``j``, all columns and species at once; Short et al. 2013 with instant capture)::

        released_k = trapped_k (1 - exp(-t_d / tau_k));  n += sum_k released_k
        target_k   = rho_k (j + first_transfers) (n / w)^beta
        captured_k = max(target_k - trapped_k, 0), scaled down together if their sum exceeds n
    """
    rho = np.asarray(density_per_px, np.float64)[:, None]
    decay = np.exp(-float(transfer_s) / np.asarray(release_time_s, np.float64))[:, None]
    img = np.array(image_e, dtype=np.float64)
    ny, nx = img.shape
    trapped = np.zeros((rho.shape[0], nx))
    inv_w = 1.0 / float(well_e)
    for j in range(ny):
        n = img[j]
        rel = trapped * (1.0 - decay)
        trapped -= rel
        n += rel.sum(axis=0)
        target = (rho * (j + first_transfers)) * np.power(np.maximum(n, 0.0) * inv_w, beta)[None, :]
        cap = np.maximum(target - trapped, 0.0)
        tot = cap.sum(axis=0)
        over = tot > n
        if over.any():
            cap[:, over] *= (n[over] / tot[over])[None, :]
            tot = cap.sum(axis=0)
        trapped += cap
        n -= tot
    return (img, trapped.sum(axis=0)) if return_trapped else img


def niel_ratio(energy_mev) -> np.ndarray:
    """NIEL of protons in silicon relative to 10 MeV [1] (approximate fit, +-30 %).

    ``(E / 10 MeV)^-0.45`` from 10 to 150 MeV and constant above (the nuclear-elastic plateau), ``(E / 10)^-0.8``
    below 10 MeV: a coarse fit to the proton NIEL curve of Summers et al. 1993 (IEEE TNS 40, 1372) and Jun
    et al. 2003 (IEEE TNS 50, 1924), where NIEL falls from ~3.6e-3 MeV cm^2/g at 10 MeV to ~1.2e-3 at
    150-1000 MeV. Good enough for a fluence-to-trap-density estimate whose damage factor is itself uncertain
    by a factor of a few.
    """
    e = np.maximum(np.asarray(energy_mev, np.float64), 1e-3)
    hi = np.power(np.minimum(e, 150.0) / 10.0, -0.45)
    lo = np.power(e / 10.0, -0.8)
    return np.where(e < 10.0, lo, hi)


def fluence_10mev_p_cm2(days: float, saa_fraction: float = 0.05, shielding_mm_al: float = 5.0,
                        spectral_index: float = 2.7) -> float:
    """10-MeV-equivalent proton fluence [p cm^-2] after ``days`` in a low Earth orbit.

    ``Phi_10 = t [f F_saa <R>_saa + (1 - f) F_leo <R>_leo]`` with the fluxes and lower energies of
    :data:`detector.cosmics.ENVIRONMENTS` (``saa``: trapped protons at the anomaly's peak, ``leo``:
    galactic cosmic rays), an ``E^-spectral_index`` spectrum, and ``<R>`` the spectrum average of
    :func:`niel_ratio` after ``shielding_mm_al`` of aluminium at normal incidence (CSDA,
    :func:`detector.cosmics.residual_energy_mev`; stopped protons do no damage in the sensor). The SAA
    flux is its peak (conservative: an average pass sees about a third of it).
    """
    from ..cosmics import ENVIRONMENTS, residual_energy_mev

    x_g_cm2 = 2.70 * shielding_mm_al / 10.0
    total = 0.0
    for env, frac in (("saa", saa_fraction), ("leo", 1.0 - saa_fraction)):
        e = ENVIRONMENTS[env]
        # quadrature of the power law in its cumulative variable (100 equal-probability energies)
        u = (np.arange(100) + 0.5) / 100
        en = e.energy_min_mev * (1.0 - u) ** (-1.0 / (spectral_index - 1.0))
        out = residual_energy_mev(en, x_g_cm2, "Al") if x_g_cm2 > 0 else en
        r = np.where(out > 0, niel_ratio(out), 0.0)
        total += frac * e.flux_per_cm2_s * float(r.mean())
    return total * days * 86400.0


class CTIParams(EffectParams):
    density_per_px: list[float] | None = Field(
        None, description="trap density of each parallel species [traps/pixel] (default: 0.1 in total, HST ACS "
                          "proportions, or from the dose model when days_in_orbit > 0)")
    release_time_s: list[float] | None = Field(
        None, description="release time constant of each species [s] (default: HST ACS's 0.74, 7.70, 37.0 "
                          "transfers)")
    parallel_transfer_s: float = Field(ML11002_PARALLEL_TRANSFER_S, gt=0, le=1.0,
                                       description="dwell per parallel transfer (one serial row read) [s]")
    beta: float = Field(0.478, gt=0, le=1, description="well-fill power (Massey et al. 2014) [1]")
    well_e: float | None = Field(None, gt=0, description="well depth of the fill law (default: full well) [e-]")
    serial_density_per_px: list[float] = Field(default_factory=list,
                                               description="serial-register trap densities [traps/pixel]")
    serial_release_time_s: list[float] = Field(default_factory=list, description="serial release times [s]")
    serial_transfer_s: float = Field(1.25e-7, gt=0, le=1e-3, description="dwell per serial transfer [s]")
    days_in_orbit: float = Field(0.0, ge=0, le=1e5, description="dose model: days in a low Earth orbit [d]")
    saa_fraction: float = Field(0.05, ge=0, le=1, description="dose model: time fraction in the SAA [1]")
    shielding_mm_al: float = Field(5.0, ge=0, le=200, description="dose model: aluminium shielding [mm]")
    damage_traps_per_um2_per_p_cm2: float = Field(
        1e-12, ge=0, le=1e-6, description="dose model: traps per um^2 of pixel per 10-MeV-eq. p/cm^2 [1]")

    @model_validator(mode="after")
    def _check(self):
        for a, b in (("density_per_px", "release_time_s"), ("serial_density_per_px", "serial_release_time_s")):
            da, db = getattr(self, a), getattr(self, b)
            if da is not None and db is not None and len(da) != len(db):
                raise ValueError(f"{a} and {b} must have the same length")
            if any(v < 0 for v in (da or [])) or any(v <= 0 for v in (db or [])):
                raise ValueError(f"{a} must be >= 0 and {b} > 0")
        if self.days_in_orbit > 0 and self.density_per_px is not None:
            raise ValueError("give density_per_px or days_in_orbit (the dose model), not both")
        return self


def _cti_variants(res):
    """CTI trails of the model's own charge for one species of unit density: ``CTI(Q) - Q`` is linear in
    the density to first order; variants over the release time (fractions of the parallel dwell)."""
    if res.sensor.kind != "ccd":
        return
    g = np.float32(res.gain)
    q = res.charge_e.astype(np.float64)
    well = res.sensor.full_well_e * res.pixel_sum
    y_first = int(res.ys[0]) + 1 if res.ys.size else 1
    unit = 0.01
    for tr in (0.74, 7.7, 37.0):
        tau = tr * ML11002_PARALLEL_TRANSFER_S
        t = ((cti_transfer(q, [unit], [tau], ML11002_PARALLEL_TRANSFER_S, 0.478, well, y_first) - q) / unit
             / g).astype(np.float32)

        def to_params(c, tau=tau):
            return ({"density_per_px": [round(float(c[0]), 5)], "release_time_s": [float(f"{tau:.4g}")]}
                    if 0 < c[0] < 100 else None)

        yield Variant([t], to_params, f"release {tr:g} transfers")


_CTI_SIGNATURE = LinearSignature(
    _cti_variants,
    lambda p, res: (f"charge trailing behind sources away from the read-out register, "
                    f"{p['density_per_px'][0]:.3g} traps/pixel releasing in {1e3 * p['release_time_s'][0]:.3g} ms: "
                    "charge-transfer inefficiency (radiation-damaged CCD)"),
    pattern="one-sided trails along the columns", extra_k=1)


@register_effect
class CTI(Effect):
    """Charge-transfer inefficiency of a CCD: trap species capture charge from passing packets and release it
    into later ones (trails away from the register). A packet of n e- reaches rho_k (n/w)^beta traps per
    pixel, a filled trap releases with probability 1 - exp(-t_d/tau_k) per transfer (CDM03, Short et al.
    2013 MNRAS 430 3078; ArCTIc well fill, Massey et al. 2014 MNRAS 439 887). Parallel and serial; densities
    given or from a proton-dose model (days_in_orbit). CCD only. Details: detector/effects/cti.py."""

    name = "cti"
    scaling = "signal"
    identity = {"density_per_px": [0.0, 0.0, 0.0]}
    stages = (Stage.COUPLING,)
    Params = CTIParams
    signature = _CTI_SIGNATURE
    halo_rows = None  # a whole column
    coupling_order = 1

    def setup(self) -> None:
        if self.sensor.kind != "ccd":
            raise DetectorError(f"cti on the CMOS sensor {self.sensor.name!r}", key="effects.cti",
                                expected="a CCD preset (a CMOS pixel is read in place, no charge transfer)")
        p = self.params
        taus = p.release_time_s or [t * p.parallel_transfer_s for t in ACS_RELEASE_TRANSFERS]
        if p.density_per_px is not None:
            dens = list(p.density_per_px)
        else:
            if p.days_in_orbit > 0:
                total = self.density_from_dose()
            else:
                total = 0.1
            rel = ACS_RELATIVE_DENSITY if len(taus) == 3 else [1.0 / len(taus)] * len(taus)
            dens = [total * r for r in rel]
        if len(dens) != len(taus):
            raise DetectorError("density_per_px and release_time_s differ in length", key="effects.cti",
                                expected="one release time per species")
        self.density, self.tau = dens, taus

    def density_from_dose(self) -> float:
        """Total parallel trap density [traps/pixel] from the dose model (module docstring)."""
        p = self.params
        phi = fluence_10mev_p_cm2(p.days_in_orbit, p.saa_fraction, p.shielding_mm_al)
        return p.damage_traps_per_um2_per_p_cm2 * self.sensor.pixel_pitch_um ** 2 * phi

    def couple(self, tile: Tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        well = p.well_e or self.sensor.full_well_e
        out = charge_e
        if any(self.density):
            out = cti_transfer(out, self.density, self.tau, p.parallel_transfer_s, p.beta, well,
                               first_transfers=tile.y0 - pad_top + 1)
        if any(p.serial_density_per_px):
            out = cti_transfer(out.T, p.serial_density_per_px, p.serial_release_time_s, p.serial_transfer_s,
                               p.beta, well, first_transfers=tile.x0 + 1).T
        return np.asarray(out, np.float32)
