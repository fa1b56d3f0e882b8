"""The always-on electrons-to-ADU chain (thesis eqs. 30-34), tiled in row bands.

Order, and why:

1. expected photo-electrons ``S`` (the scene already applied QE as a *mean*, eq. 30), times the pixel
   response (RESPONSE effects: PRNU, dead pixels);
2. plus the mean dark signal ``I_d t`` (eq. 32) and DARK effects (DSNU, hot pixels, glow): the mean of
   everything the pixel collects, which is what ``--noiseless`` writes;
3. **one** Poisson draw of that total (shot noise of photo-electrons and dark electrons together: the sum
   of independent Poisson variables is Poisson), then CHARGE effects (cosmic-ray charge);
4. clip at the full well *before* any read-out noise (a pixel cannot hold more; eq. 34);
4b. COUPLING effects, which move or share charge between pixels (brighter-fatter, charge-transfer
   inefficiency, inter-pixel capacitance): each tile is given the rows of its neighbours it needs (the
   effect's ``halo_rows``) or, for an effect that needs whole columns (CTI), the whole window at once;
5. charge-domain binning for a CCD (charge is summed in the serial register before the amplifier);
6. READ effects (nonlinearity, kTC reset noise, row noise), then Gaussian read noise (eq. 33);
7. conversion to ADU by the gain (e-/ADU), ADU effects, plus the bias (eq. 34);
8. ADC: rounding to the nearest integer (an ideal mid-tread quantiser, IEEE Std 1241-2010 sect. 4.1: the
   code transitions lie half a step either side of each code) and saturation at ``2**bit_depth - 1`` (and 0);
9. DIGITAL effects (stuck pixels), then digital binning for a CMOS (sum or average after the ADC).

Every random draw takes a generator from :meth:`Tile.rng` (frame seed) or :meth:`Tile.hardware_map`
(hardware seed); tiles are processed on a thread pool (numpy's generators and ufuncs release the GIL), so
the result is the same bytes on one thread or two.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Union

import numpy as np

from .effects.base import Effect, Stage, Tile
from .errors import DetectorError
from .rng import BAND_ROWS, standard_normal_f32
from .sensor import SensorConfig

Signal = Union[float, np.ndarray, Callable[[int, int, int, int], np.ndarray]]


# --- pure physics functions ---------------------------------------------------------------------------

#: pixels per block of the Poisson draw (its float64 means and int64 counts stay in the cache)
SHOT_BLOCK_PIXELS = 1 << 16


def shot_noise(rng: np.random.Generator, mean_e: np.ndarray) -> np.ndarray:
    """Poisson draw of the collected charge [e-] from its mean [e-] (eq. 31), returned as float32.

    Drawn in blocks of rows, in order: the generator fills an array element by element in C order, so the
    blocks get the same numbers as one call on the whole array (without its two 8-byte temporaries)."""
    if mean_e.ndim != 2 or mean_e.size <= SHOT_BLOCK_PIXELS:
        return rng.poisson(mean_e).astype(np.float32)
    out = np.empty(mean_e.shape, dtype=np.float32)
    step = max(1, SHOT_BLOCK_PIXELS // max(1, mean_e.shape[1]))
    for r in range(0, mean_e.shape[0], step):
        out[r:r + step] = rng.poisson(mean_e[r:r + step])
    return out


def read_noise(rng: np.random.Generator, signal_e: np.ndarray, sigma_e: float) -> None:
    """Add zero-mean Gaussian read noise of ``sigma_e`` [e-] in place (eq. 33)."""
    if sigma_e > 0:
        noise = standard_normal_f32(rng, signal_e.shape)
        noise *= np.float32(sigma_e)
        signal_e += noise


def adc(signal_adu: np.ndarray, bit_depth: int, dtype) -> np.ndarray:
    """Analogue-to-digital conversion: round to the nearest integer and saturate to [0, 2**bit_depth - 1].

    The ideal ADC's code transition levels lie half a step either side of every code (IEEE Std 1241-2010,
    "Standard for terminology and test methods for analog-to-digital converters", sect. 4.1): a mid-tread
    quantiser, whose error has zero mean and variance q^2/12 when the input's spread covers the step
    (Widrow & Kollar 2008, Quantization Noise, ch. 4); :func:`rounded_moments` otherwise."""
    np.rint(signal_adu, out=signal_adu)
    np.clip(signal_adu, 0, 2 ** bit_depth - 1, out=signal_adu)
    return signal_adu.astype(dtype, copy=False)


#: input standard deviation [ADU] above which the rounding's moments are Sheppard's (mean kept, + 1/12 ADU^2):
#: the exact moments differ from them by terms in exp(-2 pi^2 sigma^2) (Widrow & Kollar 2008, eqs. 4.12,
#: 5.23), below 1e-19 at this sigma
SHEPPARD_SIGMA_ADU = 1.5


def rounded_moments(mean: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance [ADU, ADU^2] of ``rint(X)`` for ``X ~ N(mean, var)`` (the ADC's output).

    Where the input's spread is narrow (sigma < :data:`SHEPPARD_SIGMA_ADU`: a low-noise read-out, or the
    average of b x b digitised pixels, whose noise is divided by b) the quantiser's output is not its input
    plus an independent uniform error: its mean follows the nearest code and its variance depends on where
    the mean falls between codes (Widrow & Kollar 2008, ch. 5). The moments are then summed over the codes
    ``n`` within 7 sigma: ``P(n) = Phi((n + 1/2 - mean) / sigma) - Phi((n - 1/2 - mean) / sigma)``. Elsewhere
    Sheppard's: ``(mean, var + 1/12)``."""
    from scipy.special import ndtr

    mean = np.asarray(mean, np.float32)
    var = np.asarray(var, np.float32)
    out_m, out_v = mean.copy(), (var + np.float32(1 / 12)).astype(np.float32)
    narrow = var < np.float32(SHEPPARD_SIGMA_ADU ** 2)
    if not narrow.any():
        return out_m, out_v
    mu = mean[narrow].astype(np.float64)
    sd = np.sqrt(np.maximum(var[narrow].astype(np.float64), 1e-12))
    m0 = np.rint(mu)
    d = mu - m0  # in [-1/2, 1/2]
    k_max = int(np.ceil(7 * float(sd.max()))) + 1
    e1 = np.zeros_like(mu)
    e2 = np.zeros_like(mu)
    for j in range(-k_max, k_max + 1):
        p = ndtr((j + 0.5 - d) / sd) - ndtr((j - 0.5 - d) / sd)
        e1 += j * p
        e2 += j * j * p
    out_m[narrow] = (m0 + e1).astype(np.float32)
    out_v[narrow] = np.maximum(e2 - e1 * e1, 0.0).astype(np.float32)
    return out_m, out_v


def bin_sum(a: np.ndarray, b: int) -> np.ndarray:
    """Sum ``b x b`` blocks (rows and columns must be multiples of ``b``)."""
    if b == 1:
        return a
    r, c = a.shape
    return a.reshape(r // b, b, c // b, b).sum(axis=(1, 3), dtype=np.float64 if a.dtype.kind in "iu" else a.dtype)


def bin_sum_digital(adu: np.ndarray, b: int) -> np.ndarray:
    """Sum ``b x b`` blocks of digitised values (float64 out), as strided slices added in turn: the same sums as
    :func:`bin_sum` of ``adu`` in float64 (each of the at most ``b^2`` float32 codes of a block is exact in
    float64 and so is their sum), without the reshaped reduction's cost (~8x less time for 2 x 2)."""
    out = adu[0::b, 0::b].astype(np.float64)
    for i in range(b):
        for j in range(b):
            if i or j:
                out += adu[i::b, j::b]
    return out


def output_dtype(bit_depth: int):
    return np.uint16 if bit_depth <= 16 else np.uint32


#: the largest finite float32 (a uniform signal above it would be an infinite tile)
FLOAT32_MAX = float(np.finfo(np.float32).max)


# --- the tiled engine -----------------------------------------------------------------------------------

class Detector:
    """A sensor plus its optional effects, turning expected electrons into a digital frame.

    Parameters
    ----------
    sensor : SensorConfig
    effects : list of Effect
        Instantiated effects (see :func:`detector.effects.build_effects`); applied in stage order and,
        within a stage, in list order.
    workers : int, optional
        Threads for the row bands (default: the number of CPUs, at most 4).
    """

    def __init__(self, sensor: SensorConfig, effects: list[Effect] | None = None, workers: int | None = None):
        self.sensor = sensor
        self.effects = list(effects or [])
        self.workers = workers or min(4, os.cpu_count() or 1)
        self._by_stage = {st: [e for e in self.effects if st in e.stages] for st in Stage}
        self._by_stage[Stage.COUPLING].sort(key=lambda e: e.coupling_order)

    @property
    def coupling_halo(self) -> int | None:
        """Rows of the neighbouring tiles the COUPLING effects need together (None: the whole window)."""
        halos = [e.halo_rows for e in self._by_stage[Stage.COUPLING]]
        return None if any(h is None for h in halos) else int(sum(halos))

    def couple(self, tile: Tile, center: np.ndarray, above: np.ndarray | None = None,
               below: np.ndarray | None = None, mean_only: bool = False) -> np.ndarray:
        """Apply the COUPLING effects to a tile's charge [e-] with its neighbours' rows; a new array."""
        pt = 0 if above is None else above.shape[0]
        pb = 0 if below is None else below.shape[0]
        a = np.concatenate([x for x in (above, center, below) if x is not None]) if (pt or pb) else center.copy()
        for e in self._by_stage[Stage.COUPLING]:
            a = e.couple(tile, a, pt, pb, mean_only)
        return np.ascontiguousarray(a[pt:a.shape[0] - pb], dtype=np.float32)

    # -- geometry and timing
    def row_start_times_s(self) -> np.ndarray:
        """Exposure start of every output row relative to the first (thesis eq. 10; zeros for global)."""
        s = self.sensor
        b = s.binning
        return (np.arange(s.output_shape[0]) * b + (b - 1) / 2.0) * s.row_time_s

    def frame_state(self, exptime_s: float, frame_seed: int) -> dict:
        """What every effect prepares once per frame (``Effect.prepare_frame``), keyed by effect name."""
        return {e.name: e.prepare_frame(exptime_s, frame_seed) for e in self.effects}

    def tiles(self, exptime_s: float, frame_seed: int, state: dict | None = None) -> list[Tile]:
        s = self.sensor
        state = self.frame_state(exptime_s, frame_seed) if state is None else state
        (h, w), y0, x0 = s.shape, s.roi_y0, s.roi_x0
        step = BAND_ROWS  # a multiple of every binning factor up to 6 and of 8
        if step % s.binning:
            step = s.binning * max(1, BAND_ROWS // s.binning)
        return [Tile(s, i, y0 + r, min(y0 + r + step, y0 + h), x0, x0 + w, exptime_s, frame_seed, state=state)
                for i, r in enumerate(range(0, h, step))]

    # -- one tile
    def _photo(self, signal: Signal, tile: Tile) -> np.ndarray:
        s = self.sensor
        r0, r1 = tile.y0 - s.roi_y0, tile.y1 - s.roi_y0
        if callable(signal):
            a = np.asarray(signal(tile.y0, tile.y1, tile.x0, tile.x1), dtype=np.float32)
        elif np.ndim(signal) == 0:
            level = float(signal)
            if 0 <= level <= FLOAT32_MAX:  # a valid number (not NaN): its tile needs no per-pixel check
                return np.full(tile.shape, level, dtype=np.float32)
            a = np.full(tile.shape, level, dtype=np.float32)
        else:
            a = np.array(signal[r0:r1], dtype=np.float32)  # copy: the tile owns its array
        if a.shape != tile.shape:
            raise DetectorError(f"expected-signal tile has shape {a.shape}", key="signal",
                                expected=f"{tile.shape} (rows, cols)")
        if a.size and not (a.min() >= 0 and a.max() < np.inf):  # one test for NaN (fails >=), inf and < 0
            bad = np.argwhere(~np.isfinite(a) | (a < 0))[0]
            raise DetectorError(f"expected signal is {a[tuple(bad)]} at pixel (x={bad[1]}, y={r0 + bad[0]})",
                                key="signal", expected="finite values >= 0 e-")
        return a

    def _run(self, stage: Stage, tile: Tile, data: np.ndarray, mean_only: bool = False) -> None:
        for eff in self._by_stage[stage]:
            if not (mean_only and (eff.stochastic or eff.pattern)):
                eff.apply(stage, tile, data)

    #: relative step of the finite difference that gives a deterministic stage's local slope [1]
    SLOPE_STEP = 1e-3

    def _run_propagating(self, stage: Stage, tile: Tile, mean: np.ndarray, var: np.ndarray) -> None:
        """:meth:`_run` on the mean, with the variance carried through the stage's deterministic effects to
        first order (the delta method: ``Var f(S) ~ f'(S)^2 Var S``; e.g. Kendall & Stuart, *The Advanced
        Theory of Statistics* vol. 1, sect. 10.6). A response non-linearity or a gain region scales the noise
        as it scales the signal: a gain of 1.1 makes the variance 1.21 times larger, a pixel 2 % compressed
        at full well is 4 % quieter. The slope ``f'`` is the stage's response to a small step of every pixel
        (``SLOPE_STEP`` of its level): exact for per-pixel laws, and for an additive effect (a bias
        structure) 1; what a coupling between pixels (crosstalk at 1e-3) does to the noise is second order."""
        effects = [e for e in self._by_stage[stage] if not (e.stochastic or e.pattern)]
        if not effects:
            return
        h = np.float32(self.SLOPE_STEP) * np.maximum(np.abs(mean), np.float32(1.0))
        up = mean + h
        for eff in effects:
            eff.apply(stage, tile, mean)
            eff.apply(stage, tile, up)
        up -= mean
        up /= h
        var *= up * up

    def _variance(self, stage: Stage, tile: Tile, mean: np.ndarray) -> float | np.ndarray:
        return sum((e.variance_e2(stage, tile, mean) for e in self._by_stage[stage] if e.stochastic or e.pattern
                    or getattr(e, "adds_variance", False)),
                   0.0)

    def mean_electrons(self, signal: Signal, tile: Tile) -> np.ndarray:
        """Expected collected charge [e-] of a tile: response x photo-electrons + dark mean + DARK effects."""
        mean = self._photo(signal, tile)
        self._run(Stage.RESPONSE, tile, mean)
        mean += np.float32(self.sensor.dark_current_e_per_s * tile.exptime_s)
        self._run(Stage.DARK, tile, mean)
        np.maximum(mean, 0, out=mean)
        return mean

    def process_tile(self, signal: Signal, tile: Tile, noiseless: bool = False) -> np.ndarray:
        s = self.sensor
        b = s.binning
        if noiseless:
            mean = self.mean_electrons(signal, tile)
            out = bin_sum(mean, b)
            return out / np.float32(b * b) if s.binning_mode == "average" else out
        charge = self.charge_tile(signal, tile)
        if self._by_stage[Stage.COUPLING]:
            charge = self.couple(tile, charge)
        return self.finish_tile(tile, charge)

    def charge_tile(self, signal: Signal, tile: Tile) -> np.ndarray:
        """The collected charge [e-] of a tile: mean, one Poisson draw, CHARGE effects, full-well clip."""
        mean = self.mean_electrons(signal, tile)
        charge = shot_noise(tile.rng("shot_noise"), mean)
        del mean
        self._run(Stage.CHARGE, tile, charge)
        np.minimum(charge, np.float32(self.sensor.full_well_e), out=charge)
        return charge

    def finish_tile(self, tile: Tile, charge: np.ndarray) -> np.ndarray:
        """From the (coupled) charge [e-] of a tile to its digital frame: binning, read-out, ADC."""
        s = self.sensor
        b = s.binning
        if s.kind == "ccd" and b > 1:
            charge = bin_sum(charge, b)
            tile.bin = b
        self._run(Stage.READ, tile, charge)
        read_noise(tile.rng("read_noise"), charge, s.read_noise_e)
        charge *= np.float32(1.0 / s.gain_e_per_adu)  # now ADU, bias not yet added
        self._run(Stage.ADU, tile, charge)
        charge += np.float32(s.bias_adu)
        dtype = output_dtype(s.bit_depth)
        adu = adc(charge, s.bit_depth, np.float32)
        self._run(Stage.DIGITAL, tile, adu)
        if b > 1 and tile.bin == 1:  # CMOS: digital binning after the ADC
            adu = bin_sum_digital(adu, b)
            tile.bin = b
            if s.binning_mode == "sum":
                np.minimum(adu, s.adc_max_adu, out=adu)
        if b > 1 and s.binning_mode == "average":
            adu = np.rint(adu / (b * b))  # the average's output word, rounded as the ADC rounds
        return adu.astype(dtype)

    def moments_tile(self, signal: Signal, tile: Tile, _split: bool = False
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mean [ADU], variance [ADU^2] and a "statistical only" flag of every output pixel of a tile.

        The same chain as :meth:`process_tile` with every random draw replaced by its moments: Poisson
        variance = mean (eq. 31); the full-well clip on the mean; read noise and the variance of
        stochastic READ effects (row noise, kTC) added in e-^2 (eq. 33); division by the gain (variance by
        its square); the ADC rounds (:func:`adc`): the mean is kept and 1/12 ADU^2 of quantisation variance added
        (Widrow & Kollar 2008, ch. 4), or, where the input's spread is under a few ADU, the exact moments of
        the rounded Gaussian (:func:`rounded_moments`); binning sums means and variances, and the average of a
        CMOS's digital binning is rounded again (its moments by :func:`rounded_moments` too). Effects that draw from the
        frame seed (``stochastic``) or whose hardware realisation a real camera does not share (``pattern``)
        are left out of the mean and add their ``variance_e2`` (cosmic rays and defects are compared by
        their statistics). Pixels whose
        mean lies within 3 sigma of the full well or of the ADC maximum are flagged: there the clipped
        distribution is not Gaussian and the pixel can only be compared statistically. Deterministic
        READ/ADU effects act on the mean and scale the variance by their local slope squared (the delta
        method, :meth:`_run_propagating`: a gain region or a response non-linearity); the COUPLING effects
        act on the mean only (brighter-fatter, CTI, IPC: what they do to the noise is diagnosed from the
        frame's correlations, not from this per-pixel variance).
        """
        s = self.sensor
        b = s.binning
        fw = np.float32(s.full_well_e)
        mean = self._photo(signal, tile)
        pattern_var = self._variance(Stage.RESPONSE, tile, mean)
        self._run(Stage.RESPONSE, tile, mean, mean_only=True)
        dark = np.full_like(mean, s.dark_current_e_per_s * tile.exptime_s)
        pattern_var = pattern_var + self._variance(Stage.DARK, tile, dark)
        mean += dark
        self._run(Stage.DARK, tile, mean, mean_only=True)
        np.maximum(mean, 0, out=mean)
        var = mean + np.float32(pattern_var)
        flag = mean + 3 * np.sqrt(var) >= fw
        np.minimum(mean, fw, out=mean)
        if self._by_stage[Stage.COUPLING] and not _split:
            mean = self.couple(tile, mean, mean_only=True)
        if _split:
            return mean, var, flag
        return self.moments_finish(tile, mean, var, flag)

    def moments_finish(self, tile: Tile, mean: np.ndarray, var: np.ndarray, flag: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Second half of :meth:`moments_tile`: from the (coupled) mean charge to ADU moments."""
        s = self.sensor
        b = s.binning
        if s.kind == "ccd" and b > 1:
            mean, var, flag = bin_sum(mean, b), bin_sum(var, b), bin_sum(flag.astype(np.float32), b) > 0
            tile.bin = b
        self._run_propagating(Stage.READ, tile, mean, var)
        var += np.float32(s.read_noise_e ** 2) + np.float32(self._variance(Stage.READ, tile, mean))
        g = np.float32(1.0 / s.gain_e_per_adu)
        mean *= g
        var *= g * g
        self._run_propagating(Stage.ADU, tile, mean, var)
        mean += np.float32(s.bias_adu)
        mean, var = rounded_moments(mean, var)
        top = np.float32(s.adc_max_adu)
        flag |= mean + 3 * np.sqrt(var) >= top
        np.clip(mean, 0, top, out=mean)
        self._run(Stage.DIGITAL, tile, mean, mean_only=True)
        if b > 1 and tile.bin == 1:
            mean, var, flag = bin_sum(mean, b), bin_sum(var, b), bin_sum(flag.astype(np.float32), b) > 0
            tile.bin = b
        if b > 1 and s.binning_mode == "average":
            mean, var = rounded_moments(mean / np.float32(b * b), var / np.float32(b ** 4))
        return mean, var, flag

    def moments(self, signal: Signal, exptime_s: float, frame_seed: int = 0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model of a frame for comparison with a measurement: mean [ADU], variance [ADU^2], flag.

        See :meth:`moments_tile`. Whole output frame in memory (float32, float32, bool).
        """
        state = self.frame_state(exptime_s, frame_seed)
        if self.needs_field_image(signal):
            signal = self.field_signal(signal, exptime_s, frame_seed, state)
        shape = self.sensor.output_shape
        mean, var = np.empty(shape, np.float32), np.empty(shape, np.float32)
        flag = np.empty(shape, bool)
        b, y0 = self.sensor.binning, self.sensor.roi_y0
        tiles = self.tiles(exptime_s, frame_seed, state)
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            if self._by_stage[Stage.COUPLING]:  # the whole mean frame is in memory anyway: couple it at once
                parts = list(pool.map(lambda t: self.moments_tile(signal, t, _split=True), tiles))
                (h, w), x0 = self.sensor.shape, self.sensor.roi_x0
                whole = Tile(self.sensor, -1, y0, y0 + h, x0, x0 + w, exptime_s, frame_seed, state=state)
                coupled = self.couple(whole, np.concatenate([p[0] for p in parts]), mean_only=True)
                jobs = [(t, coupled[t.y0 - y0:t.y1 - y0], p[1], p[2]) for t, p in zip(tiles, parts)]
                results = pool.map(lambda j: self.moments_finish(*j), jobs)
            else:
                results = pool.map(lambda t: self.moments_tile(signal, t), tiles)
            for t, (m, v, f) in zip(tiles, results):
                r0, r1 = (t.y0 - y0) // b, (t.y1 - y0) // b
                mean[r0:r1], var[r0:r1], flag[r0:r1] = m, v, f
        return mean, var, flag

    # -- whole frames
    def iter_frame(self, signal: Signal, exptime_s: float, frame_seed: int, noiseless: bool = False,
                   state: dict | None = None) -> Iterator[tuple[int, int, np.ndarray]]:
        """Yield ``(row0, row1, array)`` in output (binned) rows, in order, computed on a thread pool.

        At most ``2 x workers`` tiles are in flight, so memory stays bounded for any frame size.
        ``state`` is this frame's :meth:`frame_state` when the caller already has it (e.g. for the truth).
        """
        if exptime_s < 0 or not np.isfinite(exptime_s):
            raise DetectorError(f"exposure time {exptime_s} s", key="exposure.time_s", expected=">= 0 s")
        if not callable(signal) and np.ndim(signal) == 2 and tuple(np.shape(signal)) != self.sensor.shape:
            raise DetectorError(f"expected-signal array has shape {np.shape(signal)}", key="signal",
                                expected=f"{self.sensor.shape} (rows, cols) of the read-out window")
        state = self.frame_state(exptime_s, frame_seed) if state is None else state
        if self.needs_field_image(signal):  # whole-frame effects need the whole image once
            signal = self.field_signal(signal, exptime_s, frame_seed, state)
        tiles = self.tiles(exptime_s, frame_seed, state)
        b = self.sensor.binning
        y0 = self.sensor.roi_y0
        if self._by_stage[Stage.COUPLING] and not noiseless:
            yield from self._iter_coupled(signal, tiles, exptime_s, frame_seed, state)
            return
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            pending: deque = deque()
            it = iter(tiles)
            for t in it:
                pending.append((t, pool.submit(self.process_tile, signal, t, noiseless)))
                if len(pending) >= 2 * self.workers:
                    break
            while pending:
                t, fut = pending.popleft()
                arr = fut.result()
                t.release()  # its hardware maps are no longer needed: memory stays a few tiles'
                nxt = next(it, None)
                if nxt is not None:
                    pending.append((nxt, pool.submit(self.process_tile, signal, nxt, noiseless)))
                yield (t.y0 - y0) // b, (t.y1 - y0) // b, arr

    def _iter_coupled(self, signal: Signal, tiles: list[Tile], exptime_s: float, frame_seed: int, state: dict
                      ) -> Iterator[tuple[int, int, np.ndarray]]:
        """:meth:`iter_frame` with COUPLING effects: every tile's charge is drawn (phase A), coupled with
        its neighbours' rows, then read out (phase B). With a finite halo the tiles stream (at most a few
        tiles' charge in memory); an effect that needs whole columns (CTI, a CCD's small frame) gets the
        whole window. The coupled charge depends only on the drawn charges, so the bytes do not depend on
        the number of threads."""
        s = self.sensor
        b, y0 = s.binning, s.roi_y0
        halo = self.coupling_halo
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            if halo is None:
                charges = list(pool.map(lambda t: self.charge_tile(signal, t), tiles))
                (h, w), x0 = s.shape, s.roi_x0
                whole = Tile(s, -1, y0, y0 + h, x0, x0 + w, exptime_s, frame_seed, state=state)
                coupled = self.couple(whole, np.concatenate(charges))
                del charges
                futs = [pool.submit(self.finish_tile, t, coupled[t.y0 - y0:t.y1 - y0].copy()) for t in tiles]
                for t, f in zip(tiles, futs):
                    arr = f.result()
                    t.release()
                    yield (t.y0 - y0) // b, (t.y1 - y0) // b, arr
                return
            if any(t.y1 - t.y0 < halo for t in tiles[:-1]):
                raise DetectorError(f"coupling effects need {halo} rows of neighbours", key="effects",
                                    expected=f"a total reach below the {tiles[0].y1 - tiles[0].y0}-row tile")
            n = len(tiles)
            charge: dict = {}
            done: deque = deque()

            def ensure(i):
                if 0 <= i < n and i not in charge:
                    charge[i] = pool.submit(self.charge_tile, signal, tiles[i])

            def job(i, center, above, below):
                return self.finish_tile(tiles[i], self.couple(tiles[i], center, above, below))

            charge_i: dict = {}
            for i in range(n):
                for j in (i, i + 1, i + 2):
                    ensure(j)
                for j in (i - 1, i, i + 1):
                    if 0 <= j < n and j not in charge_i:
                        charge_i[j] = charge[j].result()
                above = charge_i[i - 1][-halo:] if i > 0 and halo else None
                below = charge_i[i + 1][:halo] if i + 1 < n and halo else None
                done.append((tiles[i], pool.submit(job, i, charge_i[i], above, below)))
                for j in [k for k in charge_i if k < i - 1]:
                    del charge_i[j], charge[j]
                while len(done) > self.workers:
                    t, f = done.popleft()
                    arr = f.result()
                    t.release()
                    yield (t.y0 - y0) // b, (t.y1 - y0) // b, arr
            while done:
                t, f = done.popleft()
                arr = f.result()
                t.release()
                yield (t.y0 - y0) // b, (t.y1 - y0) // b, arr

    def needs_field_image(self, signal: Signal) -> bool:
        """Whether the FIELD effects need the whole image: not for a uniform signal (a number) that every one
        of them leaves as it is (:meth:`Effect.leaves_uniform`, e.g. blooming below the full well), which then
        stays a number (no frame-sized array)."""
        field = self._by_stage[Stage.FIELD]
        if not field:
            return False
        if callable(signal) or np.ndim(signal) != 0:
            return True
        level = float(signal)
        return not (np.isfinite(level) and level >= 0 and all(e.leaves_uniform(level) for e in field))

    def field_signal(self, signal: Signal, exptime_s: float, frame_seed: int, state: dict) -> np.ndarray:
        """The whole expected photo-electron image after the FIELD effects (a new array)."""
        s = self.sensor
        (h, w), y0, x0 = s.shape, s.roi_y0, s.roi_x0
        whole = Tile(s, -1, y0, y0 + h, x0, x0 + w, exptime_s, frame_seed, state=state)
        img = self._photo(signal, whole)
        self._run(Stage.FIELD, whole, img)
        return img

    def expose(self, signal: Signal, exptime_s: float, frame_seed: int, noiseless: bool = False,
               state: dict | None = None) -> np.ndarray:
        """The whole frame in memory: ADU (uint16/uint32) or, with ``noiseless``, expected e- (float32)."""
        dtype = np.float32 if noiseless else output_dtype(self.sensor.bit_depth)
        out = np.empty(self.sensor.output_shape, dtype=dtype)
        for r0, r1, arr in self.iter_frame(signal, exptime_s, frame_seed, noiseless, state):
            out[r0:r1] = arr
        return out

    def truth(self, exptime_s: float, frame_seed: int, state: dict | None = None) -> dict[str, np.ndarray]:
        """Every effect's truth tables for this frame (defect lists, cosmic-ray hits ...)."""
        state = self.frame_state(exptime_s, frame_seed) if state is None else state
        tables: dict[str, np.ndarray] = {}
        for eff in self.effects:
            tables.update(eff.truth(state.get(eff.name)))
        return tables
