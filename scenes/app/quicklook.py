"""PNG quick-look of a FITS frame: block-averaged to at most ~2000 pixels, zscale + asinh stretch.

:func:`write_png` draws the frame alone; :func:`write_png_insets` adds zoomed panels at full resolution
(:class:`Inset`; :func:`streak_inset` and :func:`star_inset` pick them from the frame's TRUTH table).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits


def downsample(data: np.ndarray, max_side: int = 2000) -> tuple[np.ndarray, int]:
    """Block-mean ``data`` by the smallest integer factor that brings its longer side to <= ``max_side``.

    Bands of rows are averaged one at a time so a memory-mapped 151-Mpixel frame is never loaded whole.
    """
    k = max(1, int(np.ceil(max(data.shape) / max_side)))
    ny, nx = data.shape[0] // k, data.shape[1] // k
    out = np.empty((ny, nx), dtype=np.float32)
    for i in range(ny):
        out[i] = np.asarray(data[i * k:(i + 1) * k, : nx * k], dtype=np.float32).reshape(k, nx, k).mean(axis=(0, 2))
    return out, k


def write_png(fits_path: str | Path, png_path: str | Path, title: str | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from astropy.visualization import AsinhStretch, ImageNormalize, ZScaleInterval

    with fits.open(fits_path, memmap=True, do_not_scale_image_data=True) as hdul:
        hdu = hdul[0]
        small, k = downsample(hdu.data)
        small = small * hdu.header.get("BSCALE", 1.0) + hdu.header.get("BZERO", 0.0)
        h = hdu.header
        label = f"{h.get('DETECTOR', '')} {h.get('FRAMETYP', '')} {h.get('EXPTIME', 0)} s  [{h.get('BUNIT', '')}]"
    norm = ImageNormalize(small, interval=ZScaleInterval(), stretch=AsinhStretch(0.3))
    fig, ax = plt.subplots(figsize=(8, 8 * small.shape[0] / small.shape[1] + 0.6), dpi=110)
    im = ax.imshow(small, origin="lower", cmap="gray", norm=norm, interpolation="nearest")
    ax.set_title(title or f"{Path(fits_path).name}: {label}" + (f" (block {k}x{k})" if k > 1 else ""), fontsize=9)
    ax.set_xlabel(f"x [pixel / {k}]")
    ax.set_ylabel(f"y [pixel / {k}]")
    fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02)
    fig.tight_layout()
    fig.savefig(png_path)
    plt.close(fig)
    return Path(png_path)


# --- quick-look with zoomed insets ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Inset:
    """A zoomed panel of the quick-look: the pixels ``[y0:y1, x0:x1]`` of the written frame at full resolution.

    ``x0, y0, x1, y1`` are 0-based pixel indices of the written (possibly binned) frame, half-open.
    """

    label: str
    x0: int
    y0: int
    x1: int
    y1: int
    color: str = "tab:orange"
    percentile: float = 99.6  #: the inset's display range: this central percentile of its pixels (100: min-max)


def _box(xc: float, yc: float, half: int, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """A (2 half) x (2 half) box about (xc, yc) [pixels], shifted to lie inside a frame of ``shape``."""
    ny, nx = shape
    half = min(half, nx // 2, ny // 2)
    x0 = int(np.clip(round(xc) - half, 0, nx - 2 * half))
    y0 = int(np.clip(round(yc) - half, 0, ny - 2 * half))
    return x0, y0, x0 + 2 * half, y0 + 2 * half


def streak_inset(truth: np.ndarray, shape: tuple[int, int], half_px: int = 160, at: float = 0.5) -> Inset | None:
    """An inset on the brightest debris streak of a TRUTH table (``kind == object``), centred on the point at
    the fraction ``at`` of its recorded path ``(x0, y0) -> (x1, y1)``; None when the frame has no object."""
    if truth is None or len(truth) == 0:
        return None
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    obj = np.nonzero(kind == "object")[0]
    if obj.size == 0:
        return None
    i = obj[np.argmax(truth["flux_e"][obj])]
    r = truth[i]
    xc, yc = r["x0"] + at * (r["x1"] - r["x0"]), r["y0"] + at * (r["y1"] - r["y0"])
    name = r["name"].decode() if isinstance(r["name"], bytes) else str(r["name"])
    length = float(np.hypot(r["x1"] - r["x0"], r["y1"] - r["y0"]))
    return Inset(f"streak: {name or 'object'} ({length:.0f} px long)", *_box(xc, yc, half_px, shape),
                 color="tab:orange")


def star_inset(truth: np.ndarray, shape: tuple[int, int], half_px: int = 24, saturation_e: float | None = None,
               isolation_px: float = 60.0, avoid: Inset | None = None) -> Inset | None:
    """An inset on a bright isolated star of a TRUTH table (``kind`` star or synthetic).

    The brightest star whose total electrons stay below ``saturation_e`` (when given), with no other source
    brighter than 1 % of it within ``isolation_px``, at least ``4 half_px`` from the frame's edges and
    outside the box ``avoid`` (the streak's inset)."""
    if truth is None or len(truth) == 0:
        return None
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    star = np.nonzero(kind != "object")[0]
    ny, nx = shape
    x, y, f = truth["x"], truth["y"], truth["flux_e"]
    margin = 4 * half_px
    ok = (x[star] > margin) & (x[star] < nx - margin) & (y[star] > margin) & (y[star] < ny - margin)
    if saturation_e is not None:
        ok &= f[star] < saturation_e
    for i in star[ok][np.argsort(-f[star[ok]])][:200]:
        if avoid is not None and avoid.x0 - margin <= x[i] < avoid.x1 + margin and \
                avoid.y0 - margin <= y[i] < avoid.y1 + margin:
            continue
        near = (np.abs(x - x[i]) < isolation_px) & (np.abs(y - y[i]) < isolation_px) & (f > 0.01 * f[i])
        if near.sum() == 1:
            mag = float(truth["mag"][i])
            label = f"star: G = {mag:.1f}" if np.isfinite(mag) else "star"
            return Inset(label, *_box(x[i], y[i], half_px, shape), color="tab:cyan", percentile=100.0)
    return None


def write_png_insets(fits_path: str | Path, png_path: str | Path, insets: list[Inset],
                     title: str | None = None, max_side: int = 2000, width_in: float = 13.0,
                     dpi: int = 110) -> Path:
    """The quick-look of :func:`write_png` (the frame block-averaged to ``max_side``, zscale + asinh) with
    zoomed insets at full resolution beside it, each outlined on the main panel in its colour.

    The insets are stacked in a column right of the main panel; each has its own stretch (the central
    ``Inset.percentile`` of its pixels, asinh), so a faint streak and a bright star's core are both visible.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from astropy.visualization import (
        AsinhStretch,
        ImageNormalize,
        MinMaxInterval,
        PercentileInterval,
        ZScaleInterval,
    )
    from matplotlib.patches import Rectangle

    with fits.open(fits_path, memmap=True, do_not_scale_image_data=True) as hdul:
        hdu = hdul[0]
        h = hdu.header
        scale, zero = h.get("BSCALE", 1.0), h.get("BZERO", 0.0)
        small, k = downsample(hdu.data, max_side)
        small = small * scale + zero
        cut = [np.asarray(hdu.data[i.y0:i.y1, i.x0:i.x1], dtype=np.float32) * scale + zero for i in insets]
        label = f"{h.get('DETECTOR', '')} {h.get('FRAMETYP', '')} {h.get('EXPTIME', 0)} s  [{h.get('BUNIT', '')}]"
    n = max(len(insets), 1)
    aspect = small.shape[0] / small.shape[1]
    main_w = width_in * n / (n + aspect)  # main panel width so that the inset column is as tall as it
    fig = plt.figure(figsize=(width_in, main_w * aspect + 0.7), dpi=dpi)
    gs = fig.add_gridspec(n, 2, width_ratios=[main_w, width_in - main_w], wspace=0.06, hspace=0.18,
                          left=0.04, right=0.99, bottom=0.06, top=0.94)
    ax = fig.add_subplot(gs[:, 0])
    norm = ImageNormalize(small, interval=ZScaleInterval(), stretch=AsinhStretch(0.3))
    ax.imshow(small, origin="lower", cmap="gray", norm=norm, interpolation="nearest")
    ax.set_title(title or f"{Path(fits_path).name}: {label}" + (f" (block {k}x{k})" if k > 1 else ""), fontsize=9)
    ax.set_xlabel(f"x [pixel / {k}]", fontsize=8)
    ax.set_ylabel(f"y [pixel / {k}]", fontsize=8)
    ax.tick_params(labelsize=7)
    for j, (ins, img) in enumerate(zip(insets, cut)):
        pad = 6  # a box of a few output pixels would vanish: outline at least ~12 px of the main panel
        w, hgt = max((ins.x1 - ins.x0) / k, 2 * pad), max((ins.y1 - ins.y0) / k, 2 * pad)
        cx, cy = (ins.x0 + ins.x1) / 2 / k - 0.5, (ins.y0 + ins.y1) / 2 / k - 0.5
        ax.add_patch(Rectangle((cx - w / 2, cy - hgt / 2), w, hgt, fill=False, ec=ins.color, lw=1.4))
        ax.annotate(str(j + 1), (cx + w / 2, cy + hgt / 2), color=ins.color, fontsize=9, weight="bold",
                    xytext=(2, 2), textcoords="offset points")
        sub = fig.add_subplot(gs[j, 1])
        interval = MinMaxInterval() if ins.percentile >= 100 else PercentileInterval(ins.percentile)
        inorm = ImageNormalize(img, interval=interval, stretch=AsinhStretch(0.05))
        sub.imshow(img, origin="lower", cmap="gray", norm=inorm, interpolation="nearest",
                   extent=(ins.x0 - 0.5, ins.x1 - 0.5, ins.y0 - 0.5, ins.y1 - 0.5))
        sub.set_title(f"{j + 1}: {ins.label}  [{ins.x1 - ins.x0}x{ins.y1 - ins.y0} px, full resolution]",
                      fontsize=8, color="black")
        sub.tick_params(labelsize=6)
        for s in sub.spines.values():
            s.set_edgecolor(ins.color)
            s.set_linewidth(2.0)
    fig.savefig(png_path)
    plt.close(fig)
    return Path(png_path)
