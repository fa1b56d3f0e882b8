"""``newtsim optics vignetting|psf|pst``: the ray-traced optics products (contract in DESIGN.md).

Lives in ``scenes`` because the polychromatic PSF is weighted by a detector's QE and ``optics`` must not
import ``detector``. Results are cached by a hash of the design's content and the settings
(:mod:`optics.cache`); ``--no-cache`` recomputes.
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from pathlib import Path

import click

from optics.design import OpticsError, load_design

from .common import Outputs, json_target, write_json


@contextmanager
def _progress(label: str, enabled: bool = True):
    """A rich progress bar on stderr; yields a callable(done, total)."""
    if not enabled:
        yield None
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(TextColumn(label), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True),
                  transient=True) as bar:
        task = bar.add_task(label, total=None)

        def update(done, total):
            bar.update(task, completed=done, total=total)

        yield update


def _mitsuba():
    from optics.llvm import init_mitsuba

    return init_mitsuba()


def _design(name):
    return load_design(name)


def _perturbation(d) -> dict:
    """The design's non-zero ``[perturbation]`` entries (reported in the JSON; empty when nominal)."""
    return {k: v for k, v in d.perturbation.model_dump().items() if v}


def _echo_json(obj, path):
    write_json(obj, path)


def _outputs(design: str) -> Outputs:
    """The command's outputs; a design TOML given as a path is an input (never overwritten)."""
    return Outputs(inputs=[design] if os.path.isfile(design) else [])


@click.group()
def optics():
    """Ray tracing of the telescope (Mitsuba 3, llvm): vignetting, psf, pst.

    DESIGN is a built-in design name (art, bare, ...) or a path to a design TOML.
    """


@optics.command()
@click.argument("design")
@click.option("--grid", default=9, show_default=True, type=click.IntRange(1, 101), help="field points per axis")
@click.option("--rays", default=1_000_000, show_default=True, type=click.IntRange(100, 10 ** 9),
              help="rays per field point over the full aperture")
@click.option("--wavelength-nm", default=550.0, show_default=True, type=click.FloatRange(200, 2000))
@click.option("--obstruct", type=click.Choice(["analytic", "mesh"]), default="analytic", show_default=True,
              help="mechanical obstructions as exact solids or as Mitsuba meshes (BVH)")
@click.option("--json", "json_out", default=None, help="write the JSON here ('-' for stdout)")
@click.option("--plot", "plot_out", default=None, type=click.Path(dir_okay=False), help="PNG map and profiles")
@click.option("--fits", "fits_out", default=None, type=click.Path(dir_okay=False),
              help="FITS map of the relative illumination (for scenes)")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0))
@click.option("--no-cache", is_flag=True, help="recompute even if a cached result exists")
def vignetting(design, grid, rays, wavelength_nm, obstruct, json_out, plot_out, fits_out, seed, no_cache):
    """Relative illumination over the focal plane and the on-axis geometric throughput."""
    from optics import cache
    from optics import vignetting as vig
    from optics.sequential import SequentialTracer

    with _outputs(design) as outs:
        json_path = json_target(outs, json_out)
        plot_path = outs.file(plot_out, "--plot") if plot_out else None
        fits_path = outs.file(fits_out, "--fits") if fits_out else None
        d = _design(design)
        settings = vig.cache_settings(grid, rays, wavelength_nm, obstruct, seed)

        def compute():
            tracer = SequentialTracer(d, _mitsuba(), obstruct=obstruct)
            with _progress(f"vignetting {d.name}") as prog:
                return vig.vignetting_map(tracer, grid, rays, wavelength_nm, seed, progress=prog).to_json()

        out, hit = cache.cached_json("vignetting", d, settings, compute, use_cache=not no_cache)
        out = {"design": d.name, "perturbation": _perturbation(d), **out, "cached": hit}
        res = vig.VignettingResult.from_json(out)
        if plot_path is not None:
            vig.plot(res, plot_path, d, title=f"{d.name}: relative illumination")
        if fits_path is not None:
            vig.write_fits(res, fits_path, d.name)
        if json_path is not None:
            _echo_json(out, json_path)
    if json_out == "-" or not (json_out or plot_out or fits_out):
        _echo_json(out, None)
    elif not json_out:
        click.echo(f"on-axis throughput {out['on_axis_throughput']:.4f}, corner relative illumination "
                   f"{out['corner_relative_illumination']:.4f}", err=True)


def _band(preset: str | None, wavelength_nm: float | None, n: int):
    """Wavelengths and weights: one wavelength, or the band of a detector preset weighted by its QE."""
    import numpy as np

    if preset is None:
        return [float(wavelength_nm or 550.0)], [1.0]
    from detector.sensor import make_sensor

    sensor = make_sensor(preset)
    lo, hi = min(sensor.qe_wavelength_nm), max(sensor.qe_wavelength_nm)
    wl = np.linspace(lo + (hi - lo) / (2 * n), hi - (hi - lo) / (2 * n), n)
    w = np.asarray(sensor.qe_at(wl), dtype=float)
    keep = w > 0.02 * w.max()
    return wl[keep].round(1).tolist(), (w[keep] / w[keep].sum()).round(6).tolist()


@optics.command()
@click.argument("design")
@click.option("--field-deg", nargs=2, type=float, required=True, metavar="X Y", help="field angles [deg]")
@click.option("--wavelength-nm", default=None, type=click.FloatRange(200, 2000), help="one wavelength (default 550)")
@click.option("--band", "band", default=None, type=click.Choice(["imx411", "ml11002"]),
              help="polychromatic: the detector preset's band weighted by its QE")
@click.option("--band-samples", default=7, show_default=True, type=click.IntRange(2, 40))
@click.option("--geometric", is_flag=True, help="ray spot only (rms, extents), no diffraction")
@click.option("--seeing-arcsec", default=0.0, show_default=True, type=click.FloatRange(0, 30),
              help="convolve with seeing of this FWHM")
@click.option("--jitter-arcsec", default=0.0, show_default=True, type=click.FloatRange(0, 30),
              help="convolve with Gaussian pointing jitter of this rms")
@click.option("--json", "json_out", default=None, help="write the JSON here ('-' for stdout)")
@click.option("--fits", "fits_out", default=None, type=click.Path(dir_okay=False), help="PSF image (FITS)")
@click.option("--no-cache", is_flag=True)
def psf(design, field_deg, wavelength_nm, band, band_samples, geometric, seeing_arcsec, jitter_arcsec,
        json_out, fits_out, no_cache):
    """The PSF at one field point: encircled energy, FWHM, centroid (and the geometric spot)."""
    with _outputs(design) as outs:
        json_path = json_target(outs, json_out)
        fits_path = outs.file(fits_out, "--fits") if fits_out else None
        out = _psf(design, field_deg, wavelength_nm, band, band_samples, geometric, seeing_arcsec, jitter_arcsec,
                   fits_path, no_cache)
        if json_path is not None:
            _echo_json(out, json_path)
    if json_path is None:
        _echo_json(out, None)


def _psf(design, field_deg, wavelength_nm, band, band_samples, geometric, seeing_arcsec, jitter_arcsec, fits_out,
         no_cache) -> dict:
    d = _design(design)
    if band and wavelength_nm:
        raise OpticsError("--band and --wavelength-nm exclude each other (one wavelength, or a QE-weighted band)")
    from optics import cache
    from optics import psf as psfmod
    from optics.sequential import SequentialTracer

    wl, w = _band(band, wavelength_nm, band_samples)
    settings = {"field_deg": list(field_deg), "wavelengths_nm": wl, "weights": w, "geometric": geometric,
                "seeing": seeing_arcsec, "jitter": jitter_arcsec}
    state = {}

    def compute():
        tracer = SequentialTracer(d, _mitsuba())
        t0 = time.perf_counter()
        try:
            res = psfmod.compute_psf(tracer, field_deg=tuple(field_deg), wavelengths_nm=wl, weights=w,
                                     geometric=geometric, seeing_fwhm_arcsec=seeing_arcsec,
                                     jitter_rms_arcsec=jitter_arcsec)
        except ValueError as exc:
            if "no ray reached" not in str(exc):
                raise
            raise OpticsError(f"{d.name}: key '--field-deg': {exc} (expected a field angle inside the "
                              "telescope's field of view)") from None
        state["result"] = res
        return {**res.to_json(), "seconds": round(time.perf_counter() - t0, 3)}

    # a FITS image needs the PSF itself, which the JSON cache does not hold: compute (and store) it
    out, hit = cache.cached_json("psf", d, settings, compute, use_cache=not no_cache, read=not fits_out)
    out = {"design": d.name, "perturbation": _perturbation(d), "field_deg": list(field_deg),
           "wavelengths_nm": wl, "weights": w, **out, "cached": hit}
    if fits_out:
        psfmod.write_psf_fits(state["result"], fits_out)
    return out


@optics.command()
@click.argument("design")
@click.option("--angles", required=True, help="off-axis source angles [deg], comma separated, e.g. 5,10,30,60,90")
@click.option("--azimuth-deg", default=0.0, show_default=True, help="source azimuth about the axis [deg]")
@click.option("--rays", default=400_000, show_default=True, type=click.IntRange(1000, 10 ** 10),
              help="detector paths per angle")
@click.option("--wavelength-nm", default=550.0, show_default=True, type=click.FloatRange(200, 2000))
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0))
@click.option("--json", "json_out", default=None, help="write the JSON here ('-' for stdout)")
@click.option("--plot", "plot_out", default=None, type=click.Path(dir_okay=False), help="PST curve (PNG)")
@click.option("--no-cache", is_flag=True)
def pst(design, angles, azimuth_deg, rays, wavelength_nm, seed, json_out, plot_out, no_cache):
    """Point-source transmittance PST(angle) with a 1-sigma Monte-Carlo error per angle."""
    with _outputs(design) as outs:
        json_path = json_target(outs, json_out)
        plot_path = outs.file(plot_out, "--plot") if plot_out else None
        out = _pst(design, angles, azimuth_deg, rays, wavelength_nm, seed, plot_path, no_cache)
        if json_path is not None:
            _echo_json(out, json_path)
    if json_path is None:
        _echo_json(out, None)


def _pst(design, angles, azimuth_deg, rays, wavelength_nm, seed, plot_out, no_cache) -> dict:
    d = _design(design)
    try:
        angle_list = [float(a) for a in angles.split(",") if a.strip()]
    except ValueError:
        raise OpticsError(f"--angles {angles!r}: expected comma-separated degrees, e.g. 5,10,30") from None
    if not angle_list or any(not 0 < a <= 180 for a in angle_list):
        raise OpticsError(f"--angles {angles!r}: each angle must be in (0, 180] degrees")
    settings = {"angles": angle_list, "azimuth": azimuth_deg, "rays": rays, "wavelength_nm": wavelength_nm,
                "seed": seed}
    from optics import cache, straylight

    def compute():
        mi = _mitsuba()
        with _progress(f"PST {d.name}") as prog:
            res = straylight.pst_curve(d, mi, angle_list, azimuth_deg=azimuth_deg, rays=rays, seed=seed,
                                       wavelength_nm=wavelength_nm, progress=prog)
        return res.to_json()

    out, hit = cache.cached_json("pst", d, settings, compute, use_cache=not no_cache)
    out = {"design": d.name, **out, "cached": hit}
    if plot_out:
        straylight.plot_pst({d.name: straylight.PSTResult.from_json(out)}, plot_out)
    return out


@optics.command()
@click.argument("design")
@click.option("--plot", "plot_out", default=None, type=click.Path(dir_okay=False),
              help="2-D layout (x-z section) with ray fans (PNG)")
@click.option("--export", "export_out", default=None, type=click.Path(dir_okay=False),
              help="the telescope's meshes as GLB (named parts), PLY, STL or OBJ for any 3-D viewer")
def layout(design, plot_out, export_out):
    """The telescope's geometry: a layout drawing with traced rays, and/or its meshes for a 3-D viewer."""
    from optics.layout import make_layout
    from optics.meshes import export, telescope_parts

    if not (plot_out or export_out):
        raise OpticsError("optics layout: give --plot OUT.png and/or --export OUT.glb")
    with _outputs(design) as outs:
        export_path = outs.file(export_out, "--export") if export_out else None
        plot_path = outs.file(plot_out, "--plot") if plot_out else None
        d = _design(design)
        if export_path is not None:
            export(telescope_parts(make_layout(d)), export_path)
        if plot_path is not None:
            from optics.layout_plot import plot_layout
            from optics.sequential import SequentialTracer

            plot_layout(SequentialTracer(d, _mitsuba()), plot_path)
    for p in (export_out, plot_out):
        if p:
            click.echo(f"wrote {p}", err=True)


@optics.command()
@click.argument("design")
@click.option("--goal", type=click.Choice(["corrector", "baffle"]), required=True,
              help="corrector: smallest RMS spot over field and band (gradients); baffle: lowest PST at "
                   "--angles without vignetting the field (derivative-free, common random numbers)")
@click.option("-o", "--output", "out_toml", required=True, type=click.Path(dir_okay=False),
              help="the optimised design (TOML)")
@click.option("--json", "json_out", default=None, help="write the JSON report here ('-' for stdout)")
@click.option("--plot", "plot_out", default=None, type=click.Path(dir_okay=False), help="before/after plot (PNG)")
@click.option("--band", default="imx411", show_default=True, type=click.Choice(["imx411", "ml11002", "none"]),
              help="corrector: the detector preset's band weighted by its QE ('none': --wavelength-nm)")
@click.option("--band-samples", default=6, show_default=True, type=click.IntRange(1, 20))
@click.option("--wavelength-nm", default=550.0, show_default=True, type=click.FloatRange(200, 2000))
@click.option("--grid", default=3, show_default=True, type=click.IntRange(1, 7),
              help="corrector: field points per axis over the sensor")
@click.option("--rays", default=None, type=click.IntRange(100, 10 ** 8),
              help="rays per field point (corrector, default 2000) or PST paths per angle (baffle, default 100000)")
@click.option("--iterations", default=None, type=click.IntRange(1, 1000),
              help="corrector: least-squares evaluations (default 20); baffle: PST evaluations (default 30)")
@click.option("--angles", default=None, help="baffle: off-axis Sun angles [deg], comma separated, e.g. 10,20")
@click.option("--seed", default=0, show_default=True)
def optimize(design, goal, out_toml, json_out, plot_out, band, band_samples, wavelength_nm, grid, rays, iterations,
             angles, seed):
    """Optimise a design and write it as a new design TOML (with a before/after report)."""
    d = _design(design)
    inputs = [design] if Path(design).is_file() else []
    with Outputs(inputs=inputs) as outs:
        toml_path = outs.file(out_toml, "--output")
        json_path = json_target(outs, json_out)
        plot_path = outs.file(plot_out, "--plot") if plot_out else None
        report = _optimize(d, design, goal, plot_path, band, band_samples, wavelength_nm, grid, rays, iterations,
                           angles, seed, toml_path)
        report["output"] = str(out_toml)
        if json_path is not None:
            _echo_json(report, json_path)
    if json_out == "-":
        _echo_json(report, None)
    click.echo(f"wrote {out_toml}", err=True)


def _optimize(d, design, goal, plot_out, band, band_samples, wavelength_nm, grid, rays, iterations, angles, seed,
              out_toml) -> dict:
    """The optimisation of ``newtsim optics optimize``: writes the new design to ``out_toml``, returns the report."""
    from optics import optimize as opt

    mi = _mitsuba()
    t0 = time.perf_counter()
    if goal == "corrector":
        if angles:
            raise OpticsError("--angles belongs to --goal baffle")
        if not d.corrector.enabled:
            raise OpticsError(f"{design}: key 'corrector.enabled': --goal corrector needs a design with a corrector")
        wl, w = _band(None if band == "none" else band, wavelength_nm, band_samples)
        with _progress(f"optimise corrector {d.name}") as prog:
            res = opt.optimize_corrector(d, mi, wl, w, grid=grid, n_rays=rays or 2000, max_iter=iterations or 20,
                                         seed=seed, progress=prog)
        report = {"design": d.name, "wavelengths_nm": wl, "weights": w, **res.to_json()}
        comment = (f"{res.design.name}: corrector of '{d.name}' optimised by `newtsim optics optimize --goal "
                   f"corrector` (band {band}, {grid}x{grid} field points)\nmean RMS spot radius "
                   f"{report['mean_before_um']} -> {report['mean_after_um']} um (independent check)")
        if plot_out:
            opt.plot_corrector(res, plot_out, title=f"{d.name}: corrector optimisation (band {band})")
    else:
        if not angles:
            raise OpticsError("--goal baffle needs --angles (off-axis Sun angles [deg], e.g. 10,20)")
        try:
            angle_list = [float(a) for a in angles.split(",") if a.strip()]
        except ValueError:
            raise OpticsError(f"--angles {angles!r}: expected comma-separated degrees, e.g. 10,20") from None
        if not angle_list or any(not 0 < a <= 180 for a in angle_list):
            raise OpticsError(f"--angles {angles!r}: each angle must be in (0, 180] degrees")
        with _progress(f"optimise baffle {d.name}") as prog:
            res = opt.optimize_baffle(d, mi, angle_list, rays=rays or 100_000, max_evals=iterations or 30,
                                      seed=seed, wavelength_nm=wavelength_nm, progress=prog)
        report = {"design": d.name, **res.to_json()}
        comment = (f"{res.design.name}: baffle of '{d.name}' optimised by `newtsim optics optimize --goal baffle "
                   f"--angles {angles}`\nPST ratio after/before {report['pst_ratio']}, corner relative "
                   f"illumination {report['corner_relative_illumination_before']} -> "
                   f"{report['corner_relative_illumination_after']}")
        if plot_out:
            opt.plot_baffle(res, plot_out, title=f"{d.name}: baffle optimisation at {angles} deg")
    Path(out_toml).write_text(opt.design_toml(res.design, comment))
    report["wall_s"] = round(time.perf_counter() - t0, 2)
    return report
