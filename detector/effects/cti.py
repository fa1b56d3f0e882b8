"""Charge-transfer inefficiency (CTI) of a CCD: trap species that capture charge from the packets moving
through them and release it later, into the packets that follow (a trail behind every source).

Model: ArCTIc's well-fill model (Massey et al. 2014, MNRAS 439, 887, arXiv:1401.1151; ArCTIc, the Algorithm
for Charge Transfer Inefficiency correction, github.com/jkeger/arctic, its README and src/trap_managers.cpp)
with instant capture:

* a packet of ``n`` electrons fills the fractional volume ``V(n) = ((n - d) / (w - d))^beta`` of a pixel
  (``w`` the full well, ``d`` the notch, ``beta`` the well-fill power); species ``k`` has ``rho_k`` traps per
  pixel spread evenly in volume; the empty traps below ``V(n)`` capture at once;
* a filled trap releases with probability ``1 - exp(-t_d / tau_k)`` per transfer dwell ``t_d``, into the
  packet in its pixel at that time;
* the occupancy is tracked per volume level (ArCTIc's "watermarks"): a small packet after a large one refills
  only the levels it reaches, which have emptied since, and leaves the higher ones to keep releasing;
* every pixel's traps are empty before its first transfer; a packet at row ``j`` crosses ``j + 1`` pixels.

``express`` sets the cost: 0 follows every pixel's traps on their own (identical to ArCTic with express 0,
to 1e-12 on tests/data/peers/arctic); ``E >= 1`` follows ``E`` groups of pixels along the column, each as one
pool in which a volume level holds the traps of the pixels that the packet which last filled it had
crossed: exact to first order in the CTI (the loss of a packet and its trail, with the packet's own
depletion along the column neglected inside a group), the error falling as ``1 / E``. Each row is one
vectorised step over all columns. Charge is conserved in both: what the image loses is still in the traps
at the end of the read-out (it goes into the overscan).

Serial CTI is the same model along the rows (the serial register at column 0, ``x + 1`` transfers), after
the parallel transfer (as ArCTIc).

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
#: largest number of per-pixel trap pools (express=0) the adapter accepts (<= 1 GB of watermarks)
EXACT_MAX_POOLS = 400_000
#: ML11002 parallel dwell: one row read serially at 8 MHz (4008 pixels) [s]
ML11002_PARALLEL_TRANSFER_S = 4008 / 8e6


def cloud_volume_fraction(n_e, well_e: float, beta: float, notch_e: float = 0.0) -> np.ndarray:
    """Fractional volume of the pixel that a packet of ``n_e`` electrons reaches [1] (ArCTIc's well fill).

    ``V(n) = clip((n - d) / (w - d), 0, 1)^beta`` for ``n > d`` and 0 otherwise, with ``w`` the full well
    [e-], ``d`` the notch depth [e-] and ``beta`` the well-fill power (the volume-driven well filling of
    Massey et al. 2014, MNRAS 439, 887; ArCTIc's ``CCDPhase.cloud_fractional_volume_from_electrons`` with a
    notch >= 0 and no first-electron fill, src/ccd.cpp).
    """
    x = (np.asarray(n_e, np.float64) - notch_e) / (well_e - notch_e)
    return np.power(np.clip(x, 0.0, 1.0), beta)


class _Watermarks:
    """Trap occupancy per volume level for a batch of independent trap pools (ArCTIc's watermarks).

    Each pool holds a stack of watermarks ordered by volume, highest (oldest) first: slot ``s`` covers the
    fractional volumes ``[top[s + 1], top[s]]`` with the trapped charge ``cum[s] - cum[s - 1]`` of each
    species spread evenly over it (``cum``: cumulative from the first slot). A packet that reaches ``v``
    overwrites every level below ``v``, so the levels below it are the most recently filled: the stack's
    end. Slots 0 and 1 are empty sentinels above every volume; slots after the last are stale; the last
    slot's ``cum`` is ``total`` (kept only there). Charge is stored divided by ``gain`` (one factor
    per species, common to all pools), so release, which empties the same fraction of every level, is one
    multiplication of ``gain``. Arrays are flat and slot-major (``top``: ``slot * n + pool``, ``cum``:
    ``(slot * n + pool) * k + species``) so that one fancy index reads or writes a slot of every pool and
    species, the species of a pool side by side.
    """

    def __init__(self, n_pools: int, density_per_px, decay, capacity: int):
        self.k = len(density_per_px)
        self.rho = np.asarray(density_per_px, np.float64)
        self.decay = np.asarray(decay, np.float64)
        self.n = int(n_pools)
        self.capacity = max(int(capacity), 6)
        top = np.zeros((self.capacity + 1, self.n))
        top[0], top[1] = 3.0, 2.0
        self.top = top.reshape(-1)
        self.cum = np.zeros((self.capacity + 1) * self.k * self.n)
        self.last = np.arange(self.n) + self.n  # flat index (into top) of each pool's last slot
        self.total = np.zeros((self.k, self.n))
        self.gain = np.ones(self.k)
        self.species = np.arange(self.k)[:, None]

    def trapped_e(self) -> np.ndarray:
        """Charge held per pool [e-] (all species)."""
        return self.gain @ self.total

    def step(self, n_e: np.ndarray, multiplicity, well_e, beta, notch_e, per_species: bool = False) -> np.ndarray:
        """One dwell of the first ``len(n_e)`` pools with one packet each: release, then instant capture by
        ``multiplicity * rho_k`` traps per unit volume below the packet's reach. Returns the packets' change
        (released - captured) [e-], or with ``per_species`` each species' share of it (``k x len(n_e)``)."""
        b = n_e.shape[0]
        nn, kn = self.n, self.k * self.n
        top, cum, gain = self.top, self.cum, self.gain
        last, total = self.last[:b], self.total[:, :b]
        if per_species:
            released_k = (gain * (1.0 - self.decay))[:, None] * total
            released = released_k.sum(axis=0)
        else:
            released = (gain * (1.0 - self.decay)) @ total
        gain *= self.decay
        n_free = n_e + released
        v = (n_free - notch_e) * (1.0 / (well_e - notch_e)) if notch_e else n_free * (1.0 / well_e)
        np.clip(v, 1e-300, 1.0, out=v)
        v **= beta
        # pop the watermarks wholly within the packet's reach (the stack's end): ``it`` ends on the one the
        # packet reaches into (a sentinel if it is above all), ``low`` is the top of the last one popped
        popped = top[last] <= v
        it = last - popped * nn
        sel = np.flatnonzero(top[it] <= v)
        while sel.size:
            i_sel = it[sel] - nn
            it[sel] = i_sel
            sel = sel[top[i_sel] <= v[sel]]
        t_it = top[it]
        low = top[it + nn] * popped  # popped slots keep their tops until overwritten
        frac = (v - low) / (t_it - low)
        ic = it[None, :] * self.k + self.species
        c_p = cum[ic]
        c_p -= total  # the last slot's cum is ``total``: kept where nothing is popped
        c_p *= popped
        c_p += total
        ic -= kn
        c_p -= (c_p - cum[ic]) * frac  # the part of the watermark below the packet, overwritten
        ic += kn
        want = np.multiply.outer(self.rho / gain, v * multiplicity)
        want -= total
        want += c_p
        np.maximum(want, 0.0, out=want)
        captured = gain @ want
        short = captured > n_free  # not enough electrons: all levels fill part-way (ArCTIc)
        if short.any():
            f = np.where(short, np.maximum(n_free, 0.0) / np.where(short, captured, 1.0), 1.0)
            captured *= f
            want *= f
        change_k = released_k - gain[:, None] * want if per_species else None
        cum[ic] = c_p
        total += want
        it += nn
        top[it] = v
        last[:] = it
        if it.max() >= (self.capacity - 1) * nn:
            self._merge(np.flatnonzero(it >= (self.capacity - 1) * nn))
        if gain.min() < 1e-100:
            self.cum.reshape(-1, self.k)[...] *= gain[None, :]
            self.total *= gain[:, None]
            gain[:] = 1.0
        return change_k if per_species else released - captured

    def _merge(self, idx):
        """Make room in full stacks: merge the two adjacent watermarks that together span the smallest
        volume (their charge is kept and spread over both)."""
        s_cap, nn = self.capacity, self.n
        top = self.top.reshape(s_cap + 1, nn)
        cum = self.cum.reshape(s_cap + 1, nn, self.k)
        # every pool at once (the usual case: all stacks grow together) through slices, else a fancy index
        sel = slice(None) if idx.size == nn else idx
        cum[s_cap - 1, sel, :] = self.total[:, sel].T  # the last slot's cum, into the array for the shift
        t = top[:, sel]
        span = t[2:s_cap - 1] - t[4:s_cap + 1]  # pair (s, s + 1), s = 2 .. capacity - 2
        s = 2 + np.argmin(span, axis=0)
        # slot j takes slot j + 1 from the merged pair on (the same values as a gather, without the index); the
        # slots below the lowest merged pair keep theirs
        lo = int(s.min())
        j = np.arange(lo, s_cap)[:, None]
        top[lo:s_cap, sel] = np.where(j >= s + 1, t[lo + 1:], t[lo:s_cap])
        top[s_cap, sel] = 0.0
        c = cum[lo:, sel, :]
        cum[lo:s_cap, sel, :] = np.where((j >= s)[:, :, None], c[1:], c[:s_cap - lo])
        self.last[sel] -= nn


#: volume levels a pool keeps by default when pixels are grouped (``express`` >= 1; :func:`cti_transfer`)
EXPRESS_WATERMARKS = 40


def cti_transfer(image_e: np.ndarray, density_per_px, release_time_s, transfer_s: float, beta: float,
                 well_e: float, first_transfers: int = 1, return_trapped: bool = False, express: int = 1,
                 notch_e: float = 0.0, max_watermarks: int | None = None):
    """Apply CTI along axis 0 (the read-out moves charge towards row 0); a new float64 array [e-].

    ArCTIc's well-fill model (Massey et al. 2014, MNRAS 439, 887, arXiv:1401.1151; ArCTIc,
    github.com/jkeger/arctic): a packet of ``n`` e- fills the fractional volume
    ``V(n) = ((n - d) / (w - d))^beta`` of a pixel (:func:`cloud_volume_fraction`); species ``k`` has
    ``rho_k`` traps per pixel spread evenly in volume.
    At every dwell ``t_d`` in a pixel:

        release  : every filled trap empties with probability 1 - exp(-t_d / tau_k); into the packet
        capture  : every empty trap below V(n_free) fills at once (instant capture), n_free = n + released;
                   if that is more than n_free, every level fills the same fraction of the way.

    Occupancy is tracked per volume level (watermarks), so a small packet after a large one refills only
    the levels it reaches, which have emptied since. With ``express = E >= 1`` a group of pixels
    ``[a, b)`` is one pool: the packet of row ``j`` (absolute pixel ``r_j``) meets ``m_j = clip(r_j + 1 - a,
    0, b - a)`` of its pixels, and with ``T_k(h)`` the pool's trapped charge per unit volume at level ``h``

        captured_k = m_j rho_k V(n_free) - integral_0^V(n_free) T_k(h) dh,   then T_k(h < V) = m_j rho_k

    (a level holds the traps of the pixels that the packet which last filled it had crossed). Every pixel's traps are empty before its first
    transfer. The packet in row ``j`` crosses ``j + first_transfers`` pixels; what the image loses is still
    in the traps at the end (``return_trapped``): charge is conserved.

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
        Well-fill power.
    well_e : float [e-]
        Full-well depth of the fill law.
    first_transfers : int
        Transfers of the packet in row 0 (its absolute row + 1 for a window).
    return_trapped : bool
        Also return the charge [e-] left in the traps per column (what goes into the overscan).
    express : int
        0: every pixel's traps are followed on their own (exact: ArCTIc with express = 0 and empty traps for
        the first transfers; cost ~ rows^2). ``E >= 1``: the pixels are split into ``E`` groups along the
        column, each followed as one pool in which a volume level holds the traps of the pixels that the
        packet which last filled it had crossed (exact to first order in the CTI); the groups act from the
        farthest to the nearest, so each sees the packets as the farther ones left them. Cost ~ E rows.
    notch_e : float [e-]
        Well-notch depth ``d``.
    max_watermarks : int or None
        Volume levels kept per pool (default: 40; with ``express=0`` all, up to 64); when a stack is full,
        the two adjacent levels that span the smallest volume are merged (charge kept).
    """
    rho = np.asarray(density_per_px, np.float64)
    # kept above 1e-30 so that the stored charge's scale (``_Watermarks.gain``) stays finite
    decay = np.maximum(np.exp(-float(transfer_s) / np.asarray(release_time_s, np.float64)), 1e-30)
    img = np.array(image_e, dtype=np.float64, order="C")
    ny, nx = img.shape
    off = int(first_transfers) - 1
    if max_watermarks is None:
        max_watermarks = min(ny + off + 4, 64) if express == 0 else EXPRESS_WATERMARKS
    cap = int(max_watermarks) + 3
    if express == 0:
        # every pixel its own pool; the window's offset pixels see the image's packets too
        col = np.concatenate([np.zeros((off, nx)), img]) if off > 0 else img
        n_pix = col.shape[0]
        wm = _Watermarks(n_pix * nx, rho, decay, cap)
        trapped = np.zeros(nx)
        for t in range(n_pix):  # transfer t + 1: pixel p holds the packet of row p + t
            q = col[t:].reshape(-1)
            q += wm.step(q.copy(), 1.0, well_e, beta, notch_e)
            last = n_pix - t - 1  # this pixel has seen its last packet: what it holds goes to the overscan
            trapped += wm.trapped_e()[last * nx:(last + 1) * nx]
        out = col[off:] if off > 0 else col
        return (out, trapped) if return_trapped else out
    n_groups = max(1, min(int(express), ny + off))
    edges = np.linspace(0, ny + off, n_groups + 1).round().astype(int)
    rows = np.arange(ny) + off  # absolute pixel of each row
    trapped = np.zeros(nx)
    for a, b in zip(edges[-2::-1], edges[:0:-1]):  # farthest group first
        mult = np.clip(rows + 1 - a, 0, b - a).astype(np.float64)
        j0 = max(0, a - off)
        wm = _Watermarks(nx, rho, decay, cap)
        for j in range(j0, ny):
            img[j] += wm.step(img[j], mult[j], well_e, beta, notch_e)
        trapped += wm.trapped_e()
    return (img, trapped) if return_trapped else img


def cti_species_changes(image_e: np.ndarray, density_per_px, release_time_s, transfer_s: float, beta: float,
                        well_e: float, first_transfers: int = 1) -> np.ndarray:
    """Each species' share of what :func:`cti_transfer` (``express=1``) changes, ``k x ny x nx`` [e-]: the
    species act together on the packets, and the change of each dwell is split by the species that released
    and captured it. To first order in the densities the shares are the changes each species makes alone (a
    species sees the packets the others changed by a fraction of order their CTI), so one pass gives the
    diagnosis the trails of several release times at the cost of one (:func:`_cti_variants`)."""
    rho = np.asarray(density_per_px, np.float64)
    decay = np.maximum(np.exp(-float(transfer_s) / np.asarray(release_time_s, np.float64)), 1e-30)
    img = np.array(image_e, dtype=np.float64, order="C")
    ny, nx = img.shape
    off = int(first_transfers) - 1
    mult = (np.arange(ny) + off + 1).astype(np.float64)  # one pool per column: every pixel the packet crossed
    wm = _Watermarks(nx, rho, decay, EXPRESS_WATERMARKS + 3)  # as cti_transfer's pools
    out = np.empty((rho.size, ny, nx))
    for j in range(ny):
        d = wm.step(img[j], mult[j], well_e, beta, notch_e=0.0, per_species=True)
        out[:, j] = d
        img[j] += d.sum(axis=0)
    return out


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
    # beta = 1 is a physical state, not a limit of the form: a packet's volume in proportion to its charge (a
    # cloud of fixed density), the classical constant-fraction CTI (Janesick 2001, Scientific Charge-Coupled
    # Devices, SPIE PM83, ch. 5); a larger power would thin the cloud as it fills
    beta: float = Field(0.478, gt=0, le=1, description="well-fill power (Massey et al. 2014) [1]",
                        json_schema_extra={"unit": "1", "bound_reachable": True})
    well_e: float | None = Field(None, gt=0, description="well depth of the fill law (default: full well) [e-]")
    serial_density_per_px: list[float] = Field(default_factory=list,
                                               description="serial-register trap densities [traps/pixel]")
    serial_release_time_s: list[float] = Field(default_factory=list, description="serial release times [s]")
    serial_transfer_s: float = Field(1.25e-7, gt=0, le=1e-3, description="dwell per serial transfer [s]")
    notch_e: float = Field(0.0, ge=0, description="well-notch depth d of the fill law V = ((n-d)/(w-d))^beta [e-]")
    express: int = Field(1, ge=0, le=64, description="0: every pixel's traps followed (exact, slow); E >= 1: E "
                                                     "groups of pixels per column, each one pool (error ~ 1/E) [groups per column]")
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


#: release times of the single-species trails the diagnosis tries [transfers] (HST ACS's three species, Massey
#: et al. 2014: a fast, a middle and a slow trap), read out in either register
CTI_RELEASE_TRANSFERS = ACS_RELEASE_TRANSFERS
#: well-fill powers the diagnosis tries about its best trail (Massey et al. 2014 measure 0.478 on HST ACS;
#: the volume a packet fills grows between the square root and the first power of its charge for a buried
#: channel whose charge cloud spreads in two or three dimensions, Clarke et al. 2012, MNRAS 419, 2464)
CTI_BETAS = (0.25, 0.478, 0.75, 1.0)


def _cti_templates(res, q, direction: str, release_transfers, beta: float, unit: float = 0.01):
    """``(CTI(Q) - Q) / unit`` [ADU per trap per pixel] of the model's charge ``q`` for one species of each
    release time in ``release_transfers`` (in the register's own transfers), read out along ``direction``:
    "parallel" (towards row 0, the packet of the window's first row after ``y0 + 1`` transfers) or "serial"
    (towards column 0, after ``x0 + 1``); one pass for all (:func:`cti_species_changes`). Returns
    ``[(template, release time [s]), ...]``."""
    well = res.sensor.full_well_e * res.pixel_sum
    if direction == "serial":
        dwell = CTIParams.model_fields["serial_transfer_s"].default
        first = int(res.xs[0]) + 1 if res.xs.size else 1
        img = q.T
    else:
        dwell = ML11002_PARALLEL_TRANSFER_S
        first = int(res.ys[0]) + 1 if res.ys.size else 1
        img = q
    taus = [tr * dwell for tr in release_transfers]
    ch = cti_species_changes(img, [unit] * len(taus), taus, dwell, beta, well, first)
    # a serial trail's map in row order (C-contiguous) as every other template: a variant's values at a sample of
    # pixels are then read from it in place, not from a row-ordered copy of the whole frame made at every read
    return [(np.divide(c.T if direction == "serial" else c, unit * res.gain, order="C"), tau)
            for c, tau in zip(ch, taus)]


def _cti_variant(t: np.ndarray, tau: float, direction: str, tr: float, beta: float) -> Variant:
    def to_params(c, tau=tau):
        if not 0 < c[0] < 100:
            return None
        dens, rel = [round(float(c[0]), 5)], [float(f"{tau:.4g}")]
        out = ({"serial_density_per_px": dens, "serial_release_time_s": rel, "density_per_px": [0.0],
                "release_time_s": [ACS_RELEASE_TRANSFERS[0] * ML11002_PARALLEL_TRANSFER_S]}
               if direction == "serial" else {"density_per_px": dens, "release_time_s": rel})
        if beta != CTIParams.model_fields["beta"].default:
            out["beta"] = beta
        return out

    return Variant([t.astype(np.float32)], to_params,
                   f"{direction}, release {tr:g} transfers" + (f", beta {beta:g}" if beta != 0.478 else ""),
                   extra_k=int(beta != CTIParams.model_fields["beta"].default))


def _cti_variants(res):
    """CTI trails of the model's own charge for one species of unit density: ``CTI(Q) - Q`` is linear in
    the density to first order; variants over the register (parallel: trails along the columns; serial:
    along the rows, Massey et al. 2014 and ArCTIc model both) and the release time (:data:`CTI_RELEASE_TRANSFERS`
    of each register's dwell, one pass per register); the well-fill power is refined about the best
    (:func:`_cti_betas`)."""
    if res.sensor.kind != "ccd":
        return
    q = res.charge_e.astype(np.float64)
    for direction in ("parallel", "serial"):
        for tr, (t, tau) in zip(CTI_RELEASE_TRANSFERS, _cti_templates(res, q, direction, CTI_RELEASE_TRANSFERS, 0.478)):
            yield _cti_variant(t, tau, direction, tr, 0.478)


def _cti_betas(best: Variant, res):
    """The best trail's register and release time with the other well-fill powers (:data:`CTI_BETAS`): how
    the trail grows with the packet's charge, ``V(n) = (n / w)^beta``."""
    label = best.label.split(", ")
    direction, tr = label[0], float(label[1].split()[1])
    q = res.charge_e.astype(np.float64)
    for beta in CTI_BETAS:
        if beta != 0.478:
            (t, tau), = _cti_templates(res, q, direction, [tr], beta)
            yield _cti_variant(t, tau, direction, tr, beta)


def _cti_words(p, res) -> str:
    serial = any(p.get("serial_density_per_px") or [])
    dens = (p["serial_density_per_px"] if serial else p["density_per_px"])[0]
    tau = (p["serial_release_time_s"] if serial else p["release_time_s"])[0]
    where = ("along the rows, away from the serial register's output" if serial else
             "behind sources away from the read-out register")
    dwell = p.get("serial_transfer_s", CTIParams.model_fields["serial_transfer_s"].default) if serial else \
        p.get("parallel_transfer_s", ML11002_PARALLEL_TRANSFER_S)
    return (f"charge trailing {where}, {dens:.3g} traps/pixel releasing in {tau / dwell:.3g} transfers "
            f"({tau:.3g} s)"
            + (f" (well-fill power {p['beta']:g})" if "beta" in p else "")
            + f": {'serial' if serial else 'parallel'} charge-transfer inefficiency (radiation-damaged CCD)")


_CTI_SIGNATURE = LinearSignature(
    _cti_variants, _cti_words, pattern="one-sided trails along the columns or the rows", extra_k=2,
    refine=_cti_betas)


@register_effect
class CTI(Effect):
    """Charge-transfer inefficiency of a CCD: trap species capture charge from passing packets and release it
    into later ones (trails away from the register). A packet of n e- fills the volume ((n-d)/(w-d))^beta of
    a pixel and the empty traps there capture at once; a filled trap releases with probability
    1 - exp(-t_d/tau_k) per transfer; occupancy tracked per volume level (ArCTIc's well-fill model, Massey et
    al. 2014 MNRAS 439 887). Parallel and serial; densities given or from a proton-dose model
    (days_in_orbit); express as ArCTIc's. CCD only. Details: detector/effects/cti.py."""

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
        if p.express == 0:  # every pixel's traps: (rows + y0) x cols pools per parallel transfer
            (h, w), y0, x0 = self.sensor.shape, self.sensor.roi_y0, self.sensor.roi_x0
            pools = max((h + y0) * w, (w + x0) * h if any(p.serial_density_per_px) else 0)
            if pools > EXACT_MAX_POOLS:
                raise DetectorError(f"express=0 on a {h} x {w} window at ({y0}, {x0}): {pools} trap pools",
                                    key="effects.cti.express",
                                    expected=f"express >= 1, or a window with (rows + y0) x cols <= {EXACT_MAX_POOLS}")

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
                               first_transfers=tile.y0 - pad_top + 1, express=p.express, notch_e=p.notch_e)
        if any(p.serial_density_per_px):
            out = cti_transfer(out.T, p.serial_density_per_px, p.serial_release_time_s, p.serial_transfer_s,
                               p.beta, well, first_transfers=tile.x0 + 1, express=p.express, notch_e=p.notch_e).T
        return np.asarray(out, np.float32)
