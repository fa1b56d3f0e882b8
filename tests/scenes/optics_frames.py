"""Frames of a perturbed telescope for the alignment diagnosis (tests/scenes/test_diagnose_optics.py and
benchmarks/bench_misalignment.py).

The ML11002 full frame (36 x 24 mm, binned 2 x 2: 2004 x 1336 output pixels of 18 um) behind
the ``art`` telescope, a CSV catalogue of isolated stars (G 11-13) in 2 s, 1" of seeing, ``[psf] model = "optics"``
with a PSF cube (``grid_file``) traced for the design over the ML11002's field (``nodes`` x ``nodes``
points spanning 95 % of it). The cube is traced here rather than by ``optics.psf.cached_psf_grid``,
whose grid spans the design's focal plane (the IMX411's, 53 x 40 mm) and traces with a detector of that
size: a perturbation that moves the image by more than the 5 % margin at the grid's corners (a diagonal
tilted 0.1 deg moves it 1 mm) loses the corner's rays. Here the tracer's detector is 1.5 times larger (as
``optics.distortion`` does for the SIP), and three wavelengths at 128 pupil samples keep a cube to ~2 s per
field point.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tomli_w

PITCH_UM = 9.0
W_PX, H_PX = 4008, 2672
BAND_NM = (500.0, 650.0, 800.0)


def wide_design(design):
    """``design`` with a focal plane 1.5 times larger (a tracer whose detector does not cut moved images)."""
    from optics.design import Design

    data = design.model_dump()
    fp = data["focal_plane"]
    fp["width_mm"], fp["height_mm"] = 1.5 * fp["width_mm"], 1.5 * fp["height_mm"]
    return Design.model_validate(data)


def ml11002_fields(design, nodes: int, fill: float = 0.95) -> np.ndarray:
    """Field angles [deg] whose ideal images span ``fill`` of the ML11002 (rows from -v to +v)."""
    f = design.primary.focal_length_mm
    hu, hv = W_PX * PITCH_UM * 5e-4 * fill, H_PX * PITCH_UM * 5e-4 * fill
    u, v = np.linspace(-hu, hu, nodes), np.linspace(-hv, hv, nodes)
    U, V = np.meshgrid(u, v, indexing="xy")
    return np.degrees(np.arctan(-np.stack([U.ravel(), V.ravel()], -1) / f))


def trace_cube(mi, design, path: Path, nodes: int = 3, stamp_px: int = 21) -> Path:
    """The design's diffraction PSFs over the ML11002 (the cube ``[psf] grid_file`` reads), on stamps of
    ``stamp_px`` pixels of 9 um. A 21-pixel (189 um) stamp cuts the wings of the diffraction PSF, more of them
    for a perturbed star: the cube's change of the second moments falls short of the optics' (at field
    (0.51, 0.34) deg, a 0.1 deg diagonal tilt adds 43.7 um^2 to Myy on a 189 um stamp, 49.0 on 297 um, 49.9 on
    387 um, 49.7 in the geometric spot: the unweighted moments of the wave-optics PSF change exactly as the
    geometric spot's), so a frame made with it shows a perturbation 5-12 % smaller than it is; 33 pixels do
    not (the matrix of tests/scenes/test_diagnose_optics.py)."""
    from optics.psf import psf_grid, write_psf_fits
    from optics.sequential import SequentialTracer

    tracer = SequentialTracer(wide_design(design), mi, obstruct="analytic")
    grid = psf_grid(tracer, ml11002_fields(design, nodes), wavelengths_nm=BAND_NM, sampling_um=PITCH_UM / 3,
                    size_px=stamp_px * 3, n_pupil=128)
    write_psf_fits(grid, path)
    return path


def design_file(folder: Path, perturbation: dict | None, name: str) -> Path:
    """The ``art`` design with ``perturbation`` as a design TOML in ``folder``."""
    from optics import load_design
    from optics.design import with_perturbation

    d = load_design("art")
    if perturbation:
        d = with_perturbation(d, **perturbation)
    data = d.model_dump(mode="json", exclude_none=True)
    data["name"] = name
    p = Path(folder) / f"{name}.toml"
    p.write_text(tomli_w.dumps(data))
    return p


RA0, DEC0 = 120.95115, -29.25022


def write_catalogue(path: Path, nx: int = 25, ny: int = 16, mags=(11.0, 13.0), seed: int = 1) -> Path:
    """A CSV star table (``[sky] catalog``): ``nx`` x ``ny`` stars on a jittered lattice over the ML11002's
    field (no two closer than ~60 binned pixels: every star is isolated), G uniform in ``mags`` (unsaturated
    in 2 s on 2 x 2 binned pixels, S/N of a hundred or more)."""
    rng = np.random.default_rng(seed)
    hx, hy = 0.97 * np.degrees(np.arctan(W_PX * PITCH_UM * 5e-4 / 960.0)), 0.97 * np.degrees(np.arctan(H_PX * PITCH_UM * 5e-4 / 960.0))
    gx, gy = np.linspace(-hx, hx, nx), np.linspace(-hy, hy, ny)
    X, Y = np.meshgrid(gx, gy)
    xi = np.radians(X.ravel() + rng.uniform(-0.25, 0.25, X.size) * (gx[1] - gx[0]))
    eta = np.radians(Y.ravel() + rng.uniform(-0.25, 0.25, Y.size) * (gy[1] - gy[0]))
    d0, a0 = np.radians(DEC0), np.radians(RA0)
    # gnomonic (TAN) inverse: standard coordinates (xi east, eta north) -> RA, Dec
    den = np.cos(d0) - eta * np.sin(d0)
    ra = np.degrees(a0 + np.arctan2(xi, den)) % 360
    dec = np.degrees(np.arctan2(np.sin(d0) + eta * np.cos(d0), np.hypot(xi, den)))
    mag = rng.uniform(*mags, ra.size)
    lines = ["ra_deg,dec_deg,mag_g,bp_rp"] + [f"{a:.7f},{d:.7f},{m:.3f},0.8" for a, d, m in zip(ra, dec, mag)]
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


def scene_table(design: str, cube: str, catalogue: str, *, binning: int = 2, seeing: float = 1.0,
                width: int = W_PX, height: int = H_PX, time_s: float = 2.0) -> dict:
    """The scene (a TOML table): ``design`` (a built-in name or a design TOML), the PSF ``cube``, the star
    ``catalogue``; the full ML11002 binned 2 x 2 unless ``width``/``height``/``binning`` say otherwise."""
    return {
        "telescope": {"design": design},
        "detector": {"preset": "ml11002", "width": width, "height": height, "binning": binning},
        "pointing": {"ra_deg": RA0, "dec_deg": DEC0, "epoch": "2023-02-01T22:00:00"},
        "exposure": {"time_s": time_s, "frame": "light", "tracking": "sidereal", "seed": 3},
        "sky": {"background_mag_arcsec2": 19.72, "stars": True, "star_mag_limit": 13.0, "catalog": catalogue},
        "psf": {"model": "optics", "grid_file": cube, "seeing_fwhm_arcsec": seeing},
    }


def write_toml(path: Path, table: dict) -> Path:
    Path(path).write_text(tomli_w.dumps(table))
    return Path(path)
