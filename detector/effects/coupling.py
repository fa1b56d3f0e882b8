"""Pixel coupling at and after charge collection: the brighter-fatter effect and inter-pixel capacitance.

Both act on the drawn charge (stage COUPLING, after the full-well clip), so they shape the *noise* of a
flat as well as the mean image of a star: that is how they are told apart from an optical blur, which acts
before the Poisson draw and leaves the pixels of a flat uncorrelated.

**Brighter-fatter** (Antilogus et al. 2014, JINST 9, C03048; Coulton et al. 2018, AJ 155, 258, eq. 10;
the kernel form imSim/GalSim and the LSST pipelines use): the charge already collected repels the charge
still arriving, so pixel boundaries move away from bright pixels. With a potential ``phi = K (x) Q`` of the
pixels' charge ``Q`` [e-], the charge crossing the boundary between neighbours ``i`` and ``n`` is
``F_in = c (Q_i + Q_n)/2 (phi_i - phi_n)`` and, because the boundaries grow from zero during the exposure,
half of it is collected on average::

    Q'_i = Q_i - 1/2 sum_n F_in          (charge conserved exactly: what leaves i enters n)

For a flat of mean ``mu`` this gives, to first order in ``a = c Laplacian(K)`` (the area coefficients of
Antilogus et al. 2014, ``sum a = 0``), the covariances of Astier et al. 2019 (A&A 629, A36, eq. 20):
``Cov(Q_0, Q_ij) = a_ij mu^2`` for ``(i, j) != 0`` and ``Var Q_0 = mu + a_00 mu^2`` (the photon transfer
curve bends down). ``K`` here is a 3x3 kernel ``exp(-r / lambda)`` (``lambda`` = ``kernel_scale_px``),
whose Laplacian gives positive ``a_ij`` out to two pixels; its strength ``c`` is set by the nearest-neighbour
coefficient ``a10_per_e`` (what a flat pair measures: ``Cov_10 / mu^2``).

Default: the GalSim-matched value ``a_10 = 2.7e-7 /e-`` with ``kernel_scale_px = 0.5``. At it, a star's
size grows with its flux as fast as in GalSim's ``SiliconSensor('lsst_itl_50_8')``: an LSST ITL CCD (10 um
pixels, 100 um thick), whose pixel boundaries come from Lage's Poisson_CCD solver calibrated on measured
ITL spots and flats (Lage et al. 2017, JINST 12, C03091). The comparison is a Gaussian star of sigma
1.5 px, peaks 1e3-2e5 e-, the unweighted second-moment sigma against the flux: within 1 % (the reference and
the script that drew it: ``tests/data/peers/galsim/``; the test: ``tests/detector/test_peer_galsim_bf.py``).
Why this value: no measurement exists for the IMX411 (3.76 um pinned photodiodes, a thin epitaxial layer)
or the ML11002 (KAI-11002 interline photodiodes), so the default is that of a measured sensor, through the
model the field uses for it; it lies in the ``a_10 ~ 2-4e-7 /e-`` that flats of thick deep-depleted CCDs
show (LSST e2v/ITL sensors, Astier et al. 2019) and gives a 2.2 % nearest-neighbour correlation at 80 ke-.
The 3x3 kernel reaches the 8 neighbours only, while GalSim's boundaries feel charge several pixels away,
so compact stars grow faster than in GalSim (1.25x for sigma 1.0 px). For a real camera, measure
``a_10`` with flat pairs (``Cov_10 / mu^2``). The default was a guessed 1e-7 /e- before, 0.37-0.47x
GalSim's slope.

**Inter-pixel capacitance** (Moore et al. 2004, Opt. Eng. 45, 076402; Kannawadi et al. 2016, PASP 128,
095001): the voltage of a pixel's sense node couples capacitively into its neighbours, so each pixel *reads*
a fraction of its neighbours' charge without any charge moving::

    V = K_ipc (x) Q,   K_ipc = [[a_d, a, a_d], [a, 1 - 4a - 4a_d, a], [a_d, a, a_d]]

The kernel conserves the total signal. For a flat (white Poisson noise of variance ``mu``) the read values
are correlated: ``Cov_10 = mu sum_j K_j K_{j+(1,0)} = mu [2a(1 - 4a - 4a_d) + 4 a a_d]`` (with
``a_d = 0``: ``2 a (1 - 4 a) mu``), ``Var = mu sum_j K_j^2`` and ``rho_10 = Cov_10 / Var``. Small-pixel CMOS
sensors show ``a`` of 0.5-2 % (e.g. Kannawadi et al. for HgCdTe; for CMOS image sensors IPC is rarely
published): default ``a = 0.005``, ``a_d = 0`` for the IMX411 (assumed, not measured); a CCD reads its
charge at one output node, so its IPC is negligible (switch it on only to model a measured correlation).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..signatures import LinearSignature, Variant
from ..significance import DETECTION_SIGMA
from .base import Effect, EffectParams, Stage, Tile, register_effect


def _shift_sums(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sum of the 4 nearest neighbours, sum of the 4 diagonal ones), edges replicated (float32)."""
    p = np.pad(q, 1, mode="edge")
    n4 = p[:-2, 1:-1] + p[2:, 1:-1]
    n4 += p[1:-1, :-2]
    n4 += p[1:-1, 2:]
    d4 = p[:-2, :-2] + p[:-2, 2:]
    d4 += p[2:, :-2]
    d4 += p[2:, 2:]
    return n4, d4


def bf_kernel(scale_px: float) -> tuple[float, float, float]:
    """(K_00, K_10, K_11) of the 3x3 potential kernel ``exp(-r / scale_px)`` [1]."""
    return 1.0, float(np.exp(-1.0 / scale_px)), float(np.exp(-np.sqrt(2.0) / scale_px))


def bf_area_coefficients(scale_px: float) -> dict[tuple[int, int], float]:
    """Discrete Laplacian of the 3x3 kernel, per unit ``c``: ``a_ij / c`` for ``i, j >= 0`` up to 2 px."""
    k0, k1, k2 = bf_kernel(scale_px)
    return {(0, 0): 4 * k1 - 4 * k0, (1, 0): k0 + 2 * k2 - 4 * k1, (1, 1): 2 * k1 - 4 * k2,
            (2, 0): k1, (2, 1): k2, (2, 2): 0.0}


def brighter_fatter(charge_e: np.ndarray, a10_per_e: float, scale_px: float = 0.5) -> np.ndarray:
    """Brighter-fatter redistribution of ``charge_e`` [e-] (module docstring); a new float32 array.

    ``a10_per_e`` [1/e-] is the nearest-neighbour area coefficient of a flat (``Cov_10 / mu^2``); the
    kernel strength is ``c = a10 / (Laplacian K)_10``. No charge crosses the array's outer edges.
    """
    q = np.asarray(charge_e, np.float32)
    if a10_per_e == 0:
        return q.copy()
    k0, k1, k2 = bf_kernel(scale_px)
    c = np.float32(a10_per_e / bf_area_coefficients(scale_px)[(1, 0)])
    n4, d4 = _shift_sums(q)
    phi = q * np.float32(k0)
    n4 *= np.float32(k1)
    phi += n4
    d4 *= np.float32(k2)
    phi += d4
    del n4, d4
    out = q.copy()
    # flux across vertical boundaries (between columns x and x+1), positive towards +x
    f = (q[:, :-1] + q[:, 1:]) * (phi[:, :-1] - phi[:, 1:])
    f *= np.float32(0.25) * c  # (Q_i + Q_n)/2, times 1/2 for the growing boundary
    out[:, :-1] -= f
    out[:, 1:] += f
    f = (q[:-1] + q[1:]) * (phi[:-1] - phi[1:])
    f *= np.float32(0.25) * c
    out[:-1] -= f
    out[1:] += f
    return out


def ipc(charge_e: np.ndarray, alpha: float, alpha_diag: float = 0.0) -> np.ndarray:
    """Inter-pixel capacitance: ``K_ipc (x) Q`` (module docstring), edges replicated; a new float32 array."""
    q = np.asarray(charge_e, np.float32)
    if alpha == 0 and alpha_diag == 0:
        return q.copy()
    n4, d4 = _shift_sums(q)
    out = q * np.float32(1.0 - 4.0 * alpha - 4.0 * alpha_diag)
    n4 *= np.float32(alpha)
    out += n4
    if alpha_diag:
        d4 *= np.float32(alpha_diag)
        out += d4
    return out


# --- diagnosis signatures ---------------------------------------------------------------------------------

def _bf_variants(res):
    """Brighter-fatter of the model's own charge (stars widen with flux): ``BF(Q) - Q`` is linear in
    ``a10`` to first order; variants over the kernel scale."""
    g = np.float32(res.gain)
    q = res.charge_e
    if not (q > 0.05 * res.sensor.full_well_e * res.pixel_sum).any():
        return  # nothing bright enough to widen
    unit = 1e-7
    for scale in (0.35, 0.5, 0.8):
        t = ((brighter_fatter(q, unit, scale) - q) / g).astype(np.float32)

        def to_params(c, scale=scale):
            return {"a10_per_e": float(f"{c[0] * unit:.3g}"), "kernel_scale_px": scale} if 0 < c[0] < 1e3 else None

        yield Variant([t], to_params, f"kernel scale {scale:g} px")


def _ipc_variants(res):
    """IPC of the model's charge: ``K_ipc(Q) - Q`` per unit coupling (nearest, and nearest + diagonal)."""
    g = np.float32(res.gain)
    q = res.charge_e
    for diag in (0.0, 0.2):
        t = ((ipc(q, 1.0, diag) - q) / g).astype(np.float32)

        def to_params(c, diag=diag):
            return ({"alpha": float(f"{c[0]:.3g}"), "alpha_diag": float(f"{c[0] * diag:.3g}")}
                    if 0 < c[0] < 0.05 else None)

        yield Variant([t], to_params, f"diagonal {diag:g} of nearest")


def bf_check(fit, res) -> str:
    """Brighter-fatter widens a star by an amount that grows with its charge: its first-order change is F^2 x a
    shape, so refitted star by star its amplitude is the same for every flux (power 0 of the flux,
    :mod:`detector.flux_law`). A change of every star's image alike (a wider PSF, a blur with far wings) is F x a
    shape: the brighter-fatter template's amplitude then falls as F^-1. When the refitted amplitudes' power
    excludes 0 by DETECTION_SIGMA standard errors and lies nearer -1 (:func:`detector.flux_law.flux_law`), the
    widening is not brighter-fatter."""
    from detector.flux_law import change_slope, flux_law

    slope = change_slope(res, fit.delta_adu)
    if flux_law(slope, own=0.0, other=-1.0):
        return (f"the widening does not grow with the stars' flux: refitted star by star its amplitude goes as "
                f"{slope.describe('stars')}; brighter-fatter's would be flux^0, a change of every star alike "
                "flux^-1: a PSF change, not charge pushed out by the stars' own charge")
    return ""


_BF_SIGNATURE = LinearSignature(
    _bf_variants,
    lambda p, res: (f"bright sources wider than faint ones, charge pushed out of their cores (a_10 = "
                    f"{p['a10_per_e']:.2g} /e-): the brighter-fatter effect"),
    pattern="flux-dependent widening of bright sources", extra_k=1, check=bf_check)
#: how many standard errors the source-free pixels' neighbour correlation may fall short of what a fitted IPC
#: implies before the IPC is refused (and the least the implied correlation must reach for the test to speak)
IPC_NOISE_SIGMA = DETECTION_SIGMA


def ipc_noise_correlation(alpha: float) -> float:
    """Nearest-neighbour correlation of a flat's shot noise under IPC ``alpha`` (the docstring of :class:`IPC`)."""
    return 2 * alpha * (1 - 4 * alpha) / ((1 - 4 * alpha) ** 2 + 4 * alpha ** 2)


def _ipc_noise_evidence(fit, res):
    """(observed, implied, standard error) of the source-free pixels' nearest-neighbour correlation under the
    fitted IPC (:func:`ipc_check`); None when it cannot be measured (a binned frame, fewer than 1000 pairs)."""
    if res.sensor.binning != 1:
        return None
    var = np.maximum(res.var_adu2, 1e-12)
    z = (res.data_adu - res.model_adu) / np.sqrt(var)
    quiet = res.fit & ((res.photo_adu - res.background_photo_adu) <= 0.1 * np.sqrt(var))
    pairs = [(z[:, :-1], z[:, 1:], quiet[:, :-1] & quiet[:, 1:]), (z[:-1, :], z[1:, :], quiet[:-1, :] & quiet[1:, :])]
    a = np.concatenate([p[0][p[2]] for p in pairs]).astype(np.float64)
    b = np.concatenate([p[1][p[2]] for p in pairs]).astype(np.float64)
    n = a.size
    if n < 1000:
        return None
    a, b = a - a.mean(), b - b.mean()
    rho_obs = float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))
    shot = float(np.mean((res.charge_e / np.float32(res.gain ** 2))[quiet] / var[quiet]))
    rho_exp = ipc_noise_correlation(float(fit.params["alpha"])) * min(max(shot, 0.0), 1.0)
    return rho_obs, rho_exp, 1.0 / np.sqrt(n), n


def ipc_check(fit, res) -> str:
    """IPC couples the collected charge, its shot noise included: where no source falls, the residual's
    nearest-neighbour correlation must be ``ipc_noise_correlation(alpha)`` times the shot noise's share of the
    variance (the read noise is added after the coupling). When the data could show that correlation (at least
    2 x IPC_NOISE_SIGMA standard errors of the estimate) and lack it by more than IPC_NOISE_SIGMA, the 3x3
    smoothing the fit found is in the image (a blur, a motion), not in the pixels. Unbinned frames only (binning
    dilutes the correlation to the bin edges)."""
    ev = _ipc_noise_evidence(fit, res)
    if ev is None:
        return ""
    rho_obs, rho_exp, se, n = ev
    if rho_exp >= 2 * IPC_NOISE_SIGMA * se and rho_exp - rho_obs > IPC_NOISE_SIGMA * se:
        return (f"the noise where no source falls has a neighbour correlation of {rho_obs:.4f} +- {se:.4f} over {n} "
                f"pairs; a coupling of {fit.params['alpha']:.3g} would give {rho_exp:.4f} (its shot noise is coupled "
                "too): the smoothing is in the image (a blur or a motion), not in the pixels")
    return ""


#: the chi2 [1] by which the fitted IPC of the frame's charge that is not light (dark current, hot pixels) must
#: differ from nothing for the frame to tell the coupling of the charge from a blur of the light: a
#: DETECTION_SIGMA difference of a one-parameter fit (chi2_1 = DETECTION_SIGMA^2 = 25)
IPC_STAGE_CHI2 = DETECTION_SIGMA ** 2


def ipc_untold_from(fit, res) -> tuple[str, ...]:
    """The light's blur (``psf_blur``) when this frame cannot tell the fitted IPC from it. A 3x3 coupling of
    the pixels' charge acting on light alone is the image of a PSF changed by that same small kernel (any small
    symmetric kernel is a PSF change: to first order both add ``(var / 2) Laplacian(I)``, their fourth moments
    are a PSF's as well). What tells them apart is the stage: IPC couples the shot noise too (the noise test
    of :func:`ipc_check` can speak: the implied correlation at least 2 x IPC_NOISE_SIGMA standard errors) and
    every charge that is not light (the coupling of the model's dark charge, hot pixels included, at least
    IPC_STAGE_CHI2 of chi2). When neither can, the two are the same image in this frame."""
    ev = _ipc_noise_evidence(fit, res)
    if ev is not None and ev[1] >= 2 * IPC_NOISE_SIGMA * ev[2]:
        return ()
    dark = np.asarray(res.dark_e, np.float32)
    if dark.size > 1 and np.any(dark):
        dark = np.broadcast_to(dark, res.data_adu.shape).astype(np.float32)
        alpha, diag = float(fit.params["alpha"]), float(fit.params.get("alpha_diag", 0.0))
        t = (ipc(dark, alpha, diag) - dark) / np.float32(res.gain)
        idx, _, w = res.flat_profiled()
        if float(np.sum(t.ravel()[idx].astype(np.float64) ** 2 * w)) >= IPC_STAGE_CHI2:
            return ()
    return ("psf_blur",)


_IPC_SIGNATURE = LinearSignature(
    _ipc_variants,
    lambda p, res: (f"a fixed fraction {p['alpha']:.2g} of every pixel's signal read in its neighbours, "
                    "independent of flux: inter-pixel capacitance"),
    pattern="a flux-independent 3x3 coupling of every pixel into its neighbours", extra_k=1, check=ipc_check)
_IPC_SIGNATURE.untold = ipc_untold_from


class BrighterFatterParams(EffectParams):
    # GalSim-matched (LSST ITL, module docstring): the size-flux slope of GalSim's SiliconSensor
    a10_per_e: float = Field(2.7e-7, ge=0, le=1e-4,
                             description="nearest-neighbour area coefficient, Cov_10 / mu^2 of a flat [1/e-]")
    kernel_scale_px: float = Field(0.5, gt=0.1, le=5, description="scale of the exp(-r/scale) potential [px]")


@register_effect
class BrighterFatter(Effect):
    """Brighter-fatter: collected charge pushes pixel boundaries outwards (Antilogus et al. 2014 JINST 9
    C03048; Coulton et al. 2018 AJ 155 258). Q' = Q - 1/2 sum_n c (Q_i+Q_n)/2 (phi_i - phi_n), phi = K (x) Q,
    K = exp(-r/scale) (3x3); charge conserved; flats get Cov_ij = a_ij mu^2 with a = c Laplacian(K), a_10 given.
    Details: detector/effects/coupling.py."""

    name = "brighter_fatter"
    scaling = "signal"
    identity = {"a10_per_e": 0.0}
    stages = (Stage.COUPLING,)
    Params = BrighterFatterParams
    signature = _BF_SIGNATURE
    halo_rows = 2
    coupling_order = 0

    def couple(self, tile: Tile, charge_e, pad_top, pad_bottom, mean_only=False):
        return brighter_fatter(charge_e, self.params.a10_per_e, self.params.kernel_scale_px)


class IPCParams(EffectParams):
    alpha: float = Field(0.005, ge=0, le=0.05, description="coupling into each nearest neighbour [1]")
    alpha_diag: float = Field(0.0, ge=0, le=0.02, description="coupling into each diagonal neighbour [1]")


@register_effect
class IPC(Effect):
    """Inter-pixel capacitance: each pixel reads alpha of each nearest (alpha_diag of each diagonal)
    neighbour's charge, V = K_ipc (x) Q, charge seen but not moved (Moore et al. 2004 Opt. Eng. 45 076402).
    A flat's nearest-neighbour correlation is 2 alpha (1 - 4 alpha) / ((1 - 4 alpha)^2 + 4 alpha^2).
    Details: detector/effects/coupling.py."""

    name = "ipc"
    scaling = "signal"
    identity = {"alpha": 0.0, "alpha_diag": 0.0}
    stages = (Stage.COUPLING,)
    Params = IPCParams
    signature = _IPC_SIGNATURE
    halo_rows = 1
    coupling_order = 2

    def couple(self, tile: Tile, charge_e, pad_top, pad_bottom, mean_only=False):
        return ipc(charge_e, self.params.alpha, self.params.alpha_diag)
