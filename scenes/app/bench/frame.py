"""The labels of a rendered frame: each TRUTH row's source rendered alone on its own stamp.

The render keeps, for every TRUTH row, the samples of that source (``Setup.per_source``: a static star's one
sample, an object's or a trailed star's chain of samples); each is rendered here on the bounding box of its
own stamps with the render's PSF and rolling-shutter windows (:func:`scenes.image.signal.render_samples`,
:func:`scenes.image.signal.render_trails`), so the labels cost one more pass over the sources, not a second
frame, and hold no frame-sized float array. The stamp is multiplied by the vignetting's relative
illumination when the scene has ``[effects.vignetting]`` (the chain multiplies all the light by it) and
binned as the frame is; the pixel response non-uniformity (~1 %) is not applied. The noise model
(:meth:`NoiseModel.for_sensor`) takes the uniform background (sky or flat) and the straylight, vignetted
and binned alike, plus the sensor's dark current, read noise and quantisation.
"""

from __future__ import annotations

import math

import numpy as np

from detector.config import validate
from detector.effects.optical import VignettingParams, relative_illumination
from scenes.image import frame_wcs
from scenes.image.motion import window_overlap
from scenes.image.psf import GaussianPSF
from scenes.image.signal import Samples, SourceSignal, Trails, render_samples, render_trails

from .labels import MASK_FRACTION_SIGMA, Label, NoiseModel, SourceStamp, labels_from_sources

__all__ = ["FrameLabels", "frame_labels", "source_stamps"]


def _bin(a: np.ndarray, b: int) -> np.ndarray:
    if b == 1:
        return a
    h, w = a.shape
    return a.reshape(h // b, b, w // b, b).sum(axis=(1, 3))


def _illumination(setup):
    vig = (setup.effect_tables or {}).get("vignetting")
    if vig is None:
        return None
    params = validate(VignettingParams, vig, prefix="effects.vignetting", file=setup.scene.source)
    return relative_illumination(params, setup.detector.sensor)


def _box_of(part, b: int, shape: tuple[int, int]):
    """Unbinned window box (r0, r1, c0, c1) of a source's stamps, aligned to the binning, on the window."""
    if isinstance(part, Trails):
        r0, r1 = int(part.ylo.min()), int(part.yhi.max()) + 1
        c0, c1 = int(part.xlo.min()), int(part.xhi.max()) + 1
    elif part.x.size == 1:  # a static star (the same numbers as below, without the reductions)
        w, iy, ix = int(part.w[0]), int(np.rint(part.y[0])), int(np.rint(part.x[0]))
        r0, r1, c0, c1 = iy - w, iy + w + 1, ix - w, ix + w + 1
    else:
        w = int(part.w.max())
        r0, r1 = int(np.rint(part.y.min())) - w, int(np.rint(part.y.max())) + w + 1
        c0, c1 = int(np.rint(part.x.min())) - w, int(np.rint(part.x.max())) + w + 1
    h, wd = shape
    r0, c0 = max(0, (r0 // b) * b), max(0, (c0 // b) * b)
    r1, c1 = min(h, -(-r1 // b) * b), min(wd, -(-c1 // b) * b)
    return r0, r1, c0, c1


def render_one_sample(part: Samples, psf, r0: int, r1: int, c0: int, c1: int, row_time_s: float,
                      exptime_s: float) -> np.ndarray:
    """:func:`render_samples` of a one-sample source (a static star), the same numbers, ~3x faster.

    ``render_samples`` selects, groups and chunks the samples reaching the box and sums each stamp into it
    with ``np.bincount`` (:func:`scenes.image.signal.deposit`); one sample reaches each pixel of the box once
    (0 + v = v), so its stamp is added as a slice. The same tests decide whether it reaches the box, the same
    PSF call gives the fractions, the same products the values.
    """
    acc = np.zeros((r1 - r0, c1 - c0))
    y, e, w = part.y[0], part.e[0], int(part.w[0])
    if not (r0 - 0.5 - w - 1 <= y <= r1 - 0.5 + w + 1):  # render_samples' searchsorted window
        return acc
    iy, ix = int(np.rint(y)), int(np.rint(part.x[0]))
    if not (iy + w >= r0 and iy - w < r1 and ix + w >= c0 and ix - w < c1 and e > 0):
        return acc
    nrow, ncol = acc.shape
    off = np.arange(-w, w + 1)
    x1, y1 = part.x[:1], part.y[:1]
    cols = np.rint(x1).astype(np.int64)[:, None] + off
    rows = np.rint(y1).astype(np.int64)[:, None] + off
    frac = psf(x1, y1, cols - x1[:, None], rows - y1[:, None])
    rw = part.e[:1][:, None] * ((rows >= r0) & (rows < r0 + nrow))
    timed = np.isfinite(part.t_lo[:1])
    if row_time_s > 0 and timed.any():
        f = window_overlap(part.t_lo[:1][:, None], part.t_hi[:1][:, None], rows, row_time_s, exptime_s)
        rw = np.where(timed[:, None], rw * f, rw)
    cw = (cols >= c0) & (cols < c0 + ncol)
    vals = (frac * rw[:, :, None] * cw[:, None, :])[0]
    i0, i1 = max(0, r0 - (iy - w)), min(2 * w + 1, r0 + nrow - (iy - w))
    j0, j1 = max(0, c0 - (ix - w)), min(2 * w + 1, c0 + ncol - (ix - w))
    if i1 > i0 and j1 > j0:
        acc[iy - w + i0 - r0:iy - w + i1 - r0, ix - w + j0 - c0:ix - w + j1 - c0] += vals[i0:i1, j0:j1]
    return acc


#: stamp pixels per batch of :func:`gaussian_star_stamps` (~1 MB arrays: below the size where numpy asks the
#: kernel for huge pages, whose first touch was 5x slower on the 2-core test machine)
STAR_BATCH_PIXELS = 1 << 17


def gaussian_star_stamps(items, psf: GaussianPSF) -> dict:
    """:func:`render_one_sample` of many static stars with a Gaussian PSF, the same numbers, computed together.

    ``items``: (key, part, (r0, r1, c0, c1)) of one-sample sources; returns {key: stamp} for those drawn here
    (the others, to be drawn alone: a rolling-shutter window, a sample outside its box or without flux,
    pixel offsets not stepping by exactly 1). A Gaussian PSF's fractions are computed row by row
    (:func:`scenes.image.psf.gaussian_pixel_fractions`), its choice between the stamp and the far-tail form
    made over the rows of a call from the offsets' steps: rows stepping by exactly 1.0 take the stamp form
    alone and together, so the batch holds the per-star numbers (tests compare them bit for bit).
    """
    groups: dict[int, list] = {}
    for key, part, (r0, r1, c0, c1) in items:
        y, e, w = part.y[0], part.e[0], int(part.w[0])
        if np.isfinite(part.t_lo[0]) or not (r0 - 0.5 - w - 1 <= y <= r1 - 0.5 + w + 1):
            continue
        iy, ix = int(np.rint(y)), int(np.rint(part.x[0]))
        if iy + w >= r0 and iy - w < r1 and ix + w >= c0 and ix - w < c1 and e > 0:
            groups.setdefault(w, []).append((key, part, r0, r1, c0, c1, iy, ix))
    out = {}
    for w, group in groups.items():
        n = 2 * w + 1
        off = np.arange(-w, w + 1)
        step = max(1, STAR_BATCH_PIXELS // (n * n))
        for k in range(0, len(group), step):
            g = group[k:k + step]
            x = np.array([it[1].x[0] for it in g])
            y = np.array([it[1].y[0] for it in g])
            e = np.array([it[1].e[0] for it in g])
            r0, r1, c0, c1, iy, ix = (np.array([it[j] for it in g]) for j in range(2, 8))
            cols = np.rint(x).astype(np.int64)[:, None] + off
            rows = np.rint(y).astype(np.int64)[:, None] + off
            dx, dy = cols - x[:, None], rows - y[:, None]
            exact = np.nonzero(((dx[:, 1:] - dx[:, :-1]) == 1.0).all(axis=1)
                               & ((dy[:, 1:] - dy[:, :-1]) == 1.0).all(axis=1))[0]
            if exact.size == 0:
                continue
            if exact.size < len(g):
                g = [g[i] for i in exact]
                x, y, e, r0, r1, c0, c1, cols, rows, dx, dy = (a[exact] for a in (x, y, e, r0, r1, c0, c1, cols, rows,
                                                                                  dx, dy))
            frac = psf(x, y, dx, dy)
            rw = e[:, None] * ((rows >= r0[:, None]) & (rows < r1[:, None]))
            cw = (cols >= c0[:, None]) & (cols < c1[:, None])
            vals = frac * rw[:, :, None] * cw[:, None, :]
            for i, (key, _, a0, a1, b0, b1, yi, xi) in enumerate(g):
                acc = np.zeros((a1 - a0, b1 - b0))
                i0, i1 = max(0, a0 - (yi - w)), min(n, a1 - (yi - w))
                j0, j1 = max(0, b0 - (xi - w)), min(n, b1 - (xi - w))
                if i1 > i0 and j1 > j0:
                    acc[yi - w + i0 - a0:yi - w + i1 - a0, xi - w + j0 - b0:xi - w + j1 - b0] += vals[i, i0:i1, j0:j1]
                out[key] = acc
    return out


def render_source(part, psf, r0: int, r1: int, c0: int, c1: int, row_time_s: float, exptime_s: float) -> np.ndarray:
    """Expected electrons of one source alone on window rows r0:r1, cols c0:c1 (unbinned, float64)."""
    if isinstance(part, Samples) and part.x.size == 1:
        return render_one_sample(part, psf, r0, r1, c0, c1, row_time_s, exptime_s)
    if isinstance(part, Trails):
        if hasattr(psf, "factors"):
            acc = np.zeros((r1 - r0, c1 - c0))
            render_trails(part, psf, acc, r0, c0, row_time_s, exptime_s)
            return acc
        part = part.as_samples()
    return render_samples(part, psf, r0, r1, c0, c1, row_time_s, exptime_s)


def source_stamps(setup) -> list[SourceStamp]:
    """One :class:`SourceStamp` per TRUTH row of a prepared render (``scenes.app.render.prepare``), in
    written-frame pixels (binned) and electrons (summed over a binned pixel, vignetted)."""
    s = setup.detector.sensor
    b = int(s.binning)
    truth = setup.truth
    ri = _illumination(setup)
    cols = {k: truth[k].tolist() for k in ("kind", "name", "x", "y", "x0", "y0", "x1", "y1", "t0_s", "t1_s", "flux_e",
                                           "mag", "source_id")} if truth is not None else {}
    out = []
    drawn = {}
    if type(setup.psf) is GaussianPSF:  # static stars together (the same numbers as one by one)
        one = [(row, p, _box_of(p, b, s.shape)) for row, p in enumerate(setup.per_source or [])
               if isinstance(p, Samples) and p.x.size == 1]
        drawn = gaussian_star_stamps([it for it in one if it[2][1] > it[2][0] and it[2][3] > it[2][2]], setup.psf)
    for row, part in enumerate(setup.per_source or []):
        if callable(part):
            part = part()
        if part is None or (isinstance(part, (Samples, Trails)) and part.x.size == 0):
            continue
        r0, r1, c0, c1 = _box_of(part, b, s.shape)
        if r1 <= r0 or c1 <= c0:
            continue
        st = drawn.pop(row, None)
        if st is None:
            st = render_source(part, setup.psf, r0, r1, c0, c1, s.row_time_s, setup.exptime_s)
        if ri is not None:
            st *= ri(s.roi_y0 + np.arange(r0, r1, dtype=float), s.roi_x0 + np.arange(c0, c1, dtype=float))
        st = _bin(st, b).astype(np.float32)
        kind, name = cols["kind"][row], cols["name"][row]
        kind = kind.decode() if isinstance(kind, bytes) else str(kind)
        name = name.decode() if isinstance(name, bytes) else str(name)
        t0, t1 = cols["t0_s"][row], cols["t1_s"][row]
        static = kind != "object" and not (np.isfinite(t0) and np.isfinite(t1))
        x, y, x0, y0, x1, y1, flux, mag = (float(cols[k][row]) for k in ("x", "y", "x0", "y0", "x1", "y1", "flux_e",
                                                                          "mag"))
        out.append(SourceStamp(st, r0 // b, c0 // b, row, kind, x, y, x0, y0, x1, y1, 0.0 if static else float(t0),
                               setup.exptime_s if static else float(t1), flux, mag, name,
                               int(cols["source_id"][row])))
    return out


def noise_model(setup) -> NoiseModel:
    """The render's noise model (:meth:`NoiseModel.for_sensor`) with its background on output pixels."""
    s = setup.detector.sensor
    b = int(s.binning)
    sig = setup.signal_e
    flat = float(sig.background_e) if isinstance(sig, SourceSignal) else float(sig)
    stray = setup.straylight
    ri = _illumination(setup)
    if stray is None and ri is None:
        return NoiseModel.for_sensor(s, setup.exptime_s, flat * b * b)

    def background(y0, y1, x0, x1):
        ys, xs = s.roi_y0 + y0 * b, s.roi_x0 + x0 * b
        h, w = (y1 - y0) * b, (x1 - x0) * b
        a = np.full((h, w), flat)
        if stray is not None:
            a = a + np.asarray(stray(ys, ys + h, xs, xs + w), dtype=float)
        if ri is not None:
            a = a * ri(ys + np.arange(h, dtype=float), xs + np.arange(w, dtype=float))
        return _bin(a, b)

    return NoiseModel.for_sensor(s, setup.exptime_s, background)


class FrameLabels:
    """A frame's labels with what the formats need: shape, WCS, the rule, the stamps (label image)."""

    def __init__(self, labels: list[Label], sources: list[SourceStamp], shape, wcs, noise: NoiseModel,
                 mask_fraction_sigma: float):
        self.labels, self.sources, self.shape, self.wcs = labels, sources, tuple(shape), wcs
        self.noise, self.mask_fraction_sigma = noise, mask_fraction_sigma


def frame_labels(setup, mask_fraction_sigma: float = MASK_FRACTION_SIGMA) -> FrameLabels:
    """The labels of every TRUTH row of a prepared render.

    The stamps are rendered with BLAS on one thread: their matrix products are small (a streak's samples
    x its box, ~400 x 100), where a multi-threaded BLAS spends more in waking and synchronising its
    threads than in the product (x20-70 slower on a loaded 2-core machine: benchmarks/bench_labels.py).
    """
    from threadpoolctl import threadpool_limits

    s = setup.detector.sensor
    wcs = frame_wcs(setup.scene, s, setup.pixel_scale_arcsec, distortion=setup.distortion)
    with threadpool_limits(limits=1, user_api="blas"):
        sources = source_stamps(setup)
        noise = noise_model(setup)
        labels = labels_from_sources(sources, noise, s.output_shape, wcs, mask_fraction_sigma=mask_fraction_sigma)
    return FrameLabels(labels, sources, s.output_shape, wcs, noise, mask_fraction_sigma)


def pixel_scale(wcs) -> float:
    """Mean pixel scale [arcsec/px] of a celestial WCS."""
    from astropy.wcs.utils import proj_plane_pixel_scales

    return float(np.mean(proj_plane_pixel_scales(wcs.celestial))) * 3600.0 if wcs is not None else math.nan


def write_label_files(fl: FrameLabels, paths: dict, file_name: str, meta: dict | None = None) -> None:
    """Write one frame's labels in the formats of ``paths`` (format -> path; "fits" is an extension)."""
    from .formats import coco_document, satnet_frame, write_json, yolo_lines

    meta = dict(meta or {})
    for fmt, path in paths.items():
        if fmt == "coco":
            write_json(coco_document([{"file_name": file_name, "shape": fl.shape, "labels": fl.labels, **meta}],
                                     fl.mask_fraction_sigma), path)
        elif fmt == "satnet":
            write_json(satnet_frame(fl.labels, fl.shape, file_name, meta), path)
        elif fmt == "yolo":
            with open(path, "w") as f:
                f.write(yolo_lines(fl.labels, fl.shape))
