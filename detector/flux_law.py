"""How a change of the sources' images grows with their flux: a PSF's width, or the brighter-fatter effect.

A wider (or narrower) PSF changes every star's image by the same factor: the change of a star of flux F is
``F x s(x, y)``, linear in F. The brighter-fatter effect widens a star by an amount that grows with its own
charge (Antilogus et al. 2014, JINST 9 C03048, eq. 4: the pixel boundaries move by ``a_ij x Q``): to first
order in ``a_10`` its change is ``F^2 x s'(x, y)``. So a candidate's change, refitted with one amplitude per
source (:func:`source_amplitudes`), has amplitudes that are constant over the sources for the law the
candidate's template was built with, and that scale as ``F^(+1)`` (a PSF template meeting a brighter-fatter
widening) or ``F^(-1)`` (a brighter-fatter template meeting a widening of every source alike) for the other.
:func:`flux_slope` measures that power, ``d ln(amplitude) / d ln(F)``, with its scatter-inflated error, and
:func:`flux_law` says which of two powers the sources follow (the other excluded), or that they cannot tell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import significance

#: the least signal-to-noise ratio of a source's own amplitude for the source to enter the slope (below it the
#: amplitude's logarithm is not defined well enough to fit): a detected source, DETECTION_SIGMA
SOURCE_MIN_SNR = significance.DETECTION_SIGMA
#: the model's source light above this many standard deviations of a pixel's noise marks a source's footprint
#: (then grown by FOOTPRINT_GROW_PX to hold its wings)
FOOTPRINT_SIGMA = significance.FOOTPRINT_SIGMA
FOOTPRINT_GROW_PX = 2


@dataclass(frozen=True)
class Slope:
    """The power ``d ln(amplitude) / d ln(flux)`` of a change's per-source amplitudes and its error (inflated by
    the fit's own scatter when that exceeds the amplitudes' errors), over ``n`` sources whose fluxes span a
    factor ``flux_range``."""

    power: float
    error: float
    n: int
    flux_range: float

    def describe(self, what: str = "sources") -> str:
        """"flux^p +- e over n ``what`` (fluxes over a factor r)": the slope in a reason's words."""
        return (f"flux^{self.power:.2f} +- {self.error:.2f} over {self.n} {what} (fluxes over a factor "
                f"{self.flux_range:.3g})")


def source_amplitudes(source_adu: np.ndarray, noise_adu: np.ndarray, usable: np.ndarray, residual_adu: np.ndarray,
                      change_adu: np.ndarray, excluded: np.ndarray | None = None, own_scale: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(flux [ADU], amplitude, its standard error) of ``change_adu`` refitted on each source's footprint alone:
    the footprint is where the model's source light ``source_adu`` exceeds FOOTPRINT_SIGMA x ``noise_adu``,
    grown by FOOTPRINT_GROW_PX and labelled (touching sources are one); the amplitude is the weighted least
    squares ``sum(w d r) / sum(w d^2)`` over its ``usable`` pixels (w = 1 / noise^2). A footprint touching
    ``excluded`` (saturated pixels) is left out. With ``own_scale`` each source's brightness is fitted with it
    (the amplitude of ``change_adu`` once the source's own light ``source_adu`` is refitted on the footprint:
    the partial regression, ``(S_dr - S_ds S_sr / S_ss) / (S_dd - S_ds^2 / S_ss)``, its variance the inverse
    of the denominator)."""
    from scipy import ndimage

    noise = np.maximum(np.asarray(noise_adu, np.float64), 1e-12)
    core = np.asarray(source_adu) > FOOTPRINT_SIGMA * noise
    if FOOTPRINT_GROW_PX:
        core = ndimage.binary_dilation(core, np.ones((3, 3), bool), iterations=FOOTPRINT_GROW_PX)
    labels, n = ndimage.label(core, structure=np.ones((3, 3)))
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    index = np.arange(1, n + 1)
    use = core & usable & np.isfinite(residual_adu) & np.isfinite(change_adu)
    lab = np.where(use, labels, 0)
    w = 1.0 / noise ** 2
    d = np.where(use, change_adu, 0.0).astype(np.float64)
    r = np.where(use, residual_adu, 0.0).astype(np.float64)
    info = ndimage.sum_labels(w * d * d, lab, index)
    proj = ndimage.sum_labels(w * d * r, lab, index)
    flux = ndimage.sum_labels(np.where(core, source_adu, 0.0).astype(np.float64), labels, index)
    if own_scale:
        # the source's own light scale a nuisance of each footprint (partial regression on d and s): what a
        # brightness error leaves, F x PSF, is no part of the change's amplitude
        s = np.where(use, source_adu, 0.0).astype(np.float64)
        ss = ndimage.sum_labels(w * s * s, lab, index)
        ds = ndimage.sum_labels(w * d * s, lab, index)
        sr = ndimage.sum_labels(w * s * r, lab, index)
        ok = ss > 0
        info = np.where(ok, info - ds * ds / np.where(ok, ss, 1.0), info)
        proj = np.where(ok, proj - ds * sr / np.where(ok, ss, 1.0), proj)
    keep = info > 0
    if excluded is not None and np.any(excluded):
        touched = ndimage.maximum(np.asarray(excluded, float), labels, index) > 0
        keep &= ~np.asarray(touched, bool)
    amp = np.where(keep, proj / np.where(info > 0, info, 1.0), np.nan)
    err = np.where(keep, 1.0 / np.sqrt(np.where(info > 0, info, 1.0)), np.nan)
    return flux[keep], amp[keep], err[keep]


def flux_slope(flux: np.ndarray, amp: np.ndarray, err: np.ndarray) -> Slope | None:
    """The weighted straight line ``ln(amp) = a + p ln(flux)`` through the sources whose amplitude is positive
    and measured to SOURCE_MIN_SNR (error of ln(amp): err / amp); p's error from the normal matrix, times
    sqrt(chi2 / dof) when the points scatter more than their errors (the model's own misfit per source).
    None when the line through the sources that qualify has no degree of freedom left to measure their scatter
    about it (fewer than three) or their fluxes are all one: no bar of its own on their number or range, the
    slope's standard error (inflated by that scatter) grows as they are fewer or their fluxes closer, and
    :func:`flux_law` then finds neither law excluded by DETECTION_SIGMA of its errors."""
    ok = np.isfinite(amp) & np.isfinite(err) & (err > 0) & (flux > 0) & (amp > SOURCE_MIN_SNR * err)
    dof = int(ok.sum()) - 2  # a straight line's two parameters
    if dof < 1:
        return None
    f, a, e = flux[ok], amp[ok], err[ok]
    spread = float(f.max() / f.min())
    x, y, s = np.log(f), np.log(a), e / a
    w = 1.0 / s ** 2
    xm = np.sum(w * x) / np.sum(w)
    sxx = np.sum(w * (x - xm) ** 2)
    if sxx <= 0:
        return None
    p = float(np.sum(w * (x - xm) * y) / sxx)
    a0 = np.sum(w * (y - p * (x - xm))) / np.sum(w)
    chi2 = float(np.sum(w * (y - a0 - p * (x - xm)) ** 2))
    inflate = max(1.0, np.sqrt(chi2 / dof))
    return Slope(p, float(inflate / np.sqrt(sxx)), int(ok.sum()), spread)


def flux_law(slope: Slope | None, own: float, other: float) -> bool | None:
    """Which law the sources follow: :func:`detector.significance.law_verdict` of ``slope``'s power between
    ``own`` (the power the candidate's template assumes) and ``other``; None without a slope. A power far from
    both (2.1 +- 0.4 for laws 0 and 1, a few sources over a narrow range of flux) still excludes the one it is 5
    errors from."""
    return None if slope is None else significance.law_verdict(slope.power, slope.error, own, other)


def change_slope(res, change_adu: np.ndarray) -> Slope | None:
    """:func:`flux_slope` of a candidate's change (``change_adu``, a frame [ADU]) on the sources of the
    comparison ``res`` (a :class:`detector.signatures.Residuals`): the residual with the global levels refitted,
    the model's source light, its noise, its fitted pixels; sources with a pixel near saturation
    (:data:`detector.signatures.NEAR_SATURATION_SHARE` of the ceiling) left out (their cores do not grow).

    Each source's brightness is refitted with the change (``own_scale``): the law is about the change's shape
    growing with the flux, not about the flux itself, which the model knows only as well as the catalogue and
    the global light level. A light level or zero point off by a fraction ``e`` leaves ``e F x PSF`` on every
    source, which a widening template (negative in the core) would take up as an amplitude ``~ F^-1`` of a
    brighter-fatter template's ``F^2``: where one bright source sets the levels (its own brighter-fatter pushing
    the light level up), every fainter source would seem to follow a PSF's law."""
    if change_adu is None or np.ndim(change_adu) != 2:
        return None
    source = res.model_adu - res.without_sources_adu
    residual = res.data_adu - res.model_adu - res.level_map()
    flux, amp, err = source_amplitudes(source, np.sqrt(np.maximum(res.var_adu2, 0)), res.fit, residual,
                                       np.broadcast_to(change_adu, res.data_adu.shape), res.saturated,
                                       own_scale=True)
    return flux_slope(flux, amp, err)
