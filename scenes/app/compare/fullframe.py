"""compare and diagnose of large frames (a full 151-Mpixel IMX411) in bounded memory.

Above :data:`LARGE_FRAME_PX` output pixels no whole-frame array of the model is ever held. The model
(:meth:`detector.Detector.moments_tile`, float32 row bands of the chain) and the measurement (read
memory-mapped, band by band) are reduced on the fly, in one pass over the frame, into

(a) a **binned frame**: data, model mean, model variance, photo-signal, dark charge and background summed
    over ``k x k`` super-pixels (``k`` chosen so the binned frame holds at most :data:`BINNED_TARGET_PX`
    pixels; a ``k`` dividing both sides preferred). Outlier pixels (hot pixels, cosmic-ray hits, dead
    pixels: local ``5 sigma`` spikes grown into their ``3 sigma`` surroundings, and outlier columns found on
    the whole frame's column means, as :func:`detector.signatures.spike_stats` does) and saturated or
    flagged pixels do not enter the data's sum: the residual of a super-pixel is the mean residual of its
    good pixels times ``k^2`` (its variance scaled by ``(k^2 / n)^2``), so an unbiased estimate of the
    super-pixel's residual. The binned frame is a :class:`detector.signatures.Residuals` of a sensor with
    binning ``k b`` in sum mode (a CCD without binning becomes a CMOS with digital sum: ``k^2`` reads of one
    pixel each), so every binning-aware signature (``pixel_sum``, ``adu_sum``, ``poisson_adu``) fits it in
    the sensor's own units. The pixels of one row share row noise's offset (covariance ``c``): the variance
    of a super-pixel gets ``k^2 (k - 1) c`` beyond the sum of its pixels' variances, and two super-pixels of
    one binned row share ``k^3 c``;
(b) a stratified **sample of full-resolution row bands** (:data:`SAMPLE_BANDS` bands of
    :data:`SAMPLE_ROWS` output rows, spread evenly over the frame), kept whole with one noisy realisation of
    the model on the same rows (the outlier statistics) and stacked into one window (a
    :class:`Residuals` whose sensor's read-out window has the sample's area, so that counts scale to the
    full sensor through :func:`detector.signatures.frame_fraction`, and whose ``ys`` are the true rows);
(c) **full-resolution accumulations**: chi2 of every compared pixel, row and column profiles, the
    histogram of z, the global statistics of measurement and model;
(d) **cut-outs around the sources**: a ``(2 STAMP_HALF + 1)^2`` stamp of data, model and background around
    every catalogue star of the TRUTH table (the brightest :data:`MAX_STAMPS`), and the sums of
    :func:`scenes.app.compare.statistics.streak_profiles` along every object's track, band by band.

``compare`` reports chi2/dof, profiles, the z histogram and global statistics at full resolution over the
whole frame; regions, the residual map and the power spectrum from the binned frame; outlier counts and
the model realisation's statistics from the band sample; the stars' photometry from their cut-outs and the
streaks' profiles from their tracks; and a ``sampling`` block saying what was computed how. Coupling
effects (IPC, brighter-fatter) see their neighbour bands' rows; whole-column coupling (CTI) is refused. ``diagnose`` fits
the smooth effects (:data:`SMOOTH_EFFECTS`: vignetting, glow, gradients, straylight, gain regions, bias
structure) on the binned frame and the pixel-scale ones (PRNU, DSNU, defects, cosmic rays, row noise,
image-plane transforms ...) on the band sample with :func:`scenes.app.compare.candidates.candidates`, and
ranks the union with :func:`scenes.app.compare.candidates.rank`. The ``delta_bic`` of a candidate is that of
its own data set (the binned frame or the sample): each candidate says which (``scale``).
"""

from __future__ import annotations

import math
import sys
import threading
import time
import warnings
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy import stats as sstats

from detector import registry
from detector.errors import DetectorError
from detector.morphology import describe
from detector.signatures import (
    GROW_SIGMA,
    LINE_WINDOW,
    MAX_LINE_FRACTION,
    SPIKE_SIGMA,
    Residuals,
    SpikeStats,
    line_sigma,
)
from detector.stats import mad_std
from scenes.app.render import Setup, prepare
from scenes.measured import scene_mask

from .candidates import blind_rivals, candidates, source_candidates
from .catch_all import compare_with_catch_all
from .judge import judge_json, kind_gate, rank, verdict
from .model import (
    REALISATION_SEED,
    _wcs_offset,
    background_signal,
    data_and_realisation_spikes,
    level_sd,
    row_offset_var_adu2,
    saturation_adu,
    source_peak_mask,
)
from .parameters import explained_away, level_candidates
from .policy import DEFAULT_POLICY, DiagnosisPolicy
from .statistics import compare, misfit, outlier_counts, spectrum_peaks, star_photometry, summary, track_band, zmap

#: output pixels above which compare / diagnose take the banded, bounded-memory path
LARGE_FRAME_PX = 16_000_000
#: the binned frame holds at most this many pixels [pixels]
BINNED_TARGET_PX = 4_000_000
#: full-resolution bands of the stratified sample, and output rows per band
SAMPLE_BANDS = 6
SAMPLE_ROWS = 48
#: effects fitted on the binned frame (smooth over many pixels); every other one on the band sample. A
#: plugin's signature joins them with ``scale = "smooth"``
SMOOTH_EFFECTS = frozenset({"amp_glow", "bias_gradient", "gain_regions", "sky_gradient", "straylight", "vignetting",
                            "ghost"})
#: a super-pixel is compared when at least this fraction of its pixels is good
MIN_GOOD_FRACTION = 0.5
#: half side of the cut-outs around catalogue stars [output pixels], and the most stars cut out (brightest)
STAMP_HALF = 6
MAX_STAMPS = 2000
#: bins of the full-resolution z histogram: edges from -8 to 8 in steps of 0.2
Z_EDGES = np.linspace(-8, 8, 81)


def is_large(scene, threshold: int | None = None) -> bool:
    """Whether ``scene``'s output frame has more than ``threshold`` (default :data:`LARGE_FRAME_PX`) pixels."""
    h, w = scene.sensor().output_shape
    return h * w > (LARGE_FRAME_PX if threshold is None else threshold)


def choose_binning(shape: tuple[int, int], target_px: int | None = None) -> int:
    """The super-pixel side ``k``: the smallest with at most ``target_px`` (default :data:`BINNED_TARGET_PX`)
    binned pixels, or the first up to twice that which divides both sides of the frame (nothing cropped)."""
    target_px = BINNED_TARGET_PX if target_px is None else target_px
    h, w = shape
    kmin = max(1, math.ceil(math.sqrt(h * w / target_px)))
    for k in range(kmin, 2 * kmin + 1):
        if h % k == 0 and w % k == 0:
            return k
    return kmin


# --- the measurement, band by band ---------------------------------------------------------------------------------

class BandReader:
    """The measured frame read band by band without loading it: a raw ``numpy.memmap`` of an uncompressed
    image (BZERO/BSCALE applied per band), astropy's ``section`` (under a lock) for a tile-compressed one."""

    def __init__(self, path: str | Path, shape: tuple[int, int], binning: int):
        from astropy.io import fits

        p = Path(path)
        if not p.is_file():
            raise DetectorError("measured file not found", key="MEASURED", file=str(p), expected="an existing FITS file")
        self.path, self._lock = p, threading.Lock()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self._hdul = fits.open(p, memmap=True)
                hdu = next(h for h in self._hdul if (h.is_image or isinstance(h, fits.CompImageHDU))
                           and h.header.get("NAXIS", 0) >= 2 and h.shape and len([n for n in h.shape if n > 1]) == 2)
        except StopIteration:
            raise DetectorError("measured file has no 2-D image", file=str(p), expected="a FITS image") from None
        except Exception as exc:  # noqa: BLE001  (astropy raises many types for damaged files)
            raise DetectorError(f"measured file cannot be read as FITS ({type(exc).__name__}: {exc})", file=str(p),
                                expected="a complete FITS file") from None
        header = self._hdul[0].header.copy()
        if hdu is not self._hdul[0]:
            header.extend(hdu.header, update=True)
        self.header = header
        dshape = tuple(n for n in hdu.shape if n > 1)
        if dshape != tuple(shape):
            raise DetectorError(f"measured frame is {dshape[1]}x{dshape[0]} pixels", key="detector", file=str(p),
                                expected=f"{shape[1]}x{shape[0]} as the scene's [detector] (preset, width/height, "
                                f"binning {binning}) produces")
        for card in ("XBINNING", "YBINNING"):
            if card in header and int(header[card]) != binning:
                raise DetectorError(f"measured frame has {card} = {header[card]}", key="detector.binning", file=str(p),
                                    expected=f"{binning} as the scene")
        self.shape = dshape
        self._raw = None
        if not isinstance(hdu, fits.CompImageHDU):
            bitpix = int(hdu.header["BITPIX"])
            dtype = {8: "u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}[bitpix]
            self._raw = np.memmap(p, dtype=dtype, mode="r", offset=hdu.fileinfo()["datLoc"], shape=dshape)
            self._zero = float(hdu.header.get("BZERO", 0.0))
            self._scale = float(hdu.header.get("BSCALE", 1.0))
            if self._raw.size * self._raw.itemsize + hdu.fileinfo()["datLoc"] > p.stat().st_size:
                raise DetectorError("measured file is truncated", file=str(p), expected="a complete FITS file")
        self._hdu = hdu

    #: the scene's ``[mask]`` over the frame (True = left out: read as NaN), set by :func:`run_compare_large`
    mask: np.ndarray | None = None

    def rows(self, r0: int, r1: int) -> np.ndarray:
        """Output rows ``r0:r1`` of the measured frame as float32 ADU (NaN where the file has no value or the
        scene's mask is set)."""
        a = self._rows(r0, r1)
        if self.mask is not None:
            a[self.mask[r0:r1]] = np.nan
        return a

    def _rows(self, r0: int, r1: int) -> np.ndarray:
        if self._raw is not None:
            a = np.asarray(self._raw[r0:r1], np.float32)
            if self._scale != 1.0:
                a *= np.float32(self._scale)
            if self._zero:
                a += np.float32(self._zero)
            return a
        with self._lock:
            return np.asarray(self._hdu.section[r0:r1], np.float32).reshape(r1 - r0, -1)

    def close(self) -> None:
        self._raw = None
        self._hdul.close()


# --- one pass over the frame ----------------------------------------------------------------------------------------

@dataclass
class Pass:
    """What one pass over the frame accumulates (module docstring: (a) binned, (b) sample, (c) full res)."""

    k: int
    shape: tuple[int, int]
    # per (binned row, output column): residual, variance and count of the good pixels
    r_gc: np.ndarray
    v_gc: np.ndarray
    n_gc: np.ndarray
    # per binned pixel: model sums (every pixel)
    mean_b: np.ndarray
    var_b: np.ndarray
    photo_b: np.ndarray
    dark_b: np.ndarray
    bg_b: np.ndarray
    flagged_b: np.ndarray
    # full resolution
    row_r: np.ndarray
    row_v: np.ndarray
    row_n: np.ndarray
    col_z2: np.ndarray
    z_hist: np.ndarray
    stats: dict = field(default_factory=dict)
    sample: list = field(default_factory=list)
    sample_rows: list = field(default_factory=list)
    z_sub: list = field(default_factory=list)
    data_sub: list = field(default_factory=list)
    model_sub: list = field(default_factory=list)
    stamps: dict = field(default_factory=dict)
    stars: object = None
    streak_objects: list = field(default_factory=list)
    streak_sums: list = field(default_factory=list)
    track_boxes: list = field(default_factory=list)
    tracks: dict = field(default_factory=dict)


def _moments_acc() -> dict:
    return {"n": 0, "s": 0.0, "s2": 0.0, "min": np.inf, "max": -np.inf}


def _add_moments(acc: dict, a: np.ndarray) -> None:
    a = a[np.isfinite(a)]
    if a.size:
        a64 = a.astype(np.float64)
        acc["n"] += a.size
        acc["s"] += float(a64.sum())
        acc["s2"] += float(np.dot(a64, a64))
        acc["min"] = min(acc["min"], float(a.min()))
        acc["max"] = max(acc["max"], float(a.max()))


def _global(acc: dict, sub: np.ndarray) -> dict:
    n = max(acc["n"], 1)
    mean = acc["s"] / n
    return {"median": float(np.median(sub)) if sub.size else float("nan"), "mean": mean,
            "std": float(np.sqrt(max(acc["s2"] / n - mean * mean, 0.0))),
            "robust_std": mad_std(sub, max_n=None) if sub.size else float("nan"), "min": acc["min"], "max": acc["max"]}


def spikes_fast(z: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Local outliers of a band's normalised residual (hot, dead pixels, cosmic-ray hits), cheaply: ``|z|``
    and ``|z|`` less its 5 x 5 local mean both above SPIKE_SIGMA (:func:`detector.signatures.spike_stats`
    compares with the 3 x 3 median; a mean of 25 pixels moves by a 25th of the spike), grown once into the
    surroundings above GROW_SIGMA."""
    local = ndimage.uniform_filter(z, size=5, mode="nearest")
    az = np.abs(z)
    sp = usable & (az > SPIKE_SIGMA) & (np.abs(z - local) > SPIKE_SIGMA)
    if sp.any():
        grown = ndimage.maximum_filter(sp.view(np.uint8), size=3, mode="constant").view(bool)
        sp |= grown & usable & (az > GROW_SIGMA)
    return sp


def star_stamps_wanted(truth, shape: tuple[int, int], half: int = STAMP_HALF, max_stars: int = MAX_STAMPS):
    """The catalogue stars of the TRUTH table whose ``(2 half + 1)^2`` cut-out lies inside the frame (the
    brightest ``max_stars``): (table, rounded x, rounded y), or None without stars."""
    if truth is None or len(truth) == 0 or "kind" not in truth.dtype.names:
        return None
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    st = truth[kind == "star"]
    h, w = shape
    st = st[(st["x"] > half) & (st["x"] < w - 1 - half) & (st["y"] > half) & (st["y"] < h - 1 - half)]
    if not len(st):
        return None
    st = st[np.argsort(-st["flux_e"])][:max_stars]
    return st, np.round(st["x"]).astype(int), np.round(st["y"]).astype(int)


def stamp_mosaic(stars, stamps: dict, half: int, setup: Setup) -> tuple[Residuals, np.ndarray, np.ndarray] | None:
    """The stars' cut-outs (data, model mean, variance, background) side by side in one small frame, as a
    :class:`Residuals`, and the TRUTH rows moved to it (their offsets from the pixel centre kept); with the
    original (x, y)."""
    if stars is None:
        return None
    st, xi, yi = stars
    side = 2 * half + 1
    cell = side + 2
    n = len(st)
    ncol = int(np.ceil(np.sqrt(n)))
    nrow = int(np.ceil(n / ncol))
    keys = ("data", "mean", "var", "bg")
    mos = {key: np.zeros((nrow * cell, ncol * cell), np.float32) for key in keys}
    mos["var"][:] = 1.0
    moved = st.copy()
    ok = np.zeros(n, bool)
    for j in range(n):
        part = stamps.get(j)
        if part is None or part["rows"] < side:
            continue
        r, c = divmod(j, ncol)
        y0, x0 = r * cell + 1, c * cell + 1
        for key in keys:
            mos[key][y0:y0 + side, x0:x0 + side] = part[key]
        moved["x"][j] = x0 + half + (st["x"][j] - xi[j])
        moved["y"][j] = y0 + half + (st["y"][j] - yi[j])
        ok[j] = True
    s = setup.detector.sensor
    b = s.binning
    h, w = mos["data"].shape
    res = Residuals(mos["data"], mos["mean"], mos["var"], np.ones((h, w), bool), mos["mean"] - mos["bg"],
                    np.zeros((h, w), np.float32), s.roi_y0 + b * np.arange(h) + (b - 1) / 2.0,
                    s.roi_x0 + b * np.arange(w) + (b - 1) / 2.0, s, setup.exptime_s, SpikeStats(0, 0, 0, 0, 0),
                    SpikeStats(0, 0, 0, 0, 0), background_adu=mos["bg"])
    return res, moved[ok], st[ok]


def stamp_photometry(mosaic, shape: tuple[int, int]) -> dict:
    """:func:`scenes.app.compare.statistics.star_photometry` of every cut-out star, its positions and field
    radius those of the frame (not of the mosaic)."""
    if mosaic is None:
        return {"n": 0}
    res, moved, orig = mosaic
    out = star_photometry(res, moved, max_stars=len(moved))
    if out.get("n", 0) == 0:
        return out
    # the rows star_photometry kept, in order: match them back by their mosaic position
    key = {(round(float(a), 6), round(float(b), 6)): i for i, (a, b) in enumerate(zip(moved["x"], moved["y"]))}
    idx = np.array([key[(round(float(a), 6), round(float(b), 6))] for a, b in zip(out["x"], out["y"])])
    h, w = shape
    out["x"], out["y"] = orig["x"][idx], orig["y"][idx]
    out["r_field"] = np.hypot(out["x"] - (w - 1) / 2, out["y"] - (h - 1) / 2) / np.hypot(w / 2, h / 2)
    if out["n"] >= 3:
        ok = np.isfinite(out["flux_ratio"])
        out["flux_ratio_vs_radius_slope"] = float(np.polyfit(out["r_field"][ok], out["flux_ratio"][ok], 1)[0])
    return out


#: segments of a streak's track and half width of its band [output pixels] (as statistics.streak_profiles)
STREAK_SEGMENTS, STREAK_HALF_WIDTH = 10, 6.0


def streak_objects(truth) -> list:
    """The TRUTH rows of the objects (streaks) with a track, as :func:`statistics.streak_profiles` takes them."""
    if truth is None or len(truth) == 0 or "x0" not in truth.dtype.names:
        return []
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    return list(truth[kind != "star"])


#: an object's track cut-out (its bounding box, for the light-curve candidates) is kept up to this area [px]
MAX_TRACK_BOX_PX = 4_000_000
_TRACK_KEYS = ("data", "mean", "var", "bg", "photo", "dark", "fit")


def track_boxes(shape, objects: list) -> list:
    """The bounding box (row and column slices) of each object's track band, None when it is too large to
    cut out (:data:`MAX_TRACK_BOX_PX`) or empty."""
    from .sources import HALF_WIDTH_PX

    out = []
    for o in objects:
        band = track_band(shape, o, HALF_WIDTH_PX)
        if band is None:
            out.append(None)
            continue
        ys, xs = band["box"]
        out.append((ys, xs) if (ys.stop - ys.start) * (xs.stop - xs.start) <= MAX_TRACK_BOX_PX else None)
    return out


def track_residuals(box, parts: dict, row, setup: Setup) -> tuple[Residuals, np.ndarray]:
    """The cut-out of an object's track as :class:`Residuals` (at its true sensor coordinates) and its TRUTH row
    moved into the cut-out."""
    s = setup.detector.sensor
    b = s.binning
    ys, xs = box
    res = Residuals(parts["data"], parts["mean"], parts["var"], parts["fit"], parts["photo"], parts["dark"],
                    s.roi_y0 + b * np.arange(ys.start, ys.stop) + (b - 1) / 2.0,
                    s.roi_x0 + b * np.arange(xs.start, xs.stop) + (b - 1) / 2.0, s, setup.exptime_s,
                    SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0), background_adu=parts["bg"],
                    row_var_adu2=row_offset_var_adu2(setup.detector))
    moved = np.array([row]).copy()
    for key in ("x", "x0", "x1"):
        moved[key] -= xs.start
    for key in ("y", "y0", "y1"):
        moved[key] -= ys.start
    return res, moved


def streak_band_sums(shape, objects: list, r0: int, r1: int, data, mean, bg) -> list:
    """Per object, the sums :func:`statistics.streak_profiles` takes over the track's band, restricted to the
    output rows ``r0:r1`` (sums over bands add up to the whole track's): per segment, data and model flux over
    the background and their first moments across the track."""
    out = []
    for o in objects:
        band = track_band(shape, o, STREAK_HALF_WIDTH)
        if band is None or band["length"] < 2:
            out.append(None)
            continue
        (ys, xs) = band["box"]
        a, e = max(ys.start, r0), min(ys.stop, r1)
        if a >= e:
            out.append(None)
            continue
        sub = slice(a - ys.start, e - ys.start)
        along, across, length = band["along"][sub], band["across"][sub], band["length"]
        sel = (np.abs(across) <= STREAK_HALF_WIDTH) & (along >= 0) & (along <= length)
        seg = np.minimum((along / length * STREAK_SEGMENTS).astype(int), STREAK_SEGMENTS - 1)
        rows = slice(a - r0, e - r0)
        d = (data[rows, xs] - bg[rows, xs]).astype(np.float64)
        m = (mean[rows, xs] - bg[rows, xs]).astype(np.float64)
        n = STREAK_SEGMENTS
        out.append(np.stack([np.bincount(seg[sel], d[sel], n), np.bincount(seg[sel], m[sel], n),
                             np.bincount(seg[sel], (d * across)[sel], n), np.bincount(seg[sel], (m * across)[sel], n)]))
    return out


def streak_results(objects: list, sums: list, shape) -> list:
    """:func:`statistics.streak_profiles`' entries from the band sums."""
    out = []
    for o, acc in zip(objects, sums):
        band = track_band(shape, o, STREAK_HALF_WIDTH)
        if acc is None or band is None or band["length"] < 2:
            continue
        fd, fm, cd, cm = acc
        with np.errstate(invalid="ignore", divide="ignore"):
            name = o["name"] if "name" in o.dtype.names else b""
            out.append({"name": (name.decode() if isinstance(name, bytes) else str(name)).strip(),
                        "length_px": band["length"], "flux_ratio": fd / fm, "offset_px": cd / fd - cm / fm,
                        "total_flux_ratio": float(fd.sum() / fm.sum()) if fm.sum() > 0 else float("nan")})
    return out


#: FIELD effects that act on each pixel alone (a plane or a polynomial of light): applied band by band, where
#: the chain applies them to the whole image at once (a float32 copy of the frame and its temporaries: 2 GB on
#: the IMX411)
POINTWISE_FIELD = frozenset({"sky_gradient", "straylight"})


def _pointwise_field_signal(det, signal, exptime_s: float, state: dict):
    """The expected photo-electrons after pointwise FIELD effects, as a tile callable (what
    :meth:`detector.Detector.field_signal` gives on the whole image, band by band)."""
    from detector.effects.base import Stage, Tile

    s = det.sensor

    def tile_signal(y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        tile = Tile(s, -1, y0, y1, x0, x1, exptime_s, 0, state=state)
        a = det._photo(signal, tile)
        det._run(Stage.FIELD, tile, a)
        return a

    return tile_signal


def _sample_tiles(n_tiles: int, n: int) -> list[int]:
    """Indices of ``n`` tiles spread evenly over ``n_tiles`` (the centre of each of n equal strata)."""
    n = min(n, n_tiles)
    return sorted({min(n_tiles - 1, int((i + 0.5) * n_tiles / n)) for i in range(n)})


def _reduce_rows(a: np.ndarray, starts: np.ndarray) -> np.ndarray:
    return np.add.reduceat(a, starts, axis=0)


def run_pass(setup: Setup, reader: BandReader, k: int, sample_bands: int = SAMPLE_BANDS,
             sample_rows: int = SAMPLE_ROWS, progress=None) -> Pass:
    """One pass over the frame, band by band (the chain's tiles, on its thread pool, a few in flight)."""
    det, t = setup.detector, setup.exptime_s
    s = det.sensor
    b = s.binning
    h, w = s.output_shape
    hb, wb = h // k, w // k
    adu_sum = (b * b if s.binning_mode == "sum" else 1) if s.kind != "ccd" else 1
    sat = saturation_adu(s)
    gain = np.float32(s.gain_e_per_adu)
    signal = setup.signal_e
    state = det.frame_state(t, 0)
    from detector.effects.base import Stage

    bg_signal = background_signal(setup.signal_e)
    has_sources = bg_signal is not setup.signal_e
    field = det._by_stage[Stage.FIELD]
    if field and all(e.name in POINTWISE_FIELD for e in field):
        signal = _pointwise_field_signal(det, signal, t, state)
        bg_signal = _pointwise_field_signal(det, bg_signal, t, state) if has_sources else bg_signal
    elif field:  # whole-frame effects need the whole image once (float32, sensor pixels); the background's
        # field effects (a blur of a uniform sky: nothing) are left out here
        signal = det.field_signal(signal, t, 0, state)
    tiles = det.tiles(t, 0, state)
    real_state = det.frame_state(t, REALISATION_SEED)
    real_tiles = det.tiles(t, REALISATION_SEED, real_state)
    sampled = set(_sample_tiles(len(tiles), sample_bands))
    y0 = s.roi_y0
    stars = star_stamps_wanted(setup.truth, (h, w))
    half = STAMP_HALF
    objects = streak_objects(setup.truth)

    P = Pass(k, (h, w), np.zeros((hb, w), np.float32), np.zeros((hb, w), np.float32), np.zeros((hb, w), np.uint16),
             np.zeros((hb, wb)), np.zeros((hb, wb)), np.zeros((hb, wb)), np.zeros((hb, wb)), np.zeros((hb, wb)),
             np.zeros((hb, wb), np.int32), np.zeros(h), np.zeros(h), np.zeros(h, np.int64), np.zeros(w),
             np.zeros(len(Z_EDGES) - 1, np.int64))
    P.streak_objects, P.streak_sums = objects, [None] * len(objects)
    boxes = track_boxes((h, w), objects)
    P.track_boxes = boxes
    P.tracks = {j: {key: np.zeros((bx[0].stop - bx[0].start, bx[1].stop - bx[1].start),
                                  bool if key == "fit" else np.float32) for key in _TRACK_KEYS}
                for j, bx in enumerate(boxes) if bx is not None}
    P.stats = {"data": _moments_acc(), "model": _moments_acc(), "saturated": 0, "finite": 0, "chi2": 0.0,
               "n_fit": 0}

    coupling = bool(det._by_stage[Stage.COUPLING])
    halo = det.coupling_halo if coupling else 0
    if coupling and halo is None:
        names = ", ".join(e.name for e in det._by_stage[Stage.COUPLING] if e.halo_rows is None)
        raise DetectorError(f"{names} couples whole columns: the model of a frame this large cannot be built band by "
                            "band", key="effects", file=setup.scene.source,
                            expected=f"a [detector] width/height window of at most {LARGE_FRAME_PX} output pixels")

    def moments(sig, tile):
        """The tile's moments; coupling effects see ``halo`` rows of mean charge above and below it."""
        if not coupling:
            return det.moments_tile(sig, tile)
        from detector.effects.base import Tile

        mean, var, flag = det.moments_tile(sig, tile, _split=True)
        top, bottom = s.roi_y0, s.roi_y0 + s.shape[0]

        def rows(a, e):
            if e <= a:
                return None
            return det.moments_tile(sig, Tile(s, -1, a, e, tile.x0, tile.x1, t, 0, state=state), _split=True)[0]

        above = rows(max(top, tile.y0 - halo), tile.y0)
        below = rows(tile.y1, min(bottom, tile.y1 + halo))
        mean = det.couple(tile, mean, above, below, mean_only=True)
        return det.moments_finish(tile, mean, var, flag)

    def band(i: int):
        tile = tiles[i]
        r0, r1 = (tile.y0 - y0) // b, (tile.y1 - y0) // b
        mean, var, flag = moments(signal, tile)
        mean0 = moments(0.0, tile)[0]
        bg = moments(bg_signal, tile)[0] if has_sources else mean
        photo = mean - mean0
        dark = np.maximum(mean0 - np.float32(s.bias_adu * adu_sum), 0) * gain  # the ADC rounds: no offset
        del mean0
        data = reader.rows(r0, r1)
        finite = np.isfinite(data)
        usable = ~flag & finite & (data < sat)
        r = np.where(usable, data - mean, 0.0).astype(np.float32)
        z = r / np.sqrt(var)
        sp = spikes_fast(z, usable)
        if has_sources:  # star cores: a local outlier there is a source the model misplaces, not a defect
            sp &= ~source_peak_mask(photo, var)
        good = usable & ~sp
        r[~good] = 0.0
        z[~good] = 0.0
        vg = np.where(good, var, 0.0).astype(np.float32)
        out = {"i": i, "r0": r0, "r1": r1}
        # binned rows of this band (a super-pixel row may span two bands)
        rows = np.arange(r0, min(r1, hb * k))
        if rows.size:
            g = rows // k
            starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
            n = rows.size
            out["g"] = g[starts]
            out["r_gc"] = _reduce_rows(r[:n], starts)
            out["v_gc"] = _reduce_rows(vg[:n], starts)
            out["n_gc"] = _reduce_rows(good[:n].astype(np.uint16), starts)

            def binned(a):
                x = _reduce_rows(a[:n, :wb * k].astype(np.float64), starts)
                return x.reshape(x.shape[0], wb, k).sum(axis=2)

            out.update(mean_b=binned(mean), var_b=binned(var), photo_b=binned(photo), dark_b=binned(dark),
                       bg_b=binned(bg), flagged_b=binned(flag | ~finite).astype(np.int32))
        if stars is not None:  # the parts of the stars' cut-outs in this band
            _, xi, yi = stars
            hit = np.flatnonzero((yi + half >= r0) & (yi - half < r1))
            cut = {}
            for j in hit:
                a, e = max(yi[j] - half, r0), min(yi[j] + half + 1, r1)
                cols = slice(xi[j] - half, xi[j] + half + 1)
                cut[int(j)] = (a - (yi[j] - half), {"data": data[a - r0:e - r0, cols], "mean": mean[a - r0:e - r0, cols],
                                                    "var": var[a - r0:e - r0, cols], "bg": bg[a - r0:e - r0, cols]})
            out["stamps"] = {j: (off, {key: v.copy() for key, v in d.items()}) for j, (off, d) in cut.items()}
        if objects:
            out["streaks"] = streak_band_sums((h, w), objects, r0, r1, data, mean, bg)
            parts = {}
            full = {"data": np.where(finite, data, 0.0), "mean": mean, "var": var, "bg": bg, "photo": photo,
                    "dark": dark, "fit": good}
            for j, bx in enumerate(boxes):
                if bx is None:
                    continue
                a, e = max(bx[0].start, r0), min(bx[0].stop, r1)
                if a < e:
                    parts[j] = (a - bx[0].start, {key: np.array(full[key][a - r0:e - r0, bx[1]])
                                                  for key in _TRACK_KEYS})
            out["tracks"] = parts
        out["row_r"] = r.sum(axis=1, dtype=np.float64)
        out["row_v"] = vg.sum(axis=1, dtype=np.float64)
        out["row_n"] = good.sum(axis=1)
        out["col_z2"] = np.einsum("ij,ij->j", z, z, dtype=np.float64)
        zi = np.clip(((z[good] + 8.0) / 0.2).astype(np.int32), 0, len(Z_EDGES) - 2)
        out["z_hist"] = np.bincount(zi, minlength=len(Z_EDGES) - 1)
        out["chi2"] = float(np.dot(z[good].astype(np.float64), z[good]))
        out["n_fit"] = int(good.sum())
        out["saturated"] = int((finite & (data >= sat)).sum())
        out["finite"] = int(finite.sum())
        d_acc, m_acc = _moments_acc(), _moments_acc()
        _add_moments(d_acc, data)
        _add_moments(m_acc, mean)
        out["data_acc"], out["model_acc"] = d_acc, m_acc
        out["data_sub"] = data[::7, ::11].ravel()
        out["model_sub"] = mean[::7, ::11].ravel()
        out["z_sub"] = z[::3, ::5][good[::3, ::5]]
        if i in sampled:
            nr = min(sample_rows, r1 - r0)
            a0 = (r1 - r0 - nr) // 2
            sl = slice(a0, a0 + nr)
            real = det.process_tile(signal, real_tiles[i]).astype(np.float32)
            pf = (det.process_tile(signal, tile, noiseless=True) - det.process_tile(0.0, tile, noiseless=True)) / gain
            out["sample"] = {"rows": (r0 + a0, r0 + a0 + nr), "data": data[sl].copy(), "mean": mean[sl].copy(),
                             "var": var[sl].copy(), "flag": flag[sl].copy(), "photo": photo[sl].copy(),
                             "dark": dark[sl].copy(), "bg": bg[sl].copy(), "real": real[sl].copy(),
                             "photo_field": pf[sl].astype(np.float32)}
        return out

    def merge(o: dict) -> None:
        if "g" in o:
            g = o["g"]
            P.r_gc[g] += o["r_gc"]
            P.v_gc[g] += o["v_gc"]
            P.n_gc[g] += o["n_gc"]
            for name in ("mean_b", "var_b", "photo_b", "dark_b", "bg_b", "flagged_b"):
                getattr(P, name)[g] += o[name]
        r0, r1 = o["r0"], o["r1"]
        P.row_r[r0:r1] += o["row_r"]
        P.row_v[r0:r1] += o["row_v"]
        P.row_n[r0:r1] += o["row_n"]
        P.col_z2 += o["col_z2"]
        P.z_hist += o["z_hist"]
        for key in ("chi2", "n_fit", "saturated", "finite"):
            P.stats[key] += o[key]
        for key, acc in (("data", o["data_acc"]), ("model", o["model_acc"])):
            tot = P.stats[key]
            tot["n"] += acc["n"]
            tot["s"] += acc["s"]
            tot["s2"] += acc["s2"]
            tot["min"], tot["max"] = min(tot["min"], acc["min"]), max(tot["max"], acc["max"])
        P.data_sub.append(o["data_sub"])
        P.model_sub.append(o["model_sub"])
        P.z_sub.append(o["z_sub"])
        if "sample" in o:
            P.sample.append(o["sample"])
        for j, acc in enumerate(o.get("streaks", [])):
            if acc is not None:
                P.streak_sums[j] = acc if P.streak_sums[j] is None else P.streak_sums[j] + acc
        for j, (off, d) in o.get("tracks", {}).items():
            for key, v in d.items():
                P.tracks[j][key][off:off + v.shape[0]] = v
        for j, (off, d) in o.get("stamps", {}).items():
            st_ = P.stamps.setdefault(j, {"rows": 0, **{key: np.zeros((2 * half + 1, 2 * half + 1), np.float32)
                                                       for key in ("data", "mean", "var", "bg")}})
            n_ = d["data"].shape[0]
            for key, v in d.items():
                st_[key][off:off + n_] = v
            st_["rows"] += n_

    workers = max(1, det.workers)
    with ThreadPoolExecutor(max_workers=workers) as pool, _bar(progress, len(tiles), "model and measurement") as tick:
        pending: deque = deque()
        it = iter(range(len(tiles)))
        for i in it:
            pending.append(pool.submit(band, i))
            if len(pending) >= workers + 1:
                break
        while pending:
            merge(pending.popleft().result())
            tick()
            nxt = next(it, None)
            if nxt is not None:
                pending.append(pool.submit(band, nxt))
    P.sample.sort(key=lambda d: d["rows"][0])
    P.stars = stars
    return P


class _bar:
    """A rich progress bar over the bands on a terminal (or the caller's ``progress(name)`` callback)."""

    def __init__(self, progress, total: int, label: str):
        self.progress, self.total, self.label, self.done = progress, total, label, 0
        self._prog = None

    def __enter__(self):
        if self.progress is None and sys.stderr.isatty():
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self._prog = Progress(TextColumn(f"[bold]{self.label}[/bold]"), BarColumn(),
                                  TextColumn("{task.completed}/{task.total} bands"), TimeElapsedColumn(),
                                  transient=True)
            self._prog.__enter__()
            self._task = self._prog.add_task(self.label, total=self.total)
        return self.tick

    def tick(self):
        self.done += 1
        if self._prog is not None:
            self._prog.advance(self._task)
        elif self.progress is not None:
            self.progress(f"{self.label}: band {self.done}/{self.total}")

    def __exit__(self, *exc):
        if self._prog is not None:
            self._prog.__exit__(*exc)
        return False


# --- the reductions as Residuals -------------------------------------------------------------------------------------

def outlier_columns(P: Pass) -> np.ndarray:
    """Columns whose mean residual over the whole frame lies line_sigma standard errors from the running
    median of their neighbours (hot and dead columns; as :func:`detector.signatures.spike_stats`)."""
    n = P.n_gc.sum(axis=0, dtype=np.int64)
    mean = P.r_gc.sum(axis=0, dtype=np.float64) / np.maximum(n, 1)
    err = np.sqrt(P.v_gc.sum(axis=0, dtype=np.float64)) / np.maximum(n, 1)
    local = mean - ndimage.median_filter(mean, size=LINE_WINDOW, mode="nearest")
    zc = np.where(n > 0, local / np.maximum(err, 1e-12), 0.0)
    lines = np.abs(zc) > line_sigma(zc.size)
    return lines if lines.mean() <= MAX_LINE_FRACTION else np.zeros_like(lines)


def binned_sensor(s, k: int, shape_b: tuple[int, int]):
    """The sensor of the binned frame: binning ``k b`` over the (cropped) read-out window; a CCD without
    binning becomes a CMOS with digital sum binning (``k^2`` reads of one pixel each: the same statistics)."""
    b = s.binning
    hb, wb = shape_b
    kind = "cmos" if s.kind == "ccd" and b == 1 else s.kind
    return s.model_copy(update={"binning": k * b, "width": wb * k * b, "height": hb * k * b, "x0": s.roi_x0,
                                "y0": s.roi_y0, "kind": kind})


def binned_residuals(P: Pass, setup: Setup, lines: np.ndarray, spikes: tuple[SpikeStats, SpikeStats]) -> Residuals:
    """The binned frame as :class:`Residuals` (module docstring, (a))."""
    k = P.k
    s = setup.detector.sensor
    hb, wb = P.mean_b.shape
    keep = ~lines
    rr = np.where(keep, P.r_gc, 0.0)[:, :wb * k].reshape(hb, wb, k).sum(axis=2, dtype=np.float64)
    vv = np.where(keep, P.v_gc, 0.0)[:, :wb * k].reshape(hb, wb, k).sum(axis=2, dtype=np.float64)
    nn = np.where(keep, P.n_gc, 0)[:, :wb * k].reshape(hb, wb, k).sum(axis=2)
    full = k * k
    fit = nn >= MIN_GOOD_FRACTION * full
    scale = full / np.maximum(nn, 1)
    c = row_offset_var_adu2(setup.detector)
    data = P.mean_b + scale * rr
    var = np.where(nn > 0, scale * scale * vv, P.var_b) + full * (k - 1) * c
    mean, photo, dark, bg = P.mean_b, P.photo_b, P.dark_b, P.bg_b
    row_var = k ** 3 * c
    if s.binning_mode == "average":  # a sum of k^2 averages of b^2 pixels -> the average of (k b)^2 pixels
        f = 1.0 / full
        data, mean, photo, bg, var, row_var = data * f, mean * f, photo * f, bg * f, var * f * f, row_var * f * f
        dark = dark * f
    sb = binned_sensor(s, k, (hb, wb))
    bb = sb.binning
    ys = sb.roi_y0 + bb * np.arange(hb) + (bb - 1) / 2.0
    xs = sb.roi_x0 + bb * np.arange(wb) + (bb - 1) / 2.0
    f32 = np.float32
    return Residuals(data.astype(f32), mean.astype(f32), np.maximum(var, 1e-6).astype(f32), fit, photo.astype(f32),
                     dark.astype(f32), ys, xs, sb, setup.exptime_s, *spikes, background_adu=bg.astype(f32),
                     row_var_adu2=float(row_var),
                     level_sd=level_sd(s, float(full) if s.binning_mode == "sum" else 1.0))


def sample_residuals(P: Pass, setup: Setup) -> tuple[Residuals, np.ndarray]:
    """The band sample as one :class:`Residuals` (module docstring, (b)) and the output row of each of its
    rows."""
    s = setup.detector.sensor
    b = s.binning

    def cat(key):
        return np.concatenate([d[key] for d in P.sample])

    data, mean, var, flag = cat("data"), cat("mean"), cat("var"), cat("flag")
    rows = np.concatenate([np.arange(*d["rows"]) for d in P.sample])
    sat = saturation_adu(s)
    finite = np.isfinite(data)
    usable = ~flag & finite & (data < sat)
    data = np.where(finite, data, 0.0).astype(np.float32)
    real = cat("real")
    spikes, statistical, model_spikes = data_and_realisation_spikes(data, usable, real, flag, mean, var, s,
                                                                    setup.detector.workers or 1)
    photo = cat("photo")
    if background_signal(setup.signal_e) is not setup.signal_e:
        statistical &= ~source_peak_mask(photo, var)
    ss = s.model_copy(update={"height": rows.size * b, "y0": s.roi_y0, "x0": s.roi_x0, "width": s.roi_shape[0]})
    ys = s.roi_y0 + b * rows + (b - 1) / 2.0
    xs = s.roi_x0 + b * np.arange(data.shape[1]) + (b - 1) / 2.0
    res = Residuals(data, mean, var, usable & ~statistical, photo, cat("dark"), ys, xs, ss, setup.exptime_s, spikes,
                    model_spikes, photo_field_adu=cat("photo_field"), background_adu=cat("bg"),
                    row_var_adu2=row_offset_var_adu2(setup.detector), level_sd=level_sd(s))
    res.memo("sample_real", lambda: real)
    return res, rows


def sample_truth(truth, rows: np.ndarray, margin: int = 6):
    """The TRUTH table's stars inside the band sample, their ``y`` moved to the stacked sample's rows."""
    if truth is None or len(truth) == 0 or "y" not in truth.dtype.names:
        return truth
    pos = np.full(int(rows.max()) + 1, -1)
    pos[rows] = np.arange(rows.size)
    y = np.round(truth["y"]).astype(int)
    ok = np.zeros(len(truth), bool)
    for i, yi in enumerate(y):
        lo, hi = yi - margin, yi + margin
        if lo >= 0 and hi < pos.size and (pos[lo:hi + 1] >= 0).all() and pos[hi] - pos[lo] == hi - lo:
            ok[i] = True
    out = truth[ok].copy()
    out["y"] = out["y"] - y[ok] + pos[y[ok]]
    return out


# --- compare and diagnose ------------------------------------------------------------------------------------------

def _profiles(P: Pass, lines: np.ndarray, row_cov: float) -> dict:
    """Row and column profiles of the mean residual at full resolution (:func:`statistics.profiles`)."""
    out = {}
    keep = ~lines
    col_n = np.where(keep, P.n_gc.sum(axis=0, dtype=np.int64), 0)
    col_r = np.where(keep, P.r_gc.sum(axis=0, dtype=np.float64), 0.0)
    col_v = np.where(keep, P.v_gc.sum(axis=0, dtype=np.float64), 0.0)
    for name, r, v, n in (("row", P.row_r, P.row_v, P.row_n), ("column", col_r, col_v, col_n)):
        mean = r / np.maximum(n, 1)
        shared = row_cov * (1 - 1 / np.maximum(n, 1)) if name == "row" else 0.0
        err = np.sqrt(v / np.maximum(n, 1) ** 2 + shared)
        zz = np.where(n > 0, mean / np.maximum(err, 1e-12), 0.0)
        out[name] = {"mean_residual_adu": mean.astype(np.float32), "z": zz.astype(np.float32),
                     "chi2_per_dof": float(np.mean(zz[n > 0] ** 2)) if (n > 0).any() else float("nan")}
    return out


def run_compare_large(scene, measured: str | Path, workers: int | None = None, progress=None, *,
                      k: int | None = None, sample_bands: int = SAMPLE_BANDS, sample_rows: int = SAMPLE_ROWS) -> dict:
    """:func:`scenes.app.compare.run.run_compare` of a large frame in bounded memory (module docstring).

    Returns the same dict (``summary`` the contract's JSON, with ``sampling``); ``_residuals`` is the binned
    frame's :class:`Residuals` and ``_sample`` the band sample's."""
    t0 = time.perf_counter()
    setup = prepare(scene, workers=workers)
    s = setup.detector.sensor
    shape = s.output_shape
    k = k or choose_binning(shape)
    meas = getattr(scene, "measured", None)
    if meas is not None and (meas.trim or meas.hdu is not None):
        raise DetectorError("[measured] trim / hdu with a frame this large", key="measured", file=str(measured),
                            expected=f"a frame of at most {LARGE_FRAME_PX} pixels, or the light-sensitive HDU / "
                            "section written to its own FITS file")
    reader = BandReader(measured, shape, s.binning)
    reader.mask = scene_mask(scene, shape)
    try:
        P = run_pass(setup, reader, k, sample_bands, sample_rows, progress=progress)
        header = reader.header
    finally:
        reader.close()
    t1 = time.perf_counter()
    st = P.stats
    if st["finite"] == 0:
        raise DetectorError("measured frame has no finite pixel", file=str(measured), expected="an image with data")
    sat = st["saturated"] / max(st["finite"], 1)
    if sat > 0.5:
        raise DetectorError(f"{100 * sat:.0f} % of the measured pixels are saturated (at or above "
                            f"{saturation_adu(s):.0f} ADU)", file=str(measured),
                            expected="a frame that is not mostly saturated")
    if st["data"]["max"] == st["data"]["min"]:
        raise DetectorError(f"measured frame is constant ({st['data']['max']} ADU)", file=str(measured),
                            expected="an image with signal and noise")
    lines = outlier_columns(P)
    col_chi2 = float(P.col_z2[~lines].sum())
    col_n = int(np.where(~lines, P.n_gc.sum(axis=0, dtype=np.int64), 0).sum())
    if col_n == 0:
        raise DetectorError("no pixel of the measured frame can be compared pixel by pixel (all saturated, "
                            "flagged or outliers)", file=str(measured), expected="a frame the model predicts")
    res_s, rows = sample_residuals(P, setup)
    res_b = binned_residuals(P, setup, lines, (res_s.data_spikes, res_s.model_spikes))
    truth_s = sample_truth(setup.truth, rows)
    result = compare(res_b, None, None)
    # full resolution, whole frame
    chi2_full = col_chi2 / col_n
    n_pix = shape[0] * shape[1]
    prof = _profiles(P, lines, res_s.row_var_adu2)
    counts = outlier_counts(res_s)
    rows_excess = (prof["row"]["chi2_per_dof"] - 1) * np.sqrt(len(prof["row"]["z"]) / 2)
    cols_excess = (prof["column"]["chi2_per_dof"] - 1) * np.sqrt(len(prof["column"]["z"]) / 2)
    zsub = np.concatenate(P.z_sub).astype(np.float64)
    q = np.linspace(0.001, 0.999, 99)
    dist = dict(result["distribution"])
    dist.update(z_edges=Z_EDGES, z_hist=P.z_hist, qq_normal=sstats.norm.ppf(q),
                qq_z=np.quantile(zsub, q) if zsub.size else np.zeros(q.size),
                skew=float(sstats.skew(zsub)) if zsub.size > 2 else 0.0,
                kurtosis=float(sstats.kurtosis(zsub)) if zsub.size > 3 else 0.0)
    data_sub, model_sub = np.concatenate(P.data_sub), np.concatenate(P.model_sub)
    real = res_s.forget("sample_real")
    rsub = real[:, ::3].ravel()
    result.update({
        "chi2_per_dof": chi2_full, "n_pixels": n_pix, "n_compared": col_n, "n_statistical": n_pix - col_n,
        "measured": _global(st["data"], data_sub[np.isfinite(data_sub)]),
        "model": {"median": float(np.median(rsub)), "mean": float(real.mean()), "std": float(real.std()),
                  "robust_std": mad_std(rsub, max_n=None), "min": float(real.min()), "max": float(real.max())},
        "model_mean": _global(st["model"], model_sub),
        "profiles": prof, "distribution": dist, "outliers": counts,
        "stars": stamp_photometry(stamp_mosaic(P.stars, P.stamps, STAMP_HALF, setup), shape),
        "streaks": streak_results(P.streak_objects, P.streak_sums, shape),
        "power_peaks": spectrum_peaks(zmap(res_s), weights=np.where(res_s.fit, 1.0 / res_s.var_adu2, 0.0),
                                      row_var_adu2=res_s.row_var_adu2),
    })
    result["misfit"] = misfit(chi2_full * col_n, col_n, counts, {"rows": rows_excess, "columns": cols_excess})
    result["binned"] = {"chi2_per_dof": float(res_b.chi2() / max(res_b.n_fit, 1)), "n_compared": res_b.n_fit,
                        "chi2_per_dof_levels": result.get("chi2_per_dof_levels")}
    sampling = {
        "method": "large frame: one pass over row bands (model and measurement never whole in memory)",
        "frame_px": n_pix, "threshold_px": LARGE_FRAME_PX,
        "binning_k": k, "binned_shape": list(res_b.data_adu.shape), "binned_n_compared": res_b.n_fit,
        "bands": [[int(d["rows"][0]), int(d["rows"][1])] for d in P.sample],
        "sample_rows": int(rows.size), "sample_fraction": float(rows.size / shape[0]),
        "outlier_columns": int(lines.sum()),
        "full_resolution": ["chi2_per_dof", "n_compared", "profiles", "distribution.z_hist", "distribution.skew",
                            "distribution.kurtosis", "measured", "model_mean"],
        "binned": ["regions", "worst_regions", "power", "z_map", "chi2_per_dof_levels", "levels"],
        "sample": ["outliers", "model", "power_peaks"],
        "cut_outs": {"stars": len(P.stars[0]) if P.stars is not None else 0, "half_side_px": STAMP_HALF,
                     "quantities": ["stars", "streaks (band by band along the track)",
                                    "light-curve candidates (each object's track box)"]},
        "not_computed": ["image-plane (PSF, shift) candidates outside the band sample"],
    }
    result["sampling"] = sampling
    result["summary"] = summary(result)
    result["summary"]["sampling"] = sampling
    result["summary"]["binned"] = result["binned"]
    wcs = _wcs_offset(header, _ModelView(setup))
    warns = []
    if wcs is not None and wcs > 2:
        warns.append(f"the measured WCS puts the scene's pointing {wcs:.1f} px from the scene's optical axis: "
                     "sources will not line up")
    exptime = header.get("EXPTIME")
    if exptime is not None and abs(float(exptime) - setup.exptime_s) > 1e-3 * max(1.0, float(exptime)):
        warns.append(f"EXPTIME {exptime} s in the measured file, {setup.exptime_s} s in the scene")
    result["summary"].update(scene_file=scene.source, measured_file=str(measured), warnings=warns + setup.warnings,
                             wcs_offset_px=wcs, seconds={"model": t1 - t0, "compare": time.perf_counter() - t1})
    result["_residuals"], result["_sample"], result["_model"] = res_b, res_s, _ModelView(setup)
    result["_truth_sample"] = truth_s
    result["_tracks"] = [(P.track_boxes[j], P.tracks[j], P.streak_objects[j]) for j in sorted(P.tracks)]
    return result


class _ModelView:
    """What the callers of a comparison read of its model (``setup``, ``sensor``) on the large path, where
    no whole-frame :class:`ModelFrame` exists."""

    def __init__(self, setup: Setup):
        self.setup = setup
        self.realisation = None
        self.spikes = None

    @property
    def sensor(self):
        return self.setup.detector.sensor


def upsample_to_sample(a, res_b: Residuals, res_s: Residuals, per_pixel: float) -> np.ndarray | float:
    """A binned-frame map (or scalar) at the band sample's pixels, bilinear in the super-pixel centres, divided
    by ``per_pixel`` (``k^2`` for a sum over super-pixels: the value of one output pixel)."""
    if a is None:
        return None
    if np.ndim(a) == 0 or np.size(a) == 1:
        return float(np.asarray(a).ravel()[0]) / per_pixel
    a = np.broadcast_to(np.asarray(a, np.float32), res_b.data_adu.shape)
    step = float(res_b.sensor.binning)
    fy = (res_s.ys - res_b.ys[0]) / step
    fx = (res_s.xs - res_b.xs[0]) / step
    yy, xx = np.meshgrid(fy.astype(np.float32), fx.astype(np.float32), indexing="ij")
    out = ndimage.map_coordinates(a, [yy, xx], order=1, mode="nearest", prefilter=False)
    return (out / np.float32(per_pixel)).astype(np.float32)


def sample_score(fit, res_b: Residuals, res_s: Residuals) -> float | None:
    """delta(-2 ln L) on the full-resolution band sample of a candidate fitted on the binned frame: its mean
    change and added variance (the shot noise of a change of charge) at the sample's pixels
    (:func:`detector.signatures.pixel_score`, levels refitted). The binned frame holds ``k^2`` times less
    information on the variance than the pixels do: a smooth fit whose implied shot noise the pixels deny
    (a negative charge, a change of the noise the data do not show) is told here, as the full-resolution
    diagnosis tells it."""
    from dataclasses import replace

    from detector.signatures import pixel_score

    if fit.delta_adu is None and fit.extra_var_adu2 is None:
        return None
    sb, ss = res_b.sensor, res_s.sensor
    ratio = (sb.binning / ss.binning) ** 2
    mean_norm = ratio if sb.binning_mode == "sum" else 1.0
    var_norm = ratio if sb.binning_mode == "sum" else 1.0 / ratio
    moved = replace(fit, delta_adu=upsample_to_sample(fit.delta_adu, res_b, res_s, mean_norm),
                    extra_var_adu2=upsample_to_sample(fit.extra_var_adu2, res_b, res_s, var_norm))
    return pixel_score(moved, res_s)


def _scale_of(name: str, cls) -> str:
    sig = cls.signature
    return "binned" if name in SMOOTH_EFFECTS or getattr(sig, "scale", "") == "smooth" else "sample"


def run_diagnose_large(scene, measured: str | Path, workers: int | None = None, progress=None,
                       policy: DiagnosisPolicy = DEFAULT_POLICY, **kw) -> dict:
    """:func:`scenes.app.compare.run.run_diagnose` of a large frame: smooth effects on the binned frame,
    pixel-scale ones on the band sample, ranked together by the same judge (:mod:`.judge`); the scene's
    levels as parameter candidates from the binned frame."""
    cmp = run_compare_large(scene, measured, workers=workers, progress=progress, **kw)
    t0 = time.perf_counter()
    res_b, res_s = cmp["_residuals"], cmp["_sample"]
    present = set(scene.effects)
    reg = {n: c for n, c in registry().items() if c.signature is not None}
    smooth = {n for n, c in reg.items() if _scale_of(n, c) == "binned"}
    threads = cmp["_model"].setup.detector.workers
    cb, pb = candidates(res_b, present | (set(reg) - smooth), progress=progress, truth=None, policy=policy,
                        threads=threads)
    cs, ps = candidates(res_s, present | smooth, progress=progress, truth=cmp["_truth_sample"], policy=policy,
                        threads=threads)
    sample_deltas = {}
    for c in cb:
        c.fit.note = (c.fit.note + " " if c.fit.note else "") + f"[binned {cmp['sampling']['binning_k']}x]"
        if c.contender:
            d = sample_score(c.fit, res_b, res_s)
            sample_deltas[id(c)] = d
            if d is not None and d > policy.sample_worse:
                c.refuse("sample", f"worsens the full-resolution band sample (delta -2 ln L {d:.4g}): the pixels deny "
                                 "its mean change or the shot noise it implies")
    ct = []
    for box, parts, row in cmp.pop("_tracks", []):
        res_t, truth_t = track_residuals(box, parts, row, cmp["_model"].setup)
        ct += source_candidates(res_t, truth_t, scene, policy)
    params = level_candidates(res_b, scene, policy)
    if progress is not None:
        progress("residual morphology")
    morph = describe(res_b)
    kind_gate(cb, morph)
    catch_all = compare_with_catch_all(res_b, cb, morph)
    blind_rivals(res_b, cb, policy)  # the smooth effects on the binned frame, the pixel-scale ones on the sample
    blind_rivals(res_s, cs, policy)
    explained_away(params, rank(cb, res_b.light_source), res_b, scene)
    cands = rank(params + cb + cs + ct, res_b.light_source)
    scale = ({id(c): "binned" for c in cb} | {id(c): "sample" for c in cs} | {id(c): "cut-out" for c in ct}
             | {id(c): "binned" for c in params})
    best = next((c for c in cands if c.significant and c.kind == "effect"), None)
    remaining = None
    if best is not None and best.fit.delta_adu is not None and np.shape(best.fit.delta_adu) == res_b.data_adu.shape:
        remaining = describe(res_b, best.fit.delta_adu)
    k = cmp["sampling"]["binning_k"]
    for m in (morph, remaining):
        if m is not None:
            m.pop("empirical", None)
            m["scale_px"] = float(m.get("scale_px", 0.0)) * k
    cjson = []
    for c in cands:
        j = c.to_json()
        j["scale"] = scale[id(c)]
        if id(c) in sample_deltas:
            j["sample_delta"] = sample_deltas[id(c)]
        cjson.append(j)
    out = {"baseline": cmp["summary"], "candidates": cjson, "problems": pb + ps, "verdict": verdict(cands, morph),
           "residual_morphology": morph, "seconds": time.perf_counter() - t0, "catch_all_heldout": catch_all,
           "_compare": cmp,
           "sampling": {**cmp["sampling"], "candidates": {"binned": sorted(smooth - present),
                                                          "sample": sorted(set(reg) - smooth - present)},
                        "residual_morphology": f"on the binned frame ({k} x {k}); scale_px in output pixels"}}
    cmp["_empirical"] = None
    if remaining is not None:
        out["remaining_morphology"] = remaining
    out.update(judge_json(cands, policy))
    return out


def out_of_memory(measured, exc: MemoryError) -> DetectorError:
    """The one-line error for a comparison that exhausted the memory."""
    return DetectorError(f"out of memory while comparing ({exc})", file=str(measured),
                         expected="more free memory, or a smaller frame (a [detector] width/height window)")
