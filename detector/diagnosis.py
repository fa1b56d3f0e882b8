"""How an effect shows in the residuals of a measured frame against the model: signatures for diagnosis.

``newtsim diagnose`` asks every effect the scene lacks to fit itself to the residuals ``r = data - model``
(ADU) under the model's own per-pixel variance ``v`` (:meth:`detector.Detector.moments`) and ranks the
candidates by the Bayesian information criterion (Schwarz 1978, Ann. Stat. 6, 461)::

    delta_BIC = delta(-2 ln L) + k ln n

with ``k`` the fitted parameters and ``n`` the data points the fit used. Each effect declares *how* it
is fitted through its ``signature`` (DESIGN.md convention 1); the generic kinds are here:

* :class:`LinearSignature`: the effect adds ``sum_j c_j T_j`` to the frame (a bias ramp, a glow, a
  vignetting loss ``S rho^2``): weighted linear least squares, ``delta(-2 ln L) = delta chi^2``. Several
  *variants* (edges, scales, region grids) may be tried; the best counts one parameter more.
* :class:`VarianceSignature`: the effect adds zero-mean scatter of variance ``theta T`` (PRNU: ``T = S^2``,
  kTC: ``T = 1``): maximum likelihood of the Gaussian ``N(0, v + theta T)``.
* tail and profile statistics (defects, cosmic rays, row/column structure) are fitted by their counts and
  distributions, not by pixel positions (:class:`Residuals` carries the spike and profile statistics).

Signatures work in output pixels and ADU; :class:`Residuals` gives them the model's pieces (photo-electron
signal, dark signal, coordinates) so that templates come from the effect's own physics functions with
unit parameters, and the fitted parameters are the plugin's own.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from .sensor import SensorConfig

#: |z - median_3x3(z)| above which a pixel is a spike (hot/dead pixel, cosmic-ray hit) [sigma]
SPIKE_SIGMA = 5.0
#: |column or row mean| above which a column/row is an outlier [sigma of the mean]
LINE_SIGMA = 6.0
#: columns of the running median an outlier column is compared with [columns]
LINE_WINDOW = 9
#: pixels used at most by a variance fit (a regular subsample beyond that) [pixels]
MAX_FIT_PIXELS = 1_000_000


@dataclass
class SpikeStats:
    """Counts of local outliers of a frame's normalised residuals (data or a model realisation)."""

    single_pos: int  #: isolated positive spikes (1 pixel): hot/warm pixels
    cluster_pos: int  #: connected positive spikes of 2 or more pixels: cosmic-ray tracks
    single_neg: int  #: isolated negative spikes: dead pixels
    hot_cols: int  #: columns whose mean lies LINE_SIGMA above the model
    cold_cols: int  #: columns whose mean lies LINE_SIGMA below the model
    #: excess electrons of the positive single spikes, and data/model ratio of the negative ones
    single_pos_excess_e: np.ndarray = field(default_factory=lambda: np.zeros(0))
    single_neg_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cluster_pixels: int = 0
    col_excess_e: np.ndarray = field(default_factory=lambda: np.zeros(0))  #: per outlier hot column, per pixel

    def counts(self) -> dict[str, int]:
        return {"single_pos": self.single_pos, "cluster_pos": self.cluster_pos, "single_neg": self.single_neg,
                "hot_cols": self.hot_cols, "cold_cols": self.cold_cols}


def _median3(z: np.ndarray) -> np.ndarray:
    from scipy.ndimage import median_filter

    return median_filter(z, size=3, mode="nearest")


def spike_stats(data: np.ndarray, model: np.ndarray, var: np.ndarray, usable: np.ndarray, gain: float
                ) -> tuple[SpikeStats, np.ndarray]:
    """Find the local outliers of ``z = (data - model) / sqrt(var)``; return the statistics and the mask
    of every pixel that can only be compared statistically (spikes and outlier columns)."""
    from scipy import ndimage

    z = np.where(usable, (data - model) / np.sqrt(var), 0.0).astype(np.float32)
    local = z - _median3(z)
    pos = usable & (local > SPIKE_SIGMA) & (z > SPIKE_SIGMA)
    neg = usable & (local < -SPIKE_SIGMA) & (z < -SPIKE_SIGMA)
    lab, n = ndimage.label(pos, structure=np.ones((3, 3)))
    sizes = np.bincount(lab.ravel(), minlength=n + 1)[1:] if n else np.zeros(0, int)
    single_lab = np.nonzero(sizes == 1)[0] + 1
    single = np.isin(lab, single_lab) if single_lab.size else np.zeros_like(pos)
    # isolated negative pixels (dead pixels): no negative neighbour
    nlab, nn = ndimage.label(neg, structure=np.ones((3, 3)))
    nsizes = np.bincount(nlab.ravel(), minlength=nn + 1)[1:] if nn else np.zeros(0, int)
    # columns: mean residual of the pixels that are not spikes, in units of its standard error
    keep = usable & ~pos & ~neg
    cnt = keep.sum(axis=0)
    r = np.where(keep, data - model, 0.0)
    col_mean = r.sum(axis=0) / np.maximum(cnt, 1)
    col_err = np.sqrt(np.where(keep, var, 0.0).sum(axis=0)) / np.maximum(cnt, 1)
    # against the neighbouring columns (a running median), so smooth structure (glow, gradients) is not
    # mistaken for defective columns
    from scipy.ndimage import median_filter

    local_mean = col_mean - median_filter(col_mean, size=LINE_WINDOW, mode="nearest")
    zc = np.where(cnt > 0, local_mean / np.maximum(col_err, 1e-12), 0.0)
    hot_c, cold_c = zc > LINE_SIGMA, zc < -LINE_SIGMA
    stats = SpikeStats(
        single_pos=int(single_lab.size), cluster_pos=int(n - single_lab.size), single_neg=int((nsizes == 1).sum()),
        hot_cols=int(hot_c.sum()), cold_cols=int(cold_c.sum()),
        single_pos_excess_e=((data - model)[single] * gain).astype(np.float64),
        single_neg_ratio=np.where(model[neg] > 0, data[neg] / np.maximum(model[neg], 1e-6), 1.0),
        cluster_pixels=int(pos.sum() - single_lab.size), col_excess_e=local_mean[hot_c] * gain)
    statistical = pos | neg
    statistical[:, hot_c | cold_c] = True
    return stats, statistical


@dataclass
class Residuals:
    """The measurement against the model, as every signature sees it (output pixels).

    Attributes
    ----------
    data_adu, model_adu : 2-D float32 [ADU]
        Measured frame and the model's mean (bias included).
    var_adu2 : 2-D float32 [ADU^2]
        The model's per-pixel variance.
    fit : 2-D bool
        Pixels the model predicts deterministically (not saturated, not a spike, not an outlier column).
    photo_adu : 2-D float32 [ADU]
        The model's photo-electron part (sources, sky, flat screen) after the pixel response.
    dark_e : 2-D float32 [e-]
        The model's mean dark charge per output pixel (dark current, glow, ...).
    ys, xs : 1-D float [sensor pixels]
        Sensor coordinates of the output pixel centres.
    sensor : SensorConfig
    exptime_s : float [s]
    data_spikes, model_spikes : SpikeStats
        Local-outlier statistics of the measurement and of one noisy realisation of the model.
    """

    data_adu: np.ndarray
    model_adu: np.ndarray
    var_adu2: np.ndarray
    fit: np.ndarray
    photo_adu: np.ndarray
    dark_e: np.ndarray
    ys: np.ndarray
    xs: np.ndarray
    sensor: SensorConfig
    exptime_s: float
    data_spikes: SpikeStats
    model_spikes: SpikeStats
    _flat: dict = field(default_factory=dict, repr=False)

    @property
    def gain(self) -> float:
        return self.sensor.gain_e_per_adu

    @property
    def pixel_sum(self) -> int:
        """Sensor pixels whose charge adds into one output pixel (b^2 for sum binning, 1 for average)."""
        b = self.sensor.binning
        return b * b if self.sensor.binning_mode == "sum" else 1

    @property
    def adu_sum(self) -> int:
        """Read-out values summed into one output pixel after the ADU stage (CMOS digital sum binning)."""
        return self.pixel_sum if self.sensor.kind != "ccd" else 1

    @property
    def charge_e(self) -> np.ndarray:
        """Model mean collected charge [e-] per output pixel (photo + dark)."""
        return (self.photo_adu * self.gain + self.dark_e).astype(np.float32)

    def flat(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(index, residual, weight) of the fitted pixels, flattened once (float64 for the sums)."""
        if not self._flat:
            idx = np.flatnonzero(self.fit)
            r = (self.data_adu.ravel()[idx] - self.model_adu.ravel()[idx]).astype(np.float64)
            w = 1.0 / self.var_adu2.ravel()[idx].astype(np.float64)
            self._flat.update(idx=idx, r=r, w=w)
        return self._flat["idx"], self._flat["r"], self._flat["w"]

    @property
    def n_fit(self) -> int:
        return int(self.flat()[0].size)

    def chi2(self) -> float:
        _, r, w = self.flat()
        return float(np.dot(r * r, w))

    def subsample(self) -> np.ndarray:
        """Positions (into the flat arrays) of at most MAX_FIT_PIXELS regularly spaced fitted pixels."""
        n = self.n_fit
        step = max(1, n // MAX_FIT_PIXELS)
        return np.arange(0, n, step)


@dataclass
class Fit:
    """One effect fitted to the residuals."""

    effect: str
    params: dict
    delta_m2lnl: float  #: change of -2 ln L (negative: the effect explains something)
    k: int  #: fitted parameters
    n: int  #: data points of the likelihood
    explanation: str
    #: the mean frame change it predicts [ADU] (linear kinds) and the variance it adds [ADU^2]
    delta_adu: np.ndarray | None = None
    extra_var_adu2: np.ndarray | float | None = None
    note: str = ""

    @property
    def delta_bic(self) -> float:
        return float(self.delta_m2lnl + self.k * np.log(max(self.n, 2)))


class Signature:
    """Base of a diagnosis signature: ``fit(residuals, name) -> Fit | None`` (None: nothing to fit)."""

    kind = "custom"
    #: a short phrase for reports: which residual pattern the effect makes
    pattern = ""

    def fit(self, res: Residuals, name: str) -> Fit | None:  # pragma: no cover - abstract
        raise NotImplementedError


# --- linear templates ----------------------------------------------------------------------------------------

@dataclass
class Variant:
    """One linear model of an effect: templates [ADU per unit coefficient] and the map to parameters."""

    templates: list[np.ndarray]
    to_params: Callable[[np.ndarray], dict | None]  #: None when the coefficients are outside the bounds
    label: str = ""


def weighted_lstsq(templates: list[np.ndarray], idx: np.ndarray, r: np.ndarray, w: np.ndarray
                   ) -> tuple[np.ndarray, float]:
    """Weighted least squares of ``r`` on the templates at flat pixels ``idx``: (coefficients, delta chi2)."""
    t = np.stack([np.broadcast_to(tm, templates[0].shape if tm.ndim == 2 else tm.shape).ravel()[idx]
                  for tm in templates]).astype(np.float64)
    tw = t * w
    a = tw @ t.T
    b = tw @ r
    try:
        c = np.linalg.solve(a + 1e-12 * np.trace(a) * np.eye(len(b)), b)
    except np.linalg.LinAlgError:
        return np.zeros(len(b)), 0.0
    return c, float(-(b @ c))


class LinearSignature(Signature):
    """The effect adds a linear combination of templates to the mean frame (see module docstring).

    Parameters
    ----------
    variants : callable(Residuals) -> iterable of Variant
    explain : callable(params, Residuals) -> str
    pattern : str
    extra_k : int
        Parameters chosen among the variants (an edge, a scale), counted in the BIC.
    refine : callable(best Variant, Residuals) -> iterable of Variant, optional
        More variants around the best one (a finer scale), tried once after the first pass.
    """

    kind = "linear"

    def __init__(self, variants: Callable[[Residuals], Iterable[Variant]], explain: Callable[[dict, Residuals], str],
                 pattern: str = "", extra_k: int = 1,
                 refine: Callable[[Variant, Residuals], Iterable[Variant]] | None = None):
        self.variants, self.explain, self.pattern, self.extra_k = variants, explain, pattern, extra_k
        self.refine = refine

    def fit(self, res: Residuals, name: str) -> Fit | None:
        best = self._best(res, list(self.variants(res)))
        if best is not None and self.refine is not None:
            best = self._best(res, [best[0], *self.refine(best[0], res)]) or best
        if best is None:
            return None
        v, d, c, params = best
        k = len(v.templates) + self.extra_k
        delta = sum(ci * np.asarray(t, np.float32) for ci, t in zip(c, v.templates))
        return Fit(name, params, d, k, res.n_fit, self.explain(params, res),
                   delta_adu=np.broadcast_to(delta, res.data_adu.shape), note=v.label)

    @staticmethod
    def _best(res: Residuals, variants: list[Variant]):
        idx, r, w = res.flat()
        best = None
        for v in variants:
            c, d = weighted_lstsq(v.templates, idx, r, w)
            params = v.to_params(c)
            if params is None:
                continue
            if best is None or d < best[1]:
                best = (v, d, c, params)
        return best


# --- added variance --------------------------------------------------------------------------------------------

def ml_variance_scale(r: np.ndarray, v: np.ndarray, t: np.ndarray, z_cap: float = 8.0) -> tuple[float, float]:
    """Maximum-likelihood ``theta >= 0`` of ``r ~ N(0, v + theta t)``: (theta, delta(-2 ln L)).

    ``-2 ln L = sum r^2 / (v + theta t) + ln(v + theta t)``; each pixel's ``r^2 / v`` is capped at
    ``z_cap^2`` so a few outliers cannot dominate (they are compared by their counts instead).
    """
    r2 = np.minimum(r * r, z_cap * z_cap * v)

    def m2l(theta):
        s = v + theta * t
        return float(np.sum(r2 / s + np.log(s)))

    base = m2l(0.0)
    tmax = max(float(np.mean(r2) / max(np.mean(t), 1e-30)), 1e-30) * 10
    best = optimize.minimize_scalar(lambda lt: m2l(np.exp(lt)), bounds=(np.log(tmax) - 30, np.log(tmax)),
                                    method="bounded", options={"xatol": 1e-4})
    theta = float(np.exp(best.x))
    d = m2l(theta) - base
    return (theta, d) if d < 0 else (0.0, 0.0)


class VarianceSignature(Signature):
    """The effect adds zero-mean scatter of variance ``theta * template(res)`` [ADU^2 per unit theta]."""

    kind = "variance"

    def __init__(self, template: Callable[[Residuals], np.ndarray], to_params: Callable[[float, Residuals], dict | None],
                 explain: Callable[[dict, Residuals], str], pattern: str = ""):
        self.template, self.to_params, self.explain, self.pattern = template, to_params, explain, pattern

    def fit(self, res: Residuals, name: str) -> Fit | None:
        idx, r, w = res.flat()
        sub = res.subsample()
        t = np.broadcast_to(self.template(res), res.data_adu.shape).ravel()[idx[sub]].astype(np.float64)
        if not np.any(t > 0):
            return None
        theta, d = ml_variance_scale(r[sub], 1.0 / w[sub], t)
        params = self.to_params(theta, res)
        if params is None:
            return None
        # the likelihood was evaluated on a subsample: scale to all fitted pixels
        d *= res.n_fit / sub.size
        extra = theta * np.broadcast_to(self.template(res), res.data_adu.shape)
        return Fit(name, params, d, 1, res.n_fit, self.explain(params, res), extra_var_adu2=extra)


# --- counts ------------------------------------------------------------------------------------------------------

def poisson_deviance(observed: float, expected: float) -> float:
    """Poisson deviance ``2 [o ln(o/e) - (o - e)]`` of an observed count against its expectation."""
    e = max(expected, 1e-3)
    o = max(observed, 0.0)
    return float(2 * ((o * np.log(o / e) if o > 0 else 0.0) - (o - e)))


def count_gain(observed: float, model_expected: float) -> float:
    """delta(-2 ln L) when an effect raises the expected count from ``model_expected`` to ``observed``."""
    return -poisson_deviance(observed, model_expected)


class CountSignature(Signature):
    """The effect makes outliers (spikes, outlier columns) at unknown positions: fitted by their numbers and
    amplitudes. ``fit_counts(res) -> (params, observed, model_expected, k) | None``."""

    kind = "counts"

    def __init__(self, fit_counts: Callable[[Residuals], tuple | None], explain: Callable[[dict, Residuals], str],
                 pattern: str = ""):
        self.fit_counts, self.explain, self.pattern = fit_counts, explain, pattern

    def fit(self, res: Residuals, name: str) -> Fit | None:
        out = self.fit_counts(res)
        if out is None:
            return None
        params, observed, expected, k = out
        return Fit(name, params, count_gain(observed, expected), k, max(int(observed + expected), 2),
                   self.explain(params, res))


# --- helpers for templates --------------------------------------------------------------------------------------

def frame_fraction(res: Residuals) -> float:
    """Read-out window area over the full sensor area (to scale counts to the full-sensor parameters)."""
    s = res.sensor
    w, h = s.roi_shape
    return (w * h) / (s.sensor_width_px * s.sensor_height_px)


def sensor_uv(res: Residuals) -> tuple[np.ndarray, np.ndarray]:
    """Normalised sensor coordinates u (columns), v (rows) in [-0.5, 0.5] of the output pixels (1-D each)."""
    s = res.sensor
    return (res.xs / max(s.sensor_width_px - 1, 1) - 0.5, res.ys / max(s.sensor_height_px - 1, 1) - 0.5)


def edge_fraction(img: np.ndarray, where: str) -> float:
    """Mean of ``img`` on the 10 % border named ``where`` over its mean on the central 20 % (for words)."""
    h, w = img.shape
    c = img[int(0.4 * h):int(0.6 * h) + 1, int(0.4 * w):int(0.6 * w) + 1].mean()
    e = {"left": img[:, : max(1, w // 10)], "right": img[:, -max(1, w // 10):],
         "bottom": img[: max(1, h // 10)], "top": img[-max(1, h // 10):]}[where].mean()
    return float(e / c) if c else float("inf")
