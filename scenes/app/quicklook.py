"""PNG quick-look of a FITS frame: block-averaged to at most ~2000 pixels, zscale + asinh stretch."""

from __future__ import annotations

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
