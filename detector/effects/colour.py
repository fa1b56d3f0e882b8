"""Colour filter array of a one-shot-colour sensor: ``cfa``.

A Bayer mosaic (Bayer 1976, US patent 3,971,065) puts a red, green or blue filter over every pixel in a
2 x 2 period (two greens on one diagonal). Seen through the camera's grey model, the photo-signal of pixel
(y, x) is multiplied by the relative response of its cell,

    S'(y, x) = R[y mod 2, x mod 2] S(y, x),

with (y, x) *sensor* coordinates, so the pattern stays put under a read-out window with an odd origin. The
high-resolution mosaics put each filter over h x h pixels (h = 2: Sony Quad Bayer, Samsung Tetracell; 3:
Nonacell; 4: Tetra2pixel), period 2h: the cell of pixel (y, x) is ``((y // h) mod 2, (x // h) mod 2)``.
The response acts on the light only (sources, sky, flat screen: stage RESPONSE), not on dark charge or bias.

A binned pixel of ``b x b`` sensor pixels starting at (y0, x0) collects ``sum_pq n_p(y0) m_q(x0) R[p, q] / b^2``
with ``n_p``, ``m_q`` the numbers of its rows and columns of parity p, q: with even ``b`` every binned pixel
holds each cell ``b^2 / 4`` times and the pattern averages out to the mean response.

Approximation: the response is grey per cell. A real CFA's response is the filter's transmission integrated
against each source's spectrum times the QE, so it differs from star to star with their colour and from
the sky's (Sharma, *Digital Color Imaging Handbook*, 2003, ch. 1; PANOPTES: Guyon et al. 2021 use the
per-channel frames separately). One set of four numbers describes a flat screen or a sky-dominated frame.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from ..signatures import NEAR_SATURATION_SHARE, Fit, Signature, gls_quadratic, lstsq_delta
from ..significance import DETECTION_SIGMA
from .base import Effect, EffectParams, Stage, Tile, register_effect

# --- pure functions ---------------------------------------------------------------------------------------


def parity_fractions(starts: np.ndarray, b: int = 1, period: int = 2) -> np.ndarray:
    """Fractions of the ``b`` consecutive sensor rows (or columns) beginning at each of ``starts`` that lie in
    the mosaic's even cell (row 0 of the result) and odd cell (row 1), shape (2, len(starts)) [1]. A cell is
    ``period / 2`` pixels wide: 1 for a Bayer mosaic (period 2), 2 for a quad Bayer (period 4)."""
    s = np.asarray(starts).astype(np.int64)
    h = period // 2

    def even_below(n):  # integers i in [0, n) with (i // h) even (n >= 0 after the shift below)
        return h * (n // (2 * h)) + np.minimum(n % (2 * h), h)

    shift = 2 * h * (1 + np.abs(s).max(initial=0) // (2 * h))  # a whole number of periods: the parity is kept
    even = even_below(s + shift + b) - even_below(s + shift)
    return np.stack([even, b - even]).astype(np.float64) / b


def cfa_response(y0s: np.ndarray, x0s: np.ndarray, response, b: int = 1, period: int = 2) -> np.ndarray:
    """Mean relative response [1] of the ``b x b`` blocks of sensor pixels beginning at rows ``y0s`` and
    columns ``x0s`` (the pixel itself for ``b = 1``), for cell responses ``response = [r00, r01, r10, r11]``
    indexed by (row cell parity, column cell parity); cells of ``period / 2`` pixels; shape
    (len(y0s), len(x0s))."""
    r = np.asarray(response, np.float64).reshape(2, 2)
    return np.einsum("pi,pq,qj->ij", parity_fractions(y0s, b, period), r, parity_fractions(x0s, b, period))


def bayer_label(response) -> str:
    """A Bayer pattern name for four cell responses: the green pair is the diagonal with the larger mean; of
    the other two cells the lower is labelled red (as for a sky or a daylight-balanced screen, whose
    red response through a silicon sensor's QE is the lowest; a label only, the physics is the numbers)."""
    r = np.asarray(response, float)
    if r[0] + r[3] > r[1] + r[2]:  # green on the main diagonal: cells 01 and 10 are red/blue
        return "GRBG" if r[1] <= r[2] else "GBRG"
    return "RGGB" if r[0] <= r[3] else "BGGR"


# --- diagnosis: the photo-signal times each cell's indicator (relative responses of mean 1) ---------------------

def _cell_factors(res, period: int = 2) -> tuple[np.ndarray, np.ndarray] | None:
    """The fractions of an output pixel's sensor rows and columns in the even and odd cells (each (2, H) and
    (2, W), :func:`parity_fractions`), whose products are :func:`_cell_fractions`; None when every output pixel
    holds the four cells equally (binning by a multiple of the period: the pattern averages out)."""
    b = res.sensor.binning
    fy = parity_fractions(np.rint(res.ys - (b - 1) / 2.0), b, period)
    fx = parity_fractions(np.rint(res.xs - (b - 1) / 2.0), b, period)
    if np.allclose(fy, 0.5) and np.allclose(fx, 0.5):
        return None
    return fy, fx


def _cell_fractions(res, period: int = 2) -> np.ndarray | None:
    """Per output pixel, the fraction of its sensor pixels in each of the four cells, shape (4, H, W); None
    when every output pixel holds the four cells equally (binning by a multiple of the period: the pattern
    averages out)."""
    got = _cell_factors(res, period)
    if got is None:
        return None
    fy, fx = got
    return np.stack([fy[p][:, None] * fx[q][None, :] for p in (0, 1) for q in (0, 1)])


def _relative_cells_at(fy: np.ndarray, fx: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``f_k - f_11`` (k = 00, 01, 10) of :func:`_cell_fractions` at the pixels (``y``, ``x``), shape (3, pixels):
    the same products and differences, without the whole frame's maps."""
    last = fy[1][y] * fx[1][x]
    return np.stack([fy[p][y] * fx[q][x] - last for p, q in ((0, 0), (0, 1), (1, 0))])


#: light pixels the response fit uses at most (a random subsample, fixed seed: regular strides would alias with
#: the 2-pixel period) [pixels]
CFA_FIT_PIXELS = 1_000_000
#: |z| above which a pixel is left out of the response fit as an outlier (hot pixel, cosmic ray) [sigma]
CFA_CLIP_SIGMA = DETECTION_SIGMA


def _unsaturated(res) -> np.ndarray:
    """Light pixels well below the ADC ceiling and the full well (data and model), with a finite variance."""
    near = NEAR_SATURATION_SHARE * res.saturation_ceiling_adu
    ok = np.isfinite(res.data_adu) & (res.var_adu2 > 0) & (res.photo_adu > 0)
    return ok & (res.data_adu < near) & (res.model_adu < near)


class CFASignature(Signature):
    """Three templates ``P (f_k - f_11)``, k = 00, 01, 10 (``P`` the model's photo-signal, ``f_k`` the fraction of
    an output pixel's sensor pixels in cell k): responses ``1 + c_k``, ``c_11 = -(c_00 + c_01 + c_10)``, of mean
    1 over the cells, since their common factor is the light level the diagnosis fits anyway (a fourth
    template would be degenerate with it). Fitted jointly with the global levels by weighted least squares.

    Unlike the generic linear kind, the fit does not use only the pixels the comparison fits pixel by pixel: a
    CFA of tens of per cent makes every other column an "outlier column" and many pixels "spikes" of the grey
    model, so the fit takes every unsaturated light pixel and clips its own outliers (|z| > CFA_CLIP_SIGMA
    after the fit, iterated: hot pixels, cosmic rays), on a random subsample of at most CFA_FIT_PIXELS.
    """

    kind = "linear"
    pattern = "the light modulated with a period of 2 pixels along rows and columns"

    #: the mosaics tried: a Bayer (period 2), and each filter over 2 x 2 (period 4: Sony Quad Bayer, Samsung
    #: Tetracell), 3 x 3 (period 6: Samsung Nonacell) or 4 x 4 pixels (period 8: Samsung Tetra2pixel); the
    #: choice counts one parameter in the BIC
    PERIODS = (2, 4, 6, 8)

    def fit(self, res, name):
        if not np.any(res.photo_adu > 0):
            return None
        sample = self._sample(res)
        if sample is None:
            return None
        best = None
        for period in self.PERIODS:
            fit = self._fit_period(res, name, period, sample)
            if fit is not None:
                fit.k += 1  # the period chosen
                if best is None or fit.delta_bic < best.delta_bic:
                    best = fit
        if best is not None:  # the mean change of the chosen mosaic only (a frame-sized map)
            c, period = best.state.pop("cells")
            rel = _cell_fractions(res, period)
            rel = rel[:3] - rel[3]
            best.delta_adu = (res.photo_adu.astype(np.float64) * np.tensordot(c, rel, axes=1)).astype(np.float32)
        return best

    @staticmethod
    def _sample(res, limit: int | None = CFA_FIT_PIXELS) -> dict | None:
        """The pixels a mosaic is fitted or scored on (the same for every period): every unsaturated light pixel
        of ``res.train`` (a random subsample of at most ``limit``; None: all), their residual, weight,
        photo-signal, row and global-level templates."""
        ok = _unsaturated(res)
        idx = np.flatnonzero(ok if res.train is None else ok & res.train)
        if idx.size < 100:
            return None
        scale = 1.0
        if limit is not None and idx.size > limit:
            scale = idx.size / limit
            idx = np.sort(np.random.default_rng(0).choice(idx, limit, replace=False))
        levels = res.level_values(idx)  # the global levels this frame fits (no bias offset on a light frame)
        return {"idx": idx, "scale": scale, "yx": np.divmod(idx, res.data_adu.shape[1]),
                "r": (res.data_adu.ravel()[idx] - res.model_adu.ravel()[idx]).astype(np.float64),
                "w": 1.0 / res.var_adu2.ravel()[idx].astype(np.float64),
                "photo": res.photo_adu.ravel()[idx].astype(np.float64),
                "levels": levels if levels.size else np.zeros((1, idx.size))}

    def _fit_period(self, res, name, period, sample):
        f = _cell_factors(res, period)
        if f is None:
            return None
        idx, scale, (y, x), r, w, levels = (sample[k] for k in ("idx", "scale", "yx", "r", "w", "levels"))
        temps = sample["photo"] * _relative_cells_at(*f, y, x)
        keep = np.ones(idx.size, bool)
        row_var = float(res.row_var_adu2)  # row noise: generalised least squares over each row's pixels
        for _ in range(3):
            c, d, _ = lstsq_delta(r[keep], w[keep], temps[:, keep], levels[:, keep], y[keep], row_var)
            rest = r - c @ temps
            c_levels, _, _ = lstsq_delta(rest[keep], w[keep], levels[:, keep], None, y[keep], row_var)  # its levels
            new = np.abs(rest - c_levels @ levels) * np.sqrt(w) < CFA_CLIP_SIGMA
            if np.array_equal(new, keep):
                break
            keep = new
        # the light level L of the joint fit: the cells' responses are 1 + c_k / L (the data are L P (1 + delta_k))
        photo = sample["photo"][keep]
        wk = w[keep] * photo
        level = float(np.dot(wk, photo + (c_levels @ levels)[keep]) / np.dot(wk, photo))
        params = _cfa_params(np.asarray(c) / level, period) if level > 0 else None
        if params is None:
            return None
        # the mean change (a frame-sized map) is made by :meth:`fit` for the chosen period only
        return Fit(name, params, d * scale, len(c), int(keep.sum() * scale), _cfa_words(params, res),
                   note=f"2x2 cells of {period // 2} x {period // 2} pixels", state={"cells": (c, period)})

    def _before_after(self, res, fit, limit: int | None):
        """On this signature's own pixels (:meth:`_sample`): (index, mean change, residual before and after the
        fit, weights, rows), the global levels refitted to each (row noise in the generalised least squares) and
        the outliers beyond CFA_CLIP_SIGMA of both models clipped; None without pixels or a mean change."""
        sample = self._sample(res, limit=limit)
        if sample is None or fit.delta_adu is None:
            return None
        idx, r, w, levels, (rows, _) = (sample[k] for k in ("idx", "r", "w", "levels", "yx"))
        delta = np.asarray(fit.delta_adu, np.float64).ravel()[idx]
        row_var = float(res.row_var_adu2)

        def profiled(y):
            c, _, _ = lstsq_delta(y, w, levels, None, rows, row_var)
            return y - c @ levels

        r0, r1 = profiled(r), profiled(r - delta)
        keep = (np.abs(r0) * np.sqrt(w) < CFA_CLIP_SIGMA) | (np.abs(r1) * np.sqrt(w) < CFA_CLIP_SIGMA)
        return idx[keep], delta[keep], r0[keep], r1[keep], w[keep], rows[keep]

    def support_pixels(self, res, fit):
        """The pixels the mosaic is judged on where it acts (``scenes.app.compare.candidates.support_share``):
        its own (every unsaturated light pixel of a subsample, not only those the grey comparison fits one by
        one), as (index, mean change, residual before and after, weights) (:meth:`_before_after`)."""
        got = self._before_after(res, fit, CFA_FIT_PIXELS)
        return None if got is None else got[:5]

    def score(self, fit, res):
        """delta(-2 ln L) on this signature's own pixels (every unsaturated light pixel of ``res.train``, the
        outliers beyond CFA_CLIP_SIGMA of either model clipped), with the global levels refitted."""
        got = self._before_after(res, fit, None)
        if got is None:
            return None
        _, _, r0, r1, w, rows = got
        row_var = float(res.row_var_adu2)
        return gls_quadratic(r1, w, rows, row_var) - gls_quadratic(r0, w, rows, row_var)


def _cfa_params(c, period: int = 2) -> dict | None:
    resp = np.append(1.0 + np.asarray(c, float), 1.0 - float(np.sum(c)))
    if not np.all((resp > 0) & (resp <= 4)):
        return None
    resp = [round(float(x), 5) for x in resp]
    out = {"pattern": bayer_label(resp), "response": resp}
    if period != 2:
        out["period"] = int(period)
    return out


def _cfa_words(p, res) -> str:
    period = p.get("period", 2)
    h = period // 2
    kind = f"Bayer {p['pattern']}" if period == 2 else f"{p['pattern']} cells, each filter over {h} x {h} pixels"
    return (f"{period}-pixel periodic response of the light, cells " + "/".join(f"{x:.3g}" for x in p["response"])
            + f" (row, column cell parity 00/01/10/11; mean 1): a colour filter array ({kind})")


# --- adapter -------------------------------------------------------------------------------------------------


class CFAParams(EffectParams):
    pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"] = Field(
        "RGGB", description="Bayer layout of the cells (row-major from sensor pixel (0, 0)); a label: the "
                            "response list carries the physics")
    response: list[float] = Field(
        [0.57, 1.06, 1.06, 0.79], min_length=4, max_length=4,
        description="relative response of the cells [r00, r01, r10, r11], indexed by (row parity, column "
                    "parity) of the sensor pixel, each in (0, 4] [1]", json_schema_extra={"unit": "1"})

    period: Literal[2, 4, 6, 8] = Field(
        2, description="mosaic period [pixels]: 2 for a Bayer mosaic; 4, 6, 8 for each filter over 2 x 2 (Sony Quad "
                       "Bayer, Samsung Tetracell), 3 x 3 (Nonacell) or 4 x 4 pixels (Tetra2pixel)",
        json_schema_extra={"unit": "pixel"})

    @field_validator("response")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if not all(0 < r <= 4 for r in v):
            raise ValueError("every cell response must be in (0, 4]")
        return v


@register_effect
class ColourFilterArray(Effect):
    """Colour filter array: the light of sensor pixel (y, x) times the response of its cell,
    ``R[(y // h) mod 2, (x // h) mod 2]`` with ``h = period / 2`` (1: Bayer; 2, 3, 4: each filter over h x h
    pixels), grey per cell; see the module docstring for the colour approximation.

    Default responses: the sky of a raw PANOPTES Canon frame, G 185 / B 131 / R 93 ADU above bias per cell
    (docs/compare_realdata_sky.md), i.e. R 0.57, G 1.06, B 0.79 of a common level (RGGB).
    """

    name = "cfa"
    field_kind = "multiplicative"
    scaling = "signal"
    identity = {"response": [1.0, 1.0, 1.0, 1.0]}
    stages = (Stage.RESPONSE,)
    Params = CFAParams
    signature = CFASignature()

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        ys, xs = tile.pixel_centres()
        b = tile.bin
        data *= cfa_response(np.rint(ys - (b - 1) / 2.0), np.rint(xs - (b - 1) / 2.0), self.params.response,
                             b, self.params.period).astype(np.float32)
