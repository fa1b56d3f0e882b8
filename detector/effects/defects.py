"""Sparse hardware defects: hot/warm/stuck pixels and column defects.

Hot pixels follow the reference thesis (eqs. 35-40): every defect has a *time-to-double* ``t2``, the
exposure after which its value has doubled its zero-exposure level, i.e. ``B + r t2 = 2 B`` with ``B`` the
bias [ADU] and ``r`` the defect's excess dark rate [ADU/s], so ``r_e = B g / t2`` electrons per second
(``g`` the gain in e-/ADU). ``t2`` is drawn from a Weibull law (shape ``k``, scale ``lambda``; the
exponential law is ``k = 1``), the distribution measured on the calibration darks (``characterize`` fits
the same law, eq. 38). Defects with ``t2`` below ``hot_threshold_s`` are *hot*, the others *warm*; a
fraction are *stuck*: their value is fixed whatever the exposure.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..signatures import (
    DEFECT_K,
    TRACK_MAX_PEAK_SHARE,
    Fit,
    GroupSignature,
    Signature,
    frame_fraction,
    group_excess,
    on_source,
    outlier_pixels,
    periodic_line_peak,
    spread_check,
)
from ..significance import DETECTION_SIGMA, EXPLAINS_MOST
from ..stats import mad_std
from .base import Effect, EffectParams, Stage, Tile, register_effect
from .common import hardware_positions, in_tile, output_xy, roi_mask
from .pixel_response import MAX_DEAD_CLUSTER_PX

# --- pure functions ---------------------------------------------------------------------------------------

def draw_time_to_double(rng: np.random.Generator, n: int, law: str, shape: float, scale_s: float) -> np.ndarray:
    """Times-to-double [s] from a Weibull(shape k, scale lambda) law; ``exponential`` forces k = 1 (eq. 39-40)."""
    k = 1.0 if law == "exponential" else shape
    return scale_s * rng.weibull(k, size=n)


def hot_rate_e_per_s(t_double_s: np.ndarray, bias_adu: float, gain_e_per_adu: float) -> np.ndarray:
    """Excess dark current [e-/s] of a defect that doubles the bias level ``B`` after ``t2`` (eq. 38)."""
    return bias_adu * gain_e_per_adu / np.maximum(t_double_s, 1e-9)


#: the level [ADU] whose doubling time defines t2 on a sensor whose bias is 0 (bias-subtracted data)
NOMINAL_DOUBLING_LEVEL_ADU = 1000.0


def doubling_level_adu(bias_adu: float, override: float | None) -> float:
    """The level ``B`` of eq. 38 [ADU]: ``override`` if given, else the bias, else (bias 0: calibrated data,
    where eq. 38's reference is gone) :data:`NOMINAL_DOUBLING_LEVEL_ADU`."""
    if override is not None:
        return float(override)
    return float(bias_adu) if bias_adu > 0 else NOMINAL_DOUBLING_LEVEL_ADU


# --- diagnosis signatures (detector.signatures) -------------------------------------------------------------

def weibull_from_detections(t2_detected_s: np.ndarray, t2_limit_s: float, shape: float) -> tuple[float, float]:
    """Weibull scale [s] whose part below the detection limit ``t2_limit_s`` has the detections' median,
    and the fraction of all defects that part holds: (scale_s, detected_fraction).

    Only defects with ``t2 < t2_limit`` (excess above the spike threshold) are seen; their conditional
    median is ``F^-1(F(t2_limit) / 2)`` with ``F(t) = 1 - exp(-(t / lambda)^k)`` (eq. 39).
    """
    from scipy.optimize import brentq

    med = float(np.median(t2_detected_s))

    def cond_median(lam):
        f = -np.expm1(-(t2_limit_s / lam) ** shape)
        return lam * (-np.log1p(-f / 2)) ** (1 / shape)

    lo, hi = 1e-6 * t2_limit_s, 1e6 * t2_limit_s
    try:
        lam = brentq(lambda ll: np.log(cond_median(np.exp(ll)) / med), np.log(lo), np.log(hi))
        lam = float(np.exp(lam))
    except ValueError:
        lam = t2_limit_s
    return lam, float(-np.expm1(-(t2_limit_s / lam) ** shape))


def _hot_counts(res):
    d, m = res.data_spikes, res.model_spikes
    if d.single_pos <= m.single_pos or d.single_pos_excess_e.size == 0:
        return None
    s, t = res.sensor, res.exptime_s
    if t <= 0:
        return None
    level, extra = doubling_level_adu(s.bias_adu, None), {}
    if s.bias_adu <= 0:  # a bias-subtracted frame: t2 refers to a nominal level instead of the bias
        extra = {"doubling_level_adu": level}
    rate = np.maximum(d.single_pos_excess_e, 1e-3) / t
    t2 = hot_rate_e_per_s(rate, level, s.gain_e_per_adu)  # t2 = B g / rate (the same relation)
    limit_e = float(np.min(d.single_pos_excess_e))
    t2_limit = float(hot_rate_e_per_s(np.array([limit_e / t]), level, s.gain_e_per_adu)[0])
    shape = 0.8
    scale, frac = weibull_from_detections(t2, t2_limit, shape)
    count = round((d.single_pos - m.single_pos) / max(frac, 1e-6) / frame_fraction(res))
    count = min(count, 10_000_000)
    return ({"count": count, "law": "weibull", "weibull_shape": shape, "scale_s": round(scale, 3), **extra},
            d.single_pos, m.single_pos, 2)


def hot_defects(res, groups: np.ndarray) -> np.ndarray:
    """The groups of bright pixels that may be hot or warm pixels: one pixel, or a pixel holding more than
    TRACK_MAX_PEAK_SHARE of its group's signal (a hot pixel and the few per cent its neighbours couple), seen
    whole (not touching a saturated or flagged pixel), not on the model's sources. Groups whose charge spreads
    over their pixels are tracks or blobs (:func:`detector.signatures.is_track`), not a pixel's own leakage."""
    if groups.size == 0:
        return groups
    ok = (((groups["n"] == 1) | (groups["peak_share"] > TRACK_MAX_PEAK_SHARE)) & ~groups["edge"]
          & ~on_source(res, groups["peak"]))
    return groups[ok]


def _hot_groups(res):
    """Hot and warm pixels from the chi2 their groups of bright pixels carry beyond what the model's realisation
    makes (:func:`detector.signatures.group_gain`, as dead pixels and particle tracks are judged): ten pixels
    at 100 sigma are a finding whatever their number, which a count of spikes alone (a two-sample Poisson
    ratio of 10 against 0: a delta of -14) does not see. The law's parameters from :func:`_hot_counts`."""
    counted = _hot_counts(res)
    if counted is None:
        return None
    params = counted[0]
    npx = outlier_pixels(res)
    got = group_excess(hot_defects(res, res.data_spikes.pos_groups), hot_defects(res, res.model_spikes.pos_groups),
                       DEFECT_K, npx)
    if got is None:
        return None
    delta, n_data, n_model = got
    return params, delta, n_data, n_model, 2


def column_mixture_gain(x: np.ndarray, threshold: float) -> tuple[float, int]:
    """delta(-2 ln L) of column means ``x`` [standard errors] explained by a mixture of normal columns
    N(0, 1) and outlier populations -- hot columns N(mu_h, 1 + tau_h^2) with mu_h >= threshold and dead
    (cold) columns N(mu_c, 1 + tau_c^2) with mu_c <= -threshold -- against normal columns only (EM fit of
    the fractions, means and spreads). Returns (delta, parameters fitted)."""
    comps = []
    for sign in (1, -1):
        sel = sign * x > threshold
        if sel.any():
            comps.append([sign, sel.mean(), float(x[sel].mean()), max(float(x[sel].var()), 0.0)])
    if not comps:
        return 0.0, 0

    def logn(v, mu, var):
        return -0.5 * ((v - mu) ** 2 / var + np.log(2 * np.pi * var))

    for _ in range(100):
        f0 = 1 - sum(c[1] for c in comps)
        logs = [np.log(max(f0, 1e-12)) + logn(x, 0.0, 1.0)] + [np.log(max(c[1], 1e-12)) + logn(x, c[2], 1 + c[3])
                                                               for c in comps]
        tot = np.logaddexp.reduce(logs, axis=0)
        for c, lg in zip(comps, logs[1:]):
            g = np.exp(lg - tot)
            sg = max(g.sum(), 1e-12)
            c[1] = sg / x.size
            mu = float((g * x).sum() / sg)
            c[2] = c[0] * max(c[0] * mu, threshold)
            c[3] = max(float((g * (x - c[2]) ** 2).sum() / sg) - 1, 0.0)
    f0 = 1 - sum(c[1] for c in comps)
    logs = [np.log(max(f0, 1e-12)) + logn(x, 0.0, 1.0)] + [np.log(max(c[1], 1e-12)) + logn(x, c[2], 1 + c[3])
                                                           for c in comps]
    d = -2 * float(np.sum(np.logaddexp.reduce(logs, axis=0) - logn(x, 0.0, 1.0)))
    return min(d, 0.0), 3 * len(comps)


class ColumnSignature(Signature):
    """Hot and dead columns from the likelihood of the column means, not only their number.

    Every column's mean residual against its running median (``SpikeStats.col_z``, in standard errors,
    rescaled by their robust scatter so that a white excess of variance is not taken for columns) is
    modelled as normal columns plus hot and dead populations (:func:`column_mixture_gain`); what the
    model's own realisation gives the same way is subtracted (what the model already produces). The
    parameters are the plugin's: outlier columns scaled to the sensor width, their median excess rate.
    """

    kind = "columns"
    pattern = "outlier columns"
    outlier_count = True

    def score(self, fit, res):
        return None  # compared by the statistics of all the columns, not pixel by pixel

    #: a defective column is defective along its length: the median of its eight stretches' mean excess is at
    #: least this fraction of the strongest one's
    MIN_EVENNESS = 0.25

    def plausible(self, fit, res) -> str:
        from ..signatures import line_sigma

        z = res.data_spikes.col_z
        if z.size != res.data_adu.shape[1]:
            return ""
        cols = np.flatnonzero(np.abs(np.nan_to_num(z)) > line_sigma(z.size))
        if not cols.size:
            return ""
        # defects sit at random columns: column means that repeat with a period are a periodic pattern seen
        # through the columns (as a pickup is seen through the rows, periodic_line_peak), not defective columns
        peak = self._column_period(res)
        if peak is not None:
            return (f"the column means repeat with a period of {peak[0]:.3g} columns (its power {peak[1]:.3g} times "
                    "its neighbours'): a periodic pattern seen through the columns, not defective columns")
        at_sources = self._at_source_columns(res)
        if at_sources:
            return at_sources
        # every pixel of the columns (an outlier column is not fitted pixel by pixel), spikes clipped at 5 sigma,
        # as an excess over the row's other pixels: a level the frame's fitted levels leave in every column of a
        # row is in none of its stretches alone
        d = self._excess_over_row_median(res, cols)
        lim = 5 * np.sqrt(res.var_adu2[:, cols])
        r = np.where(np.isfinite(d), np.clip(d, -lim, lim), 0.0)
        seg = np.array_split(np.arange(r.shape[0]), 8)
        excess = np.abs(np.stack([r[s_].mean(axis=0) for s_ in seg]))  # (8, columns): mean excess per stretch
        # a defective column is defective along its length: its typical stretch carries a good part of its
        # strongest stretch's excess; a blob, a ring or a track crossing it leaves most stretches empty
        evenness = float(np.median(np.median(excess, axis=0) / np.maximum(excess.max(axis=0), 1e-30)))
        if evenness < self.MIN_EVENNESS:
            return (f"the outlier columns' excess sits in a few stretches of their rows (typical stretch "
                    f"{100 * evenness:.0f} % of the strongest): a local structure crossing them, not defective columns")
        short, run = self.short_run_share(d, res.var_adu2[:, cols], clip=5.0)
        if short > self.MAX_SHORT_RUN_SHARE:
            return (f"the outlier columns' excess is carried by short groups of outlying pixels ({100 * short:.0f} % of "
                    f"their net excess in runs of at most {self.MAX_CLUSTER_RUN:.0f} rows, a cluster's side; median run "
                    f"{run:.0f} rows): defective pixels or clusters "
                    "crossing those columns, not defective columns")
        return ""

    @staticmethod
    def _excess_over_row_median(res, cols: np.ndarray) -> np.ndarray:
        """The residual of the columns ``cols`` [ADU] (every row, the frame's fitted levels removed) less the
        median of the row's other usable pixels (the whole row but those columns; col_z's own reference is
        local, this one removes what every column of a row shares); a row without any is NaN."""
        level, _ = res.level_maps()
        r = res.data_adu - res.model_adu - level
        use = res.outlier_usable & np.isfinite(r)
        use[:, cols] = False
        ref = np.full(r.shape[0], np.nan)
        some = use.any(axis=1)
        if some.any():
            ref[some] = np.nanmedian(np.where(use, r, np.nan)[some], axis=1)
        return r[:, cols] - ref[:, None]

    @staticmethod
    def _at_source_columns(res) -> str:
        """A reason when the outlier columns follow the model's sources beyond chance
        (:func:`detector.signatures.columns_follow_sources`), else ""."""
        from ..signatures import columns_follow_sources

        got = columns_follow_sources(res)
        if got is None:
            return ""
        return (f"the outlier columns follow the sources' light ({got['top']} of {got['cols'].size} among the tenth "
                f"of the columns that hold the most, chance {got['chance']:.2g}; the other columns' means rise with "
                f"their source light at {got['follow']:.1f} sigma): light spread along the read-out from the sources "
                "(smear while the rows are shifted with the shutter open, blooming, charge-transfer trails), not "
                "defective columns, which sit where the sensor's defects are whatever the scene")

    @classmethod
    def _column_period(cls, res) -> tuple[float, float] | None:
        """(period [columns], ratio) of a significant period of the column means (:func:`periodic_line_peak` of
        their local excess over their running mean of LINE_WINDOW columns, in standard errors: a running median
        flips with the majority of a fast square wave), or None."""
        from scipy.ndimage import uniform_filter1d

        from ..signatures import LINE_WINDOW

        m, ok = cls._column_means(res)
        if ok.sum() < 16:
            return None
        use = res.outlier_usable
        se = np.sqrt(np.where(use, res.var_adu2, 0.0).sum(axis=0)) / np.maximum(use.sum(axis=0), 1)
        u = np.where(ok, (m - uniform_filter1d(m, LINE_WINDOW, mode="nearest")) / np.maximum(se, 1e-12), 0.0)
        return periodic_line_peak(u)

    #: a defective column's outlying pixels come in long runs along it (a trap to the serial register, a whole
    #: column): a run no longer than the side of the largest cluster of defective pixels (a square of
    #: MAX_DEAD_CLUSTER_PX pixels, EMVA 1288 sect. 8.4, Janesick 2007 ch. 8: 5 rows) is a pixel defect or a
    #: cluster that happens to cross it [rows]
    MAX_CLUSTER_RUN = math.sqrt(MAX_DEAD_CLUSTER_PX)
    #: ... which may carry at most this share of the outlier columns' net excess (the long runs carry most of
    #: what the column claim covers: EXPLAINS_MOST)
    MAX_SHORT_RUN_SHARE = EXPLAINS_MOST

    @classmethod
    def short_run_share(cls, d: np.ndarray, var: np.ndarray, sigma: float = 5.0, grow: float = 2.0,
                        clip: float | None = None) -> tuple[float, float]:
        """(share, median run length): of the columns' net excess (``d`` [ADU] per row x column, summed along
        each column in the sign of its sum), the share carried by runs of outlying pixels no longer than
        MAX_CLUSTER_RUN consecutive rows, a cluster's side (a run holds a pixel beyond ``sigma`` standard
        deviations in that sign and goes on while its pixels stay beyond ``grow``: hysteresis, so a column a few
        sigma off is not cut into pieces by its noise); and the median length of the outlying runs [rows]. A defective column spreads its excess along its length (whether or not its
        pixels stand out one by one); clusters of defective pixels put all of it in a few short runs.
        (0, 0) without an excess."""
        d = np.where(np.isfinite(d), d, 0.0)
        sd = np.sqrt(np.maximum(var, 1e-12))
        z = d / sd
        if clip is not None:  # each pixel's excess counted up to `clip` sigma: a hot pixel is not a column's worth
            d = np.clip(d, -clip * sd, clip * sd)
        net = short = 0.0
        lengths = []
        for j in range(d.shape[1]):
            sign = 1.0 if d[:, j].sum() >= 0 else -1.0
            e = sign * float(d[:, j].sum())
            col = sign * z[:, j] > grow  # hysteresis: a run starts at an outlier and goes on above `grow`
            seed = sign * z[:, j] > sigma
            edges = np.flatnonzero(np.diff(np.concatenate([[0], col.astype(np.int8), [0]])))
            s_short = 0.0
            for a_, b_ in zip(edges[::2], edges[1::2]):
                if not seed[a_:b_].any():
                    continue
                lengths.append(b_ - a_)
                if b_ - a_ <= cls.MAX_CLUSTER_RUN:
                    s_short += sign * float(d[a_:b_, j].sum())
            net += max(e, s_short)
            short += s_short
        if net <= 0 or not lengths:
            return 0.0, 0.0
        return short / net, float(np.median(lengths))

    @staticmethod
    def _gain(z: np.ndarray) -> tuple[float, int, np.ndarray]:
        from ..signatures import line_sigma

        n = z.size
        z = z[np.isfinite(z)] if z.size else z
        if z.size < 16:
            return 0.0, 0, z
        scale = max(1.0, mad_std(z, max_n=None))
        x = z / scale
        d, k = column_mixture_gain(x, line_sigma(n))
        return d, k, x

    @staticmethod
    def _source_columns(res) -> np.ndarray:
        """Columns holding a pixel the model fills to within 80 % of the full well: a saturated source's
        column, where excess charge is blooming (it starts at the source), not a column defect."""
        fw = res.sensor.full_well_e * res.pixel_sum
        return (res.charge_e >= 0.8 * fw).any(axis=0)

    def fit(self, res, name):
        from ..signatures import line_sigma

        src = self._source_columns(res)
        zd = np.where(src, np.nan, res.data_spikes.col_z) if res.data_spikes.col_z.size == src.size else \
            res.data_spikes.col_z
        d_data, k, x = self._gain(zd)
        if k == 0:
            return None
        zm = res.model_spikes.col_z
        d_model = self._gain(np.where(src, np.nan, zm) if zm.size == src.size else zm)[0] if zm.size else 0.0
        d = min(d_data - d_model, 0.0)
        s = res.sensor
        frac = s.roi_shape[0] / s.sensor_width_px
        # the output columns of the two populations (x holds the finite columns, source columns are NaN)
        finite = np.flatnonzero(np.isfinite(zd))
        bar = line_sigma(zd.size)
        hot_j, cold_j = finite[x > bar], finite[x < -bar]
        exc = res.data_spikes.col_excess_e  # of the outlier columns (source columns are not told apart here)
        rate = float(np.median(exc)) * self._per_sensor_pixel(res) if exc.size else 0.0
        resp = self._response(res, cold_j)
        params = {"hot_columns": round(hot_j.size / frac), "hot_rate_e_per_s": round(max(rate, 0.0), 4),
                  "dead_columns": round(cold_j.size / frac),
                  "dead_response": round(float(np.median(resp)), 4) if resp.size else 0.0,
                  "hot_at": self._sensor_columns(res, hot_j), "dead_at": self._sensor_columns(res, cold_j),
                  "dead_at_response": [round(float(r), 4) for r in resp]}
        rates, rows = self._hot_extent(res, hot_j)
        params["hot_at_rate_e_per_s"] = [round(float(r), 5) for r in rates]
        if any(r is not None for r in rows):  # a trap's column: the excess on one side of it
            height = s.sensor_height_px
            params["hot_at_rows"] = [list(r) if r is not None else [0, height] for r in rows]
        return Fit(name, params, d, k, int(x.size), _column_words(params, res))

    @staticmethod
    def _sensor_columns(res, cols: np.ndarray) -> list[int]:
        """The first sensor column of each output column ``cols`` (from the residuals' sensor coordinates of the
        pixel centres: a binned column spans ``binning`` sensor columns)."""
        b = res.sensor.binning
        return [round(float(res.xs[j]) - (b - 1) / 2.0) for j in cols]

    @staticmethod
    def _column_means(res) -> tuple[np.ndarray, np.ndarray]:
        """Each column's mean residual [ADU] over its usable pixels, pixels beyond DETECTION_SIGMA of the column's
        median left out (a hot pixel or a track crossing it), and which columns have any."""
        use = res.outlier_usable
        r = res.data_adu - res.model_adu
        sd = np.sqrt(np.maximum(res.var_adu2, 1e-12))
        med = np.nanmedian(np.where(use, r, np.nan), axis=0)
        keep = use & (np.abs(r - np.nan_to_num(med)[None, :]) < DETECTION_SIGMA * sd)
        n = keep.sum(axis=0)
        return np.where(keep, r, 0.0).sum(axis=0) / np.maximum(n, 1), n > 0

    @classmethod
    def _hot_extent(cls, res, cols: np.ndarray) -> tuple[np.ndarray, list]:
        """Each hot column's excess dark current [e-/s per sensor pixel] and the sensor rows ``(start, stop)`` it
        lies in (None: the whole column). A charge trap in a column leaks into the pixels transferred through
        it, the rows on one side of it (Janesick 2007, ch. 8): the excess is the whole column or one side of a
        change point, whichever explains more chi2 beyond the change point's Schwarz price (ln n). The excess is
        measured above each row's median of the column's LINE_WINDOW neighbours (the other outlier columns left
        out), pixels beyond DETECTION_SIGMA of their running median along the column left out (a hot pixel, a
        track; a trap's step is not one)."""
        from scipy.ndimage import median_filter

        from ..signatures import LINE_WINDOW

        if cols.size == 0:
            return np.zeros(0), []
        normal = cls._column_means(res)[1]
        normal[cols] = False
        use = res.outlier_usable
        b = res.sensor.binning
        rates, rows = [], []
        for j in cols:
            lo, hi = max(j - LINE_WINDOW, 0), min(j + LINE_WINDOW + 1, normal.size)
            near = np.flatnonzero(normal[lo:hi]) + lo
            # each row's level from the neighbours in that row: a residual that trends along the column (a light
            # level off times a vignetting, row offsets) is not a trap's change point
            r_near = (res.data_adu[:, near] - res.model_adu[:, near]).astype(np.float64)
            base = np.median(r_near, axis=1) if near.size else np.zeros(res.data_adu.shape[0])
            v = np.maximum(res.var_adu2[:, j].astype(np.float64), 1e-12)
            x = res.data_adu[:, j].astype(np.float64) - res.model_adu[:, j] - base
            good = use[:, j] & np.isfinite(x)
            if good.any():  # a hot pixel or a track stands out of its neighbours along the column; a trap's step not
                local = median_filter(np.where(good, x, np.median(x[good])), size=5, mode="nearest")
                good &= np.abs(x - local) < DETECTION_SIGMA * np.sqrt(v)
            w = np.where(good, 1.0 / v, 0.0)
            s_, w_ = np.cumsum(np.where(good, x, 0.0) * w), np.cumsum(w)
            extent, mean = None, (s_[-1] / w_[-1] if w_[-1] > 0 else 0.0)
            if w_[-1] > 0 and x.size > 2:
                whole = s_[-1] ** 2 / w_[-1]
                with np.errstate(divide="ignore", invalid="ignore"):
                    low = np.where(w_[:-1] > 0, s_[:-1] ** 2 / w_[:-1], 0.0)  # rows [0, k]
                    up_w = w_[-1] - w_[:-1]
                    high = np.where(up_w > 0, (s_[-1] - s_[:-1]) ** 2 / up_w, 0.0)  # rows (k, n)
                k_lo, k_hi = int(np.argmax(low)), int(np.argmax(high))
                if max(low[k_lo], high[k_hi]) - whole > np.log(max(int(good.sum()), 2)):
                    if low[k_lo] >= high[k_hi]:
                        first, last, mean = 0, k_lo, s_[k_lo] / w_[k_lo]
                    else:
                        first, last, mean = k_hi + 1, x.size - 1, (s_[-1] - s_[k_hi]) / up_w[k_hi]
                    # a side that reaches the frame's edge goes on beyond it, to the sensor's edge (the trap's side)
                    extent = (0 if first == 0 else round(float(res.ys[first]) - (b - 1) / 2.0),
                              res.sensor.sensor_height_px if last == x.size - 1
                              else round(float(res.ys[last]) + (b - 1) / 2.0) + 1)
            rates.append(max(float(mean), 0.0) * res.gain * cls._per_sensor_pixel(res))
            rows.append(extent)
        return np.asarray(rates), rows

    @staticmethod
    def _response(res, cols: np.ndarray) -> np.ndarray:
        """The photo-response each dead column keeps, relative to its neighbours [1]. Each column's scale of the
        model's photo-signal that the data hold, ``q = 1 + sum(r p / v) / sum(p^2 / v)`` (r the residual, p the
        model's photo-signal, v the variance, over the column's usable pixels), divided by the median ``q`` of
        the other columns (a light level the model has wrong scales every column alike), in [0, 1); 0 where
        the frame holds no light to measure it (a dark: a dead column shows nothing there)."""
        if cols.size == 0:
            return np.zeros(0)
        use = res.outlier_usable
        p = np.where(use, res.photo_adu, 0.0)
        v = np.maximum(res.var_adu2, 1e-12)
        info = (p * p / v).sum(axis=0)
        others = info > 0
        others[cols] = False
        if not others.any():
            return np.zeros(cols.size)
        r = np.where(use, res.data_adu - res.model_adu, 0.0)
        q = 1.0 + (r * p / v).sum(axis=0) / np.maximum(info, 1e-300)
        rho = q[cols] / float(np.median(q[others]))
        # one dead sensor column in an output column of b: rho = 1 - (1 - r) / b (the response stage acts before
        # the binning), so the sensor column keeps r = 1 - b (1 - rho)
        r_col = 1.0 - res.sensor.binning * (1.0 - rho)
        # the light's response known to worse than 100 % (info < 1): nothing measured, a dead column
        return np.where(info[cols] >= 1.0, np.clip(r_col, 0.0, 0.999), 0.0)

    @staticmethod
    def _per_sensor_pixel(res) -> float:
        """[1/s per output-pixel electron]: a hot sensor column adds its rate x t to each of its pixels before the
        binning, b of them in an output column of b (1/b of a b x b average): an output pixel's excess E [e-]
        is ``rate t pixel_sum / b``."""
        return res.sensor.binning / res.pixel_sum / max(res.exptime_s, 1e-9)


def _column_words(p, res):
    seen = len(p.get("hot_at") or []) + len(p.get("dead_at") or [])
    weak = f", keeping {100 * p['dead_response']:.3g} % of the light" if p.get("dead_response") else ""
    return (f"whole columns above ({p['hot_columns']} on the sensor, {p['hot_rate_e_per_s']:.3g} e-/s) or below "
            f"({p['dead_columns']}{weak}) their neighbours: column defects ({seen} in the window, placed where "
            f"they were seen)")


_HOT_SIGNATURE = GroupSignature(
    _hot_groups,
    lambda p, res: (f"isolated bright pixels that do not move with the sky ({p['count']} on the sensor, "
                    f"time-to-double scale {p['scale_s']:.3g} s): hot and warm pixels"),
    pattern="isolated positive spikes", check=spread_check("pos"))
_COLUMN_SIGNATURE = ColumnSignature()


# --- adapters ----------------------------------------------------------------------------------------------

class HotPixelParams(EffectParams):
    count: int = Field(1000, ge=0, le=10_000_000, description="defective pixels on the full sensor [pixels]")
    law: Literal["weibull", "exponential"] = "weibull"
    weibull_shape: float = Field(0.8, gt=0.05, le=20, description="Weibull shape k of time-to-double [1]")
    scale_s: float = Field(600.0, gt=0, le=1e9, description="Weibull scale lambda of time-to-double [s]")
    stuck_fraction: float = Field(0.0, ge=0, le=1, description="fraction of defects stuck at a fixed value [1]")
    stuck_value_adu: float | None = Field(None, ge=0, description="value of stuck pixels (default: ADC maximum) [ADU]")
    hot_threshold_s: float = Field(60.0, gt=0, description="t2 below which a defect is labelled hot, else warm [s]")
    doubling_level_adu: float | None = Field(
        None, gt=0, description="level B whose doubling time is t2 (default: the bias; 1000 ADU when the bias is 0) "
                                "[ADU]", json_schema_extra={"unit": "adu"})


@register_effect
class HotPixels(Effect):
    """Hot, warm and stuck pixels with a Weibull (or exponential) law of time-to-double (thesis eqs. 35-40).

    Each defect adds ``r_e t`` electrons to the mean before the shot-noise draw (so it carries its own
    Poisson noise), with ``r_e = B g / t2`` (see module docstring). Stuck pixels are set to a fixed ADU value
    after the ADC. Positions and ``t2`` from the hardware seed: the same defects every frame.
    FITS table ``HOTPIX``: x, y, kind, t_double_s, rate_e_per_s.
    """

    name = "hot_pixels"
    scaling = "exposure"
    identity = {"count": 0}
    stages = (Stage.DARK, Stage.DIGITAL)
    Params = HotPixelParams
    pattern = True
    signature = _HOT_SIGNATURE

    def setup(self) -> None:
        p, s = self.params, self.sensor
        self.ys, self.xs, rng = hardware_positions(s, self.name, p.count)
        n = self.ys.size
        self.t2 = draw_time_to_double(rng, n, p.law, p.weibull_shape, p.scale_s)
        level = doubling_level_adu(s.bias_adu, p.doubling_level_adu)
        self.rate = hot_rate_e_per_s(self.t2, level, s.gain_e_per_adu).astype(np.float32)
        self.stuck = rng.random(n) < p.stuck_fraction
        self.stuck_value = float(s.adc_max_adu if p.stuck_value_adu is None else min(p.stuck_value_adu, s.adc_max_adu))

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        sel, r, c = in_tile(tile, self.ys, self.xs)
        if stage is Stage.DARK:
            data[r, c] += self.rate[sel] * np.float32(tile.exptime_s)  # positions are distinct
        else:
            st = self.stuck[sel]
            data[r[st], c[st]] = self.stuck_value

    def truth(self, state=None) -> dict[str, np.ndarray]:
        m = roi_mask(self.sensor, self.ys, self.xs)
        x, y = output_xy(self.sensor, self.ys[m], self.xs[m])
        kind = np.where(self.stuck[m], "stuck", np.where(self.t2[m] < self.params.hot_threshold_s, "hot", "warm"))
        t = np.zeros(int(m.sum()), dtype=[("x", "i4"), ("y", "i4"), ("x_sensor", "i4"), ("y_sensor", "i4"),
                                            ("kind", "S5"), ("t_double_s", "f8"), ("rate_e_per_s", "f8")])
        t["x"], t["y"], t["x_sensor"], t["y_sensor"] = x, y, self.xs[m], self.ys[m]
        t["kind"], t["t_double_s"], t["rate_e_per_s"] = kind, self.t2[m], self.rate[m]
        return {"HOTPIX": t}


class ColumnDefectParams(EffectParams):
    hot_columns: int = Field(5, ge=0, le=100_000, description="columns with excess dark current [columns]")
    hot_rate_e_per_s: float = Field(5.0, ge=0, le=1e6, description="excess dark current of a hot column [e-/s]")
    dead_columns: int = Field(2, ge=0, le=100_000, description="columns without photo-response [columns]")
    dead_response: float = Field(0.0, ge=0, lt=1, description="relative photo-response of a dead column "
                                 "(0: none; a weak column between 0 and 1) [1]")
    hot_at: list[int] | None = Field(None, description="sensor columns of hot columns where they were measured "
                                     "(0-based); the rest of ``hot_columns`` are drawn elsewhere")
    dead_at: list[int] | None = Field(None, description="sensor columns of dead columns where they were measured "
                                      "(0-based); the rest of ``dead_columns`` are drawn elsewhere")
    hot_at_rate_e_per_s: list[float] | None = Field(None, description="the measured excess dark current of each "
                                                    "column of ``hot_at`` (default ``hot_rate_e_per_s``) [e-/s]")
    dead_at_response: list[float] | None = Field(None, description="the measured relative response of each column "
                                                 "of ``dead_at`` (default ``dead_response``) [1]")
    hot_at_rows: list[list[int]] | None = Field(None, description="the sensor rows [start, stop) of each column of "
                                                "``hot_at`` that hold its excess (a trap's column: the rows on one "
                                                "side of the trap; default the whole column)")

    @model_validator(mode="after")
    def _check(self):
        for key, count in (("hot_at", self.hot_columns), ("dead_at", self.dead_columns)):
            at = getattr(self, key) or []
            if len(at) > count or len(set(at)) < len(at) or any(c < 0 for c in at):
                raise ValueError(f"{key} must list at most {key.split('_')[0]}_columns = {count} distinct "
                                 f"non-negative sensor columns, got {at}")
        if set(self.hot_at or []) & set(self.dead_at or []):
            raise ValueError("a column cannot be in both hot_at and dead_at")
        for key, at, lo, hi in (("hot_at_rate_e_per_s", "hot_at", 0.0, 1e6), ("dead_at_response", "dead_at", 0.0, 1.0)):
            v = getattr(self, key)
            if v is not None and (len(v) != len(getattr(self, at) or []) or any(not lo <= x <= hi for x in v)):
                raise ValueError(f"{key} must hold one value in [{lo:g}, {hi:g}] per column of {at} "
                                 f"({len(getattr(self, at) or [])}), got {v}")
        rows = self.hot_at_rows
        if rows is not None and (len(rows) != len(self.hot_at or []) or any(len(r) != 2 or not 0 <= r[0] < r[1]
                                                                           for r in rows)):
            raise ValueError(f"hot_at_rows must hold one [start, stop) pair of sensor rows, 0 <= start < stop, per "
                             f"column of hot_at ({len(self.hot_at or [])}), got {rows}")
        return self


@register_effect
class ColumnDefects(Effect):
    """Hot and dead columns: a charge trap or a leaky transfer gate affects a whole column (Janesick 2007,
    ch. 8, "column defects"; common in CCDs, also in CMOS column amplifiers). Hot columns add
    ``hot_rate_e_per_s t`` electrons (a measured column: its own ``hot_at_rate_e_per_s``, over its
    ``hot_at_rows``) to the mean of every pixel of the column; dead columns lose their
    photo-response (keep ``dead_response`` of it: a weak column). Columns from the hardware seed; table
    ``COLDEF``. Columns measured in a frame (``hot_at``, ``dead_at``: what ``diagnose`` finds in the read-out
    window) are placed where they were seen; the rest of each population is drawn among the other columns
    outside the read-out window (the window shows every defective column it holds).
    """

    name = "column_defects"
    scaling = "exposure"
    identity = {"hot_columns": 0, "dead_columns": 0}
    stages = (Stage.RESPONSE, Stage.DARK)
    Params = ColumnDefectParams
    signature = _COLUMN_SIGNATURE

    @property
    def pattern(self) -> bool:
        """A hardware realisation the real camera does not share, unless its columns were measured (``hot_at``,
        ``dead_at``): then they are the camera's own and act in the model's mean frame (the rest of the
        populations lie outside the read-out window)."""
        return self.params.hot_at is None and self.params.dead_at is None

    def setup(self) -> None:
        from ..rng import generator

        p, s = self.params, self.sensor
        w = s.sensor_width_px
        rng = generator(s.hardware_seed, self.name)
        if p.hot_at is None and p.dead_at is None:
            cols = rng.permutation(w)[: min(w, p.hot_columns + p.dead_columns)]
            self.hot, self.dead = np.sort(cols[: p.hot_columns]), np.sort(cols[p.hot_columns:])
            self.hot_rate = np.full(self.hot.size, p.hot_rate_e_per_s)
            self.dead_resp = np.full(self.dead.size, p.dead_response)
            self.hot_rows = None
            return
        hot_at, dead_at = np.asarray(p.hot_at or [], int), np.asarray(p.dead_at or [], int)
        rates = np.asarray(p.hot_at_rate_e_per_s or [p.hot_rate_e_per_s] * hot_at.size, float)
        resp = np.asarray(p.dead_at_response or [p.dead_response] * dead_at.size, float)
        x0, x1 = s.roi_x0, s.roi_x0 + s.roi_shape[0]
        free = np.setdiff1d(np.arange(w), np.concatenate([hot_at, dead_at]))
        free = rng.permutation(free[(free < x0) | (free >= x1)])
        n_hot = max(p.hot_columns - hot_at.size, 0)
        n_dead = max(p.dead_columns - dead_at.size, 0)
        hot = np.concatenate([hot_at, free[:n_hot]])
        dead = np.concatenate([dead_at, free[n_hot:n_hot + n_dead]])
        rates = np.concatenate([rates, np.full(hot.size - hot_at.size, p.hot_rate_e_per_s)])
        resp = np.concatenate([resp, np.full(dead.size - dead_at.size, p.dead_response)])
        rows = np.asarray((p.hot_at_rows or [[0, s.sensor_height_px]] * hot_at.size)
                          + [[0, s.sensor_height_px]] * (hot.size - hot_at.size), np.int64).reshape(-1, 2)

        def on_sensor(cols):  # sorted, the columns beyond the sensor's width dropped
            order = np.argsort(cols)
            return order[cols[order] < w]

        keep_h, keep_d = on_sensor(hot), on_sensor(dead)
        self.hot, self.hot_rate = hot[keep_h], rates[keep_h]
        self.hot_rows = rows[keep_h] if p.hot_at_rows is not None else None
        self.dead, self.dead_resp = dead[keep_d], resp[keep_d]

    @staticmethod
    def _local(tile: Tile, cols: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        inside = (cols >= tile.x0) & (cols < tile.x1)
        return (cols[inside] - tile.x0) // tile.bin, values[inside]

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if stage is Stage.RESPONSE:
            j, v = self._local(tile, self.dead, self.dead_resp)
            data[:, j] *= v.astype(np.float32)
        elif self.hot_rows is None:
            j, v = self._local(tile, self.hot, self.hot_rate)
            data[:, j] += (v * tile.exptime_s).astype(np.float32)
        else:  # measured extents: each column's excess over its rows
            ys = tile.pixel_centres()[0]
            inside = (self.hot >= tile.x0) & (self.hot < tile.x1)
            for c, r, (a, b) in zip(self.hot[inside], self.hot_rate[inside], self.hot_rows[inside]):
                data[(ys >= a) & (ys < b), (c - tile.x0) // tile.bin] += np.float32(r * tile.exptime_s)

    def truth(self, state=None) -> dict[str, np.ndarray]:
        s = self.sensor
        cols = np.concatenate([self.hot, self.dead])
        kind = np.array(["hot"] * self.hot.size + ["dead"] * self.dead.size, dtype="S4")
        inside = (cols >= s.roi_x0) & (cols < s.roi_x0 + s.roi_shape[0])
        t = np.zeros(int(inside.sum()), dtype=[("x", "i4"), ("x_sensor", "i4"), ("kind", "S4"), ("rate_e_per_s", "f8")])
        t["x_sensor"], t["kind"] = cols[inside], kind[inside]
        t["x"] = (cols[inside] - s.roi_x0) // s.binning
        t["rate_e_per_s"] = np.concatenate([self.hot_rate, np.zeros(self.dead.size)])[inside]
        return {"COLDEF": t}
