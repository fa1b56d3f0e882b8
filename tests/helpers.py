"""Builders shared by the tests: small sensors and scene files written from a dict.

Import as ``from helpers import small_sensor, write_scene`` (tests/ is on the path through conftest.py).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import tomli_w
from astropy.io import fits
from astropy.wcs import WCS

from detector import make_sensor


def small_sensor(preset: str = "ml11002", width: int = 720, height: int = 720, **overrides):
    """A small window of a preset sensor (read noise 4 e-, gain 1.5 e-/ADU, dark 0.2 e-/s unless given)."""
    base = {"width": width, "height": height, "read_noise_e": 4.0, "gain_e_per_adu": 1.5,
            "dark_current_e_per_s": 0.2}
    base.update(overrides)
    return make_sensor(preset, base)


#: a small ML11002 dark frame scene (the starting point most scene tests change)
SMALL_DARK = {
    "detector": {"preset": "ml11002", "width": 256, "height": 192},
    "exposure": {"time_s": 10.0, "frame": "dark"},
    "sky": {"stars": False},
}


def merge(base: dict, changes: dict) -> dict:
    """``base`` with ``changes`` merged table by table (a copy; ``None`` deletes a key)."""
    out = copy.deepcopy(base)
    for k, v in changes.items():
        if v is None:
            out.pop(k, None)
        elif isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def write_scene(path: str | Path, table: dict | None = None, **changes) -> Path:
    """Write a scene TOML: ``table`` (default :data:`SMALL_DARK`) with ``changes`` merged; returns the path."""
    p = Path(path)
    p.write_text(tomli_w.dumps(merge(table if table is not None else SMALL_DARK, changes)))
    return p


def star_field_toml(size: int, extra: str = "") -> str:
    """A ``size`` x ``size`` ML11002 window on the Navstar 71 field: 10 s, catalogue stars to G = 15, sky
    19.72 mag/arcsec^2, a 3" Gaussian PSF; ``extra`` TOML (an ``[[objects]]`` table, say) appended."""
    return f"""
[telescope]
design = "art"
[detector]
preset = "ml11002"
width = {size}
height = {size}
[pointing]
ra_deg = 120.95115
dec_deg = -29.25022
epoch = "2023-02-01T22:00:00"
[exposure]
time_s = 10.0
frame = "light"
tracking = "sidereal"
[sky]
background_mag_arcsec2 = 19.72
stars = true
star_mag_limit = 15.0
[psf]
model = "gaussian"
fwhm_arcsec = 3.0
""" + extra


#: a debris streak through the centre of that field (200,000 photons at the aperture)
STREAK_TOML = """
[[objects]]
ra_deg = 120.95115
dec_deg = -29.25022
rate_ra_deg_s = 0.0008
rate_dec_deg_s = -0.0005
photons = 200000
"""

#: a 256 x 256 ML11002 window of empty sky (20 mag/arcsec^2, 5 s): the small frame of the error paths
SMALL_SKY_TOML = """
[detector]
preset = "ml11002"
width = 256
height = 256
[exposure]
time_s = 5.0
[sky]
stars = false
background_mag_arcsec2 = 20.0
"""

# --- measuring frames ----------------------------------------------------------------------------------------
def isolated_stars(path, fwhm_px: float, min_flux_e: float = 2e3, radius_fwhm: float = 5.0) -> dict:
    """Centroids and sums of the isolated bright stars of a noiseless frame (sky and dark removed).

    A star is kept when its box of half-width r = radius_fwhm x FWHM + 1 lies inside the frame and no other
    TRUTH source brighter than 1e-4 of it lies within 3 r. Returns arrays ``cx, cy`` (measured first
    moments), ``x, y`` (the file's WCS applied to the TRUTH ra/dec), ``tx, ty`` (TRUTH x, y), ``sum`` and
    ``flux`` (TRUTH flux_e), in pixels of the written frame.
    """
    with fits.open(path) as hd:
        img = hd[0].data.astype(np.float64)
        hdr = hd[0].header
        t = hd["TRUTH"].data
    b = hdr["XBINNING"]
    img = img - (hdr["SKYRATE"] * b * b + hdr["DARKCUR"] * b * b) * hdr["EXPTIME"]
    xw, yw = WCS(hdr).all_world2pix(t["ra_deg"], t["dec_deg"], 0, tolerance=1e-9)
    r = math.ceil(radius_fwhm * fwhm_px) + 1
    out = {k: [] for k in ("cx", "cy", "x", "y", "tx", "ty", "sum", "flux")}
    for i in np.argsort(-t["flux_e"]):
        xi, yi, f = t["x"][i], t["y"][i], t["flux_e"][i]
        if not (r + 1 < xi < img.shape[1] - r - 2 and r + 1 < yi < img.shape[0] - r - 2) or f < min_flux_e:
            continue
        d = np.hypot(t["x"] - xi, t["y"] - yi)
        if np.any((d > 0) & (d < 3 * r) & (t["flux_e"] > 1e-4 * f)):
            continue
        ix, iy = round(xi), round(yi)
        stamp = img[iy - r:iy + r + 1, ix - r:ix + r + 1]
        yy, xx = np.mgrid[iy - r:iy + r + 1, ix - r:ix + r + 1]
        s = stamp.sum()
        for k, v in (("cx", (xx * stamp).sum() / s), ("cy", (yy * stamp).sum() / s), ("x", xw[i]), ("y", yw[i]),
                     ("tx", xi), ("ty", yi), ("sum", s), ("flux", f)):
            out[k].append(v)
    return {k: np.array(v) for k, v in out.items()}


def shared_row(cache: dict, key, tmp_path_factory, compute):
    """``compute(workdir)`` of a validation case, once per test session, also across pytest-xdist workers.

    In one process the row is kept in ``cache``. Under pytest-xdist the workers of a run share a folder
    (beside their base temporary folders, named by the run's id): the first worker to need a key computes it
    under a lock and pickles the row there; the others wait for the lock and read it. So the cases of one
    module can be spread over the workers (``conftest.py``: SHARED_ROW_MODULES) and a test that needs them
    all (a confusion matrix) computes none twice."""
    import fcntl
    import os
    import pickle

    if key in cache:
        return cache[key]
    name = "_".join(map(str, key)) if isinstance(key, tuple) else str(key)
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if not run:
        cache[key] = compute(tmp_path_factory.mktemp(name))
        return cache[key]
    shared = tmp_path_factory.getbasetemp().parent / f"shared-rows-{run}"
    shared.mkdir(exist_ok=True)
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            done = shared / f"{name}.pickle"
            if done.is_file():
                cache[key] = pickle.loads(done.read_bytes())
            else:
                cache[key] = compute(tmp_path_factory.mktemp(name))
                tmp = done.with_suffix(f".tmp{os.getpid()}")
                tmp.write_bytes(pickle.dumps(cache[key]))
                tmp.replace(done)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return cache[key]


def residuals_of(data, model, var, photo, sensor):
    """A :class:`detector.signatures.Residuals` of whole arrays [ADU]: every pixel fitted, no dark, no spikes."""
    from detector.signatures import Residuals, SpikeStats

    h, w = data.shape
    return Residuals(data.astype(np.float32), model.astype(np.float32), var.astype(np.float32),
                     np.ones((h, w), bool), photo.astype(np.float32), np.zeros((h, w), np.float32),
                     np.arange(h, dtype=float), np.arange(w, dtype=float), sensor, 10.0,
                     SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def gaussian_stars(sigma, fluxes, shape=(120, 160), spacing=36):
    """Gaussian stars of total ``fluxes`` [ADU] and width ``sigma`` [px] on a grid, four to a row (a float64 image)."""
    import numpy as np

    img = np.zeros(shape)
    y, x = np.mgrid[: shape[0], : shape[1]]
    for i, f in enumerate(fluxes):
        cy, cx = 20 + spacing * (i // 4), 20 + spacing * (i % 4)
        img += f * np.exp(-((y - cy) ** 2 + (x - cx) ** 2) / (2 * sigma ** 2)) / (2 * np.pi * sigma ** 2)
    return img
