"""An independent test of ``newtsim diagnose``: effects in forms no plugin shares, and effects no plugin models.

``hidden_effects.py`` proves the diagnosis on one real-world form per catalogue effect; this set (issue 10)
asks whether it generalises. It reuses that example's machinery (its base scenes, model and measured
scenes, ``Levels``, ``RealWorld`` effects acting at their physical stage, frame making, the error metric)
and adds:

* **catalogue effects in other forms**: every effect of the catalogue with a diagnosis signature in at
  least two functional forms that differ from the plugin's own *and* from ``hidden_effects.py``'s (other
  profile shapes, centres, scales, laws), one strong and one weaker ("near threshold": roughly 5-10x
  below the strong one; not calibrated against the detection threshold), on both cameras (ML11002 CCD,
  IMX411 CMOS), on full sensors (binned) and on windows;
* **effects in no plugin** (``ooc``: out of catalogue): dust donuts, a diffraction ring around the stars,
  a read-noise gradient, a bias drifting during the read-out, satellite glints, fringes, an electronic
  pickup pattern, a persistent image of a previous pointing, a periodic row pick-up; and, added in the sixth
  round as probes before any rule was written for them, a read-out smear, a rolling-shutter flicker, a
  satellite trail, tree rings and an amplifier undershoot. Their right answer is not a name but an honest
  description: each records the expected ``kind`` ("additive", "multiplicative", "redistributed",
  "mixed") and ``geometry`` (words of "radial", "gradient", "rows", "columns", "periodic", "sources",
  "local", "streak", "rings", "blobs") that the diagnosis's ``residual_morphology`` block must match;
* **null frames**: every base scene (the seven of ``hidden_effects.py`` and eight more) with nothing hidden.

For every case: the first significant and plausible candidate (``plausible``, ``implausible_because``,
``heldout_delta`` and the top-level ``residual_morphology`` are read with ``.get()``: absent keys mean
"plausible" and "no morphology"), the error before and after one ``--apply`` of that candidate
(:func:`scenes.app.compare.run.apply_best` with the measured frame, as ``diagnose --apply`` does: the first
significant candidate, or when nothing is significant but the residual is, its empirical map), and the seconds.

Summary metrics (``OUT_DIR/unseen.md``, ``unseen.json``, ``unseen.png``, also printed):

* named first: catalogue cases whose first candidate is one of the accepted names;
* confidently wrong: a significant, plausible first candidate that is wrong; for an out-of-catalogue case
  any significant plausible candidate naming a catalogue effect is wrong (an empirical map is not); a wrong
  first candidate that the diagnosis itself says it cannot tell apart (``indistinguishable``: as good on
  held-out pixels) from an accepted name is not confidently wrong, it is counted as ambiguous (the strict
  count, which ignores the diagnosis's doubt, is reported too);
* morphology match: out-of-catalogue cases whose ``residual_morphology`` is significant with the expected
  kind and at least one expected geometry word;
* error halved: after / before <= 0.5 (over every non-null case; a case fails unless the error fell by half or
  its error before was already within the noise, 3 standard deviations, :func:`error_halved`);
* null frames clean: no significant candidate.

Usage::

    python examples/diagnose/unseen_effects.py [OUT_DIR] [--cases a,b] [--workers N] [--seed S] [--keep]

(default OUT_DIR ``unseen_effects_out``, 2 worker processes). ``--list`` prints the cases.
The test ``tests/scenes/test_diagnose_unseen.py`` runs a fast subset and (slow) the whole set.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import runpy
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage, signal

from detector.effects.base import Stage
from detector.effects.blooming import bleed_columns
from detector.rng import generator

HE = runpy.run_path(str(Path(__file__).resolve().with_name("hidden.py")), run_name="hidden_effects")
RealWorld, Levels = HE["RealWorld"], HE["Levels"]
model_scene, make_frame, write_scene, error_of = HE["model_scene"], HE["make_frame"], HE["write_scene"], HE["error_of"]
truth_chi2_after_levels = HE["truth_chi2_after_levels"]
STATISTICAL = HE["STATISTICAL"]

# --- more base scenes (added to hidden_effects' BASES, which model_scene / measured_scene read) ----------------

_STAR_SKY = {"pointing": {"ra_deg": 120.95115, "dec_deg": -29.25022, "epoch": "2023-02-01T22:00:00"},
             "psf": {"model": "gaussian", "fwhm_arcsec": 3.0}}

NEW_BASES: dict[str, dict] = {
    # a flat on a 512x512 window at the centre of the CMOS
    "flat_imx": {"detector": {"preset": "imx411", "width": 512, "height": 512},
                 "exposure": {"time_s": 10.0, "frame": "light"},
                 "sky": {"stars": False, "flat_e_per_s": 3000.0}},
    # a 4096x4096 corner of the CMOS (its amplifier corner is elsewhere) binned 8x8 under a faint flat (the
    # CMOS sums 64 read-out values of 16 bits: 64 x (500 ADU bias + 164 ADU) stays below 65535)
    "flat_imx_bin": {"detector": {"preset": "imx411", "width": 4096, "height": 4096, "x0": 0, "y0": 0, "binning": 8},
                     "exposure": {"time_s": 10.0, "frame": "light"},
                     "sky": {"stars": False, "flat_e_per_s": 20.0}},
    # bias frames of that corner of the CMOS, binned 8x8
    "bias_imx": {"detector": {"preset": "imx411", "width": 4096, "height": 4096, "x0": 0, "y0": 0, "binning": 8},
                 "exposure": {"time_s": 0.0, "frame": "bias"},
                 "sky": {"stars": False}},
    # the whole CCD binned 8x8, 300 s dark
    "dark_full": {"detector": {"preset": "ml11002", "binning": 8},
                  "exposure": {"time_s": 300.0, "frame": "dark"},
                  "sky": {"stars": False}},
    # a 10 s star field on a 512x512 window at the centre of the CMOS
    "stars_imx": {"detector": {"preset": "imx411", "width": 512, "height": 512},
                  "exposure": {"time_s": 10.0, "frame": "light", "tracking": "sidereal"},
                  "sky": {"background_mag_arcsec2": 19.72, "stars": True, "star_mag_limit": 15.0}, **_STAR_SKY},
    # a 30 s star field under a bright sky (18 mag/arcsec2) on the CCD: a bright frame with stars
    "stars_bright": {"detector": {"preset": "ml11002", "width": 512, "height": 512},
                     "exposure": {"time_s": 30.0, "frame": "light", "tracking": "sidereal"},
                     "sky": {"background_mag_arcsec2": 18.0, "stars": True, "star_mag_limit": 15.0}, **_STAR_SKY},
    # a 10 s frame of the sky alone (no stars) on a 4096x4096 corner of the CMOS binned 8x8: light over a large
    # field (straylight), the sum of 64 read-out values below 16 bits
    # a 10 s star field on a 512x512 window at the centre of the CMOS under a sharp PSF (1.2 arcsec FWHM, ~2.5 px):
    # undersampled stars show pixel-scale couplings (IPC) that a 3 arcsec PSF (6 px) smooths away
    "stars_imx_sharp": {"detector": {"preset": "imx411", "width": 512, "height": 512},
                        "exposure": {"time_s": 10.0, "frame": "light", "tracking": "sidereal"},
                        "sky": {"background_mag_arcsec2": 19.72, "stars": True, "star_mag_limit": 15.0},
                        "pointing": _STAR_SKY["pointing"], "psf": {"model": "gaussian", "fwhm_arcsec": 1.2}},
    "sky_imx_bin": {"detector": {"preset": "imx411", "width": 4096, "height": 4096, "x0": 0, "y0": 0, "binning": 8},
                    "exposure": {"time_s": 10.0, "frame": "light"},
                    "sky": {"background_mag_arcsec2": 19.72, "stars": False}, **_STAR_SKY},
}
HE["BASES"].update(NEW_BASES)
BASES = HE["BASES"]


# --- coordinates ------------------------------------------------------------------------------------------------

def _win(tile):
    """Window coordinates of the tile's current pixels: x, y [sensor px from the window origin] and the window
    size (w, h) [sensor px]."""
    ys, xs = tile.pixel_centres()
    s = tile.sensor
    w, h = s.roi_shape
    return xs - s.roi_x0, ys - s.roi_y0, w, h


def _hw(tile, name, draw, shape):
    """A hardware map (:meth:`Tile.hardware_map`) reduced to the data's ``shape`` (block mean when binned)."""
    m = tile.hardware_map(name, draw)
    if m.shape != tuple(shape):
        b = tile.bin
        m = m[:shape[0] * b, :shape[1] * b].reshape(shape[0], b, shape[1], b).mean(axis=(1, 3))
    return m


def _sky_free(data):
    """The sources of a photo-electron image: the image minus its median (the sky), clipped at 0."""
    return np.maximum(data - np.float32(np.median(data)), 0)


def _remap(data, src_y, src_x):
    """The image sampled at (src_y, src_x) [array px], bilinear, edges extended."""
    return ndimage.map_coordinates(data, [src_y, src_x], order=1, mode="nearest").astype(np.float32)


def _centred_grid(data, tile):
    """Window pixel grids (y, x) [array px] and the sensor centre in array px (yc, xc)."""
    ys, xs = tile.pixel_centres()
    s = tile.sensor
    yy, xx = np.meshgrid(np.arange(data.shape[0], dtype=float), np.arange(data.shape[1], dtype=float), indexing="ij")
    yc = ((s.sensor_height_px - 1) / 2 - ys[0]) / tile.bin
    xc = ((s.sensor_width_px - 1) / 2 - xs[0]) / tile.bin
    return yy, xx, yc, xc


# --- catalogue effects in other forms ---------------------------------------------------------------------------

class RadialFallOff(RealWorld):
    """Relative illumination falling radially about a point (window fractions ``cu``, ``cv``) and reaching
    ``1 - depth`` at the farthest window corner: ``law`` "gauss" (exp(-r^2 / 2 s^2)), "cos4"
    (cos^4(atan(r / F))) or "cone" (1 - depth r / r_max). Not the plugin's ``1 - a2 rho^2 - a4 rho^4`` about
    the sensor's axis and corner radius."""

    name = "uw_falloff"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        p = self.params
        x, y, w, h = _win(tile)
        x0, y0 = p.cu * (w - 1), p.cv * (h - 1)
        r = np.hypot(x[None, :] - x0, y[:, None] - y0)
        rmax = max(np.hypot(cx - x0, cy - y0) for cx in (0, w - 1) for cy in (0, h - 1))
        g = 1 - p.depth
        if p.law == "gauss":
            f = np.exp(np.log(g) * (r / rmax) ** 2)
        elif p.law == "cos4":
            big_f = rmax / np.tan(np.arccos(g ** 0.25))
            f = np.cos(np.arctan(r / big_f)) ** 4
        else:
            f = 1 - p.depth * r / rmax
        data *= f.astype(np.float32)


class LorentzGlow(RealWorld):
    """Glow [e-/s] from a point at window fractions (``pu``, ``pv``) (outside the window when beyond [0, 1]):
    ``A / (1 + d^2 / d0^2)`` (a Lorentzian, not the plugin's exponential of the distance to an edge)."""

    name = "uw_glow"
    stages = (Stage.DARK,)

    def apply(self, stage, tile, data):
        p = self.params
        x, y, w, h = _win(tile)
        d2 = (x[None, :] - p.pu * w) ** 2 + (y[:, None] - p.pv * h) ** 2
        data += (p.amplitude_e_per_s / (1 + d2 / p.d0_px ** 2) * tile.exptime_s).astype(np.float32)


class EdgeBumpGlow(RealWorld):
    """Glow [e-/s] along the left sensor edge, Gaussian along it (centre ``yc_frac`` of the height, width
    ``sigma_px``) and falling as exp(-x / ``lambda_px``) inwards: a glow localised at the middle of an edge."""

    name = "uw_edge_glow"
    stages = (Stage.DARK,)

    def apply(self, stage, tile, data):
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        rate = p.amplitude_e_per_s * np.exp(-xs[None, :] / p.lambda_px) * np.exp(
            -(ys[:, None] - p.yc_frac * s.sensor_height_px) ** 2 / (2 * p.sigma_px ** 2))
        data += (rate * tile.exptime_s).astype(np.float32)


class ThermalDark(RealWorld):
    """Dark rate under a linear temperature field across the sensor, ``T = dtx (u - 1/2) + dty (v - 1/2)`` [K],
    with the dark current doubling every ``t2_k`` kelvin: ``D (2^(T / t2) - 1)`` added [e-/s] (the exponential
    law, not the plugin's linearised ramp; Widenhorn et al. 2002)."""

    name = "uw_thermal_dark"
    stages = (Stage.DARK,)

    def apply(self, stage, tile, data):
        p, s = self.params, self.sensor
        u, v = HE["_uv"](tile)
        t = p.dtx * (u[None, :] - 0.5) + p.dty * (v[:, None] - 0.5)
        rate = s.dark_current_e_per_s * (np.exp2(t / p.t2_k) - 1.0)
        data += (rate * tile.exptime_s).astype(np.float32)
        np.maximum(data, 0, out=data)


class SawtoothBias(RealWorld):
    """Bias [ADU]: a sawtooth along the columns (``cycles`` across the sensor, ``ptp_adu`` peak to peak)."""

    name = "uw_saw_bias"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        u, _ = HE["_uv"](tile)
        saw = (p.cycles * u + 0.3) % 1.0 - 0.5
        data += np.broadcast_to((p.ptp_adu * saw)[None, :], data.shape).astype(np.float32)


class DomeBias(RealWorld):
    """Bias [ADU]: a Gaussian dome of ``amp_adu`` about window fractions (cu, cv), width ``sigma_frac`` of the
    window (not the plugin's ramps and centred bowl)."""

    name = "uw_dome_bias"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        x, y, w, h = _win(tile)
        d2 = ((x[None, :] / w - p.cu) ** 2 + (y[:, None] / h - p.cv) ** 2) / p.sigma_frac ** 2
        data += (p.amp_adu * np.exp(-d2 / 2)).astype(np.float32)


class SideBleed(RealWorld):
    """Blooming that leaks sideways: above ``threshold`` x full well, ``side`` of the excess goes to the two
    neighbouring columns, the rest spills along the column (``up_fraction`` upwards)."""

    name = "uw_side_bleed"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        thr = np.float32(p.threshold * self.sensor.full_well_e)
        side = np.float32(p.side) * np.maximum(data - thr, 0)
        data -= side
        bleed_columns(data, float(thr), p.up_fraction)
        data[:, 1:] += side[:, :-1] / 2
        data[:, :-1] += side[:, 1:] / 2


class SoftBleed(RealWorld):
    """A soft bleed: the charge above ``threshold`` x full well leaves the pixel and is spread along the
    column with an exponential profile of ``length_px`` (``up_share`` upwards), not filled up to the full well."""

    name = "uw_soft_bleed"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        thr = np.float32(p.threshold * self.sensor.full_well_e)
        excess = np.maximum(data - thr, 0)
        if not excess.any():
            return
        data -= excess
        n = int(6 * p.length_px) + 1
        k = np.exp(-np.arange(1, n + 1) / p.length_px)
        kern = np.concatenate([(1 - p.up_share) * k[::-1] / k.sum(), [0.0], p.up_share * k / k.sum()])
        # a convolution: the charge of row i reaches row i + d with weight kern[centre + d] (up: higher rows)
        data += ndimage.convolve1d(excess, kern.astype(np.float32), axis=0, mode="constant")


class QuadBayer(RealWorld):
    """A high-resolution colour filter array: ``2 cell x 2 cell`` pixels under each dye (``cell = 2``: 4 x 4
    pixels, a period of 8, as Samsung's Tetra2pixel; not the plugin's Bayer 2x2 cells), responses ``response``
    (4 values, cell order by row then column)."""

    name = "uw_quad_cfa"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        p = self.params
        ys, xs = tile.pixel_centres()
        cy, cx = (ys.astype(int) // (2 * p.cell)) % 2, (xs.astype(int) // (2 * p.cell)) % 2
        if p.cell == 1:
            cy, cx = ys.astype(int) % 2, xs.astype(int) % 2
        resp = np.asarray(p.response).reshape(2, 2)[cy[:, None], cx[None, :]]
        if p.column_drift:
            x, _, w, _ = _win(tile)
            resp = resp * (1 + p.column_drift * (x[None, :] / w - 0.5))
        data *= resp.astype(np.float32)


class LeakColumns(RealWorld):
    """Hot columns whose rate grows linearly along the column (a leak fed from the far end): 0 at the top of the
    sensor, ``rate_e_per_s`` at the bottom (not the plugin's whole columns at one rate)."""

    name = "uw_leak_cols"
    stages = (Stage.DARK,)

    def setup(self):
        s, p = self.sensor, self.params
        rng = generator(s.hardware_seed, self.name)
        self.cols = rng.choice(np.arange(s.roi_x0, s.roi_x0 + s.roi_shape[0]), p.n_columns, replace=False)

    def apply(self, stage, tile, data):
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        ramp = (p.rate_e_per_s * ys / s.sensor_height_px * tile.exptime_s).astype(np.float32)
        for c in self.cols:
            j = np.nonzero(np.abs(xs - c) < tile.bin / 2 + 1e-9)[0]
            if j.size:
                data[:, j[0]] += ramp


class WeakColumns(RealWorld):
    """Columns of lower response (``response``, a fabrication defect), multiplicative on the light."""

    name = "uw_weak_cols"
    stages = (Stage.RESPONSE,)

    def setup(self):
        s, p = self.sensor, self.params
        rng = generator(s.hardware_seed, self.name)
        self.cols = rng.choice(np.arange(s.roi_x0, s.roi_x0 + s.roi_shape[0]), p.n_columns, replace=False)

    def apply(self, stage, tile, data):
        _ys, xs = tile.pixel_centres()
        for c in self.cols:
            j = np.nonzero(np.abs(xs - c) < tile.bin / 2 + 1e-9)[0]
            if j.size:
                data[:, j[0]] *= np.float32(self.params.response)


class SegmentTracks(RealWorld):
    """Charged-particle tracks as straight segments (``n`` per frame in the window, length uniform in
    [``lmin``, ``lmax``] px, random direction, lognormal deposit of median ``e_per_px``): not the plugin's
    particle flux and straggling model."""

    name = "uw_tracks"
    stages = (Stage.CHARGE,)
    stochastic = True

    def prepare_frame(self, exptime_s, frame_seed):
        p, s = self.params, self.sensor
        rng = generator(frame_seed, self.name)
        w, h = s.roi_shape
        pts = []
        for _ in range(p.n):
            x0, y0 = rng.uniform(0, w), rng.uniform(0, h)
            ln, a = rng.uniform(p.lmin, p.lmax), rng.uniform(0, np.pi)
            m = max(int(ln * 3), 2)
            t = np.linspace(0, ln, m)
            q = p.e_per_px * ln / m * np.exp(0.5 * rng.standard_normal(m))
            pts.append(np.stack([y0 + t * np.sin(a), x0 + t * np.cos(a), q], 1))
        return np.concatenate(pts)

    def apply(self, stage, tile, data):
        pts = tile.state[self.name]
        s = self.sensor
        y = (pts[:, 0] + s.roi_y0 - tile.y0) / tile.bin
        x = (pts[:, 1] + s.roi_x0 - tile.x0) / tile.bin
        ok = (y >= 0) & (y < data.shape[0]) & (x >= 0) & (x < data.shape[1])
        np.add.at(data, (y[ok].astype(int), x[ok].astype(int)), pts[ok, 2].astype(np.float32))


class DelayedCrosstalk(RealWorld):
    """Crosstalk between ``n_channels`` read-out channels, coupling ``alpha`` (negative: undershoot), the
    copy delayed by ``delay_px`` columns and smeared by an electronic tail (0.6 / 0.3 / 0.1), ``mirrored``
    or not (the plugin: one coefficient, no delay, no tail)."""

    name = "uw_xtalk"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        rows, cols = data.shape
        wc = cols // p.n_channels
        view = data[:, :wc * p.n_channels].reshape(rows, p.n_channels, wc)
        src = view - np.median(view)
        src = np.maximum(src, 0)
        if p.mirrored:
            src = np.where((np.arange(p.n_channels) % 2 == 1)[None, :, None], src[:, :, ::-1], src)
        tail = np.zeros_like(src)
        for k, wt in enumerate((0.6, 0.3, 0.1)):
            sh = p.delay_px + k
            tail[:, :, sh:] += wt * src[:, :, :wc - sh]
        tot = tail.sum(axis=1, keepdims=True)
        add = np.float32(p.alpha) * (tot - tail)
        if p.mirrored:
            add = np.where((np.arange(p.n_channels) % 2 == 1)[None, :, None], add[:, :, ::-1], add)
        view += add


class DeadClusters(RealWorld):
    """Clusters of ``size`` x ``size`` dead or weak pixels (response ``response``) at ``count`` positions on
    the sensor (a particle of debris, a damaged spot), not isolated pixels."""

    name = "uw_dead_clusters"
    stages = (Stage.RESPONSE,)

    def setup(self):
        from detector.effects.common import hardware_positions

        self.ys, self.xs, _ = hardware_positions(self.sensor, self.name, self.params.count)

    def apply(self, stage, tile, data):
        from detector.effects.common import in_tile

        p = self.params
        for dy in range(p.size):
            for dx in range(p.size):
                _sel, r, c = in_tile(tile, self.ys + dy, self.xs + dx)
                data[r, c] *= np.float32(p.response)


class LawDSNU(RealWorld):
    """DSNU with another law: "uniform" (relative half-width sqrt(3) ``sigma``) or "student" (t with 3 degrees
    of freedom, scaled to relative std ``sigma``); not the plugin's lognormal."""

    name = "uw_dsnu"
    stages = (Stage.DARK,)
    pixel_scatter = True

    def apply(self, stage, tile, data):
        p = self.params
        if p.law == "uniform":
            def draw(rng, shape):
                return (1 + p.sigma * np.sqrt(3) * rng.uniform(-1, 1, shape)).astype(np.float32)
        else:
            def draw(rng, shape):
                return np.maximum(1 + p.sigma * rng.standard_t(3, shape) / np.sqrt(3), 0).astype(np.float32)
        m = _hw(tile, self.name, draw, data.shape)
        data += np.float32(self.sensor.dark_current_e_per_s * tile.exptime_s * tile.bin ** 2) * (m - 1)


class SoftGainRegions(RealWorld):
    """Amplifier gains of vertical strips (boundaries ``splits`` as sensor fractions, any number, unequal widths)
    with ``tanh`` transitions of ``width_px`` (the plugin: a uniform grid with sharp steps). ``axis`` "x"
    (columns) or "y" (rows)."""

    name = "uw_gains"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        coord, size = (xs, s.sensor_width_px) if p.axis == "x" else (ys, s.sensor_height_px)
        g = np.full(coord.shape, p.gains[0], float)
        for b, (g0, g1) in zip(p.splits, zip(p.gains[:-1], p.gains[1:])):
            g += (g1 - g0) * 0.5 * (1 + np.tanh((coord - b * size) / max(p.width_px, 1e-3)))
        data *= (g[None, :] if p.axis == "x" else g[:, None]).astype(np.float32)


class ParetoHotPixels(RealWorld):
    """Hot pixels with Pareto-distributed rates (``xm_e_per_s``, index ``alpha``), optionally in vertical
    pairs (``pairs``: the pixel below shares the rate), not the plugin's Weibull law."""

    name = "uw_hot"
    stages = (Stage.DARK,)

    def setup(self):
        from detector.effects.common import hardware_positions

        p = self.params
        self.ys, self.xs, rng = hardware_positions(self.sensor, self.name, p.count)
        self.rate = (p.xm_e_per_s * (1 - rng.random(self.ys.size)) ** (-1 / p.alpha)).astype(np.float32)

    def apply(self, stage, tile, data):
        from detector.effects.common import in_tile

        p = self.params
        for dy in range(2 if p.pairs else 1):
            sel, r, c = in_tile(tile, self.ys + dy, self.xs)
            data[r, c] += self.rate[sel] * np.float32(tile.exptime_s)


class KneeNonlinearity(RealWorld):
    """A response knee: linear up to ``knee`` x full well, slope ``slope`` above (a piecewise-linear compression)."""

    name = "uw_knee"
    stages = (Stage.READ,)

    def apply(self, stage, tile, data):
        k = np.float32(self.params.knee * self.sensor.full_well_e * tile.bin ** 2)
        over = np.maximum(data - k, 0)
        data -= np.float32(1 - self.params.slope) * over


class GammaNonlinearity(RealWorld):
    """A power-law ("gamma") response ``S' = S (S / S0)^(gamma - 1)``, normalised at ``s0_frac`` x full well:
    compressive above S0 and expansive below it when gamma < 1 (the plugin: ``S (1 - beta S / FW)``)."""

    name = "uw_gamma"
    stages = (Stage.READ,)

    def apply(self, stage, tile, data):
        s0 = np.float32(self.params.s0_frac * self.sensor.full_well_e * tile.bin ** 2)
        x = np.maximum(data, 1e-3) / s0
        data *= x ** np.float32(self.params.gamma - 1)


class ColumnPRNU(RealWorld):
    """PRNU with a column pattern (each column's response off by ``col_rms``) plus a ``white`` part; or a
    lognormal white map (``law`` "lognormal") of relative std ``white``."""

    name = "uw_prnu"
    stages = (Stage.RESPONSE,)

    @property
    def pixel_scatter(self) -> bool:
        """A white map is drawn per pixel (:attr:`RealWorld.pixel_scatter`); a column pattern is seen through the
        column means, as a template."""
        return self.params.law == "lognormal" or not self.params.col_rms

    def apply(self, stage, tile, data):
        p = self.params
        _ys, xs = tile.pixel_centres()
        if p.law == "lognormal":
            m = _hw(tile, self.name, lambda rng, shape: np.exp(p.white * rng.standard_normal(shape)
                                                                 - p.white ** 2 / 2).astype(np.float32), data.shape)
            data *= m
            return
        colmap = np.random.default_rng(self.sensor.hardware_seed + 5).standard_normal(self.sensor.sensor_width_px)
        c = colmap[np.clip(xs.astype(int), 0, colmap.size - 1)]
        w = _hw(tile, self.name, lambda rng, shape: rng.standard_normal(shape, dtype=np.float32), data.shape)
        data *= (1 + p.col_rms * c[None, :] + p.white * w).astype(np.float32)


class ShapedReadNoise(RealWorld):
    """Extra read-out noise [e-]: "laplace" (heavy-tailed, std ``sigma_e``), "alternate" (Gaussian ``sigma_e``
    in even columns only: two sense-node designs) (the plugin: Gaussian kTC of one capacitance)."""

    name = "uw_noise"
    stages = (Stage.READ,)
    stochastic = True

    def apply(self, stage, tile, data):
        p = self.params
        rng = tile.rng(self.name)
        if p.law == "laplace":
            data += rng.laplace(0, p.sigma_e / np.sqrt(2), data.shape).astype(np.float32)
        else:
            _, xs = tile.pixel_centres()
            even = (np.floor(xs).astype(int) // tile.bin) % 2 == 0
            data += (rng.standard_normal(data.shape) * p.sigma_e * even[None, :]).astype(np.float32)


class TelegraphRows(RealWorld):
    """Row offsets [e-] of a random telegraph: a ``fraction`` of the rows jumps by +-``jump_e`` (bursts of
    interference), or a sinusoidal pickup of ``jump_e`` with ``period_rows`` (``law`` "pickup"), or heavy-tailed
    offsets of rms ``jump_e`` (``law`` "student": Student t, 3 degrees of freedom), plus ``white_e``: not the
    plugin's white Gaussian offsets."""

    name = "uw_rows"
    stages = (Stage.READ,)
    stochastic = True

    def prepare_frame(self, exptime_s, frame_seed):
        p, s = self.params, self.sensor
        n = s.sensor_height_px
        rng = generator(frame_seed, self.name)
        if p.law == "pickup":
            off = p.jump_e * np.sin(2 * np.pi * np.arange(n) / p.period_rows + rng.uniform(0, 2 * np.pi))
        elif p.law == "student":  # Student t, 3 degrees of freedom (variance 3 x scale^2), rms jump_e
            off = p.jump_e / np.sqrt(3.0) * rng.standard_t(3.0, n)
        else:
            off = np.where(rng.random(n) < p.fraction, p.jump_e * rng.choice([-1.0, 1.0], n), 0.0)
        return (off + p.white_e * rng.standard_normal(n)).astype(np.float32)

    def apply(self, stage, tile, data):
        ys, _ = tile.pixel_centres()
        data += tile.state[self.name][np.floor(ys).astype(int)][:, None]


class ExtraLight(RealWorld):
    """Additive light [e-/s per pixel] on the photo-signal: "quadratic" (a bowl ``level`` x ((x - xq)^2 + 0.5 (y -
    yq)^2) / R^2 about window fractions (pu, pv), R the window diagonal; straylight) or "point" (``level`` x
    (d_c / d)^2 of the distance to a point at window fractions (pu, pv), d_c its distance to the centre,
    minus its value at the centre)."""

    name = "uw_light"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        if not data.any():
            return
        p = self.params
        x, y, w, h = _win(tile)
        px, py = p.pu * w, p.pv * h
        if p.law == "quadratic":
            rate = p.level * ((x[None, :] - px) ** 2 + 0.5 * (y[:, None] - py) ** 2) / (w * w + h * h)
        else:
            dc2 = (w / 2 - px) ** 2 + (h / 2 - py) ** 2
            rate = p.level * (dc2 / ((x[None, :] - px) ** 2 + (y[:, None] - py) ** 2) - 1)
        data += (rate * tile.exptime_s).astype(np.float32)
        np.maximum(data, 0, out=data)


def _moffat_kernel(fwhm_px, beta, half=7):
    a = fwhm_px / (2 * np.sqrt(2 ** (1 / beta) - 1))
    r2 = np.add.outer(np.arange(-half, half + 1) ** 2, np.arange(-half, half + 1) ** 2)
    k = (1 + r2 / a ** 2) ** (-beta)
    return (k / k.sum()).astype(np.float32)


class ShapedBlur(RealWorld):
    """PSF broadening of another shape: "moffat" (a Moffat kernel of ``fwhm_px``, ``beta``: wings a Gaussian
    has not) or "varying" (a Gaussian blur whose sigma grows linearly across the window from ``s0`` to ``s1`` px)."""

    name = "uw_blur"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        if p.law == "moffat":
            out = ndimage.convolve(data, _moffat_kernel(p.fwhm_px, p.beta), mode="nearest")
        else:
            n = 6
            blurred = [ndimage.gaussian_filter(data, s, mode="nearest") for s in np.linspace(p.s0, p.s1, n)]
            u = np.linspace(0, n - 1, data.shape[1])
            i0 = np.clip(np.floor(u).astype(int), 0, n - 2)
            t = (u - i0)[None, :]
            stack = np.stack(blurred)
            cols = np.arange(data.shape[1])
            out = (1 - t) * stack[i0, :, cols].T + t * stack[i0 + 1, :, cols].T
        data[...] = np.maximum(out, 0)


def _smear(data, offsets):
    """The mean of the image shifted by each (dy, dx) [px] (a motion during the exposure): exact sub-pixel
    shifts (phase ramps in Fourier space, the edges extended first), so the smear is the path's alone; a
    bilinear shift would add its own blur of up to 0.125 px^2 per axis (t (1 - t) for a fraction t)."""
    off = np.asarray(offsets, np.float64)
    pad = int(np.ceil(np.abs(off).max())) + 4
    big = np.pad(np.asarray(data, np.float64), pad, mode="edge")
    fy = np.fft.fftfreq(big.shape[0])[:, None]
    fx = np.fft.rfftfreq(big.shape[1])[None, :]
    kernel = np.zeros((fy.size, fx.size), np.complex128)
    for dy, dx in off:
        kernel += np.exp(-2j * np.pi * (fy * dy + fx * dx))
    out = np.fft.irfft2(np.fft.rfft2(big) * kernel / len(off), s=big.shape)
    return out[pad:-pad, pad:-pad].astype(np.float32)


class MotionPath(RealWorld):
    """Image motion during the exposure along a path: "sine" (oscillation of amplitude ``amp_px`` along
    ``angle_deg``: an arcsine distribution, a wind-shake or a drive resonance), "walk" (a random walk of
    ``n`` steps of ``amp_px``), "accel" (a drift ``(dx, dy)`` at constant acceleration: a trail brighter at
    its start) or "arc" (a drift along a circular arc of chord ``amp_px`` and sagitta ``sag_px``)."""

    name = "uw_motion"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        n = 32
        t = (np.arange(n) + 0.5) / n
        if p.law == "sine":
            s = p.amp_px * np.sin(2 * np.pi * t)
            a = np.radians(p.angle_deg)
            offs = list(zip(s * np.sin(a), s * np.cos(a)))
        elif p.law == "walk":
            rng = np.random.default_rng(p.seed)
            steps = np.cumsum(rng.standard_normal((n, 2)) * p.amp_px, axis=0)
            steps -= steps.mean(axis=0)
            offs = [tuple(v) for v in steps]
        elif p.law == "accel":
            f = t * t - np.mean(t * t)
            offs = list(zip(f * p.dy, f * p.dx))
        else:
            x = (t - 0.5) * p.amp_px
            y = p.sag_px * (1 - (2 * t - 1) ** 2)
            y -= y.mean()
            a = np.radians(p.angle_deg)
            offs = list(zip(x * np.sin(a) + y * np.cos(a), x * np.cos(a) - y * np.sin(a)))
        data[...] = np.maximum(_smear(data, offs), 0)


class ComaTail(RealWorld):
    """An asymmetric PSF: ``frac`` of each source's light in a one-sided exponential tail of ``length_px``
    along ``angle_deg`` (coma-like), or an elongated Lorentzian-wing smear ("lorentz", ``length_px`` its
    half width, ``frac`` its share)."""

    name = "uw_coma"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        half = int(6 * p.length_px) + 2
        t = np.arange(-half, half + 1, dtype=float)
        if p.law == "coma":
            prof = np.where(t > 0, np.exp(-t / p.length_px), 0.0)
        else:
            prof = 1 / (1 + (t / p.length_px) ** 2)
        prof /= prof.sum()
        a = np.radians(p.angle_deg)
        k = np.zeros((2 * half + 1, 2 * half + 1))
        for ti, w in zip(t, prof):
            yy, xx = half + ti * np.sin(a), half + ti * np.cos(a)
            y0, x0 = int(np.floor(yy)), int(np.floor(xx))
            fy, fx = yy - y0, xx - x0
            for dy, wy in ((0, 1 - fy), (1, fy)):
                for dx, wx in ((0, 1 - fx), (1, fx)):
                    if 0 <= y0 + dy < k.shape[0] and 0 <= x0 + dx < k.shape[1]:
                        k[y0 + dy, x0 + dx] += w * wy * wx
        k *= p.frac
        k[half, half] += 1 - p.frac
        data[...] = np.maximum(signal.oaconvolve(np.pad(data, half, mode="edge"), k.astype(np.float32),
                                                 mode="same")[half:-half, half:-half], 0)


class AffineOffset(RealWorld):
    """A pointing offset (``dx``, ``dy``) [px] with a small rotation ``rot_deg`` and a plate-scale change
    ``scale`` about the sensor centre (the plugin's similarity transform, drawn here independently)."""

    name = "uw_affine"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        yy, xx, yc, xc = _centred_grid(data, tile)
        c, s = np.cos(np.radians(p.rot_deg)), np.sin(np.radians(p.rot_deg))
        u, v = xx - xc - p.dx, yy - yc - p.dy  # inverse map: output -> source
        su = (c * u + s * v) / (1 + p.scale) + xc
        sv = (-s * u + c * v) / (1 + p.scale) + yc
        data[...] = np.maximum(_remap(data, sv, su), 0)


class ShiftedGhost(RealWorld):
    """A ghost of every source ``alpha`` of its flux, either shifted by a fixed vector (``dx``, ``dy``) [px]
    ("shift": a reflection between two flat surfaces) or mirrored through a point offset (``dx``, ``dy``)
    from the sensor centre ("mirror"), spread over an annulus of radii (``r_in``, ``r_out``) or a Gaussian of
    sigma ``r_out`` ("gauss"); the plugin: mirrored through the axis, a uniform disc."""

    name = "uw_ghost"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        src = _sky_free(data)
        if p.geometry == "shift":
            moved = ndimage.shift(src, (p.dy, p.dx), order=1, mode="constant")
        else:
            yy, xx, yc, xc = _centred_grid(data, tile)
            moved = _remap(src, 2 * (yc + p.dy) - yy, 2 * (xc + p.dx) - xx)
            moved[(2 * (yc + p.dy) - yy < 0) | (2 * (yc + p.dy) - yy > data.shape[0] - 1)
                  | (2 * (xc + p.dx) - xx < 0) | (2 * (xc + p.dx) - xx > data.shape[1] - 1)] = 0
        half = int(np.ceil(3 * p.r_out)) + 1
        t = np.arange(-half, half + 1)
        r = np.hypot(t[:, None], t[None, :])
        k = ((r >= p.r_in) & (r <= p.r_out)).astype(float) if p.shape == "annulus" else np.exp(-r * r / (2 * p.r_out ** 2))
        k /= k.sum()
        data += np.float32(p.alpha) * signal.oaconvolve(moved, k.astype(np.float32), mode="same").astype(np.float32)


class BrownDistortion(RealWorld):
    """Distortion of another law: "tangential" (Brown-Conrady decentering, ``p1``, ``p2`` [px^-1]) or "r5" (a
    pure fifth-order radial term ``r' = r (1 + k2 r^4)``, ``k2`` [px^-4]) about the sensor centre (the
    plugin: a third-order radial term)."""

    name = "uw_distortion"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        yy, xx, yc, xc = _centred_grid(data, tile)
        x, y = xx - xc, yy - yc
        r2 = x * x + y * y
        if p.law == "tangential":
            dx = p.p1 * (r2 + 2 * x * x) + 2 * p.p2 * x * y
            dy = p.p2 * (r2 + 2 * y * y) + 2 * p.p1 * x * y
        else:
            dx, dy = x * p.k2 * r2 * r2, y * p.k2 * r2 * r2
        data[...] = np.maximum(_remap(data, yy - dy, xx - dx), 0)  # to first order: the inverse map


# --- catalogue effects in other forms: pixel coupling, CTI, RTS, straylight ---------------------------------------

#: the largest share of a pixel's charge one explicit step of :func:`_bf_moved` may move out of it: the flow runs
#: down the potential of the charge itself (a diffusion), whose explicit step overshoots once it moves a
#: pixel's whole charge (a hot pixel left darker than the sky around it); stronger flows are taken in as many
#: steps as keep each below this share (the step's error ~ its share squared)
BF_MAX_STEP_SHARE = 0.1
#: the most steps :func:`_bf_moved` takes (a coupling that needs more is no brighter-fatter of a real sensor)
BF_MAX_STEPS = 1000


def _bf_flows(q, k, c, q_nl_e=None):
    """The charge [e-] crossing each boundary in one step of :func:`_bf_moved`: along the columns, then the
    rows, each in the layout ``np.swapaxes(q, 0, axis)`` (the flow from a pixel to the next one along the axis,
    positive when charge leaves the first)."""
    phi = ndimage.correlate(q, k.astype(np.float32), mode="nearest")
    out = []
    for ax in (0, 1):
        a = np.swapaxes(q, 0, ax)
        ph = np.swapaxes(phi, 0, ax)
        pair = a[:-1] + a[1:]
        f = pair * (ph[:-1] - ph[1:]) * np.float32(0.25 * c)
        if q_nl_e:
            f *= 1 + pair / np.float32(2 * q_nl_e)
        out.append(f)
    return out


def _bf_apply(q, flows):
    """``q`` with the flows of :func:`_bf_flows` moved (in place; charge conserved)."""
    for ax, f in enumerate(flows):
        o = np.swapaxes(q, 0, ax)
        o[:-1] -= f
        o[1:] += f
    return q


def _bf_step_share(q, flows) -> float:
    """The largest share of a pixel's charge (at least 1 e-) the flows move out of it."""
    leave = np.zeros(q.shape, np.float64)
    for ax, f in enumerate(flows):
        lv = np.swapaxes(leave, 0, ax)
        lv[:-1] += np.maximum(f, 0)
        lv[1:] += np.maximum(-f, 0)
    return float(np.max(leave / np.maximum(q, 1.0)))


def _bf_moved(q, k, c, q_nl_e=None):
    """Brighter-fatter charge moved by boundaries shifting with the potential ``k (x) q`` (any odd kernel,
    centred), the flux across a boundary ``c (Q_i + Q_n)/4 (phi_i - phi_n)`` (the plugin's half flux of the
    growing boundary); with ``q_nl_e`` the coupling grows with the pair's charge, ``c (1 + (Q_i + Q_n) / (2
    q_nl))``. Charge conserved (what leaves a pixel enters its neighbour). A flow that would move more than
    BF_MAX_STEP_SHARE of some pixel's charge in one step is taken in ``n`` equal steps of ``c / n``, the
    potential recomputed at each (one step, the same numbers, for every flow below that share). ``n`` follows
    the charge handed in: read out in bands, each band with its own (a band's halo rows cover one step, so the
    seams of a multi-step flow are approximate: ~0.1 e- at a drawn a_10 of 3.9e-7 /e-)."""
    out = q.copy()
    flows = _bf_flows(out, k, c, q_nl_e)
    n = int(np.ceil(_bf_step_share(out, flows) / BF_MAX_STEP_SHARE))
    if n <= 1:
        return _bf_apply(out, flows)
    if n > BF_MAX_STEPS:
        raise ValueError(f"brighter-fatter coupling c = {c:.3g}: one step moves {n * BF_MAX_STEP_SHARE:.3g} of a "
                         f"pixel's charge, more than {BF_MAX_STEPS} steps of {BF_MAX_STEP_SHARE:g} (no real sensor)")
    for _ in range(n):
        _bf_apply(out, _bf_flows(out, k, c / n, q_nl_e))
    return out


def _lap10(k):
    """The discrete Laplacian of a centred kernel at the nearest neighbour along a row: a_10 per unit c."""
    h = k.shape[0] // 2
    return k[h, h] + k[h, h + 2] + k[h - 1, h + 1] + k[h + 1, h + 1] - 4 * k[h, h + 1]


class GaussianNonlinearBF(RealWorld):
    """Brighter-fatter with a 7x7 Gaussian potential (sigma ``sigma_px``) whose coupling grows with the charge,
    ``c (1 + Q_pair / (2 q_nl))`` (``q_nl_frac`` x full well): the area coefficients change with the signal,
    the "b" terms of Astier et al. 2019 (A&A 629, A36, arXiv:1905.08677); the plugin: a 3x3 exp(-r / s)
    kernel, linear in the charge. ``a10_per_e``: the nearest-neighbour area coefficient at low signal. The
    Gaussian must be convex at one pixel (sigma below ~0.75 px) for a repulsion (c > 0) to give the positive
    a_10 flats show; a wider one would make a positive a_10 an attraction (brighter-narrower)."""

    name = "uw_bf_gauss_nl"
    stages = (Stage.COUPLING,)
    halo_rows = 4
    coupling_order = 0

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        t = np.arange(-3, 4)
        k = np.exp(-(t[:, None] ** 2 + t[None, :] ** 2) / (2 * p.sigma_px ** 2))
        k /= k[3, 3]
        if _lap10(k) <= 0:
            raise ValueError(f"sigma_px = {p.sigma_px}: the potential is not convex at one pixel (no repulsion "
                             "gives a positive a_10)")
        return _bf_moved(np.asarray(charge_e, np.float32), k, p.a10_per_e / _lap10(k),
                         p.q_nl_frac * self.sensor.full_well_e)


class CoulombBF(RealWorld):
    """Brighter-fatter with a long-range Coulomb potential ``1 / sqrt(r^2 + r0^2)`` over 9x9 pixels (the field
    of the collected charge falls as a power law: Coulton et al. 2018, AJ 155, 258, arXiv:1711.06273, derive
    the kernel from electrostatics), not the plugin's 3x3 exponential; ``a10_per_e`` sets its strength."""

    name = "uw_bf_coulomb"
    stages = (Stage.COUPLING,)
    halo_rows = 6
    coupling_order = 0

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        t = np.arange(-4, 5)
        k = 1 / np.sqrt(t[:, None] ** 2 + t[None, :] ** 2 + p.r0_px ** 2)
        k /= k[4, 4]
        return _bf_moved(np.asarray(charge_e, np.float32), k, p.a10_per_e / _lap10(k))


class AsymmetricIPC(RealWorld):
    """Inter-pixel capacitance with a non-centrosymmetric 3x3 kernel (``left``, ``right``, ``up``, ``down``
    differ; ``diag`` on the diagonals), as measured on hybrid CMOS arrays (Kannawadi et al. 2016, PASP 128,
    095001); the plugin: one coupling for the four nearest neighbours. The kernel conserves the signal."""

    name = "uw_ipc_asym"
    stages = (Stage.COUPLING,)
    halo_rows = 1
    coupling_order = 2

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        # correlate: out[i, j] = sum k[a, b] q[i + a - 1, j + b - 1], so the pixel to the right (j + 1) reads
        # k[1, 0] of q[i, j] ("right": the coupling towards +x) and the one above (i + 1, "up": +y) reads k[0, 1]
        return HE["couple_3x3"](charge_e, [[p.diag, p.up, p.diag], [p.right, 0.0, p.left], [p.diag, p.down, p.diag]])


class SignalDependentIPC(RealWorld):
    """Inter-pixel capacitance that changes with the signal: each pixel couples ``alpha(Q) = a0 + (a1 - a0) Q /
    FW`` of its charge into each nearest neighbour (the coupling capacitance changes as the node's depletion
    changes: Donlon et al. 2018, arXiv:1805.09413, 0.68-1.45 % over an H2RG's full well); the plugin: one
    coupling at every signal. Charge seen, not moved; the total conserved."""

    name = "uw_ipc_signal"
    stages = (Stage.COUPLING,)
    halo_rows = 1
    coupling_order = 2

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        q = np.asarray(charge_e, np.float32)
        a = np.float32(p.a0) + np.float32((p.a1 - p.a0) / self.sensor.full_well_e) * np.maximum(q, 0)
        share = a * q
        pad = np.pad(share, 1, mode="edge")
        return q - 4 * share + pad[:-2, 1:-1] + pad[2:, 1:-1] + pad[1:-1, :-2] + pad[1:-1, 2:]


def _cti_columns(img, rho_cols, decay, beta, well_e, first, capture=1.0):
    """Parallel CTI of one trap species whose density differs per column (``rho_cols`` [traps/px], one per
    column), release per transfer ``1 - decay``, well fill ``(n / w)^beta``, capture of a fraction ``capture``
    of the free traps within reach per transfer (1: instant, CDM03; Short et al. 2013, MNRAS 430, 3078);
    the read-out towards row 0 (:func:`detector.effects.cti.cti_transfer` with one species)."""
    img = np.array(img, np.float64)
    trapped = np.zeros(img.shape[1])
    for j in range(img.shape[0]):
        n = img[j]
        rel = trapped * (1.0 - decay)
        trapped -= rel
        n += rel
        target = rho_cols * (j + first) * np.power(np.maximum(n, 0.0) / well_e, beta)
        cap = np.minimum(np.maximum(target - trapped, 0.0) * capture, n)
        trapped += cap
        n -= cap
    return img


class ColumnCTI(RealWorld):
    """CTI whose trap density differs from column to column: ``density`` [traps/px] x a lognormal factor per
    column (``col_sigma_ln``, the hardware) x a linear trend across the sensor (``trend``: the damage is a local
    property of the silicon; Massey et al. 2014, MNRAS 439, 887, arXiv:1401.1151, measure the trap density
    map of HST ACS), one species releasing in ``release_transfers``, well-fill power ``beta`` (the plugin: the
    same density in every column, release 0.74 / 7.7 / 37 transfers, beta 0.478)."""

    name = "uw_cti_columns"
    stages = (Stage.COUPLING,)
    halo_rows = None
    coupling_order = 1

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p, s = self.params, self.sensor
        colf = np.exp(p.col_sigma_ln * np.random.default_rng(s.hardware_seed + 17).standard_normal(s.sensor_width_px)
                      - p.col_sigma_ln ** 2 / 2)
        _ys, xs = tile.pixel_centres()
        xi = np.clip(np.floor(xs).astype(int), 0, s.sensor_width_px - 1)
        rho = p.density * colf[xi] * (1 + p.trend * (xs / (s.sensor_width_px - 1) - 0.5))
        return _cti_columns(charge_e, rho, np.exp(-1.0 / p.release_transfers), p.beta, s.full_well_e,
                            tile.y0 - pad_top + 1).astype(np.float32)


class LinearSlowCaptureCTI(RealWorld):
    """The classical constant-fraction CTI (a packet loses the same fraction at every signal: well-fill power
    ``beta`` = 1; Janesick 2001, Scientific Charge-Coupled Devices, SPIE PM83, ch. 5) with a finite capture
    (``capture`` of the free traps in reach per transfer; CDM03's capture probability, Short et al. 2013, MNRAS
    430, 3078) and one species releasing in ``release_transfers`` (the plugin: instant capture, beta 0.478)."""

    name = "uw_cti_linear"
    stages = (Stage.COUPLING,)
    halo_rows = None
    coupling_order = 1

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p, s = self.params, self.sensor
        rho = np.full(np.shape(charge_e)[1], p.density)
        return _cti_columns(charge_e, rho, np.exp(-1.0 / p.release_transfers), 1.0, s.full_well_e,
                            tile.y0 - pad_top + 1, capture=p.capture).astype(np.float32)


def _rts_pixels(sensor, name, fraction):
    """Sensor rows and columns of the RTS pixels in the read-out window (a fixed draw of the whole measured chip,
    window independent) and the generator that draws their properties next."""
    rng = generator(sensor.hardware_seed, name)
    n = sensor.sensor_width_px * sensor.sensor_height_px
    flat = np.unique(rng.integers(0, n, rng.binomial(n, fraction)))
    rows, cols = flat // sensor.sensor_width_px, flat % sensor.sensor_width_px
    w, h = sensor.roi_shape
    keep = (rows >= sensor.roi_y0) & (rows < sensor.roi_y0 + h) & (cols >= sensor.roi_x0) & (cols < sensor.roi_x0 + w)
    return rows[keep], cols[keep], rng


def _add_at_pixels(tile, data, rows, cols, values):
    sel = (rows >= tile.y0) & (rows < tile.y1) & (cols >= tile.x0) & (cols < tile.x1)
    if sel.any():
        b = tile.bin
        np.add.at(data, ((rows[sel] - tile.y0) // b, (cols[sel] - tile.x0) // b), values[sel].astype(np.float32))


class TwoTrapRTS(RealWorld):
    """RTS pixels with two independent traps each (a multi-level signal: the sum of two telegraphs; Kirton &
    Uren 1989, Adv. Phys. 38, 367), gamma-distributed amplitudes (shape 2, means ``mean1_e`` and ``mean2_e``),
    log-normal mean dwell times (median ``tau_med_s``, ``tau_sigma_ln``: traps at one depth, not McWhorter's
    log-uniform spread), read by CDS ``cds_s`` apart (the plugin: one trap, log-normal amplitude, log-uniform
    10 us - 100 ms, 5 us)."""

    name = "uw_rts_twotrap"
    stages = (Stage.READ,)
    stochastic = True

    def setup(self):
        p = self.params
        self.rows, self.cols, rng = _rts_pixels(self.sensor, self.name, p.fraction)
        n = self.rows.size
        self.amp = np.stack([rng.gamma(2.0, p.mean1_e / 2, n), rng.gamma(2.0, p.mean2_e / 2, n)])
        self.tau = p.tau_med_s * np.exp(p.tau_sigma_ln * rng.standard_normal((2, 2, n)))

    def apply(self, stage, tile, data):
        from detector.effects.rts import rts_offsets

        rng = tile.rng(self.name)
        off = sum(rts_offsets(rng, self.amp[k], self.tau[k, 0], self.tau[k, 1], 3, self.params.cds_s) for k in (0, 1))
        _add_at_pixels(tile, data, self.rows, self.cols, off)


class ThreeStateRTS(RealWorld):
    """RTS pixels whose trap has three states (empty, captured, a metastable configuration: the "anomalous"
    RTS of Kirton & Uren 1989, Adv. Phys. 38, 367) with output levels 0, A, ``mid`` A, visited in the cycle
    0 -> 1 -> 2 -> 0 with exponential dwell times of means log-uniform in [``tau_lo_s``, ``tau_hi_s``],
    amplitude A uniform in [``amp_lo_e``, ``amp_hi_e``], read by CDS ``cds_s`` apart (the plugin: two states)."""

    name = "uw_rts_threestate"
    stages = (Stage.READ,)
    stochastic = True

    def setup(self):
        from scipy.linalg import expm

        p = self.params
        self.rows, self.cols, rng = _rts_pixels(self.sensor, self.name, p.fraction)
        n = self.rows.size
        self.amp = rng.uniform(p.amp_lo_e, p.amp_hi_e, n)
        tau = np.exp(rng.uniform(np.log(p.tau_lo_s), np.log(p.tau_hi_s), (n, 3)))
        self.pi = tau / tau.sum(axis=1, keepdims=True)  # stationary law of a cycle: pi_i ~ tau_i
        self.trans = np.empty((n, 3, 3))
        for i in range(n):
            q = np.zeros((3, 3))
            for s in range(3):
                q[s, s], q[s, (s + 1) % 3] = -1 / tau[i, s], 1 / tau[i, s]
            self.trans[i] = expm(q * p.cds_s)

    def apply(self, stage, tile, data):
        rng = tile.rng(self.name)
        n = self.rows.size
        s0 = (rng.random(n)[:, None] > np.cumsum(self.pi, axis=1)).sum(axis=1).clip(0, 2)
        s1 = (rng.random(n)[:, None] > np.cumsum(self.trans[np.arange(n), s0], axis=1)).sum(axis=1).clip(0, 2)
        level = np.array([0.0, 1.0, self.params.mid])
        _add_at_pixels(tile, data, self.rows, self.cols, self.amp * (level[s1] - level[s0]))


class HarveyHalo(RealWorld):
    """Straylight of a bright source just outside the field: the halo of light its image scatters off the
    mirror, falling as the Harvey law of a polished surface, ``L (1 + (d / d0)^2)^(-s/2)`` [e-/s/px] of the
    distance ``d`` to the source at window fractions (``pu``, ``pv``) (Harvey 1976; Breault 1995, Handbook of
    Optics I, ch. 38), scaled to ``near_e_per_s`` at the window corner nearest to it; additive light, growing
    with the exposure (the plugin: a second-order polynomial about the sensor centre)."""

    name = "uw_straylight_halo"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        if not data.any():
            return
        p = self.params
        x, y, w, h = _win(tile)
        sx, sy = p.pu * w, p.pv * h

        def law(d2):
            return (1 + d2 / p.d0_px ** 2) ** (-p.index / 2)

        near = min((cx - sx) ** 2 + (cy - sy) ** 2 for cx in (0, w - 1) for cy in (0, h - 1))
        rate = p.near_e_per_s / law(near) * law((x[None, :] - sx) ** 2 + (y[:, None] - sy) ** 2)
        data += (rate * tile.exptime_s).astype(np.float32)


class BaffleArc(RealWorld):
    """Straylight from a glint on a baffle edge lit by an off-axis source: a broad arc of light, a ring of
    radius ``radius_frac`` (window diagonals) about a centre at window fractions (``cu``, ``cv``) outside the
    field, Gaussian across (``width_frac`` of the diagonal), ``peak_e_per_s`` on its crest (Breault 1995,
    Handbook of Optics I, ch. 38: baffle-edge diffraction and glints); additive light, growing with exposure."""

    name = "uw_straylight_arc"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        if not data.any():
            return
        p = self.params
        x, y, w, h = _win(tile)
        diag = np.hypot(w, h)
        r = np.hypot(x[None, :] - p.cu * w, y[:, None] - p.cv * h) / diag
        rate = p.peak_e_per_s * np.exp(-0.5 * ((r - p.radius_frac) / p.width_frac) ** 2)
        data += (rate * tile.exptime_s).astype(np.float32)


# --- effects that no plugin models ------------------------------------------------------------------------------

class DustDonuts(RealWorld):
    """Shadows of dust on a window or filter out of focus: ``n`` rings (radius uniform in [``rmin``, ``rmax``]
    sensor px, a ring of width 0.35 r darker by ``depth`` uniform in [``dmin``, ``dmax``], a shallower centre:
    the central obstruction's hole), multiplicative on the light."""

    name = "ooc_dust"
    stages = (Stage.RESPONSE,)

    def setup(self):
        p, s = self.params, self.sensor
        rng = np.random.default_rng(p.seed)
        w, h = s.roi_shape
        self.c = np.stack([rng.uniform(0.1 * w, 0.9 * w, p.n) + s.roi_x0,
                           rng.uniform(0.1 * h, 0.9 * h, p.n) + s.roi_y0], 1)
        self.r = rng.uniform(p.rmin, p.rmax, p.n)
        self.d = rng.uniform(p.dmin, p.dmax, p.n)

    def apply(self, stage, tile, data):
        ys, xs = tile.pixel_centres()
        f = np.ones(data.shape)
        for (cx, cy), r, d in zip(self.c, self.r, self.d):
            rr = np.hypot(xs[None, :] - cx, ys[:, None] - cy)
            ring = np.exp(-0.5 * ((rr - r) / (0.15 * r)) ** 2) + 0.4 * (rr < r)
            f *= 1 - d * np.minimum(ring, 1)
        data *= f.astype(np.float32)


class DiffractionRing(RealWorld):
    """A diffraction ring around every source: ``frac`` of each source's light moved from its core to a thin
    ring of ``radius_px`` (redistributed: the flux is conserved)."""

    name = "ooc_ring"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        src = _sky_free(data)
        half = int(np.ceil(p.radius_px + 3))
        t = np.arange(-half, half + 1)
        r = np.hypot(t[:, None], t[None, :])
        k = np.exp(-0.5 * ((r - p.radius_px) / 0.8) ** 2)
        k /= k.sum()
        data += np.float32(p.frac) * (signal.oaconvolve(src, k.astype(np.float32), mode="same") - src)
        np.maximum(data, 0, out=data)


class ReadNoiseGradient(RealWorld):
    """Extra read noise [ADU] growing linearly across the columns from 0 to ``sigma_adu`` (an amplifier whose
    noise depends on the distance to it): variance only, no mean change."""

    name = "ooc_noise_gradient"
    stages = (Stage.ADU,)
    stochastic = True

    def apply(self, stage, tile, data):
        x, _, w, _ = _win(tile)
        sig = self.params.sigma_adu * x / w
        data += (tile.rng(self.name).standard_normal(data.shape) * sig[None, :]).astype(np.float32)


class ReadoutBiasDrift(RealWorld):
    """A bias drifting during the read-out [ADU]: rows are read in order, the bias settles as
    ``A exp(-t / tau)`` (``tau`` a fraction of the read-out) plus a random walk of ``walk_adu`` per row; additive,
    along the rows, a new realisation every frame."""

    name = "ooc_bias_drift"
    stages = (Stage.ADU,)
    stochastic = True

    def prepare_frame(self, exptime_s, frame_seed):
        p, s = self.params, self.sensor
        n = s.sensor_height_px
        t = np.arange(n) / n
        walk = np.cumsum(generator(frame_seed, self.name).standard_normal(n)) * p.walk_adu
        return (p.amp_adu * np.exp(-t / p.tau) + walk - walk.mean()).astype(np.float32)

    def apply(self, stage, tile, data):
        ys, _ = tile.pixel_centres()
        data += tile.state[self.name][np.floor(ys).astype(int)][:, None]


class Glints(RealWorld):
    """Satellite glints: ``n`` short bright blobs (elongated Gaussians, ``length_px`` x 1.5 px, ``e_total`` e-
    each) at random places, in this frame only (additive, local)."""

    name = "ooc_glint"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        rng = np.random.default_rng(p.seed)
        yy, xx = np.mgrid[0:data.shape[0], 0:data.shape[1]]
        for _ in range(p.n):
            cy, cx = rng.uniform(0.15, 0.85, 2) * data.shape
            a = rng.uniform(0, np.pi)
            u = (xx - cx) * np.cos(a) + (yy - cy) * np.sin(a)
            v = -(xx - cx) * np.sin(a) + (yy - cy) * np.cos(a)
            g = np.exp(-0.5 * ((u / (p.length_px / 2.355)) ** 2 + (v / 1.5) ** 2))
            data += (p.e_total * g / g.sum()).astype(np.float32)


class Fringes(RealWorld):
    """Interference fringes of a thin sensor: multiplicative ``1 + amp cos(phase)``, a period of ``period_px``
    whose direction turns slowly across the window (a thickness wedge with a bow)."""

    name = "ooc_fringes"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        p = self.params
        x, y, w, h = _win(tile)
        a = np.radians(p.angle_deg)
        u = np.cos(a) * x[None, :] + np.sin(a) * y[:, None]
        bow = 0.15 * ((x[None, :] / w - 0.5) ** 2 + (y[:, None] / h - 0.5) ** 2) * w
        data *= (1 + p.amp * np.cos(2 * np.pi * (u + bow) / p.period_px)).astype(np.float32)


class Herringbone(RealWorld):
    """Electronic pickup during the read-out [ADU]: a sinusoid along the read-out sequence (period
    ``period_px`` in pixels read, the row length not a multiple of it) that draws diagonal stripes, ``amp_adu``;
    additive, periodic."""

    name = "ooc_herringbone"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        x, y, w, _ = _win(tile)
        n = y[:, None] * (w + 37) + x[None, :]
        data += (p.amp_adu * np.sin(2 * np.pi * n / p.period_px)).astype(np.float32)


class Persistence(RealWorld):
    """A persistent image of the previous pointing: ``frac`` of the sources' light, from a frame offset by
    (``dx``, ``dy``) px and blurred by ``sigma_px`` (released trapped charge): additive, local, not at the
    sources."""

    name = "ooc_persistence"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        src = ndimage.gaussian_filter(_sky_free(data), p.sigma_px)
        data += np.float32(p.frac) * ndimage.shift(src, (p.dy, p.dx), order=1, mode="constant").astype(np.float32)


class ReadoutSmear(RealWorld):
    """Light collected while the rows are shifted out with the shutter open (a frame-transfer or shutterless
    read, or a shutter that closes late): every pixel gets ``frac_per_row`` [1] (the row-shift time over the
    exposure) of the light of every pixel of its column, a streak along the whole column through each bright
    source (Janesick 2001, Scientific CCDs, sect. 5.4, "smear"). Here the window's own column light only."""

    name = "ooc_smear"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        col = data.sum(axis=0, dtype=np.float64)
        data += (self.params.frac_per_row * col).astype(np.float32)[None, :]


class Flicker(RealWorld):
    """A flickering lamp read by a rolling shutter: the light of each row is ``1 + amp sin(2 pi y / period_rows
    + phase)`` (a 100 Hz mains flicker and the row time of the read set the period; Sony IMX rolling shutters
    read a row every few microseconds): a multiplicative pattern of rows, periodic (not a gain region)."""

    name = "ooc_flicker"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        _, y, _, _ = _win(tile)
        data *= (1.0 + p.amp * np.sin(2 * np.pi * y / p.period_rows + 0.7)).astype(np.float32)[:, None]


class SatelliteTrail(RealWorld):
    """A satellite crossing the field during the exposure, absent from the model: a straight trail of
    ``e_per_px`` [e- per pixel of its length] with a Gaussian cross-section of ``sigma_px``, from window
    fractions (u0, v0) to (u1, v1) (additive, local, a line)."""

    name = "ooc_trail"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        h, w = data.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        x0, y0, x1, y1 = p.u0 * w, p.v0 * h, p.u1 * w, p.v1 * h
        dx, dy = x1 - x0, y1 - y0
        length = np.hypot(dx, dy)
        t = np.clip(((xx - x0) * dx + (yy - y0) * dy) / length ** 2, 0.0, 1.0)
        d = np.hypot(xx - (x0 + t * dx), yy - (y0 + t * dy))
        prof = np.exp(-0.5 * (d / p.sigma_px) ** 2) / (np.sqrt(2 * np.pi) * p.sigma_px)
        data += (p.e_per_px * prof).astype(np.float32)


class BiasJump(RealWorld):
    """The bias level jumps by ``step_adu`` [ADU] after a fraction ``at`` of the rows are read (a reference
    voltage that settles to a new value mid-frame): additive, rows."""

    name = "ooc_bias_jump"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        _, v = HE["_uv"](tile)
        data += np.where(v >= self.params.at, np.float32(self.params.step_adu), np.float32(0))[:, None]


class TreeRings(RealWorld):
    """Tree rings: the dopant concentration of the silicon boule varies in rings about its axis, far off the
    sensor, so the response has concentric arcs of ``amp`` [1] with a period ``period_px`` [sensor px] about
    sensor fractions (cu, cv) (LSST sensors: Park et al. 2017, JINST 12 C05015): multiplicative."""

    name = "ooc_tree_rings"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        p, s = self.params, tile.sensor
        ys, xs = tile.pixel_centres()
        r = np.hypot((xs[None, :] - p.cu * s.sensor_width_px), (ys[:, None] - p.cv * s.sensor_height_px))
        data *= (1.0 + p.amp * np.sin(2 * np.pi * r / p.period_px)).astype(np.float32)


class AmplifierUndershoot(RealWorld):
    """The output amplifier's undershoot after a bright pixel: each pixel loses ``alpha`` [1] of the signal read
    ``1 .. 3 x tail_px`` pixels before it in its row (exponential, e-folding ``tail_px``; the read-out goes along
    increasing x), a dark trail after every bright source along its row (a self-crosstalk of the channel)."""

    name = "ooc_undershoot"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        n = int(np.ceil(3 * p.tail_px))
        k = np.exp(-np.arange(1, n + 1) / p.tail_px)
        k /= k.sum()
        sig = np.maximum(data - np.float32(np.median(data)), 0).astype(np.float64)
        out = np.zeros_like(sig)
        for j, kj in enumerate(k, start=1):
            out[:, j:] += kj * sig[:, :-j]
        data -= (p.alpha * out).astype(np.float32)


# --- the cases --------------------------------------------------------------------------------------------------

@dataclass
class UnseenCase:
    """One case: a catalogue effect in another form (``accept``: the names that are right), an effect in no
    plugin (``accept`` empty, ``kind`` and ``geometry`` expected of ``residual_morphology``), or a null."""

    name: str
    base: str
    description: str
    make: object = None  #: callable(sensor) -> list of Effects added to the measured camera (None: null)
    accept: tuple = ()  #: right names (catalogue cases)
    effect: str | None = None  #: the catalogue effect (confusion-matrix row); None for ooc / null
    strength: str = "strong"
    kind: str | None = None
    geometry: tuple = ()
    levels: Levels = field(default_factory=Levels)

    @property
    def group(self) -> str:
        return "null" if self.make is None else ("ooc" if not self.accept else "catalogue")

    @property
    def label(self) -> str:
        return self.effect or ("none" if self.make is None else f"ooc:{self.name}")


def _lv(i: int) -> Levels:
    """Levels of the measured camera, alternating in sign from case to case (1-1.5 %, 2-3 %, 0.3-0.6 ADU)."""
    sgn = (-1) ** i
    return Levels(light=sgn * (0.010 + 0.005 * (i % 2)), dark=-sgn * (0.02 + 0.01 * (i % 3 == 0)),
                  bias_adu=sgn * (0.3 + 0.1 * (i % 4)))


def _c(effect, name, base, desc, make, strength="strong", accept=None):
    return UnseenCase(name, base, desc, make, accept=accept or (effect,), effect=effect, strength=strength)


def _o(name, base, desc, make, kind, geometry):
    return UnseenCase(name, base, desc, make, kind=kind, geometry=geometry)


_CASE_LIST = [
    # vignetting: the issue's own example (20 % at the corners of a 512x512 window, off centre) and two more
    _c("vignetting", "vig_gauss_window", "flat", "Gaussian fall-off about (0.35, 0.60) of a 512 window, 20 % at "
       "the farthest corner", lambda s: [RadialFallOff(s, law="gauss", cu=0.35, cv=0.60, depth=0.20)]),
    _c("vignetting", "vig_cone_imxbin", "flat_imx_bin", "linear cone fall-off about (0.55, 0.45) of a binned CMOS "
       "window, 4 % at the farthest corner", lambda s: [RadialFallOff(s, law="cone", cu=0.55, cv=0.45, depth=0.04)],
       "weak"),
    _c("vignetting", "vig_cos4_full", "flat_full", "cos^4 fall-off about (0.70, 0.30) of the whole CCD, 3 % at the "
       "farthest corner", lambda s: [RadialFallOff(s, law="cos4", cu=0.70, cv=0.30, depth=0.03)], "weak"),
    # amp_glow
    _c("amp_glow", "glow_lorentz_opposite", "dark_corner", "Lorentzian glow (d0 150 px, 0.3 e-/s) from the window's "
       "corner opposite the amplifier", lambda s: [LorentzGlow(s, pu=-0.02, pv=1.02, d0_px=150.0,
                                                               amplitude_e_per_s=0.3)]),
    _c("amp_glow", "glow_edge_bump_full", "dark_full", "glow at the middle of the left CCD edge: Gaussian along it "
       "(400 px), exp(-x / 200 px) inwards, 0.004 e-/s", lambda s: [EdgeBumpGlow(
           s, amplitude_e_per_s=0.004, lambda_px=200.0, yc_frac=0.5, sigma_px=400.0)], "weak"),
    # dark_gradient: a temperature gradient with the exponential law of the dark current
    _c("dark_gradient", "dark_thermal_full", "dark_full", "temperature 4 K warmer at the right edge than the left, 2 K "
       "cooler at the top, dark current doubling every 6.3 K", lambda s: [ThermalDark(s, dtx=4.0, dty=-2.0, t2_k=6.3)]),
    _c("dark_gradient", "dark_thermal_weak", "dark_full", "temperature 1.5 K cooler at the right edge, 1 K warmer at "
       "the top, doubling every 6.3 K", lambda s: [ThermalDark(s, dtx=-1.5, dty=1.0, t2_k=6.3)], "weak"),
    # bias_gradient
    _c("bias_gradient", "bias_sawtooth_full", "bias_full", "sawtooth bias along the columns, 3 cycles, 1.5 ADU p-p",
       lambda s: [SawtoothBias(s, cycles=3.0, ptp_adu=1.5)]),
    _c("bias_gradient", "bias_dome_imx", "bias_imx", "Gaussian bias dome of 0.4 ADU about (0.7, 0.3) of a binned "
       "CMOS window", lambda s: [DomeBias(s, amp_adu=0.4, cu=0.7, cv=0.3, sigma_frac=0.3)], "weak"),
    # blooming
    _c("blooming", "bloom_sideways", "stars", "spill above 0.85 FW, 15 % of the excess into the neighbouring "
       "columns, the rest 30 % upwards", lambda s: [SideBleed(s, threshold=0.85, side=0.15, up_fraction=0.3)]),
    _c("blooming", "bloom_soft_bright", "stars_bright", "soft bleed above 0.95 FW: exponential profile of 4 px along "
       "the column, 70 % upwards", lambda s: [SoftBleed(s, threshold=0.95, length_px=4.0, up_share=0.7)], "weak"),
    # cfa
    _c("cfa", "cfa_quad_bayer", "flat", "mosaic CFA with 4x4 pixels under each dye (period 8), responses 0.62 / 1.0 / 0.98 / 0.75",
       lambda s: [QuadBayer(s, cell=2, response=[0.62, 1.0, 0.98, 0.75], column_drift=0.0)]),
    _c("cfa", "cfa_weak_imx", "flat_imx", "weak RGGB CFA 0.985 / 1.0 / 1.0 / 0.99 with a 1 % drift across the window",
       lambda s: [QuadBayer(s, cell=1, response=[0.985, 1.0, 1.0, 0.99], column_drift=0.01)], "weak"),
    # column_defects
    _c("column_defects", "cols_leak_ramp", "dark", "6 hot columns whose rate grows linearly along the column to "
       "0.3 e-/s", lambda s: [LeakColumns(s, n_columns=6, rate_e_per_s=0.3)]),
    _c("column_defects", "cols_weak_imx", "flat_imx", "8 columns of 96 % response on a CMOS flat",
       lambda s: [WeakColumns(s, n_columns=8, response=0.96)], "weak"),
    # cosmic_rays
    _c("cosmic_rays", "cr_segments", "dark", "40 straight tracks 3-40 px, 300 e-/px lognormal",
       lambda s: [SegmentTracks(s, n=40, lmin=3.0, lmax=40.0, e_per_px=300.0)]),
    _c("cosmic_rays", "cr_segments_imx", "dark_corner", "12 straight tracks 3-20 px, 150 e-/px on a CMOS dark",
       lambda s: [SegmentTracks(s, n=12, lmin=3.0, lmax=20.0, e_per_px=150.0)], "weak"),
    # crosstalk
    _c("crosstalk", "xtalk_3ch_delayed", "stars", "3 channels, coupling 2.5e-3, delayed by 2 columns with a tail",
       lambda s: [DelayedCrosstalk(s, n_channels=3, alpha=2.5e-3, delay_px=2, mirrored=False)]),
    _c("crosstalk", "xtalk_2ch_undershoot_imx", "stars_imx", "2 mirrored channels, coupling -1.2e-3 (undershoot), "
       "delayed by 1 column", lambda s: [DelayedCrosstalk(s, n_channels=2, alpha=-1.2e-3, delay_px=1, mirrored=True)],
       "weak"),
    # dead_pixels
    _c("dead_pixels", "dead_clusters", "flat", "3x3 clusters of 20 % response (5000 on the sensor)",
       lambda s: [DeadClusters(s, count=5000, size=3, response=0.2)]),
    _c("dead_pixels", "dead_weak_imx", "flat_imx", "weak pixels of 75 % response on a CMOS flat (~150 in the window)",
       lambda s: [DeadClusters(s, count=86000, size=1, response=0.75)], "weak"),
    # dsnu
    _c("dsnu", "dsnu_uniform", "dark", "DSNU with a uniform law, relative std 0.26",
       lambda s: [LawDSNU(s, law="uniform", sigma=0.26)]),
    _c("dsnu", "dsnu_student_full", "dark_full", "DSNU with a Student-t (3 dof) law, relative std 0.4, binned CCD",
       lambda s: [LawDSNU(s, law="student", sigma=0.4)], "weak"),
    # gain_regions
    _c("gain_regions", "gains_soft_strips", "flat_full", "3 vertical amplifier strips (30/45/25 %), gains "
       "1.012/0.990/1.004, tanh transitions of 20 px", lambda s: [SoftGainRegions(
           s, axis="x", splits=[0.30, 0.75], gains=[1.012, 0.990, 1.004], width_px=20.0)]),
    _c("gain_regions", "gains_rows_imxbin", "flat_imx_bin", "top/bottom amplifiers split at sensor row 2500, gains "
       "0.997/1.003", lambda s: [SoftGainRegions(s, axis="y", splits=[2500 / 10640], gains=[0.997, 1.003],
                                                  width_px=1.0)], "weak"),
    # hot_pixels
    _c("hot_pixels", "hot_pareto", "dark", "20000 hot pixels with Pareto rates (x_m 0.2 e-/s, index 1.5)",
       lambda s: [ParetoHotPixels(s, count=20000, xm_e_per_s=0.2, alpha=1.5, pairs=False)]),
    _c("hot_pixels", "hot_pairs_imx", "dark_corner", "hot pixels in vertical pairs on a CMOS dark, Pareto rates "
       "(x_m 0.15 e-/s, index 2)", lambda s: [ParetoHotPixels(s, count=300000, xm_e_per_s=0.15, alpha=2.0,
                                                                pairs=True)], "weak"),
    # nonlinearity
    _c("nonlinearity", "nl_knee_bright", "stars_bright", "response knee at 0.5 FW, slope 0.8 above",
       lambda s: [KneeNonlinearity(s, knee=0.5, slope=0.8)]),
    _c("nonlinearity", "nl_gamma_imx", "stars_imx", "power-law response, gamma 0.99, normalised at 0.1 FW",
       lambda s: [GammaNonlinearity(s, gamma=0.99, s0_frac=0.1)], "weak"),
    # prnu
    _c("prnu", "prnu_columns", "flat", "PRNU column pattern 0.6 % rms + 0.3 % white",
       lambda s: [ColumnPRNU(s, law="columns", col_rms=0.006, white=0.003)]),
    _c("prnu", "prnu_lognormal_imx", "flat_imx", "lognormal PRNU, 0.2 % on a CMOS flat",
       lambda s: [ColumnPRNU(s, law="lognormal", col_rms=0.0, white=0.002)], "weak"),
    # reset_noise
    _c("reset_noise", "ktc_laplace", "dark", "Laplace-distributed read-out noise of 8 e- std",
       lambda s: [ShapedReadNoise(s, law="laplace", sigma_e=8.0)]),
    _c("reset_noise", "ktc_alternate_imx", "dark_corner", "extra 1.6 e- Gaussian noise in even columns only (CMOS)",
       lambda s: [ShapedReadNoise(s, law="alternate", sigma_e=1.6)], "weak"),
    # row_noise
    _c("row_noise", "rows_telegraph", "dark", "10 % of the rows jump by +-8 e- (telegraph bursts) + 1 e- white",
       lambda s: [TelegraphRows(s, law="telegraph", fraction=0.1, jump_e=8.0, white_e=1.0, period_rows=1.0)]),
    _c("row_noise", "rows_student_imx", "dark_corner", "heavy-tailed row offsets: Student t with 3 degrees of "
       "freedom, 0.15 e- rms per sensor row (CMOS, binned 2)",
       lambda s: [TelegraphRows(s, law="student", fraction=0.0, jump_e=0.15, white_e=0.0, period_rows=1.0)], "weak"),
    # sky_gradient (or the straylight candidate the issue asks for)
    _c("sky_gradient", "sky_quadratic", "stars", "quadratic additive light across the field (straylight), "
       "bowl about (1.3, -0.2) of the window, 2 e-/s/px at the far corner",
       lambda s: [ExtraLight(s, law="quadratic", pu=1.3, pv=-0.2, level=1.5)], accept=("sky_gradient", "straylight")),
    _c("sky_gradient", "sky_point_imx", "stars_imx", "light from a point 3 windows beyond the left edge, 1/d^2: "
       "+0.11 / -0.07 e-/s/px at the near / far edge (relative to the centre)", lambda s: [ExtraLight(s, law="point", pu=-3.0, pv=0.3, level=0.3)],
       "weak", accept=("sky_gradient", "straylight")),
    # psf_blur
    _c("psf_blur", "blur_moffat", "stars", "Moffat broadening (FWHM 1.6 px, beta 2.5)",
       lambda s: [ShapedBlur(s, law="moffat", fwhm_px=1.6, beta=2.5, s0=0.0, s1=0.0)]),
    _c("psf_blur", "blur_varying_imx", "stars_imx", "Gaussian blur growing across the window from 0.2 to 0.7 px",
       lambda s: [ShapedBlur(s, law="varying", fwhm_px=0.0, beta=0.0, s0=0.2, s1=0.7)], "weak"),
    # jitter (an elongated smear: psf_elongation is also a right name)
    _c("jitter", "jitter_sine", "stars", "sinusoidal oscillation of 1.6 px amplitude along 60 deg",
       lambda s: [MotionPath(s, law="sine", amp_px=1.6, angle_deg=60.0)], accept=("jitter", "psf_elongation")),
    _c("jitter", "jitter_walk_imx", "stars_imx", "random-walk image motion, 32 steps of 0.12 px",
       lambda s: [MotionPath(s, law="walk", amp_px=0.12, seed=4)], "weak", accept=("jitter", "psf_elongation",
                                                                                   "psf_blur")),
    # psf_elongation
    _c("psf_elongation", "elong_coma", "stars", "one-sided exponential tail (1.5 px, 40 % of the light) along 20 deg",
       lambda s: [ComaTail(s, law="coma", length_px=1.5, frac=0.4, angle_deg=20.0)],
       accept=("psf_elongation", "jitter")),
    _c("psf_elongation", "elong_lorentz_imx", "stars_imx", "Lorentzian smear (half width 0.8 px, 30 %) along 120 deg",
       lambda s: [ComaTail(s, law="lorentz", length_px=0.8, frac=0.3, angle_deg=120.0)], "weak",
       accept=("psf_elongation", "jitter")),
    # pointing_offset
    _c("pointing_offset", "offset_rotated", "stars", "offset (0.6, -0.4) px with a 0.03 deg rotation about the "
       "sensor centre", lambda s: [AffineOffset(s, dx=0.6, dy=-0.4, rot_deg=0.03, scale=0.0)]),
    _c("pointing_offset", "offset_scaled_imx", "stars_imx", "offset (0.12, 0.08) px with a 2e-4 plate-scale change",
       lambda s: [AffineOffset(s, dx=0.12, dy=0.08, rot_deg=0.0, scale=2e-4)], "weak"),
    # pointing_drift
    _c("pointing_drift", "drift_accelerating", "stars", "trail (5, 2) px at constant acceleration",
       lambda s: [MotionPath(s, law="accel", dx=5.0, dy=2.0)]),
    _c("pointing_drift", "drift_arc_imx", "stars_imx", "curved trail: a 3 px chord with a 0.6 px sagitta along 150 deg",
       lambda s: [MotionPath(s, law="arc", amp_px=3.0, sag_px=0.6, angle_deg=150.0)], "weak"),
    # ghost
    _c("ghost", "ghost_shifted_annulus", "stars", "ghost shifted by (60, -40) px (not mirrored), an annulus of "
       "6-12 px, 2e-3 of the flux", lambda s: [ShiftedGhost(s, geometry="shift", dx=60.0, dy=-40.0, shape="annulus",
                                                            r_in=6.0, r_out=12.0, alpha=2e-3)]),
    _c("ghost", "ghost_gauss_offaxis_imx", "stars_imx", "ghost mirrored through a point (100, 50) px off the axis, "
       "Gaussian of 8 px, 6e-3 of the flux", lambda s: [ShiftedGhost(s, geometry="mirror", dx=100.0, dy=50.0,
                                                                     shape="gauss", r_in=0.0, r_out=8.0,
                                                                     alpha=6e-3)], "weak"),
    # distortion
    _c("distortion", "dist_tangential", "stars", "decentering (tangential) distortion, p1 = 2e-6, p2 = -1e-6 /px",
       lambda s: [BrownDistortion(s, law="tangential", p1=2e-6, p2=-1e-6, k2=0.0)]),
    _c("distortion", "dist_r5_imx", "stars_imx", "fifth-order radial distortion, 0.15 px at the window corners",
       lambda s: [BrownDistortion(s, law="r5", p1=0.0, p2=0.0, k2=0.15 / 362.0 ** 5)], "weak"),
    # --- out of catalogue ---
    _o("dust_donuts", "flat", "8 dust donuts, radius 20-60 px, 5-20 % deep",
       lambda s: [DustDonuts(s, n=8, rmin=20.0, rmax=60.0, dmin=0.05, dmax=0.20, seed=3)],
       "multiplicative", ("rings", "local", "blobs")),
    _o("dust_donuts_full", "flat_full", "6 dust donuts on the whole CCD (binned 8), radius 120-300 px, 5-15 % deep",
       lambda s: [DustDonuts(s, n=6, rmin=120.0, rmax=300.0, dmin=0.05, dmax=0.15, seed=5)],
       "multiplicative", ("rings", "local", "blobs")),
    _o("diffraction_ring", "stars", "3 % of each star's light moved to a ring of 8 px",
       lambda s: [DiffractionRing(s, frac=0.03, radius_px=8.0)], "redistributed", ("sources", "rings")),
    _o("readnoise_gradient", "bias_full", "extra read noise growing across the columns from 0 to 4 ADU",
       lambda s: [ReadNoiseGradient(s, sigma_adu=4.0)], "additive", ("gradient", "columns")),
    _o("bias_drift_readout", "bias_full", "bias settling during the read-out: 3 ADU exp(-t / 0.25 T) + a 0.05 ADU "
       "random walk per row", lambda s: [ReadoutBiasDrift(s, amp_adu=3.0, tau=0.25, walk_adu=0.05)],
       "additive", ("rows", "gradient")),
    _o("satellite_glint", "stars", "3 glints: 12 px x 1.5 px blobs of 4e5 e- each",
       lambda s: [Glints(s, n=3, length_px=12.0, e_total=4e5, seed=8)], "additive", ("local", "blobs")),
    _o("fringes", "flat", "fringes 2 % deep, period 45 px along 30 deg with a bow",
       lambda s: [Fringes(s, amp=0.02, period_px=45.0, angle_deg=30.0)], "multiplicative", ("periodic",)),
    _o("herringbone", "bias_imx", "read-out pickup 0.8 ADU with a period of 9.3 pixels read (diagonal stripes)",
       lambda s: [Herringbone(s, amp_adu=0.8, period_px=9.3)], "additive", ("periodic",)),
    _o("persistence", "stars", "persistent image of the previous pointing: 0.4 % of the sources shifted by "
       "(137, -88) px, blurred 1.5 px", lambda s: [Persistence(s, frac=0.004, dx=137.0, dy=-88.0, sigma_px=1.5)],
       "additive", ("local", "blobs")),
    # a periodic pick-up is not row noise: row offsets are independent from row to row (issue 10's own rule,
    # "fitted per-row offsets uncorrelated from row to row"); with its 0.3 e- of white row offsets under the
    # 1.2 e- line, the honest answer is a description of rows with a period (until the fifth round this was a
    # catalogue case of row_noise, which the diagnosis rightly refused)
    _o("rows_pickup_imx", "dark_corner", "sinusoidal pickup along the rows, 1.2 e-, period 37 rows, + 0.3 e- white "
       "(CMOS)", lambda s: [TelegraphRows(s, law="pickup", fraction=0.0, jump_e=1.2, white_e=0.3, period_rows=37.0)],
       "additive", ("rows", "periodic")),
    # added in the sixth round, before any rule was written for it: a streak along the columns of every source
    _o("readout_smear", "stars", "shutter open during the read-out: every pixel gets 1e-4 of its column's light "
       "(5 % of each source smeared along its whole column)", lambda s: [ReadoutSmear(s, frac_per_row=1e-4)],
       "additive", ("columns", "sources")),
    _o("flicker_rows_imx", "flat_imx", "flickering flat lamp read by the rolling shutter: 0.5 % modulation of the "
       "light, period 61 rows", lambda s: [Flicker(s, amp=0.005, period_rows=61.0)], "multiplicative",
       ("rows", "periodic")),
    _o("satellite_trail", "stars", "an unmodelled satellite trail across the window, 400 e- per pixel of its "
       "length, 1.2 px wide", lambda s: [SatelliteTrail(s, u0=0.05, v0=0.2, u1=0.9, v1=0.75, e_per_px=400.0,
                                                        sigma_px=1.2)], "additive", ("local", "streak")),
    # a bias that steps once, the same in every column: a spatial structure of the bias level (the hidden-effect
    # suite's bias_gradient has an amplifier step too), not out of the catalogue (added as a probe, then
    # classed; one frame cannot tell a fixed step from one that moves from frame to frame)
    _c("bias_gradient", "bias_jump", "bias_full", "the bias level steps by 1.5 ADU after 40 % of the rows are read",
       lambda s: [BiasJump(s, step_adu=1.5, at=0.4)]),
    _o("tree_rings", "flat_full", "tree rings of the silicon: 0.4 % arcs with a period of 120 px about a point far "
       "off the sensor (-0.4, 1.3)", lambda s: [TreeRings(s, amp=0.004, period_px=120.0, cu=-0.4, cv=1.3)],
       "multiplicative", ("rings", "periodic", "radial")),
    _o("amp_undershoot", "stars", "the amplifier's undershoot: each pixel loses 1 % of the signal read in the 2-6 "
       "pixels before it in its row", lambda s: [AmplifierUndershoot(s, alpha=0.01, tail_px=2.0)],
       "additive", ("sources", "rows")),
    # --- catalogue effects added later (appended: the levels of the cases above keep their index) ---
    # brighter_fatter
    _c("brighter_fatter", "bf_gauss_nonlinear", "stars", "brighter-fatter with a 7x7 Gaussian potential (sigma "
       "0.6 px), a_10 = 1e-6 /e- growing with the charge (x2 at half the full well)",
       lambda s: [GaussianNonlinearBF(s, a10_per_e=1e-6, sigma_px=0.6, q_nl_frac=0.5)]),
    _c("brighter_fatter", "bf_coulomb_imx", "stars_imx", "brighter-fatter with a 9x9 Coulomb potential "
       "1/sqrt(r^2 + 0.25), a_10 = 2e-7 /e- (CMOS)", lambda s: [CoulombBF(s, a10_per_e=2e-7, r0_px=0.5)], "weak"),
    # cti (a CCD only: no charge transfer in a CMOS pixel)
    _c("cti", "cti_columns", "stars", "CTI of one species (release 3 transfers, beta 0.35), 0.08 traps/px x a "
       "lognormal factor per column (sigma_ln 0.5) x a +-40 % trend across the sensor",
       lambda s: [ColumnCTI(s, density=0.08, col_sigma_ln=0.5, trend=0.8, release_transfers=3.0, beta=0.35)]),
    _c("cti", "cti_linear_slow", "stars", "constant-fraction CTI (beta 1), 0.3 traps/px, half the free traps "
       "captured per transfer, release 12 transfers", lambda s: [LinearSlowCaptureCTI(
           s, density=0.3, capture=0.5, release_transfers=12.0)], "weak"),
    # ipc
    _c("ipc", "ipc_asymmetric_imx", "stars_imx_sharp", "non-centrosymmetric IPC: 1.2 % to the right, 0.4 % to the "
       "left, 0.9 % up, 0.5 % down, 0.1 % diagonals (CMOS)", lambda s: [AsymmetricIPC(
           s, left=0.004, right=0.012, up=0.009, down=0.005, diag=0.001)]),
    _c("ipc", "ipc_signal_imx", "stars_imx_sharp", "signal-dependent IPC: 0.15 % at zero signal to 0.5 % at the full "
       "well (CMOS)", lambda s: [SignalDependentIPC(s, a0=0.0015, a1=0.005)], "weak"),
    # rts_noise (a CMOS thing: one source follower per pixel)
    _c("rts_noise", "rts_twotrap_imxbin", "dark_corner", "0.3 % of the pixels with two traps each (gamma "
       "amplitudes, means 60 and 25 e-), log-normal dwell times about 15 us, CDS 4 us (CMOS binned 2)",
       lambda s: [TwoTrapRTS(s, fraction=0.003, mean1_e=60.0, mean2_e=25.0, tau_med_s=1.5e-5, tau_sigma_ln=1.0,
                             cds_s=4e-6)]),
    _c("rts_noise", "rts_threestate_imx", "dark_cmos", "0.2 % of the pixels with a three-state trap (levels 0, A, "
       "0.45 A; A uniform 15-40 e-), dwell times 3-40 us, CDS 4 us", lambda s: [ThreeStateRTS(
           s, fraction=0.002, amp_lo_e=15.0, amp_hi_e=40.0, mid=0.45, tau_lo_s=3e-6, tau_hi_s=4e-5, cds_s=4e-6)],
       "weak"),
    # straylight (a plane of it is also a sky gradient: both names are right)
    _c("straylight", "stray_harvey_halo", "stars", "Harvey-law halo (d0 60 px, index 2.2) of a source beyond "
       "the window's lower right corner at (1.25, 1.35), 3 e-/s/px at that corner",
       lambda s: [HarveyHalo(s, pu=1.25, pv=1.35, d0_px=60.0, index=2.2, near_e_per_s=3.0)],
       accept=("straylight", "sky_gradient")),
    _c("straylight", "stray_baffle_arc_imxbin", "sky_imx_bin", "a broad arc of baffle glint across a binned CMOS "
       "sky frame: ring of radius 1.1 diagonals about (-0.5, 1.3), width 0.2, 0.03 e-/s/px on its crest (0.15 % "
       "of the sky)",
       lambda s: [BaffleArc(s, cu=-0.5, cv=1.3, radius_frac=1.1, width_frac=0.2, peak_e_per_s=0.03)], "weak",
       accept=("straylight", "sky_gradient")),
]
CASES: dict[str, UnseenCase] = {}
for _i, _case in enumerate(_CASE_LIST):
    _case.levels = _lv(_i)
    CASES[_case.name] = _case
for _i, _b in enumerate(BASES):
    CASES[f"null_{_b}"] = UnseenCase(f"null_{_b}", _b, "no hidden effect", levels=_lv(_i + 1))


# --- one case -----------------------------------------------------------------------------------------------------

def _named_effects() -> set[str]:
    """Names that a candidate can give for a catalogue effect (the registry and the source candidates)."""
    import detector

    return set(detector.registry()) | {"light_curve", "straylight"}


def _geometry_words(g) -> set[str]:
    if g is None:
        return set()
    if isinstance(g, (list, tuple)):
        return {str(w).lower() for w in g}
    return set(str(g).lower().replace(",", " ").replace("/", " ").split())


def morphology_match(morph: dict | None, kind: str | None, geometry: tuple) -> bool:
    """``residual_morphology`` significant, of the expected ``kind`` and with at least one expected geometry word."""
    if not morph or not morph.get("significant"):
        return False
    return morph.get("kind") == kind and bool(_geometry_words(morph.get("geometry")) & set(geometry))


#: the scene's PSF parameters (:mod:`scenes.app.compare.parameters`): a round blur of the PSF is a PSF that
#: is wider or has other wings than the scene's (a convolution of the PSF with a kernel; Gaussian widths add in
#: quadrature), so wherever ``psf_blur`` is an accepted name, a refit of the PSF's width or profile is too
PSF_PARAMETERS = ("psf_width", "psf_profile")


def accepted_names(accept) -> tuple:
    """The names that count as right for a case whose accepted effects are ``accept``."""
    accept = tuple(accept)
    return accept + PSF_PARAMETERS if "psf_blur" in accept else accept


def diagnose_case(case: UnseenCase, model_toml: Path, measured: Path, support, workdir: Path,
                  workers: int | None = None, truth_change_adu=None) -> dict:
    """Diagnose ``measured`` against ``model_toml``, apply the first significant plausible candidate (or the
    morphology's empirical map) with the measured frame, compare again."""
    from scenes.app.compare import run_compare, run_diagnose
    from scenes.app.compare.run import apply_best
    from scenes.scene import load_scene

    accept = accepted_names(case.accept)
    t0 = time.perf_counter()
    out = run_diagnose(load_scene(str(model_toml)), measured, workers=workers)
    seconds = time.perf_counter() - t0
    cands = out["candidates"]
    morph = out.get("residual_morphology")
    best = next((c for c in cands if c.get("significant") and c.get("plausible", True)), None)
    first_any = next((c for c in cands if c.get("significant")), None)
    named = _named_effects()
    wrong_named = [c for c in cands if c.get("significant") and c.get("plausible", True)
                   and c["effect"] in named and c["effect"] not in accept]
    metric = "misfit" if (case.effect or (best or {}).get("effect")) in STATISTICAL else "chi2_minus_1"
    row = {"case": case.name, "group": case.group, "label": case.label, "base": case.base,
           "strength": case.strength if case.make else "-", "description": case.description,
           "accept": list(accept), "kind": case.kind, "geometry": list(case.geometry),
           "first": best["effect"] if best else "none",
           "first_delta_bic": best["delta_bic"] if best else None,
           "first_heldout_delta": best.get("heldout_delta") if best else None,
           "first_params": best["params"] if best else None,
           "first_explanation": best.get("explanation") if best else None,
           "first_any": first_any["effect"] if first_any else "none",
           "first_any_plausible": first_any.get("plausible") if first_any else None,
           "implausible": [(c["effect"], c.get("implausible_because")) for c in cands
                           if c.get("plausible") is False][:8],
           "ranking": [(c["effect"], round(float(c["delta_bic"]), 1), c.get("significant"), c.get("plausible"),
                        c.get("heldout_delta"), c.get("explains_where_it_acts")) for c in cands[:6]],
           "significant": out.get("significant", []),
           "residual_morphology": {k: v for k, v in morph.items() if not str(k).startswith("_")}
           if isinstance(morph, dict) else None,
           "verdict": out.get("verdict"), "seconds": round(seconds, 2), "metric": metric,
           "cannot_tell_apart": ([best["effect"], *out.get("indistinguishable", [])]
                                 if best is not None and out.get("indistinguishable") else []),
           "before": error_of(out["_compare"], support),
           "truth_chi2_levels": truth_chi2_after_levels(out["_compare"]["_residuals"], truth_change_adu)}
    row["named_first"] = row["first"] in accept if accept else None
    if case.group == "ooc":
        row["confidently_wrong"] = bool(wrong_named)
        row["wrong_names"] = [(c["effect"], round(float(c["delta_bic"]), 1)) for c in wrong_named[:4]]
        row["morphology_match"] = morphology_match(morph if isinstance(morph, dict) else None, case.kind,
                                                   case.geometry)
    elif case.group == "catalogue":
        # a first candidate the diagnosis says it cannot tell apart from others (as good on held-out pixels) is a
        # claim about the group: not confidently wrong when an accepted name is in it (counted as "ambiguous")
        row["confidently_wrong"] = best is not None and best["effect"] not in accept and not (
            set(row["cannot_tell_apart"]) & set(accept))
        row["confidently_wrong_strict"] = best is not None and best["effect"] not in accept
    else:
        row["confidently_wrong"] = best is not None
        row["clean"] = first_any is None
    # what `diagnose --apply` does: the first significant candidate, or the residual's empirical map
    new, target = apply_best(load_scene(str(model_toml)), out, workdir / f"{case.name}.applied.toml", measured)
    if new is not None:
        row["applied"] = target.get("effect")
        row["after"] = error_of(run_compare(load_scene(str(new)), measured, workers=workers), support)
        b, a = row["before"][metric], row["after"][metric]
        row["error_before"], row["error_after"] = b, a
        row["error_ratio"] = a / b if b > 0 else float("nan")
    return row


def run_case(name: str, workdir: Path, seed: int = 11, workers: int | None = None) -> dict:
    """Make the measured frame of case ``name`` and diagnose it (one process, no shared state)."""
    case = CASES[name]
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    model = write_scene(model_scene(case.base, case.effect), workdir / f"{name}.model.toml")
    info = make_frame(case.base, case.make, case.levels, workdir / f"{name}.fits", seed=seed, workers=workers)
    row = diagnose_case(case, model, Path(info["measured"]), info["support"], workdir, workers=workers,
                        truth_change_adu=info.get("truth_change_adu"))
    row.update(truth=info["truth"], truth_chi2=info["truth_chi2"], scatter_sigma=info.get("scatter_sigma"),
               levels=vars(case.levels), case_seconds=round(time.perf_counter() - t0, 1))
    return row


def _run_one(args):
    name, workdir, seed, workers = args
    try:
        return run_case(name, Path(workdir), seed=seed, workers=workers)
    except Exception as exc:  # noqa: BLE001 - a case that fails is reported, the others go on
        import traceback

        case = CASES[name]
        return {"case": name, "group": case.group, "label": case.label, "base": case.base, "first": "error",
                "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()[-2000:],
                "confidently_wrong": False, "accept": list(case.accept)}


def run_cases(names, workdir: Path | None = None, seed: int = 11, workers: int = 2, progress=None) -> list[dict]:
    """Every case of ``names``, ``workers`` processes at a time (each renders and diagnoses on one thread);
    ``progress(name, row)`` is called as each case finishes."""
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory()
        workdir = Path(tmp.name)
    try:
        jobs = [(n, str(workdir / n), seed, 1 if workers > 1 else None) for n in names]
        if workers <= 1:
            rows = []
            for j in jobs:
                rows.append(_run_one(j))
                if progress:
                    progress(j[0], rows[-1])
            return rows
        rows = {}
        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork")) as pool:
            futs = {pool.submit(_run_one, j): j[0] for j in jobs}
            for f in as_completed(futs):
                rows[futs[f]] = f.result()
                if progress:
                    progress(futs[f], rows[futs[f]])
        return [rows[n] for n in names]
    finally:
        if tmp is not None:
            tmp.cleanup()


# --- summary ------------------------------------------------------------------------------------------------------

#: standard deviations within which an error before the apply is "within the noise" (nothing to halve)
WITHIN_NOISE_SD = 3.0
#: the profiled misfit (:func:`error_of`) below which a frame is within the noise: its 99th percentile on 300
#: null frames of the outlier-count bases (each with a random case's level offsets and no hidden effect; run
#: seed 3602, :func:`scenes.app.validation.random_forms.misfit_null`,
#: ``python examples/diagnose/misfit_null.py``): 5.13 (median 1.13; 8.7 % of
#: the nulls exceed 3). The misfit sums ten standardised positive parts (the chi2, seven outlier counts, the
#: rows and the columns), so a null's is not 0 and its spread is not one standard deviation's
NULL_MISFIT = 5.1


def error_halved(row: dict) -> bool:
    """The error fell by at least half after the apply; or, with nothing to halve, the error before was within
    the noise: for ``chi2_minus_1``, chi2/dof - 1 below 3 sqrt(2 / n) over the support (3 standard deviations
    of chi2/dof); for ``misfit`` (outlier-count effects: one track, a few hot pixels), a misfit below
    :data:`NULL_MISFIT`, the 99th percentile of null frames' (a sum of standardised excesses ``max(0, z)``,
    :func:`scenes.app.compare.statistics.misfit`: one track on a dark is a count the comparison of two Poisson
    draws, data and one model realisation, cannot tell from the model's, before as after a correct apply)."""
    if row.get("error_ratio") is not None and row["error_ratio"] <= 0.5:
        return True
    before = row.get("before") or {}
    if row.get("metric") == "chi2_minus_1" and before.get("n_support"):
        return before["chi2_minus_1"] < WITHIN_NOISE_SD * np.sqrt(2 / before["n_support"])
    if row.get("metric") == "misfit" and before.get("misfit") is not None:
        return before["misfit"] < NULL_MISFIT
    return False


def summary(rows: list[dict]) -> dict:
    cat = [r for r in rows if r["group"] == "catalogue"]
    ooc = [r for r in rows if r["group"] == "ooc"]
    nul = [r for r in rows if r["group"] == "null"]
    eff = cat + ooc

    def frac(n, d):
        return {"n": n, "of": d, "rate": n / d if d else float("nan")}

    return {"named_first": frac(sum(bool(r.get("named_first")) for r in cat), len(cat)),
            "named_first_strong": frac(sum(bool(r.get("named_first")) for r in cat if r.get("strength") == "strong"),
                                       sum(r.get("strength") == "strong" for r in cat)),
            "named_first_weak": frac(sum(bool(r.get("named_first")) for r in cat if r.get("strength") == "weak"),
                                     sum(r.get("strength") == "weak" for r in cat)),
            "confidently_wrong": frac(sum(bool(r.get("confidently_wrong")) for r in eff), len(eff)),
            "confidently_wrong_catalogue": frac(sum(bool(r.get("confidently_wrong")) for r in cat), len(cat)),
            "confidently_wrong_ooc": frac(sum(bool(r.get("confidently_wrong")) for r in ooc), len(ooc)),
            "confidently_wrong_strict": frac(sum(bool(r.get("confidently_wrong_strict", r.get("confidently_wrong")))
                                                 for r in eff), len(eff)),
            "ambiguous_right": frac(sum(bool(r.get("cannot_tell_apart")) and not r.get("named_first") and
                                        bool(set(r["cannot_tell_apart"]) & set(r.get("accept", []))) for r in cat),
                                    len(cat)),
            "missed_catalogue": frac(sum(r.get("first") == "none" for r in cat), len(cat)),
            "morphology_match": frac(sum(bool(r.get("morphology_match")) for r in ooc), len(ooc)),
            "error_halved": frac(sum(error_halved(r) for r in eff), len(eff)),
            "error_halved_catalogue": frac(sum(error_halved(r) for r in cat), len(cat)),
            "null_clean": frac(sum(r.get("first_any", r.get("first")) == "none" for r in nul), len(nul)),
            "errors": [r["case"] for r in rows if r.get("first") == "error"],
            "seconds": round(sum(r.get("case_seconds", 0) for r in rows), 1)}


def confusion(rows: list[dict]) -> dict:
    """Hidden effect (catalogue name, ``ooc:...`` or none) x first significant plausible candidate."""
    labels = sorted({r["label"] for r in rows if r["group"] == "catalogue"}) + \
        sorted({r["label"] for r in rows if r["group"] == "ooc"}) + ["none"]
    found = sorted({r["first"] for r in rows} - set(labels))
    cols = [c for c in labels if not c.startswith("ooc:")][:-1] + found + ["none"]
    m = np.zeros((len(labels), len(cols)), int)
    for r in rows:
        m[labels.index(r["label"]), cols.index(r["first"])] += 1
    return {"rows": labels, "cols": cols, "matrix": m.tolist()}


def heat_map(conf: dict, summ: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = np.asarray(conf["matrix"])
    fig, ax = plt.subplots(figsize=(0.42 * m.shape[1] + 3.5, 0.36 * m.shape[0] + 2), dpi=100)
    ax.imshow(m, cmap="Blues", vmin=0, vmax=max(1, m.max()))
    ax.set_xticks(range(m.shape[1]), conf["cols"], rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(m.shape[0]), conf["rows"], fontsize=8)
    for (i, j), v in np.ndenumerate(m):
        if v:
            ax.text(j, i, str(v), ha="center", va="center", fontsize=8, color="white" if v > m.max() / 2 else "k")
    ax.set_xlabel("first significant plausible candidate")
    ax.set_ylabel("hidden effect (ooc: in no plugin)")
    nf, cw = summ["named_first"], summ["confidently_wrong"]
    ax.set_title(f"newtsim diagnose on unseen forms: named first {nf['n']}/{nf['of']}, confidently wrong "
                 f"{cw['n']}/{cw['of']}, null clean {summ['null_clean']['n']}/{summ['null_clean']['of']}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _f(x):
    if x is None:
        return "-"
    if isinstance(x, float) and not np.isfinite(x):
        return "nan"
    return f"{x:.3g}" if isinstance(x, (int, float)) else str(x)


def markdown(rows: list[dict], summ: dict, conf: dict) -> str:
    def pct(k):
        d = summ[k]
        return f"{d['n']}/{d['of']}" + (f" ({100 * d['rate']:.0f} %)" if d["of"] else "")

    lines = ["| metric | value |", "|---|---|",
             f"| named first (catalogue cases) | {pct('named_first')} |",
             f"| named first, strong / weak | {pct('named_first_strong')} / {pct('named_first_weak')} |",
             f"| confidently wrong (all effect cases) | {pct('confidently_wrong')} |",
             (f"| confidently wrong, catalogue / out of catalogue | {pct('confidently_wrong_catalogue')} / "
             f"{pct('confidently_wrong_ooc')} |"),
             (f"| wrong first, counting those the diagnosis says it cannot tell apart from an accepted name | "
              f"{pct('confidently_wrong_strict')} |"),
             (f"| first not accepted but flagged as not told apart from an accepted name (catalogue) | "
              f"{pct('ambiguous_right')} |"),
             f"| catalogue effect missed (nothing significant) | {pct('missed_catalogue')} |",
             f"| morphology kind + geometry match (out of catalogue) | {pct('morphology_match')} |",
             f"| error halved after one apply (all effect cases) | {pct('error_halved')} |",
             f"| error halved, catalogue cases | {pct('error_halved_catalogue')} |",
             f"| null frames clean | {pct('null_clean')} |", ""]
    if summ["errors"]:
        lines += [f"cases that raised: {', '.join(summ['errors'])}", ""]
    lines += [("truth chi2: the chi2 the hidden effect's exact template removes from a noise-free frame (how "
               "detectable the case is whatever the diagnosis; '-' for an effect that adds noise). A one-amplitude "
               "template needs about 2 ln N (~25) of it to pass a BIC test."), "",
              ("| case | group | base | strength | truth chi2 | first (delta BIC) | accepted | wrong? | runner-up | "
               "morphology (kind / geometry) | expected | error before | after | ratio | s |"),
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("first") == "error":
            lines.append(f"| {r['case']} | {r['group']} | {r['base']} | - | - | ERROR {r['error'][:80]} | - | - | - "
                         f"| - | - | - | - | - | - |")
            continue
        first = f"{r['first']} ({_f(r['first_delta_bic'])})" if r["first"] != "none" else "none"
        runner = next((f"{e} ({_f(d)})" for e, d, sig, *_ in r["ranking"] if e != r["first"]), "-")
        mo = r.get("residual_morphology")
        mtxt = (f"{mo.get('kind')} / {mo.get('geometry')}" + ("" if mo.get("significant") else " (n.s.)")) if mo else "-"
        exp = f"{r['kind']} / {', '.join(r['geometry'])}" if r["group"] == "ooc" else "-"
        m = r["metric"]
        lines.append(f"| {r['case']} | {r['group']} | {r['base']} | {r['strength']} | {_f(r.get('truth_chi2'))} | "
                     f"{first} | "
                     f"{', '.join(r['accept']) or '-'} | {'**yes**' if r.get('confidently_wrong') else 'no'} | "
                     f"{runner} | {mtxt} | {exp} | {_f(r['before'][m])} | {_f(r.get('after', {}).get(m))} | "
                     f"{_f(r.get('error_ratio'))} | {_f(r.get('case_seconds'))} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", nargs="?", default="unseen_effects_out")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all; --list shows them)")
    ap.add_argument("--workers", type=int, default=2, help="parallel processes (default 2)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--keep", action="store_true", help="keep the frames and scenes in OUT/work")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--half", choices=("all", "tuning", "heldback"), default="all",
                    help="only the cases of one half of the suite (scenes/app/validation/halves.py: the tuning half "
                         "may be looked at while changing the diagnosis, the held-back half is only reported)")
    ap.add_argument("--summarise", action="store_true", help="no new runs: rebuild the reports from the rows "
                    "stored in OUT/rows/*.json (e.g. after re-running some cases into the same OUT)")
    args = ap.parse_args(argv)
    from .halves import half_of, select

    if args.list:
        for n, c in CASES.items():
            print(f"{n:28s} {c.group:9s} {c.base:13s} {c.strength if c.make else '-':6s} {half_of(n):8s} "
                  f"{c.description}")
        return 0
    names = select([n for n in args.cases.split(",") if n] or list(CASES), args.half)
    bad = [n for n in names if n not in CASES]
    if bad:
        print(f"unseen_effects.py: --cases: unknown case(s) {', '.join(bad)} (see --list)", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.summarise:
        rows = [json.loads((out / "rows" / f"{n}.json").read_text()) for n in names
                if (out / "rows" / f"{n}.json").exists()]
        return report(rows, out, wall=None, half=args.half)
    t0 = time.perf_counter()
    done = {"n": 0}

    (out / "rows").mkdir(exist_ok=True)

    def progress(label, row):
        done["n"] += 1
        (out / "rows" / f"{label}.json").write_text(json.dumps(row, indent=1, default=float) + "\n")
        print(f"[{done['n']}/{len(names)}] {label}: first {row.get('first')} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)

    rows = run_cases(names, workdir=out / "work" if args.keep else None, seed=args.seed, workers=args.workers,
                     progress=progress)
    return report(rows, out, wall=round(time.perf_counter() - t0, 1), half=args.half)


def report(rows: list[dict], out: Path, wall: float | None, half: str = "all") -> int:
    """Write OUT/unseen.md, unseen.json, unseen.png from the rows and print the table (``half``: which half of
    the suite the rows are, scenes/app/validation/halves.py)."""
    summ = summary(rows)
    summ["wall_seconds"] = wall
    summ["half"] = half
    conf = confusion(rows)
    md = (f"Half of the suite: {half}\n\n" if half != "all" else "") + markdown(rows, summ, conf)
    (out / "unseen.md").write_text(md)
    (out / "unseen.json").write_text(json.dumps({"summary": summ, "confusion": conf, "cases": rows}, indent=1,
                                                default=float) + "\n")
    heat_map(conf, summ, out / "unseen.png")
    print(md)
    print(f"wall {summ['wall_seconds']} s; wrote {out / 'unseen.md'}, {out / 'unseen.json'}, {out / 'unseen.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
