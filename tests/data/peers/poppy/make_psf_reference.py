"""Diffraction reference from POPPY: the ART pupil's PSF at 450, 650 and 850 nm.

Run in its own environment (POPPY is not a newtsim dependency):

    python3 -m venv /work/peerenv/poppy && /work/peerenv/poppy/bin/pip install poppy
    /work/peerenv/poppy/bin/python tests/data/peers/poppy/make_psf_reference.py

The pupil is built from ``optics/designs/art.toml`` (read with tomllib; nothing of newtsim is imported)
and the obstruction rules of ``optics/layout.py`` (its module docstring and ``make_layout``), as seen on
axis from the sky:

- the primary's clear aperture, a circle of radius D/2 = 200 mm;
- the diagonal and its holder, a cylinder of radius b = minor_axis / 2 = 102.5 mm whose axis is shifted
  by -offset / sqrt2 = -19.02 mm along x (the diagonal's offset away from the focuser);
- four spider vanes of width w = 2 mm along +x, +y, -x, -y, each from 0.9 b = 92.25 mm from the tube's
  axis outwards (beyond the rim).

The aberrations are left out: this is the pupil's own diffraction, the PSF newtsim computes for the ART
pupil with a perfect primary (``art.toml`` with the corrector disabled and the detector at the
paraboloid's focus). POPPY propagates to the focal plane by its matrix Fourier transform (Soummer et al.
2007), Fraunhofer with a focal length f = 960 mm: a focal-plane length x [um] is the angle x / f. Two
pupils:

- ``flat``: the textbook model, the entrance pupil above as a flat, uniform screen (POPPY's analytic
  elements; NPIX = 4000 samples across 0.4 m, i.e. exactly 0.1 mm, so the 2 mm vanes are 20 whole
  samples wide; the circles grey-pixel anti-aliased);
- ``exit``: the same screen as the paraboloid's converging beam presents it to the focus, i.e. in
  direction cosines (Debye; Born & Wolf 8.8): the ray reflected at radius rho meets the axis under
  sin(theta) = rho / (f + rho^2 / 4f), so the pupil is mapped to X = f sin(theta) (the rim from 200 to
  197.9 mm) with the amplitude sqrt(|d^2 p / d^2 k| / cos(theta)) that keeps the energy of each ray tube.
  This is the pupil newtsim's diffraction integral sees; the screen is sampled 4 x 4 per pupil sample
  (anti-aliased) through the inverse map rho = 2 f (1 - cos(theta)) / sin(theta).

Stored (``psf.npz`` and ``psf.json``), per pupil and wavelength (keys ``<pupil>_<quantity>_<nm>``):
- ``ee``: the encircled energy at ``ee_radius_um`` relative to the total energy entering the pupil
  (``normalize="first"``), summed over POPPY's oversampled image (OVERSAMPLE x OVERSAMPLE samples per 1 um
  pixel), each sample split 5 x 5 so that the circle cuts it finely; ``measure_ee``: the same from
  ``poppy.utils.measure_ee`` (its radial bins of one sample; kept for reference);
- ``image``: the PSF integrated over 1 um pixels, 81 x 81, centred, fraction of the total energy per
  pixel (the oversampled image summed);
- ``spike_fraction``: the energy in the spikes: the pixels within 1 px of the u or v axis between 8 and
  40 um from the centre, less the same number of pixels along the diagonals (the round halo), over the
  total energy.
"""

import json
import math
import platform
import time
from pathlib import Path

import astropy.units as u
import numpy as np
import poppy
import tomllib

ROOT = Path(__file__).resolve().parents[4]
HERE = Path(__file__).parent
WAVELENGTHS_NM = (450.0, 650.0, 850.0)
NPIX = 4000
PIXEL_UM = 1.0
SIZE_PX = 81
OVERSAMPLE = 8
EE_RADII_UM = np.round(np.concatenate([np.arange(0.25, 5.0, 0.25), np.arange(5.0, 40.01, 1.0)]), 4)


def spike_fraction(img, r_in=8.0, r_out=40.0, half_width=1):
    """Spike energy of a centred image with 1 um pixels (module docstring)."""
    n = img.shape[0]
    c = (n - 1) // 2
    y, x = np.mgrid[0:n, 0:n] - c
    r = np.hypot(x, y)
    ring = (r >= r_in) & (r <= r_out)
    axes = ring & ((np.abs(x) <= half_width) | (np.abs(y) <= half_width))
    diag = ring & ((np.abs(x - y) <= half_width) | (np.abs(x + y) <= half_width))
    return float(img[axes].sum() - img[diag].sum() * axes.sum() / diag.sum())


def direct_ee(over, dx_um, radii_um, split=5):
    """EE of a centred image of samples dx_um wide: each sample split x split, the sub-samples counted
    where their centres lie inside the radius."""
    n = over.shape[0]
    c = (np.arange(n * split) + 0.5) / split - n / 2          # sub-sample centres [sample units]
    d_all, w_all = [], []
    for i0 in range(0, n * split, 400):
        yy = c[i0:i0 + 400][:, None]
        d = np.hypot(c[None, :], yy).ravel() * dx_um
        w = np.repeat(np.repeat(over[i0 // split:(i0 + 400) // split], split, 0), split, 1).ravel() / split ** 2
        d_all.append(d.astype(np.float32))
        w_all.append(w)
    d = np.concatenate(d_all)
    w = np.concatenate(w_all)
    o = np.argsort(d, kind="stable")
    cum = np.concatenate([[0.0], np.cumsum(w[o])])
    return cum[np.searchsorted(d[o], radii_um, side="right")]


def exit_pupil(design, npix, oversub=4):
    """The ``flat`` screen seen in direction cosines from the paraboloid's focus (module docstring)."""
    p, s, sp = design["primary"], design["secondary"], design["spider"]
    f = p["focal_length_mm"]
    R = p["diameter_mm"] / 2
    b = s["minor_axis_mm"] / 2
    cx = -s.get("offset_mm", 0.0) / math.sqrt(2)
    hw = sp.get("width_mm", 2.0) / 2
    start = 0.9 * b
    D = p["diameter_mm"]
    dx = D / npix
    out = np.zeros((npix, npix))
    sub = (np.arange(oversub) + 0.5) / oversub - 0.5
    xs = ((np.arange(npix) - (npix - 1) / 2)[:, None] + sub[None, :]).ravel() * dx   # fine X [mm]
    for r0 in range(0, npix, 50):
        ys = ((np.arange(r0, min(r0 + 50, npix)) - (npix - 1) / 2)[:, None] + sub[None, :]).ravel() * dx
        X, Y = np.meshgrid(xs, ys, indexing="xy")
        k = np.hypot(X, Y) / f                                   # sin(theta)
        kc = np.clip(k, 1e-12, 0.999)
        rho = 2 * f * (1 - np.sqrt(1 - kc ** 2)) / kc
        rho = np.where(k < 1e-9, k * f, rho)
        scale = np.where(k < 1e-9, 1.0, rho / np.maximum(k * f, 1e-300))
        px, py = X * scale, Y * scale
        # d rho / d k = rho' from k = rho / (f + rho^2 / 4f): dk/drho = (f - rho^2/4f) / (f + rho^2/4f)^2
        dk_drho = (f - rho ** 2 / (4 * f)) / (f + rho ** 2 / (4 * f)) ** 2
        jac = scale / dk_drho                  # |d^2p/d^2k| = (rho/k)(drho/dk), up to the constant f
        amp2 = jac / np.sqrt(1 - np.minimum(kc, 0.999) ** 2)
        m = (np.hypot(px, py) <= R) & (np.hypot(px - cx, py) > b)
        for ang in (0.0, 90.0, 180.0, 270.0):
            ca, sa = math.cos(math.radians(ang)), math.sin(math.radians(ang))
            along, across = px * ca + py * sa, -px * sa + py * ca
            m &= ~((along >= start) & (np.abs(across) <= hw))
        a = np.sqrt(amp2) * m
        nr = len(ys) // oversub
        out[r0:r0 + nr] = a.reshape(nr, oversub, npix, oversub).mean(axis=(1, 3))
    return out


def pupil(design):
    p, s, sp = design["primary"], design["secondary"], design["spider"]
    R = p["diameter_mm"] / 2 * 1e-3
    b = s["minor_axis_mm"] / 2 * 1e-3
    cx = -s.get("offset_mm", 0.0) / math.sqrt(2) * 1e-3
    w = sp.get("width_mm", 2.0) * 1e-3
    r_tube = design["tube"]["inner_diameter_mm"] / 2 * 1e-3
    start, end = 0.9 * b, min(r_tube, R * 1.01)
    parts = [poppy.CircularAperture(radius=R, name="primary"),
             poppy.InverseTransmission(poppy.CircularAperture(radius=b, shift_x=cx, name="diagonal"))]
    length, mid = end - start, 0.5 * (start + end)
    n = sp.get("vanes", 4)
    assert n == 4 and sp.get("angle_deg", 0.0) == 0.0, "the script builds four vanes along the axes"
    for sx, sy, wd, ht in ((mid, 0.0, length, w), (-mid, 0.0, length, w),
                           (0.0, mid, w, length), (0.0, -mid, w, length)):
        parts.append(poppy.InverseTransmission(poppy.RectangleAperture(width=wd, height=ht, shift_x=sx,
                                                                       shift_y=sy)))
    geom = {"radius_mm": R * 1e3, "obstruction_radius_mm": b * 1e3, "obstruction_centre_x_mm": cx * 1e3,
            "vane_width_mm": w * 1e3, "vane_from_mm": start * 1e3, "vane_to_mm": end * 1e3}
    return poppy.CompoundAnalyticOptic(opticslist=parts, name="ART pupil", mergemode="and"), geom


def main():
    t0 = time.time()
    design = tomllib.loads((ROOT / "optics" / "designs" / "art.toml").read_text())
    f_mm = design["primary"]["focal_length_mm"]
    D = design["primary"]["diameter_mm"] * 1e-3
    optic, geom = pupil(design)
    arcsec_per_um = 206264.806247 / (f_mm * 1e3)
    exit_amp = exit_pupil(design, NPIX)
    optics = {"flat": optic,
              "exit": poppy.ArrayOpticalElement(transmission=exit_amp, pixelscale=D / NPIX * u.m / u.pixel,
                                                name="ART exit pupil")}
    # the pupil's transmitted area as POPPY samples it
    wf = poppy.Wavefront(wavelength=650e-9, npix=NPIX, diam=D)
    area_mm2 = float(np.sum(optic.get_transmission(wf)) * (D / NPIX * 1e3) ** 2)
    arrays, rows = {}, []
    for kind, element in optics.items():
        osys = poppy.OpticalSystem(npix=NPIX, pupil_diameter=D * u.m)
        osys.add_pupil(element)
        osys.add_detector(pixelscale=PIXEL_UM * arcsec_per_um, fov_pixels=SIZE_PX, oversample=OVERSAMPLE)
        for lam in WAVELENGTHS_NM:
            hdul = osys.calc_psf(wavelength=lam * 1e-9, normalize="first")
            over = hdul[0].data.astype(float)              # oversampled: OVERSAMPLE^2 samples per pixel
            ee_fn = poppy.utils.measure_ee(hdul, ext=0)
            ee_m = np.asarray(ee_fn(EE_RADII_UM * arcsec_per_um), dtype=float)
            ee = direct_ee(over, PIXEL_UM / OVERSAMPLE, EE_RADII_UM)
            n = SIZE_PX
            img = over.reshape(n, OVERSAMPLE, n, OVERSAMPLE).sum(axis=(1, 3))
            arrays[f"{kind}_image_{int(lam)}"] = img
            arrays[f"{kind}_ee_{int(lam)}"] = ee
            arrays[f"{kind}_measure_ee_{int(lam)}"] = ee_m
            rows.append({"pupil": kind, "wavelength_nm": lam, "energy_in_stamp": float(img.sum()),
                         "spike_fraction": spike_fraction(img), "ee_at_2um": float(np.interp(2.0, EE_RADII_UM, ee)),
                         "ee_at_10um": float(np.interp(10.0, EE_RADII_UM, ee)), "ee_at_40um": float(ee[-1]),
                         "max_abs_measure_ee_minus_ee": float(np.nanmax(np.abs(ee_m - ee)))})
            print(rows[-1], flush=True)
    arrays["ee_radius_um"] = EE_RADII_UM
    np.savez_compressed(HERE / "psf.npz", **arrays)
    meta = {
        "peer": "POPPY", "version": poppy.__version__, "python": platform.python_version(), "numpy": np.__version__,
        "command": "/work/peerenv/poppy/bin/python tests/data/peers/poppy/make_psf_reference.py",
        "design_file": "optics/designs/art.toml", "pupil": geom, "pupil_area_mm2": area_mm2,
        "npix": NPIX, "pupil_sample_mm": D / NPIX * 1e3, "focal_length_mm": f_mm,
        "pixel_um": PIXEL_UM, "size_px": SIZE_PX, "oversample": OVERSAMPLE, "normalize": "first",
        "ee": "summed over the oversampled image, samples split 5 x 5 (module docstring); measure_ee: "
              "poppy.utils.measure_ee(hdul, ext=0) at ee_radius_um (as angles r / f)",
        "spike_fraction": "pixels within 1 px of the u/v axes at 8-40 um less as many along the diagonals",
        "wavelengths": rows, "seconds": round(time.time() - t0, 1),
    }
    (HERE / "psf.json").write_text(json.dumps(meta, indent=1) + "\n")


if __name__ == "__main__":
    main()
