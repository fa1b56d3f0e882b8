"""Brighter-fatter reference from GalSim's SiliconSensor: a star's size against its flux.

Run in its own environment (GalSim is not a newtsim dependency):

    python3 -m venv /work/peerenv/galsim && /work/peerenv/galsim/bin/pip install galsim
    /work/peerenv/galsim/bin/python tests/data/peers/galsim/make_bf_reference.py

Sensor: GalSim's default ``SiliconSensor('lsst_itl_50_8')``: an LSST ITL CCD (10 um pixels, 100 um thick),
its pixel boundaries from Craig Lage's Poisson_CCD solver, calibrated on ITL spot and flat data (Lage et al.
2017, JINST 12, C03091), with charge diffusion (``diffusion_factor = 1``) and boundaries recomputed every
``nrecalc = 10000`` electrons. Stars: circular Gaussians (sigma 1.0 and 1.5 px before diffusion) centred
on a pixel centre, drawn by photon shooting at fluxes giving peaks of about 1e3 to 2e5 e-.

Each star is drawn twice with the same random seeds (the photons' and the sensor's own, which draws the
diffusion and conversion depths): once at full strength and once at strength 1e-6 (the same photons and
the same diffusion with the boundaries practically fixed; strength 0 is refused). The difference of the
two sizes is the brighter-fatter growth with the photon noise cancelled.

Size: sigma = sqrt((Ixx + Iyy) / 2) from unweighted second moments inside a circle of APERTURE_PX about
the light-weighted centroid (the estimator the newtsim test applies to its own images). The slope
d sigma / d F [px per e-] comes from a straight-line fit of the mean sigma difference against the total
flux F. The normalised mean image at strength 1e-6 is stored too: newtsim's test applies its own
brighter-fatter to exactly this star.
"""

import json
import platform
import sys
import time
from pathlib import Path

import galsim
import numpy as np

SENSOR = "lsst_itl_50_8"
SIGMAS_PX = (1.0, 1.5)
PEAKS_E = (1e3, 1e4, 3e4, 6e4, 1e5, 1.5e5, 2e5)
STAMP = 33
APERTURE_PX = 8.0
REPEATS = 4
SEED = 20250325
OUT = Path(__file__).with_name("bf_size_flux.json")


def sigma_px(img, aperture=APERTURE_PX):
    """Unweighted second-moment size inside a circle of ``aperture`` px about the centroid."""
    n = img.shape[0]
    y, x = np.mgrid[0:n, 0:n].astype(float)
    w = img.astype(float)
    cx, cy = (w * x).sum() / w.sum(), (w * y).sum() / w.sum()
    m = (x - cx) ** 2 + (y - cy) ** 2 <= aperture ** 2
    w = w * m
    cx, cy = (w * x).sum() / w.sum(), (w * y).sum() / w.sum()
    ixx = (w * (x - cx) ** 2).sum() / w.sum()
    iyy = (w * (y - cy) ** 2).sum() / w.sum()
    return float(np.sqrt((ixx + iyy) / 2))


def main():
    t0 = time.time()
    stars = []
    for k, sig in enumerate(SIGMAS_PX):
        # peak fraction of a pixel-integrated Gaussian centred on a pixel
        peak_frac = galsim.Gaussian(sigma=sig).drawImage(nx=STAMP, ny=STAMP, scale=1.0).array.max()
        rows, profile = [], np.zeros((STAMP, STAMP))
        for i, peak in enumerate(PEAKS_E):
            flux = float(round(peak / peak_frac))
            d_sig, s_full, s_weak, peaks = [], [], [], []
            for r in range(REPEATS):
                seed = SEED + 1000 * k + 10 * i + r
                ims = []
                for strength in (1.0, 1e-6):
                    # the sensor draws its own diffusion and conversion depths: seed it too
                    sensor = galsim.SiliconSensor(SENSOR, strength=strength, rng=galsim.BaseDeviate(seed + 7))
                    im = galsim.ImageF(STAMP, STAMP, scale=1.0)
                    galsim.Gaussian(sigma=sig, flux=flux).drawImage(
                        im, method="phot", sensor=sensor, rng=galsim.BaseDeviate(seed))
                    ims.append(im.array.astype(float))
                a, b = sigma_px(ims[0]), sigma_px(ims[1])
                s_full.append(a)
                s_weak.append(b)
                d_sig.append(a - b)
                peaks.append(float(ims[0].max()))
                profile += ims[1]
            rows.append({"flux_e": flux, "target_peak_e": peak, "peak_e": float(np.mean(peaks)),
                         "sigma_px": float(np.mean(s_full)), "sigma_weak_px": float(np.mean(s_weak)),
                         "dsigma_px": float(np.mean(d_sig)),
                         "dsigma_sem_px": float(np.std(d_sig, ddof=1) / np.sqrt(REPEATS))})
        f = np.array([r["flux_e"] for r in rows])
        ds = np.array([r["dsigma_px"] for r in rows])
        slope, icpt = np.polyfit(f, ds, 1)
        profile /= profile.sum()
        stars.append({"sigma_psf_px": sig, "rows": rows,
                      "slope_px_per_e": float(slope), "intercept_px": float(icpt),
                      "slope_per_1e5_peak_px": float(slope * 1e5 / peak_frac),
                      "profile": [[float(f"{v:.6e}") for v in row] for row in profile]})
        print(f"sigma {sig}: dsigma/dF = {slope:.4e} px/e-", file=sys.stderr)
    out = {
        "peer": "GalSim", "version": galsim.__version__, "python": platform.python_version(),
        "numpy": np.__version__,
        "command": "/work/peerenv/galsim/bin/python tests/data/peers/galsim/make_bf_reference.py",
        "sensor": SENSOR, "sensor_note": "LSST ITL CCD, 10 um pixels, 100 um thick (GalSim default)",
        "sensor_kwargs": {"diffusion_factor": 1.0, "qdist": 3, "nrecalc": 10000, "strength": 1.0,
                          "reference_strength": 1e-6},
        "stamp_px": STAMP, "aperture_px": APERTURE_PX, "repeats": REPEATS, "seed": SEED,
        "size_estimator": "sqrt((Ixx+Iyy)/2), unweighted moments inside aperture_px of the centroid",
        "slope_fit": "least squares dsigma_px = a + b flux_e over the rows",
        "profile_note": "mean image at reference_strength over all fluxes and repeats, sum 1, star at the "
                        "centre pixel (index 16, 16)",
        "seconds": round(time.time() - t0, 1),
        "stars": stars,
    }
    OUT.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
