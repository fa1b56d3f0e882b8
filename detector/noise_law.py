"""Whether a change of the frame is charge or an offset of the read-out, by the shot noise it carries.

Charge, of light or dark current, is counted: its variance equals its mean (Poisson; Janesick 2007, Photon
Transfer, SPIE PM170, ch. 2-3, the photon transfer curve's shot-noise regime). An offset added at the read-out
(a bias structure, an amplifier's pattern) carries no noise of its own. On one dark frame a dark-rate field and
a bias structure of the same shape make the same mean image; only the variance tells them apart.

The frame's own noise is measured on differences of horizontally adjacent pixel pairs, ``d = r_a - r_b`` of the
residual ``r = data - model``: a structure smooth over two pixels cancels in them, whatever its origin and
however badly any candidate fits it, while their variance is ``v_a + v_b`` plus the two pixels' extra noise.
The squared differences are fitted (weighted least squares, ``Var(d^2) = 2 (v_a + v_b)^2`` for Gaussian noise)
as ``d^2 - (v_a + v_b) = s x + c0 + c1 (v_a + v_b)``, with ``x`` the change's shot-noise variance at the pair
(``(delta_a + delta_b) / g``, :attr:`detector.signatures.Residuals.poisson_adu` per ADU) and two nuisances that
any mean level or a read noise (``c0``) and a gain (``c1``) off by a little would leave. ``s`` is 1 for charge
and 0 for an offset; :func:`detector.significance.law_verdict` says which of the two the frame excludes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import significance

#: a pair whose difference exceeds this many standard deviations of its model noise is an outlier (a cosmic ray, a
#: hot pixel the spikes missed) and left out: a detection (DETECTION_SIGMA, 6e-7 of Gaussian pairs); an extra
#: variance as large as the model's, the most this test weighs, moves it to 3.5 sigma of the true noise (5e-4 of
#: the pairs, their share of the sum of squares ~1e-2 of its excess)
OUTLIER_SIGMA = significance.DETECTION_SIGMA


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


#: the most pixel pairs the fit reads: every k-th row beyond it (a numerical budget: 2^18 pairs measure the share of
#: a change of 10 % of the variance to +-0.03, and the whole of a 2048^2 frame would cost seconds per candidate)
MAX_PAIRS = 2 ** 18


def noise_share(residual_adu: np.ndarray, var_adu2: np.ndarray, usable: np.ndarray, change_adu: np.ndarray,
                poisson_adu: float) -> NoiseShare | None:
    """The :class:`NoiseShare` of ``change_adu`` (a mean change of the frame [ADU], the candidate's) in the
    residual ``residual_adu`` (data - model [ADU]) of model variance ``var_adu2`` [ADU^2], on the ``usable``
    pixels (module docstring; at most MAX_PAIRS pairs, from evenly spaced rows). None without MIN_TEST_PIXELS pairs
    or when the change's variance is not measurable apart from the nuisances (a uniform change: a level, which a
    read noise or a gain off by as much would also explain)."""
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
    d = (ra[ok] - rb[ok]) ** 2
    v = va[ok] + vb[ok]
    x = (da[ok] + db[ok]) * poisson_adu
    keep = np.isfinite(d) & np.isfinite(x) & (v > 0) & (d <= OUTLIER_SIGMA ** 2 * v)
    if keep.sum() < significance.MIN_TEST_PIXELS:
        return None
    d, v, x = d[keep], v[keep], x[keep]
    wt = 0.5 / (v * v)  # 1 / Var(d^2) for Gaussian pixel noise
    y = d - v
    # weighted normal equations of y = s x + c0 + c1 v, the nuisances (1, v) profiled out of x's
    cols = (x, np.ones_like(x), v)
    gram = np.array([[float(np.sum(wt * a * b)) for b in cols] for a in cols])
    rhs = np.array([float(np.sum(wt * a * y)) for a in cols])
    yy = float(np.sum(wt * y * y))
    scale = np.sqrt(np.maximum(np.diag(gram)[1:], 1e-300))
    gn = np.linalg.pinv(gram[1:, 1:] / np.outer(scale, scale), rcond=1e-10) / np.outer(scale, scale)
    xx = gram[0, 0] - gram[0, 1:] @ gn @ gram[1:, 0]
    if not np.isfinite(xx) or xx <= 1e-10 * gram[0, 0]:
        return None
    xy = rhs[0] - gram[0, 1:] @ gn @ rhs[1:]
    s = float(xy / xx)
    chi2 = yy - rhs[1:] @ gn @ rhs[1:] - s * xy
    dof = y.size - 1 - int(np.linalg.matrix_rank(gram[1:, 1:] / np.outer(scale, scale), tol=1e-10))
    inflate = max(1.0, float(np.sqrt(max(chi2, 0.0) / max(dof, 1))))
    return NoiseShare(s, inflate / float(np.sqrt(xx)), int(y.size))
