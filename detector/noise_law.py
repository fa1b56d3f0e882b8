"""Whether a change of the frame is charge or an offset of the read-out, by the shot noise it carries.

Charge, of light or dark current, is counted: its variance equals its mean (Poisson; Janesick 2007, Photon
Transfer, SPIE PM170, ch. 2-3, the photon transfer curve's shot-noise regime). An offset added at the read-out
(a bias structure, an amplifier's pattern) carries no noise of its own. On one dark frame a dark-rate field and
a bias structure of the same shape make the same mean image; only the variance tells them apart. (Charge that
diffuses before it is collected stays Poisson and independent from pixel to pixel: a displaced Poisson process
is a Poisson process of the blurred intensity. What couples the noise of neighbours after collection, an
inter-pixel capacitance or brighter-fatter, lowers the measured share by about its coupling: 2 % per side of
IPC, ~0.84.)

The frame's own noise is measured on differences of horizontally adjacent pixel pairs, ``d = r_a - r_b`` of the
residual ``r`` once the candidate's own change is taken off (``data - model - delta``): what remains of a
structure smooth over two pixels cancels in them, while their variance is ``v_a + v_b`` plus the two pixels'
extra noise. The squared differences are fitted (weighted least squares, ``Var(d^2) = 2 V^2`` for Gaussian noise
of variance ``V``; the weights refitted once with the fitted ``V``) as ``d^2 - (v_a + v_b) = s x + c0 + c1 (v_a +
v_b)``, with ``x`` the change's shot-noise variance at the pair (``(delta_a + delta_b) / g``,
:attr:`detector.signatures.Residuals.poisson_adu` per ADU) and two nuisances that a mean level or a read noise
(``c0``) and a gain (``c1``) off by a little would leave; a change of the shape of the model's own variance is
then not measured apart from a gain (no verdict). The error is the larger of the fit's (inflated by its scatter)
and a jackknife over blocks of columns (a column pattern left out of the model repeats down the rows: its pairs
are not independent). ``s`` is 1 for charge and 0 for an offset; :func:`noise_law` says which of the two the frame
shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import significance

#: a pair whose difference exceeds this many standard deviations of its noise is an outlier (a cosmic ray, a hot
#: pixel the spikes missed) and left out: a detection (DETECTION_SIGMA, 6e-7 of Gaussian pairs). The noise here is
#: the model's plus the change's own shot noise (the charge reading), so that a strong field of charge keeps its
#: pairs; an offset's pairs then keep theirs to a little more than 5 sigma
OUTLIER_SIGMA = significance.DETECTION_SIGMA
#: the most pixel pairs the fit reads: every k-th row beyond it (a numerical budget: 2^18 pairs measure the share of
#: a change of 10 % of the variance to +-0.03, and the whole of a 2048^2 frame would cost seconds per candidate)
MAX_PAIRS = 2 ** 18
#: blocks of columns of the jackknife error (a numerical setting: enough for a variance of the error, few enough
#: that each block holds many columns of a pattern)
JACKKNIFE_BLOCKS = 16


@dataclass(frozen=True)
class NoiseShare:
    """The share ``s`` of a change's shot noise the frame's pixel-to-pixel noise carries (1: charge, 0: an offset
    of the read-out) and its standard error, over ``pairs`` pixel pairs."""

    share: float
    error: float
    pairs: int

    def describe(self) -> str:
        """"s +- e of its shot noise over n pixel pairs": the share in a reason's words."""
        return f"{self.share:.2f} +- {self.error:.2f} of its shot noise over {self.pairs} pixel pairs"


def noise_law(share: NoiseShare | None, own: float, other: float) -> bool | None:
    """Which law the frame's noise follows (1: charge, 0: an offset): True when ``share`` excludes ``own`` by
    DETECTION_SIGMA standard errors, lies nearer ``other`` and agrees with ``other`` within DETECTION_SIGMA errors;
    False the other way round; None otherwise. A share far from both laws (the noise of something neither reading
    holds: a pattern the model lacks, a coupling of neighbours) says nothing of the two."""
    if share is None:
        return None
    got = significance.law_verdict(share.share, share.error, own, other)
    if got is None:
        return None
    near = other if got else own
    return got if abs(share.share - near) < significance.DETECTION_SIGMA * share.error else None


def _solve(gram: np.ndarray, rhs: np.ndarray, yy: float, n: int) -> tuple[float, float] | None:
    """(s, its error inflated by the fit's scatter) of the weighted normal equations
    ``gram`` (3x3: x, 1, v), ``rhs``, ``yy`` over ``n`` pairs, the two nuisances profiled out of x (a Schur
    complement; a nuisance collinear with the other dropped). None when x is not measurable apart from them."""
    scale = np.sqrt(np.maximum(np.diag(gram)[1:], 1e-300))
    norm = gram[1:, 1:] / np.outer(scale, scale)
    gn = np.linalg.pinv(norm, rcond=1e-10) / np.outer(scale, scale)
    xx = gram[0, 0] - gram[0, 1:] @ gn @ gram[1:, 0]
    if not np.isfinite(xx) or xx <= 1e-10 * gram[0, 0]:
        return None
    xy = rhs[0] - gram[0, 1:] @ gn @ rhs[1:]
    s = float(xy / xx)
    chi2 = yy - rhs[1:] @ gn @ rhs[1:] - s * xy
    dof = n - 1 - int(np.linalg.matrix_rank(norm, tol=1e-10))
    return s, max(1.0, float(np.sqrt(max(chi2, 0.0) / max(dof, 1)))) / float(np.sqrt(xx))


def noise_share(residual_adu: np.ndarray, var_adu2: np.ndarray, usable: np.ndarray, change_adu: np.ndarray,
                poisson_adu: float) -> NoiseShare | None:
    """The :class:`NoiseShare` of ``change_adu`` (a mean change of the frame [ADU], the candidate's) in the
    residual ``residual_adu`` [ADU] (data - model - the change) of model variance ``var_adu2`` [ADU^2], on the
    ``usable`` pixels (module docstring; at most MAX_PAIRS pairs, from evenly spaced rows). None without
    MIN_TEST_PIXELS pairs or when the change's variance is not measurable apart from the nuisances (a uniform
    change: a level, which a read noise or a gain off by as much would also explain)."""
    h, w = residual_adu.shape
    w2 = w - w % 2
    if w2 < 2:
        return None
    step = max(1, int(np.ceil(h * (w2 // 2) / MAX_PAIRS)))

    def pairs(a):
        a = np.broadcast_to(np.asarray(a), (h, w))[::step, :w2]
        return a[:, 0::2].astype(np.float64), a[:, 1::2].astype(np.float64)

    ua, ub = pairs(usable)
    ok = (ua > 0) & (ub > 0)
    ra, rb = pairs(residual_adu)
    va, vb = pairs(var_adu2)
    da, db = pairs(change_adu)
    block = np.broadcast_to((np.arange(w2 // 2) * JACKKNIFE_BLOCKS) // max(w2 // 2, 1), ok.shape)[ok]
    d = (ra[ok] - rb[ok]) ** 2
    v = va[ok] + vb[ok]
    x = (da[ok] + db[ok]) * poisson_adu
    keep = np.isfinite(d) & np.isfinite(x) & (v > 0) & (d <= OUTLIER_SIGMA ** 2 * (v + np.maximum(x, 0.0)))
    if keep.sum() < significance.MIN_TEST_PIXELS:
        return None
    d, v, x, block = d[keep], v[keep], x[keep], block[keep]
    y = d - v
    cols = (x, np.ones_like(x), v)

    def sums(wt, sel=slice(None)):
        c = [a[sel] for a in cols]
        ww, yv = wt[sel], y[sel]
        gram = np.array([[float(np.dot(ww * a, b)) for b in c] for a in c])
        return gram, np.array([float(np.dot(ww * a, yv)) for a in c]), float(np.dot(ww * yv, yv))

    wt = 0.5 / (v * v)  # 1 / Var(d^2) for Gaussian noise of the model's variance
    gram, rhs, yy = sums(wt)
    if _solve(gram, rhs, yy, y.size) is None:
        return None
    # the weights refitted once with the noise the fit finds (a strong field of charge is noisier than the model)
    gn = np.linalg.pinv(gram, rcond=1e-12)
    coef = gn @ rhs
    fitted = np.maximum(v + coef[0] * x + coef[1] + coef[2] * v, 0.1 * v)
    wt = 0.5 / (fitted * fitted)
    gram, rhs, yy = sums(wt)
    got = _solve(gram, rhs, yy, y.size)
    if got is None:
        return None
    s, err = got
    # the jackknife over blocks of columns: the sums of each block taken off the whole
    parts = [sums(wt, block == b) for b in range(JACKKNIFE_BLOCKS)]
    loo = [_solve(gram - g, rhs - r, yy - q, y.size) for g, r, q in parts if g[1, 1] > 0]
    loo = [t[0] for t in loo if t is not None]
    if len(loo) >= 2:
        k = len(loo)
        err = max(err, float(np.sqrt((k - 1) / k * np.sum((np.asarray(loo) - np.mean(loo)) ** 2))))
    return NoiseShare(s, err, int(y.size))
