"""Random telegraph signal (RTS) noise of CMOS pixels: a single oxide trap in the pixel's source-follower
transistor captures and emits one carrier, switching the pixel's output between discrete levels.

Physics (Kirton & Uren 1989, Adv. Phys. 38, 367; for image-sensor pixels Wang, Rao, Mierop & Theuwissen
2006, IEDM, "Random telegraph signal in CMOS image sensor pixels"; Chao et al. 2019, IEEE J. Electron
Devices Soc. 7, 227, statistics of RTN in small-pixel stacked CIS): the trap is a two-state Markov process
with exponentially distributed dwell times, mean ``tau_0`` (empty) and ``tau_1`` (filled). It is filled a
fraction ``p_1 = tau_1 / (tau_0 + tau_1)`` of the time. The exact transition over an interval ``dt``::

    P(1 | 0, dt) = p_1 (1 - exp(-dt / tau_c)),  P(0 | 1, dt) = p_0 (1 - exp(-dt / tau_c)),
    1 / tau_c = 1 / tau_0 + 1 / tau_1

A pixel is read by correlated double sampling (reset sample, then signal sample ``cds_interval_s`` later):
its RTS offset is ``A [s(t_sig) - s(t_rst)]``, three levels ``-A, 0, +A`` (``levels = 3``); with
``levels = 2`` the offset is ``A s(t_sig)`` (an RTS that CDS does not cancel, e.g. a dark-current RTS,
two levels ``0, A``).

Population (hardware seed, fixed per chip): a fraction ``fraction`` of the pixels carries a trap; its
amplitude ``A`` [e-] is log-normal (median ``amplitude_e``, log-sigma ``amplitude_sigma_ln``: the
long-tailed amplitude distributions of Wang et al. 2006 and Chao et al. 2019); ``tau_0`` and ``tau_1`` are
log-uniform between ``tau_min_s`` and ``tau_max_s`` (McWhorter: traps at depths uniformly distributed in
the oxide have log-uniform time constants). State (frame seed): each frame the trap state at the row's read
time is drawn from the stationary law and the second sample from the transition above, so consecutive
frames of a sequence are independent draws and a sequence shows blinking pixels; a run of frames in the
same state follows the geometric law ``P(k) = p^(k-1) (1 - p)`` (the frame-sampled form of the exponential
dwell law). A rolling shutter samples each row at its own time, but with frames independent the row time
does not change the law, so it is not used.

Defaults for the IMX411: no RTS statistics are published for it; the defaults (0.05 % of the pixels,
median 3 e- (its read noise is 3.5 e- at gain 0), log-sigma 0.7, time constants 10 us - 100 ms, CDS
interval 5 us) follow the orders of magnitude of Wang et al. 2006 and Chao et al. 2019 for small-pixel CIS.
A CCD's output amplifier has one transistor for all pixels: RTS pixels do not exist there (the effect still
runs if asked, modelling whatever population is given).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..rng import generator
from ..stats import mad_std
from ..signatures import Fit, Signature
from ..significance import MAX_DEFECT_FRACTION
from .base import Effect, EffectParams, Stage, Tile, register_effect


def telegraph_transition(rng: np.random.Generator, state: np.ndarray, tau0_s, tau1_s, dt_s: float) -> np.ndarray:
    """The states ``dt_s`` later of two-state Markov traps now in ``state`` (0/1), exactly (module docstring)."""
    tau0, tau1 = np.asarray(tau0_s, np.float64), np.asarray(tau1_s, np.float64)
    p1 = tau1 / (tau0 + tau1)
    mix = 1.0 - np.exp(-dt_s * (1.0 / tau0 + 1.0 / tau1))
    p_next1 = np.where(state == 1, 1.0 - (1.0 - p1) * mix, p1 * mix)
    return (rng.random(np.shape(state)) < p_next1).astype(np.int8)


def telegraph_sequence(rng: np.random.Generator, tau0_s: float, tau1_s: float, times_s: np.ndarray) -> np.ndarray:
    """States (0/1) of one trap at increasing ``times_s``, starting from the stationary law (exact chain)."""
    p1 = tau1_s / (tau0_s + tau1_s)
    out = np.empty(len(times_s), np.int8)
    s = np.int8(rng.random() < p1)
    out[0] = s
    for i in range(1, len(times_s)):
        s = telegraph_transition(rng, np.array([s]), tau0_s, tau1_s, float(times_s[i] - times_s[i - 1]))[0]
        out[i] = s
    return out


def rts_offsets(rng: np.random.Generator, amplitude_e, tau0_s, tau1_s, levels: int, cds_interval_s: float
                ) -> np.ndarray:
    """One frame's RTS offsets [e-] of a set of trap pixels (stationary first sample; module docstring)."""
    tau0, tau1 = np.asarray(tau0_s, np.float64), np.asarray(tau1_s, np.float64)
    p1 = tau1 / (tau0 + tau1)
    s_rst = (rng.random(p1.shape) < p1).astype(np.int8)
    s_sig = telegraph_transition(rng, s_rst, tau0, tau1, cds_interval_s)
    amp = np.asarray(amplitude_e, np.float64)
    return amp * (s_sig - s_rst) if levels == 3 else amp * s_sig


def _mean_flip_probability(tau_min_s: float, tau_max_s: float, cds_interval_s: float) -> float:
    """Per-pixel probability of a downward CDS step ``P(s_rst = 1, s_sig = 0) = p_1 p_0 (1 - exp(-dt/tau_c))``,
    averaged over log-uniform time constants (a 64 x 64 grid in log tau)."""
    t = np.exp(np.linspace(np.log(tau_min_s), np.log(tau_max_s), 64))
    t0, t1 = np.meshgrid(t, t)
    p1 = t1 / (t0 + t1)
    return float((p1 * (1 - p1) * (1.0 - np.exp(-cds_interval_s * (1 / t0 + 1 / t1)))).mean())


#: |z| beyond which every pixel enters the one-frame RTS likelihood; below it a regular subsample of at most
#: RTS_CORE_PIXELS pixels stands for the rest (weighted by the share it stands for) [model sigma]
RTS_TAIL_Z = 3.0
RTS_CORE_PIXELS = 10_000
#: the largest fraction of the pixels that may show an RTS step in one frame [1]: the populations measured in
#: CMOS image sensors are below a few per cent of the pixels (Wang et al. 2006; Chao et al. 2019), of which only
#: those whose trap changes state between the two CDS samples step; a heavier "tail" is a noise of every pixel
#: (the bar of every anomalous-pixel population, MAX_DEFECT_FRACTION)
RTS_MAX_ACTIVE = MAX_DEFECT_FRACTION
#: median step amplitudes [model sigma] the fit tries (log-spaced) and the log-normal spreads of the amplitudes
RTS_AMPLITUDES_SIGMA = tuple(float(x) for x in np.geomspace(1.0, 60.0, 14))
RTS_SPREADS_LN = (0.15, 0.4, 0.7, 1.0)
#: Gauss-Hermite nodes of the log-normal amplitude law
RTS_NODES = 7
#: below this noise [ADC codes] the likelihood is that of the read codes, not a density (the lattice of codes is
#: then coarse against the noise: a density's error there grows as (code / sigma)^2 / 24 per pixel)
RTS_CODED_SIGMA = 3.0
#: on read codes (the noise below RTS_CODED_SIGMA codes) the smallest step [codes] the likelihood may claim: a step
#: of about one code lands on the nearest codes of the core, whose frequencies measure the core's own law on the
#: lattice (its fractional offset and width, a rounding or averaging the model gets slightly wrong) as much as
#: steps; only steps beyond the neighbouring codes are resolved as steps (three textbook 16 x 16 average-binned
#: IMX411 biases of 315 nulls were given RTS steps of exactly one code, docs/null_calibration.md)
RTS_MIN_CODED_STEP = 2.0
#: the smallest median step [model sigma] the likelihood may claim: a step below RTS_TAIL_Z noise sigmas widens
#: the core's tails (a read noise's own kurtosis) rather than standing out of it, and one frame cannot tell the
#: two apart (a textbook-free null IMX411 dark was given steps of 1.0 sigma in 1 % of its pixels)
RTS_MIN_STEP_SIGMA = RTS_TAIL_Z


def _amplitude_nodes(a: float, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Amplitudes and weights of a log-normal law (median ``a``, log-sigma ``s``) on RTS_NODES nodes."""
    x, w = np.polynomial.hermite_e.hermegauss(RTS_NODES)
    return a * np.exp(s * x), w / w.sum()


def _log_normal_mass(x: np.ndarray, v: np.ndarray, q: float) -> np.ndarray:
    """ln of the likelihood of reading ``x`` [ADU] under N(0, v): its density or, with a code width ``q`` > 0, the
    probability of the code ``[x - q/2, x + q/2]`` (a read value known only to its ADC code: where the noise is
    below a few codes, a density would take the code lattice for structure), in the tail nearer to it."""
    if q <= 0:
        return -0.5 * x * x / v - 0.5 * np.log(2 * np.pi * v)
    from scipy.special import log_ndtr

    sd = np.sqrt(v)
    lo, hi = (x - 0.5 * q) / sd, (x + 0.5 * q) / sd
    flip = lo > 0
    a, b = np.where(flip, -hi, lo), np.where(flip, -lo, hi)
    la, lb = log_ndtr(a), log_ndtr(b)
    return lb + np.log1p(-np.exp(np.minimum(la - lb, -1e-12)))


def _log_component(r: np.ndarray, v: np.ndarray, amps: np.ndarray, wts: np.ndarray, symmetric: bool,
                   q: float = 0.0) -> np.ndarray:
    """ln of the likelihood of ``r`` [ADU] for an offset of amplitude drawn from (amps, wts) [ADU] -- both signs
    with equal probability (``symmetric``: a CDS-read telegraph step) or positive only -- plus N(0, v) (per code of
    width ``q`` when > 0: :func:`_log_normal_mass`)."""
    out = np.full(r.shape, -np.inf)
    for a, w in zip(amps, wts):
        lp = _log_normal_mass(r - a, v, q)
        if symmetric:
            lp = np.logaddexp(lp, _log_normal_mass(r + a, v, q)) + np.log(0.5)
        out = np.logaddexp(out, np.log(w) + lp)
    return out


def _log_ratio(lr: np.ndarray, f: float) -> np.ndarray:
    """ln of ``(1 - f) + f exp(lr)`` per pixel: the mixture's density over the core's."""
    return np.logaddexp(np.log1p(-f), np.log(f) + lr)


def _fraction_em(lr: np.ndarray, wt: np.ndarray, cap: float, iters: int = 200) -> float:
    """The fraction ``f <= cap`` maximising ``sum wt ln((1 - f) + f exp(lr))`` (EM; the function is concave)."""
    f = 1e-3
    for _ in range(iters):
        resp = np.exp(np.log(f) + lr - _log_ratio(lr, f))
        new = min(max(float(np.sum(wt * resp) / np.sum(wt)), 1e-9), cap)
        if abs(new - f) < 1e-4 * f:
            return new
        f = new
    return f


def rts_frame_sample(res) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, float] | None:
    """The pixels the one-frame RTS likelihood uses: (residual [ADU], variance [ADU^2], weight, pixels stood for,
    ADC code width [ADU] when the likelihood is that of the codes, else 0).

    Every usable pixel where no light falls (an RTS step is light-independent, and where light falls a dead
    pixel or a response may also lower a pixel), its residual against the level-profiled model less its local
    mean (a Gaussian of WHITE_SCALE px over the fitted pixels: smooth structure is not pixel steps) and less the
    robust (median) offsets of its row and its column (row noise, defective columns: whole lines, not isolated
    pixels; a sparse RTS population leaves a line median unchanged). The variance is the model's plus the
    rounding of the ADC codes (a read value is known to +-0.5 ADU), widened by the residual's robust scatter
    when that exceeds it (a white excess of every pixel is not sparse steps). Pixels beyond RTS_TAIL_Z all count; the rest
    through a regular subsample weighted by the share it stands for."""
    from scipy.ndimage import gaussian_filter

    from ..signatures import ROUNDING_VAR_ADU2, WHITE_SCALE, on_read_codes
    from .pixel_response import _lit

    usable = res.outlier_usable
    if res.train is not None:
        usable = usable & res.train
    level = res.level_map()
    r = (res.data_adu.astype(np.float64) - res.model_adu - level)
    v = res.var_adu2.astype(np.float64)
    ok = usable & np.isfinite(r) & np.isfinite(v) & (v > 0)
    flat_idx = np.flatnonzero(ok)
    if flat_idx.size < 100:
        return None
    dark = ~_lit(res, flat_idx)
    if dark.sum() < 100:
        return None
    fit = ok & res.fit
    w = np.where(fit, 1.0 / np.where(v > 0, v, 1.0), 0.0)
    num = gaussian_filter(np.where(fit, r * w, 0.0), WHITE_SCALE, mode="nearest")
    den = gaussian_filter(w, WHITE_SCALE, mode="nearest")
    r = r - num / np.maximum(den, 1e-30)
    # line offsets as clipped means (a step counts at most RTS_TAIL_Z sigma in its line's mean; a median would
    # snap to the lattice of ADC codes where the noise is below a code)
    lim = RTS_TAIL_Z * np.sqrt(np.where(ok, v, 0.0) + ROUNDING_VAR_ADU2)
    for axis in (1, 0):
        rc = np.where(ok, np.clip(r, -lim, lim), 0.0)
        m = rc.sum(axis=axis) / np.maximum(ok.sum(axis=axis), 1)
        r = r - (m[:, None] if axis == 1 else m[None, :])
    idx = flat_idx[dark]
    rr, vv = r.ravel()[idx], v.ravel()[idx]
    # read values on integer ADC codes where the noise spans few codes: the likelihood of each code (q = 1 ADU);
    # elsewhere the density, the rounding's 1/12 ADU^2 added to the variance (Sheppard's correction)
    q = 1.0 if on_read_codes(res, idx) and float(np.median(vv)) < (RTS_CODED_SIGMA * 1.0) ** 2 else 0.0
    # the core's width: a white excess of every pixel (a read noise or a DSNU the model lacks, candidates of their
    # own) widens it; the sparse steps beyond it are what RTS is asked to explain. Measured robustly (the MAD) on a
    # density; on codes (whose moments and quantiles are the lattice's, not the noise's) by the codes' likelihood
    if q == 0.0:
        vv = vv + ROUNDING_VAR_ADU2
        vv = vv * max(1.0, mad_std(rr / np.sqrt(vv), max_n=None)) ** 2
    else:
        sub = slice(None, None, max(1, rr.size // RTS_CORE_PIXELS))
        scales = np.geomspace(1.0, 10.0, 25)
        m2l = [float(-np.sum(_log_normal_mass(rr[sub], vv[sub] * c, q))) for c in scales]
        vv = vv * float(scales[int(np.argmin(m2l))])
    return (*rts_tail_sample(rr, vv), int(idx.size), q)


def rts_tail_sample(r: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(r, v, weight): every pixel beyond RTS_TAIL_Z, and a regular subsample of at most RTS_CORE_PIXELS of the
    others weighted by the share of them it stands for (the likelihood's sum over the core, estimated)."""
    tail = np.abs(r) > RTS_TAIL_Z * np.sqrt(v)
    core = np.flatnonzero(~tail)
    step = max(1, core.size // RTS_CORE_PIXELS)
    pick = core[::step]
    sel = np.concatenate([np.flatnonzero(tail), pick])
    wt = np.concatenate([np.ones(int(tail.sum())), np.full(pick.size, core.size / max(pick.size, 1))])
    return r[sel], v[sel], wt


def rts_frame_fit(r: np.ndarray, v: np.ndarray, wt: np.ndarray, cap: float = RTS_MAX_ACTIVE, q: float = 0.0) -> dict:
    """Maximum likelihood of one frame's RTS steps (Kirton & Uren 1989; Wang et al. 2006): each pixel is
    ``N(0, v)`` or, with probability ``f``, offset by ``+A`` or ``-A`` with equal probability (a trap that changed
    state between the reset and the signal sample of CDS: module docstring), ``A`` log-normal (median ``a``,
    log-sigma ``s``): a sparse, heavy-tailed, *symmetric* mixture on top of the Gaussian noise.

    The likelihood ratio against ``N(0, v)`` is a sum over the pixels below the model and the pixels above it.
    Positive outliers have other causes (hot pixels, particle hits, each a candidate of its own); negative ones
    on pixels without light only a step down. So (f, a, s) are fitted on the pixels below the model
    (``delta_neg``), and the pixels above are *predicted* with them (``delta_pos``): RTS is credited with
    ``delta_neg + max(delta_pos, delta_neg)`` -- the steps up it predicts, when there (a population of steps
    up alone is not credited beyond its mirror, and steps up it predicts but that are missing count against it).
    Amplitudes on a grid of RTS_AMPLITUDES_SIGMA x RTS_SPREADS_LN, the fraction by EM; with ``q`` > 0 each pixel's
    likelihood is that of its ADC code of width ``q`` [ADU] (:func:`_log_normal_mass`).

    Returns delta (<= 0 when RTS explains something), f, a [ADU], s, delta_neg, delta_pos."""
    sd = float(np.median(np.sqrt(v)))
    neg = r < 0
    lc = _log_normal_mass(r, v, q)
    best = None
    for k in RTS_AMPLITUDES_SIGMA:
        if k < RTS_MIN_STEP_SIGMA or (q > 0 and k * sd < RTS_MIN_CODED_STEP * q):
            continue
        for s in RTS_SPREADS_LN:
            lr = _log_component(r, v, *_amplitude_nodes(k * sd, s), symmetric=True, q=q) - lc
            f = _fraction_em(lr[neg], wt[neg], cap)
            dn = float(-2 * np.sum(wt[neg] * _log_ratio(lr[neg], f)))
            if best is None or dn < best[0]:
                best = (dn, f, k * sd, s, lr)
    if best is None:
        return {"delta": 0.0, "f": 0.0, "a_adu": 0.0, "s": 0.0, "delta_neg": 0.0, "delta_pos": 0.0,
                "n_tail": int(np.sum(wt == 1))}
    dn, f, a, s, lr = best
    dp = float(-2 * np.sum(wt[~neg] * _log_ratio(lr[~neg], f)))
    return {"delta": dn + max(dp, dn), "f": float(f), "a_adu": float(a), "s": float(s), "delta_neg": dn,
            "delta_pos": dp, "n_tail": int(np.sum(wt == 1))}


def rts_population(f_active: float, binning: int, cds_interval_s: float = 5e-6) -> dict:
    """The plugin's population parameters for a per-frame step fraction ``f_active`` of the output pixels: one
    frame measures only the product of the trap fraction and the probability that a trap steps between the two
    CDS samples, so the fraction is given for the plugin's default time constants, or, when that would exceed
    5 % of the pixels, for fast traps (mean dwell times 1 - 10 CDS intervals) that step in most frames."""
    d = RTSParams()
    per = 2 * _mean_flip_probability(d.tau_min_s, d.tau_max_s, cds_interval_s)
    frac = f_active / (per * binning ** 2)
    if frac <= 0.05:
        return {"fraction": float(f"{frac:.3g}")}
    lo, hi = cds_interval_s, 10 * cds_interval_s
    per = 2 * _mean_flip_probability(lo, hi, cds_interval_s)
    return {"fraction": float(f"{min(f_active / (per * binning ** 2), 0.099):.3g}"), "tau_min_s": lo,
            "tau_max_s": hi}


class RTSFrameSignature(Signature):
    """Random telegraph steps on one frame, by the likelihood of a symmetric sparse mixture (:func:`rts_frame_fit`)
    over the pixels where no light falls (:func:`rts_frame_sample`); compared over the whole frame, not scored on
    a held-out half (a few tens of stepping pixels)."""

    kind = "counts"
    pattern = "isolated pixels stepped up and down by equal amounts, independent of light"

    def score(self, fit, res):
        return None

    def plausible(self, fit, res) -> str:
        """A CCD reads every pixel through one output amplifier: a trap in its transistor makes a temporal noise of
        the read-out (steps along the rows as it switches), not isolated pixels stepping each on its own
        (Janesick 2007, Photon Transfer, ch. 11; Wang et al. 2006: RTS pixels are the in-pixel source followers
        of CMOS sensors)."""
        if getattr(res.sensor, "kind", "") == "ccd":
            return ("a CCD reads every pixel through one output amplifier: isolated pixels stepping each on its own "
                    "are not its telegraph noise (dead or cold pixels, a heavy-tailed pixel noise)")
        return ""

    def fit(self, res, name):
        sample = rts_frame_sample(res)
        if sample is None:
            return None
        r, v, wt, n, q = sample
        out = rts_frame_fit(r, v, wt, q=q)
        if out["f"] <= 0 or out["delta_neg"] >= 0:
            return None
        g = res.gain
        params = {**rts_population(out["f"], res.sensor.binning), "amplitude_e": round(out["a_adu"] * g, 3),
                  "amplitude_sigma_ln": out["s"]}
        expl = (f"isolated pixels stepping up and down by ~{params['amplitude_e']:.3g} e- where no light falls "
                f"({100 * out['f']:.2g} % of the pixels in this frame, as many below the model as above): random "
                "telegraph noise")
        return Fit(name, params, out["delta"], 3, n, expl, state=out)


_RTS_SIGNATURE = RTSFrameSignature()


class RTSParams(EffectParams):
    fraction: float = Field(5e-4, ge=0, le=0.1, description="fraction of the pixels with an RTS trap [1]")
    amplitude_e: float = Field(3.0, gt=0, le=1e4, description="median RTS amplitude [e-]")
    amplitude_sigma_ln: float = Field(0.7, ge=0, le=3, description="log-normal sigma of the amplitude [1]")
    tau_min_s: float = Field(1e-5, gt=0, le=1e4, description="shortest mean dwell time [s]")
    tau_max_s: float = Field(0.1, gt=0, le=1e5, description="longest mean dwell time [s]")
    levels: Literal[2, 3] = Field(3, description="3: CDS difference (-A, 0, +A); 2: state at read (0, A)")
    cds_interval_s: float = Field(5e-6, gt=0, le=1.0, description="reset-to-signal sampling interval [s]")

    @model_validator(mode="after")
    def _check(self):
        if self.tau_max_s < self.tau_min_s:
            raise ValueError("tau_max_s must be >= tau_min_s")
        return self


#: rows per hardware band of the RTS population (sensor rows)
_RTS_BAND = 240


@register_effect
class RTSNoise(Effect):
    """Random telegraph signal: a fraction of the pixels (hardware seed) has a two-state source-follower
    trap with exponential dwell times (log-uniform means) and a log-normal amplitude; read by CDS it gives
    offsets -A, 0, +A (levels = 3) or 0, A (levels = 2), drawn anew every frame (frame seed): a sequence
    shows blinking pixels (Kirton & Uren 1989; Wang et al. 2006 IEDM). Details: detector/effects/rts.py."""

    name = "rts_noise"
    scaling = "none"
    identity = {"fraction": 0.0}
    stages = (Stage.READ,)
    Params = RTSParams
    stochastic = True
    signature = _RTS_SIGNATURE

    def population(self, y0: int, y1: int) -> tuple[np.ndarray, ...]:
        """(rows, cols, amplitude_e, tau0_s, tau1_s) of the trap pixels in sensor rows [y0, y1), drawn per
        band of the full sensor from the hardware seed (independent of the window and the tiles)."""
        s, p = self.sensor, self.params
        out = []
        for b in range(y0 // _RTS_BAND, (y1 - 1) // _RTS_BAND + 1):
            key = ("rts", b)
            if key not in self._bands:
                rows = min(_RTS_BAND, s.sensor_height_px - b * _RTS_BAND)
                rng = generator(s.hardware_seed, self.name, b)
                n = rng.binomial(rows * s.sensor_width_px, p.fraction)
                flat = np.sort(rng.choice(rows * s.sensor_width_px, size=n, replace=False))
                amp = p.amplitude_e * np.exp(p.amplitude_sigma_ln * rng.standard_normal(n))
                lo, hi = np.log(p.tau_min_s), np.log(p.tau_max_s)
                t0, t1 = np.exp(rng.uniform(lo, hi, n)), np.exp(rng.uniform(lo, hi, n))
                self._bands[key] = (b * _RTS_BAND + flat // s.sensor_width_px, flat % s.sensor_width_px, amp, t0, t1)
            out.append(self._bands[key])
        cat = [np.concatenate([o[i] for o in out]) for i in range(5)]
        keep = (cat[0] >= y0) & (cat[0] < y1)
        return tuple(c[keep] for c in cat)

    def setup(self) -> None:
        self._bands: dict = {}

    def variance_e2(self, stage: Stage, tile: Tile, mean_e):
        """Mean RTS variance per pixel [e-^2] (fraction x the offset's variance, for the model of a frame)."""
        p = self.params
        a2 = p.amplitude_e ** 2 * np.exp(2 * p.amplitude_sigma_ln ** 2)  # E[A^2] of the log-normal
        # expectation over the log-uniform time constants (a 64 x 64 grid in log tau)
        t = np.exp(np.linspace(np.log(p.tau_min_s), np.log(p.tau_max_s), 64))
        t0, t1 = np.meshgrid(t, t)
        p1 = t1 / (t0 + t1)
        if p.levels == 3:
            per = 2.0 * p1 * (1 - p1) * (1.0 - np.exp(-p.cds_interval_s * (1 / t0 + 1 / t1)))
        else:
            per = p1 * (1 - p1)
        return p.fraction * a2 * float(per.mean())

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if self.params.fraction == 0:
            return
        rows, cols, amp, t0, t1 = self.population(tile.y0, tile.y1)
        keep = (cols >= tile.x0) & (cols < tile.x1)
        if not keep.any():
            return
        rows, cols, amp, t0, t1 = rows[keep], cols[keep], amp[keep], t0[keep], t1[keep]
        off = rts_offsets(tile.rng(self.name), amp, t0, t1, self.params.levels, self.params.cds_interval_s)
        b = tile.bin
        np.add.at(data, ((rows - tile.y0) // b, (cols - tile.x0) // b), off.astype(np.float32))
