"""Make the ArCTIc reference outputs that tests/detector/test_cti_arctic.py compares newtsim's CTI with.

Run in ArCTIc's own environment (arcticpy needs numpy < 2 and the GNU Scientific Library):

    python3 -m venv /work/peerenv/arctic
    /work/peerenv/arctic/bin/pip install 'numpy<2' arcticpy matplotlib scipy   # (apt: libgsl-dev)
    /work/peerenv/arctic/bin/python tests/data/peers/arctic/make_arctic_refs.py

It writes arctic_refs.npz next to this file: the input images (``<case>_in``) and ArCTIc's outputs
(``<case>_out``) for every case, plus the parameters and the arcticpy version (``meta``, a JSON string).

Model (ArCTIc's well-fill model, Massey et al. 2014, MNRAS 439, 887, arXiv:1401.1151; ArCTIc 2023):
* HST ACS trap species as in ArCTIc's README example: instant capture, densities 0.6, 1.6, 1.4 traps per
  pixel, release timescales 0.74, 7.70, 37.0 transfers (dwell time 1); full well 84700 e-, well-fill power
  0.478, no notch;
* express = 0 (every transfer computed), empty traps before each pixel's first transfer
  (ROE empty_traps_for_first_transfers=True: every pixel's traps start empty), no pruning of watermarks
  (prune_frequency = 0), no window offset (the packet in row j makes j + 1 transfers);
* parallel clocking moves charge towards row 0, serial towards column 0 (ArCTIc transposes); both: parallel
  then serial.
"""

import json
from importlib.metadata import version
from pathlib import Path

import arcticpy as ac
import numpy as np

DENSITY_PER_PX = [0.6, 1.6, 1.4]
RELEASE_TRANSFERS = [0.74, 7.70, 37.0]
FULL_WELL_E = 84700.0
WELL_FILL_POWER = 0.478
WELL_NOTCH_E = 0.0


def run(image, parallel=True, serial=False):
    traps = [ac.TrapInstantCapture(density=d, release_timescale=t) for d, t in zip(DENSITY_PER_PX, RELEASE_TRANSFERS)]
    ccd = ac.CCD(full_well_depth=FULL_WELL_E, well_fill_power=WELL_FILL_POWER, well_notch_depth=WELL_NOTCH_E)
    roe = ac.ROE(dwell_times=[1.0], empty_traps_for_first_transfers=True)
    kw = {}
    if parallel:
        kw.update(parallel_ccd=ccd, parallel_roe=roe, parallel_traps=traps, parallel_express=0,
                  parallel_prune_frequency=0, parallel_prune_n_electrons=0.0)
    if serial:
        kw.update(serial_ccd=ccd, serial_roe=roe, serial_traps=traps, serial_express=0,
                  serial_prune_frequency=0, serial_prune_n_electrons=0.0)
    return np.asarray(ac.add_cti(np.array(image, dtype=np.float64), verbosity=0, **kw), dtype=np.float64)


def point_columns(n_rows=300, row=100):
    """One column per (flux, background): 100, 1000, 10000 e- on 0 and on 50 e- per pixel."""
    cols = []
    for bg in (0.0, 50.0):
        for flux in (100.0, 1000.0, 10000.0):
            c = np.full(n_rows, bg)
            c[row] += flux
            cols.append(c)
    return np.stack(cols, axis=1)


def gaussian_stars(shape=(96, 96)):
    """Four round Gaussian stars (sigma 1.2-2.5 px, 500-200000 e-) on a 50 e- background."""
    y, x = np.mgrid[: shape[0], : shape[1]]
    img = np.full(shape, 50.0)
    for y0, x0, sig, flux in ((20.3, 30.6, 1.2, 500.0), (45.7, 70.2, 1.8, 5000.0), (70.1, 20.4, 2.5, 50000.0),
                              (80.5, 60.5, 1.5, 200000.0)):
        img += flux / (2 * np.pi * sig**2) * np.exp(-((y - y0) ** 2 + (x - x0) ** 2) / (2 * sig**2))
    return img


def main():
    out = {}
    cases = {
        "parallel_points": (point_columns(), True, False),
        "serial_points": (point_columns().T.copy(), False, True),
        "parallel_stars": (gaussian_stars(), True, False),
        "serial_stars": (gaussian_stars(), False, True),
        "both_stars": (gaussian_stars(), True, True),
    }
    for name, (img, par, ser) in cases.items():
        out[name + "_in"] = img
        out[name + "_out"] = run(img, par, ser)
    meta = {
        "arcticpy_version": version("arcticpy"), "numpy_version": np.__version__,
        "density_per_px": DENSITY_PER_PX, "release_timescale_transfers": RELEASE_TRANSFERS,
        "dwell_time_transfers": 1.0, "full_well_depth_e": FULL_WELL_E, "well_fill_power": WELL_FILL_POWER,
        "well_notch_depth_e": WELL_NOTCH_E, "trap_type": "TrapInstantCapture", "express": 0,
        "empty_traps_for_first_transfers": True, "prune_frequency": 0, "window_offset": 0,
        "point_cases": "columns: 100, 1000, 10000 e- at row 100 of 300 on 0 e-, then the same on 50 e-",
        "command": "/work/peerenv/arctic/bin/python tests/data/peers/arctic/make_arctic_refs.py",
    }
    path = Path(__file__).with_name("arctic_refs.npz")
    np.savez_compressed(path, meta=np.array(json.dumps(meta)), **out)
    print(f"wrote {path}")
    for k in cases:
        print(k, "input", out[k + "_in"].sum(), "output", out[k + "_out"].sum())


if __name__ == "__main__":
    main()
