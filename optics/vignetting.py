"""Vignetting: relative illumination over the focal plane from full-aperture ray bundles.

For each field point a bundle of rays fills the primary's clear aperture (stratified R2 sampling of the
rim-plane disk, see :func:`optics.sequential.pupil_uniform`) and is traced through every obstruction;
the geometric throughput T(field) is the fraction that reaches the detector plane (mirror reflectance
excluded; rays that land outside the sensor's edge still count: vignetting is a property of the beam,
not of where the sensor ends). The relative illumination is RI = T(field) / T(axis), 1.0 on axis, the
factor the scenes package multiplies into the image; the on-axis throughput itself is reported apart
(it is 1 - (d_sec/D)^2 - spider for a Newtonian).

Binomial error of each T: sqrt(T (1 - T) / N) (stratified sampling makes the true error smaller).

Speed and precision. Every field point sees the same pupil points: drjit makes them once
(:func:`optics.sequential.pupil_uniform_dr`, up to :data:`CHUNK` at a time) and keeps them in memory, and one
float32 counting kernel per field traces them and adds each ray's loss code into eight counters; no ray
crosses to numpy, and the fields' kernels are queued without waiting for each other (the process waits once
per row of the grid: :meth:`optics.sequential.SequentialTracer.loss_counts_fields`). float32 moves a ray's landing point by at most 0.3 um and changes the fate of a few rays per
million that graze an edge: maps agree with the float64 kernel's to a few rays per field, a hundredth of the
binomial error (module :mod:`optics.sequential`, "Precision"). docs/performance.md, "The sequential trace",
has the profile and the speed against batoid.

Independent checks (tests/optics/test_vignetting.py): the two-circle overlap formula for the diagonal
(e.g. Sidgwick, Amateur Astronomer's Handbook, 1980, sect. 10; Suiter, Star Testing Astronomical
Telescopes, 1994, appendix) and (d_sec/D)^2 plus the spider's area for the on-axis obstruction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .sequential import DETECTOR_MISS, LOSS_NAMES, OK, SequentialTracer, pupil_uniform_dr

#: pupil points kept in memory at once (float32: 8 bytes a point), traced for every field before the next
CHUNK = 1 << 24
#: the counting kernel in float32 (module docstring, "Speed and precision")
SINGLE = True


@dataclass
class VignettingResult:
    field_x_deg: np.ndarray            # (nx,)
    field_y_deg: np.ndarray            # (ny,)
    u_mm: np.ndarray                   # detector position of each column (ideal image of field_x)
    v_mm: np.ndarray
    throughput: np.ndarray             # (ny, nx) geometric throughput T
    throughput_err: np.ndarray         # (ny, nx) binomial 1-sigma
    on_axis_throughput: float
    on_axis_err: float
    rays_per_field: int
    seconds: float = 0.0
    loss_fractions: dict = field(default_factory=dict)   # on axis: where the light goes

    @classmethod
    def from_json(cls, data: dict) -> VignettingResult:
        """Rebuild from :meth:`to_json` output (e.g. a cached result)."""
        return cls(np.asarray(data["field_x_deg"]), np.asarray(data["field_y_deg"]), np.asarray(data["u_mm"]),
                   np.asarray(data["v_mm"]), np.asarray(data["throughput"]), np.asarray(data["throughput_err"]),
                   data["on_axis_throughput"], data["on_axis_err"], data["rays_per_field"],
                   data.get("seconds", 0.0), data.get("on_axis_losses", {}))

    @property
    def relative_illumination(self) -> np.ndarray:
        return self.throughput / self.on_axis_throughput

    def to_json(self) -> dict:
        return {
            "field_x_deg": self.field_x_deg.tolist(), "field_y_deg": self.field_y_deg.tolist(),
            "u_mm": self.u_mm.tolist(), "v_mm": self.v_mm.tolist(),
            "relative_illumination": np.round(self.relative_illumination, 6).tolist(),
            "throughput": np.round(self.throughput, 6).tolist(),
            "throughput_err": np.round(self.throughput_err, 6).tolist(),
            "on_axis_throughput": round(self.on_axis_throughput, 6),
            "on_axis_err": round(self.on_axis_err, 6),
            "corner_relative_illumination": round(float(np.min(self.relative_illumination)), 6),
            "rays_per_field": self.rays_per_field,
            "rays_per_s": round(self.rays_per_field * (self.throughput.size + 1) / max(self.seconds, 1e-9)),
            "seconds": round(self.seconds, 3),
            "on_axis_losses": self.loss_fractions,
        }


def map_fields(layout, grid: tuple[int, int]):
    """The field points of a map: ``(fields, fx, fy, u, v)``, ``fields`` the list of (theta_x, theta_y)
    [deg] traced in order (the axis first, then row by row), fx/fy [deg] and u/v [mm] the grid's axes
    (the outer points are the ideal images of the sensor's edges, u = -f tan(theta_x))."""
    nx, ny = grid
    f = layout.focal_length
    hu, hv = layout.detector_half
    u = np.linspace(-hu, hu, nx) if nx > 1 else np.zeros(1)
    v = np.linspace(-hv, hv, ny) if ny > 1 else np.zeros(1)
    fx = np.degrees(np.arctan(-u / f))
    fy = np.degrees(np.arctan(-v / f))
    fields = [(0.0, 0.0)] + [(float(fx[i]), float(fy[j])) for j in range(ny) for i in range(nx)]
    return fields, fx, fy, u, v


def vignetting_map(tracer: SequentialTracer, grid: int | tuple[int, int] = 9, rays: int = 1_000_000,
                   wavelength_nm: float = 550.0, seed: int = 0, progress=None) -> VignettingResult:
    """Geometric throughput over a ``grid`` of field points spanning the detector.

    Parameters
    ----------
    tracer : SequentialTracer
    grid : int or (nx, ny)
        Field points per axis; the outer ones are the ideal images of the sensor's edges.
    rays : int
        Rays per field point over the full aperture.
    progress : callable(done, total), optional
    """
    import time

    nx, ny = (grid, grid) if isinstance(grid, int) else grid
    if nx < 1 or ny < 1 or rays < 100:
        raise ValueError("vignetting needs grid >= 1 and at least 100 rays per field point")
    L = tracer.layout
    fields, fx, fy, u, v = map_fields(L, (nx, ny))
    t0 = time.perf_counter()
    # every field sees the same pupil points: made by drjit once per chunk, kept in memory across fields,
    # and traced by one float32 counting kernel per field (module docstring, "Speed and precision")
    counts = np.zeros((len(fields), len(LOSS_NAMES)), dtype=np.int64)
    chunks = range(0, rays, CHUNK)
    total = nx * ny * len(chunks)
    for c, start in enumerate(chunks):
        px, py = pupil_uniform_dr(min(CHUNK, rays - start), L.r_primary, seed, single=SINGLE, start=start)
        report = (lambda k, c=c: progress(c * nx * ny + max(k - 1, 0), total)) if progress else None
        counts += tracer.loss_counts_fields(fields, px, py, wavelength_nm, single=SINGLE, sync_every=nx,
                                            progress=report)
        del px, py
    through = (counts[:, OK] + counts[:, DETECTOR_MISS]) / rays
    t_axis = through[0]
    losses = {k: round(float(c / rays), 6) for k, c in enumerate(counts[0])}
    T = through[1:].reshape(ny, nx)
    seconds = time.perf_counter() - t0
    err = np.sqrt(T * (1 - T) / rays)
    return VignettingResult(fx, fy, u, v, T, err, float(t_axis), math.sqrt(t_axis * (1 - t_axis) / rays),
                            rays, seconds, {LOSS_NAMES[k]: frac for k, frac in losses.items() if frac > 0})


def two_circle_fraction(r1: float, r2: float, s: float) -> float:
    """Overlap area of circles of radii ``r1`` (the beam) and ``r2`` (the stop) whose centres are ``s``
    apart, as a fraction of circle 1's area [1]."""
    if s >= r1 + r2:
        return 0.0
    if s <= abs(r2 - r1):
        return 1.0 if r2 >= r1 else (r2 / r1) ** 2
    a1 = r1 * r1 * math.acos((s * s + r1 * r1 - r2 * r2) / (2 * s * r1))
    a2 = r2 * r2 * math.acos((s * s + r2 * r2 - r1 * r1) / (2 * s * r2))
    a3 = 0.5 * math.sqrt((-s + r1 + r2) * (s + r1 - r2) * (s - r1 + r2) * (s + r1 + r2))
    return (a1 + a2 - a3) / (math.pi * r1 * r1)


def diagonal_two_circle(design, field_deg: float) -> float:
    """Fraction of the converging beam that the diagonal intercepts at ``field_deg`` [deg], treating the
    flat as a circular stop of its minor axis at its distance d from focus: beam radius D d / 2f,
    centred f tan(theta) (1 - d/f) off axis."""
    f, d = design.primary.focal_length_mm, design.secondary.distance_to_focus_mm
    D, m = design.primary.diameter_mm, design.secondary.minor_axis_mm
    h = f * math.tan(math.radians(field_deg))
    return two_circle_fraction(D * d / (2 * f), m / 2, h * (1 - d / f))


def write_fits(result: VignettingResult, path, design_name: str = "", extra_cards: dict | None = None):
    """FITS map of the relative illumination sampled at detector positions (u, v) [mm] (linear axes:
    u = CRVAL1 + (i + 1 - CRPIX1) CDELT1 for column i); extension ERR holds the 1-sigma error.
    The scenes package resamples it to pixels."""
    from astropy.io import fits

    ri = result.relative_illumination.astype(np.float32)
    hdr = fits.Header()
    du = float(result.u_mm[1] - result.u_mm[0]) if len(result.u_mm) > 1 else 1.0
    dv = float(result.v_mm[1] - result.v_mm[0]) if len(result.v_mm) > 1 else 1.0
    for k, val, com in [("CTYPE1", "DET-U", "focal-plane u [mm] (unfolded x)"),
                        ("CTYPE2", "DET-V", "focal-plane v [mm] (y)"),
                        ("CUNIT1", "mm", ""), ("CUNIT2", "mm", ""),
                        ("CRPIX1", 1.0, ""), ("CRPIX2", 1.0, ""),
                        ("CRVAL1", float(result.u_mm[0]), ""), ("CRVAL2", float(result.v_mm[0]), ""),
                        ("CDELT1", du, ""), ("CDELT2", dv, ""),
                        ("BUNIT", "", "relative illumination, 1 on axis"),
                        ("THRU0", result.on_axis_throughput, "on-axis geometric throughput"),
                        ("RAYS", result.rays_per_field, "rays per field point"),
                        ("DESIGN", design_name, "optics design")]:
        hdr[k] = (val, com)
    for k, val in (extra_cards or {}).items():
        hdr[k] = val
    err = (result.throughput_err / result.on_axis_throughput).astype(np.float32)
    hdul = fits.HDUList([fits.PrimaryHDU(ri, hdr), fits.ImageHDU(err, name="ERR")])
    hdul.writeto(path, overwrite=True)
    return path


def read_fits(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u_mm, v_mm, relative_illumination[v, u]) from a map written by :func:`write_fits`."""
    from astropy.io import fits

    with fits.open(path) as hdul:
        h = hdul[0].header
        ri = np.asarray(hdul[0].data, dtype=np.float64)
    u = h["CRVAL1"] + (np.arange(ri.shape[1]) + 1 - h["CRPIX1"]) * h["CDELT1"]
    v = h["CRVAL2"] + (np.arange(ri.shape[0]) + 1 - h["CRPIX2"]) * h["CDELT2"]
    return u, v, ri


def plot(result: VignettingResult, path, design=None, title: str = ""):
    """Map of the relative illumination over the sensor, and its profile along both axes with the
    two-circle prediction for the diagonal alone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ri = result.relative_illumination
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ext = [result.u_mm[0], result.u_mm[-1], result.v_mm[0], result.v_mm[-1]]
    im = a1.imshow(ri, origin="lower", extent=ext, cmap="viridis", vmin=min(ri.min(), 0.9), vmax=1.0,
                   interpolation="bicubic", aspect="equal")
    cs = a1.contour(result.u_mm, result.v_mm, ri, levels=8, colors="w", linewidths=0.6)
    a1.clabel(cs, fmt="%.3f", fontsize=7)
    fig.colorbar(im, ax=a1, label="relative illumination")
    a1.set_xlabel("u [mm]")
    a1.set_ylabel("v [mm]")
    a1.set_title(title or "relative illumination over the sensor")
    j0, i0 = len(result.v_mm) // 2, len(result.u_mm) // 2
    a2.errorbar(np.abs(result.field_x_deg), ri[j0, :], result.throughput_err[j0, :] / result.on_axis_throughput,
                fmt="o", ms=3, label="traced, along u")
    a2.errorbar(np.abs(result.field_y_deg), ri[:, i0], result.throughput_err[:, i0] / result.on_axis_throughput,
                fmt="s", ms=3, label="traced, along v")
    if design is not None:
        th = np.linspace(0, max(np.abs(result.field_x_deg).max(), 1e-3), 100)
        a2.plot(th, [diagonal_two_circle(design, t) for t in th], "k--", lw=1,
                label="two-circle formula (diagonal only)")
    a2.set_xlabel("field angle [deg]")
    a2.set_ylabel("relative illumination")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8)
    a2.set_title(f"on-axis throughput {result.on_axis_throughput:.4f}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def cache_settings(grid, rays: int, wavelength_nm: float, obstruct: str, seed: int) -> dict:
    """The settings that key a cached map (:mod:`optics.cache`), with the counting kernel's precision: the
    float32 kernel's maps differ from the float64 kernel's by a few rays per field (module docstring), so a
    map cached by the older code is not returned for the newer one's settings."""
    return {"grid": grid, "rays": rays, "wavelength_nm": wavelength_nm, "obstruct": obstruct, "seed": seed,
            "kernel": "float32" if SINGLE else "float64"}


def cached_map_fits(design, grid: int = 9, rays: int = 200_000, seed: int = 0, use_cache: bool = True):
    """Path of a FITS vignetting map of ``design`` in the optics cache, ray-traced on first use.

    Starts Mitsuba itself (``optics.llvm.init_mitsuba``): this is an entry point for the scenes package.
    """
    from . import cache
    from .llvm import init_mitsuba

    settings = cache_settings(grid, rays, 550.0, "analytic", seed)

    def compute():
        tracer = SequentialTracer(design, init_mitsuba(), obstruct="analytic")
        return vignetting_map(tracer, grid, rays, 550.0, seed).to_json()

    data, _ = cache.cached_json("vignetting", design, settings, compute, use_cache=use_cache)
    path = cache.cache_dir() / f"vignetting-{cache.cache_key('vignetting', design, settings)}.fits"
    if not path.is_file() or not use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.fits")
        write_fits(VignettingResult.from_json(data), tmp, design.name)
        tmp.replace(path)
    return path
