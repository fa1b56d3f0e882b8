"""Point-spread functions integrated exactly over the pixels (thesis eqs. 4, 48, 51-52).

A pixel does not sample the PSF at its centre: it collects everything that falls on its area. The
fraction of a point source's energy that pixel ``(i, j)`` (centre at integer coordinates, spanning
``[i - 1/2, i + 1/2] x [j - 1/2, j + 1/2]``) receives from a source at ``(x, y)`` is

    P_ij = integral over the pixel of I(u - x, v - y) du dv                              (thesis eq. 51)

Gaussian PSF (thesis eq. 4), ``I = exp(-r^2 / 2 sigma^2) / (2 pi sigma^2)``, sigma = FWHM / 2.3548: the
integral separates and is exact (thesis eq. 52),

    P_ij = 1/4 [erf((i + 1/2 - x)/(sqrt2 sigma)) - erf((i - 1/2 - x)/(sqrt2 sigma))]
               [erf((j + 1/2 - y)/(sqrt2 sigma)) - erf((j - 1/2 - y)/(sqrt2 sigma))].

Gaussian pointing jitter of rms ``s_j`` per axis convolves the PSF: sigma^2 -> sigma^2 + s_j^2 (exact).

Moffat PSF (Moffat 1969, A&A 3, 455; thesis eq. 48),
``I = (beta - 1) / (pi alpha^2) (1 + r^2 / alpha^2)^(-beta)``, ``alpha = FWHM / (2 sqrt(2^(1/beta) - 1))``,
normalised to 1 for beta > 1 and not separable. Each pixel is integrated with an n x n Gauss-Legendre
rule (a supersampling whose error is bounded): the integrand is analytic except at r^2 = -alpha^2, a
distance alpha from the real axis, so on a pixel of half-width h = 1/2 the one-dimensional rule converges
as rho^(-2n) with rho = 2 alpha + sqrt(4 alpha^2 + 1) (Bernstein-ellipse bound; Trefethen 2008, SIAM Rev.
50, 67). ``n`` is chosen so that rho^(-2n) <= 1e-7; the test suite measures the worst pixel error against a
brute-force 256 x 256 midpoint supersampling (below 1e-6 of the source flux). Jitter with a Moffat PSF is a
convolution with a Gaussian done by a 2-D Gauss-Hermite quadrature over the jitter offsets, of the
smallest odd order whose central stamp agrees with order + 4 to 1e-7 of the flux (checked once, when the
PSF is made; 11 nodes per axis for s_j / alpha = 0.3): the cost grows with the jitter, prefer the
Gaussian model when the jitter is a sizeable part of the PSF.

Stamps are truncated at a half-width ``R``: at least 4 FWHM, more for bright sources so that the energy
outside the stamp stays below max(0.5 e-, 1e-9 of the flux) and never above 1e-3 of the flux (Gaussian:
tail exp(-R^2 / 2 sigma^2); Moffat: (1 + R^2 / alpha^2)^(1 - beta), the energy outside the circle of
radius R, an upper bound for the square); a Moffat stamp stops sooner where its edge is fainter than
TAIL_SB_E = 0.01 e- per pixel with at most 1e-3 of the flux beyond (the halo of a wide-winged PSF, which
no frame shows). Beyond a core of k pixels about the source the Moffat's pixel integrals take 2 Gauss-Legendre
nodes per axis, which the same error bound allows there (``MoffatPSF.far_rule``: k is set by the tolerance and
the jitter's outer nodes, not by alpha; 15 px at the default 1e-7 without jitter). Half-widths are rounded
up to a short geometric ladder so that sources share stamp sizes (vectorisation). At most ``MAX_RADIUS_PX``.

The hook for other PSFs (e.g. an optics PSF that varies over the field): any object with

``__call__(x, y, dx, dy) -> ndarray (n, wy, wx)``
    fraction of the energy of the source at ``(x[k], y[k])`` [unbinned pixels of the read-out window]
    falling in the pixel whose centre is at ``(x[k] + dx[k, c], y[k] + dy[k, r])``, ``dx`` (n, wx) and
    ``dy`` (n, wy) being the column and row offsets of the stamp [pixels];
``radius_px(flux_e) -> ndarray of int``
    the stamp half-width for sources of these total fluxes [pixels];
``fwhm_px``, ``describe()``
    nominal FWHM [pixels] and a short dict for the FITS header,
``factors(x, y, dx, dy) -> (ex (n, wx), ey (n, wy))`` (optional)
    for a separable PSF (P = ey x ex): streaks are then rendered as matrix products (much faster),

can be passed as ``psf=`` to :func:`scenes.image.build.build_sources` (and to ``scenes.app.render.prepare`` /
``scenes.app.render.render``). ``x, y`` are 0-based unbinned pixels of the read-out window: add
``SensorConfig.roi_x0`` / ``roi_y0`` for full-sensor pixels, then subtract ``(W - 1) / 2``, ``(H - 1) / 2``
of the sensor and multiply by the pitch for the focal-plane position (u, v) [mm] of an optics PSF cube.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.special import erfc, ndtr

GAUSS_FWHM = 2.0 * math.sqrt(2.0 * math.log(2.0))  # FWHM / sigma of a Gaussian
MOFFAT_BETA_KOLMOGOROV = 4.765  # Trujillo et al. 2001, MNRAS 328, 977
MIN_RADIUS_FWHM = 4.0  # smallest stamp half-width [FWHM]
MAX_RADIUS_PX = 512
TAIL_E = 0.5  # electrons allowed outside a stamp ...
TAIL_REL_MAX = 1e-3  # ... but never more than this fraction of the source
TAIL_REL_MIN = 1e-9  # ... and no need to go below this fraction
#: surface brightness at a Moffat stamp's edge [e- per pixel] below which the light beyond it (at most TAIL_REL_MAX
#: of the source) is left out even when it exceeds TAIL_E: a hundredth of an electron per pixel, and less beyond,
#: which no frame shows under its read and shot noise (>= 1 e-). A Moffat of beta 1.8 keeps 0.5 e- of a 1e6 e-
#: star only beyond 4e4 alpha: every stamp of a wide-winged PSF hit MAX_RADIUS_PX, a million pixels each
TAIL_SB_E = 0.01
#: the largest core half-width :attr:`MoffatPSF.far_rule` considers [pixels]: within its core a Moffat stamp is
#: integrated at the full Gauss-Legendre order, beyond it (offsets of at least k pixels along either axis: the
#: integrand's poles that much farther from the pixel) at 2 nodes per axis; a PSF whose 2-node core would be wider
#: keeps the full order everywhere (a jitter of 5 px already: its outer Gauss-Hermite nodes lie ~70 px out)
_MOFFAT_CORE_MAX_PX = 64
_LADDER = 1.25  # stamp half-widths: w_min * 1.25^k


class PixelPSF(Protocol):
    """The pixel-integrated PSF interface (see the module notes)."""

    fwhm_px: float

    def __call__(self, x: np.ndarray, y: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray: ...

    def radius_px(self, flux_e) -> np.ndarray: ...

    def describe(self) -> dict: ...


def normal_interval_mass(a, b):
    """Standard-normal probability of ``[a, b]`` (a <= b), accurate in both tails.

    ``Phi(b) - Phi(a)``, evaluated with erfc on the side of the interval's midpoint so that far-tail
    pixels keep their relative precision instead of cancelling to zero.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    flip = (a + b) < 0.0
    lo = np.where(flip, -b, a)
    hi = np.where(flip, -a, b)
    s = 1.0 / math.sqrt(2.0)
    return 0.5 * (erfc(lo * s) - erfc(hi * s))


def gaussian_pixel_fractions(d, sigma: float, stamp: bool = False):
    """Fraction of a 1-D Gaussian of rms ``sigma`` [px] in unit pixels centred at offsets ``d`` [px] (eq. 52).

    When the offsets of each row of ``d`` are consecutive pixels (a stamp; steps of 1 to 1e-9, the
    rounding of ``column - x`` far from the origin), the normal CDF is evaluated once per pixel edge and
    differenced (absolute error ~1e-16 of the flux per pixel, plus <= 1e-9 x the peak density from the
    shared edges); otherwise each pixel's interval is integrated on its own, accurate in the far tails.
    ``stamp=True``: the caller vouches that every row of ``d`` is such a stamp (``column - x`` of consecutive
    integer columns), and the steps are not tested.
    """
    d = np.asarray(d, dtype=float)
    if stamp and d.ndim == 2 and d.shape[1] > 1 and d.size:
        consecutive = True
    else:
        step = d[:, 1:] - d[:, :-1] if d.ndim == 2 and d.shape[1] > 1 and d.size else None
        consecutive = step is not None and step.min() >= 1.0 - 1e-9 and step.max() <= 1.0 + 1e-9
    if consecutive:  # edges d - 1/2 and the last d + 1/2, scaled, their CDF and its differences: one buffer
        cdf = np.empty((d.shape[0], d.shape[1] + 1))
        np.add(d[:, -1], 0.5, out=cdf[:, -1])
        np.subtract(d, 0.5, out=cdf[:, :-1])
        cdf *= 1.0 / sigma
        ndtr(cdf, out=cdf)
        return np.subtract(cdf[:, 1:], cdf[:, :-1])
    return normal_interval_mass((d - 0.5) / sigma, (d + 0.5) / sigma)


def _ladder(w: np.ndarray, w_min: int) -> np.ndarray:
    """Round half-widths up to w_min * 1.25^k (integers), capped at MAX_RADIUS_PX."""
    w = np.maximum(np.asarray(w, dtype=float), w_min)
    k = np.ceil(np.log(w / w_min) / math.log(_LADDER) - 1e-9)
    out = np.ceil(w_min * _LADDER ** np.maximum(k, 0))
    return np.minimum(out, MAX_RADIUS_PX).astype(np.int64)


def _tail_fraction(flux_e) -> np.ndarray:
    f = np.maximum(np.asarray(flux_e, dtype=float), 1e-300)
    return np.clip(TAIL_E / f, TAIL_REL_MIN, TAIL_REL_MAX)


@dataclass(frozen=True)
class GaussianPSF:
    """Circular Gaussian PSF (thesis eq. 4), pixel-integrated with error functions (eqs. 51-52).

    Parameters
    ----------
    fwhm_px : full width at half maximum [pixels] (> 0)
    jitter_px : rms pointing jitter per axis [pixels]; added in quadrature to sigma
    """

    fwhm_px: float
    jitter_px: float = 0.0

    @property
    def sigma_px(self) -> float:
        """rms per axis of the PSF convolved with the jitter [pixels]."""
        return math.hypot(self.fwhm_px / GAUSS_FWHM, self.jitter_px)

    def __call__(self, x, y, dx, dy) -> np.ndarray:
        ex, ey = self.factors(x, y, dx, dy)
        return ey[:, :, None] * ex[:, None, :]

    def factors(self, x, y, dx, dy, stamp: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The separable form: column fractions (n, wx) and row fractions (n, wy), P = ey (x) ex (eq. 52).
        ``stamp``: every row of ``dx`` and ``dy`` is consecutive pixels (:func:`gaussian_pixel_fractions`)."""
        s = self.sigma_px
        return gaussian_pixel_fractions(dx, s, stamp), gaussian_pixel_fractions(dy, s, stamp)

    def radius_px(self, flux_e) -> np.ndarray:
        s = self.sigma_px
        w_min = math.ceil(MIN_RADIUS_FWHM * GAUSS_FWHM * s + 0.5)
        r_tail = s * np.sqrt(2.0 * np.log(1.0 / _tail_fraction(flux_e)))
        return _ladder(np.ceil(r_tail + 0.5), w_min)

    def describe(self) -> dict:
        return {"model": "gaussian", "fwhm_px": self.fwhm_px, "jitter_px": self.jitter_px,
                "sigma_px": self.sigma_px}


def _gauss_hermite_offsets(sigma: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes [px] and weights (sum 1) of an n-point Gauss-Hermite rule for a Gaussian of rms sigma."""
    t, w = np.polynomial.hermite.hermgauss(n)
    return math.sqrt(2.0) * sigma * t, w / math.sqrt(math.pi)


@dataclass(frozen=True)
class MoffatPSF:
    """Circular Moffat PSF (Moffat 1969; thesis eq. 48), pixel-integrated by Gauss-Legendre cubature.

    Parameters
    ----------
    fwhm_px : full width at half maximum [pixels]
    beta : Moffat exponent (> 1; 4.765 for Kolmogorov turbulence, Trujillo et al. 2001)
    jitter_px : rms pointing jitter per axis [pixels] (Gauss-Hermite convolution)
    tol : target relative error of the 1-D Gauss-Legendre rule per pixel (sets the order)
    """

    fwhm_px: float
    beta: float = MOFFAT_BETA_KOLMOGOROV
    jitter_px: float = 0.0
    tol: float = 1e-7
    _nodes: tuple = field(init=False, repr=False, compare=False)
    _jitter: tuple = field(init=False, repr=False, compare=False)
    _far: tuple = field(init=False, repr=False, compare=False)  #: (k, the far rule's nodes or None)

    def __post_init__(self):
        if not self.beta > 1:
            raise ValueError(f"Moffat beta = {self.beta}: must be > 1 (normalisable)")
        n = self.order
        u, w = np.polynomial.legendre.leggauss(n)
        object.__setattr__(self, "_nodes", (0.5 * u, 0.5 * w))
        object.__setattr__(self, "_jitter", self._jitter_rule())
        k, n_far = self._far_rule()
        uf, wf = np.polynomial.legendre.leggauss(n_far)
        object.__setattr__(self, "_far", (k, (0.5 * uf, 0.5 * wf) if k else None))

    @property
    def alpha_px(self) -> float:
        """Moffat core width alpha = FWHM / (2 sqrt(2^(1/beta) - 1)) [pixels]."""
        return self.fwhm_px / (2.0 * math.sqrt(2.0 ** (1.0 / self.beta) - 1.0))

    @property
    def order(self) -> int:
        """Gauss-Legendre nodes per pixel axis: rho^(-2n) <= tol, rho = 2 alpha + sqrt(4 alpha^2 + 1)."""
        return self._order_for(2.0 * self.alpha_px + math.sqrt(4.0 * self.alpha_px ** 2 + 1.0))

    def _order_for(self, rho: float) -> int:
        return int(min(32, max(2, math.ceil(math.log(1.0 / self.tol) / (2.0 * math.log(rho))))))

    @property
    def far_rule(self) -> tuple[int, int]:
        """(k, n): pixels offset from the source by at least ``k`` [pixels] along either axis take ``n`` nodes per
        axis (:meth:`_far_rule`, found once when the PSF is made)."""
        k, nodes = self._far
        return (k, nodes[0].size) if k else (0, self.order)

    def _far_rule(self) -> tuple[int, int]:
        """(k, n): pixels offset from the source by at least ``k`` [pixels] along either axis take ``n`` nodes per
        axis. For such a pixel each 1-D rule's integrand has its poles at least ``D = k - 1/2 - (the largest
        jitter offset)`` from the pixel's centre along the real axis (the x-integrand's at
        ``x = +-i sqrt(alpha^2 + y^2)``, the pixel ``|x| >= k``; the y-integrand's at ``+-i sqrt(alpha^2 + x^2)``,
        imaginary part ``>= |x|``), so the Bernstein ellipse of the pixel (half-width 1/2) reaching them has
        ``rho >= 2 D + sqrt(4 D^2 - 1)``: the same bound rho^(-2n) <= tol as the core's. ``k`` is the smallest that
        gives 2 nodes (at most :data:`_MOFFAT_CORE_MAX_PX`); (0, order) when that saves nothing."""
        jo = float(np.max(np.abs(self._jitter[0]))) if self._jitter[0].size else 0.0
        n = self.order
        for k in range(2, _MOFFAT_CORE_MAX_PX + 1):
            d = k - 0.5 - jo
            if d > 0.5 and self._order_for(2.0 * d + math.sqrt(4.0 * d * d - 1.0)) <= 2:
                return (k, 2) if n > 2 else (0, n)
        return 0, n

    @property
    def jitter_nodes(self) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Hermite offsets [px] and weights of the jitter convolution (one node without jitter)."""
        return self._jitter

    def _jitter_rule(self) -> tuple[np.ndarray, np.ndarray]:
        """The smallest odd Gauss-Hermite order whose central 9 x 9 stamp agrees with order + 4 to 1e-7."""
        if self.jitter_px <= 0:
            return np.zeros(1), np.ones(1)
        offs = np.arange(-4, 5, dtype=float)[None, :]
        prev = None
        for n in range(3, 64, 4):
            rule = _gauss_hermite_offsets(self.jitter_px, n)
            cur = self._stamp(np.zeros(1), np.zeros(1), offs + 0.3, offs - 0.2, rule)
            if prev is not None and np.abs(cur - prev[1]).max() < 1e-7:
                return prev[0]
            prev = (rule, cur)
        return prev[0]

    def profile(self, r2) -> np.ndarray:
        """Surface density I(r) [1/pixel^2] at squared radii ``r2`` [pixel^2]."""
        a2 = self.alpha_px ** 2
        return (self.beta - 1.0) / (math.pi * a2) * (1.0 + np.asarray(r2) / a2) ** (-self.beta)

    def __call__(self, x, y, dx, dy) -> np.ndarray:
        k, far_nodes = self._far
        dx = np.asarray(dx, dtype=float)
        dy = np.asarray(dy, dtype=float)
        if not k:
            return self._stamp(x, y, dx, dy, self._jitter)
        cols = np.any(np.abs(dx) < k, axis=0)  # the core: within k of some source along the axis
        rows = np.any(np.abs(dy) < k, axis=0)
        if cols.all() and rows.all():
            return self._stamp(x, y, dx, dy, self._jitter)
        out = self._stamp(x, y, dx, dy, self._jitter, far_nodes)
        if cols.any() and rows.any():
            out[np.ix_(np.arange(out.shape[0]), rows, cols)] = self._stamp(x, y, dx[:, cols], dy[:, rows], self._jitter)
        return out

    def _stamp(self, x, y, dx, dy, jitter_rule, nodes=None) -> np.ndarray:
        u, w = self._nodes if nodes is None else nodes
        a2 = self.alpha_px ** 2
        norm = (self.beta - 1.0) / (math.pi * a2)
        dx = np.asarray(dx, dtype=float)
        dy = np.asarray(dy, dtype=float)
        out = np.zeros((dx.shape[0], dy.shape[1], dx.shape[1]))
        jo, jw = jitter_rule
        for ox, wox in zip(jo, jw):
            for oy, woy in zip(jo, jw):
                for uy, wy in zip(u, w):
                    ty = (dy + (uy - oy)) ** 2 / a2  # (n, wy)
                    for ux, wx in zip(u, w):
                        tx = (dx + (ux - ox)) ** 2 / a2  # (n, wx)
                        r = 1.0 + ty[:, :, None] + tx[:, None, :]
                        out += (wox * woy * wy * wx) * r ** (-self.beta)
        out *= norm
        return out

    def radius_px(self, flux_e) -> np.ndarray:
        """The stamp half-width: the energy beyond it below max(TAIL_E, TAIL_REL_MIN of the flux) (the module
        notes) or, if smaller, the radius beyond which at most TAIL_REL_MAX of the flux is left out at a surface
        brightness below TAIL_SB_E at the edge (a wide-winged PSF's faint halo)."""
        fwhm = math.hypot(self.fwhm_px, GAUSS_FWHM * self.jitter_px)
        w_min = math.ceil(MIN_RADIUS_FWHM * fwhm + 0.5)
        a, b = self.alpha_px, self.beta
        flux = np.maximum(np.asarray(flux_e, dtype=float), 1e-300)
        r_tail = a * np.sqrt(_tail_fraction(flux) ** (-1.0 / (b - 1.0)) - 1.0)
        r_rel = a * math.sqrt(TAIL_REL_MAX ** (-1.0 / (b - 1.0)) - 1.0)  # (1 + R^2/a^2)^(1 - b) = TAIL_REL_MAX
        peak = flux * (b - 1.0) / (math.pi * a * a)  # I(R) = peak (1 + R^2/a^2)^(-b) = TAIL_SB_E
        r_sb = a * np.sqrt(np.maximum((peak / TAIL_SB_E) ** (1.0 / b) - 1.0, 0.0))
        r = np.minimum(r_tail, np.maximum(r_rel, r_sb)) + 3.0 * self.jitter_px
        return _ladder(np.ceil(r + 0.5), w_min)

    def describe(self) -> dict:
        return {"model": "moffat", "fwhm_px": self.fwhm_px, "beta": self.beta, "alpha_px": self.alpha_px,
                "jitter_px": self.jitter_px, "gl_order": self.order}


def psf_from_config(model: str, fwhm_arcsec: float, beta: float, jitter_rms_arcsec: float,
                    pixel_scale_arcsec: float) -> GaussianPSF | MoffatPSF:
    """The scene's ``[psf]`` table -> a pixel-integrated PSF in unbinned pixels of ``pixel_scale_arcsec``."""
    fwhm = fwhm_arcsec / pixel_scale_arcsec
    jit = jitter_rms_arcsec / pixel_scale_arcsec
    if model == "gaussian":
        return GaussianPSF(fwhm, jit)
    if model == "moffat":
        return MoffatPSF(fwhm, beta, jit)
    raise ValueError(f"unknown PSF model {model!r}")
