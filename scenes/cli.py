"""The ``newtsim`` command line (contract in DESIGN.md).

User mistakes (bad scene keys, missing files, out-of-range parameters) print one line naming the file, the
key and what was expected, and exit with status 2; never a traceback.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from detector import DetectorError
from detector.jsonable import jsonable
from optics.design import OpticsError

from .cli_batch import batch as batch_command
from .cli_compare import compare as compare_cmd
from .cli_compare import diagnose as diagnose_cmd
from .cli_optics import optics as optics_group

EXIT_USER_ERROR = 2


class _Group(click.Group):
    """Turns user errors raised anywhere below into one line on stderr."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (DetectorError, OpticsError) as exc:
            click.echo(f"newtsim: error: {exc}", err=True)
            ctx.exit(EXIT_USER_ERROR)


def _write_json(obj, path: str | None) -> None:
    text = json.dumps(jsonable(obj), indent=2, allow_nan=False)
    if path in (None, "-"):
        click.echo(text)
    else:
        Path(path).write_text(text + "\n")


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="newtsim")
def cli():
    """newtsim: what a Newtonian telescope with a CCD or CMOS camera records.

    \b
    render        a scene to a FITS frame (+ PNG quick-look)
    batch         many frames (sweeps, time sequences, Monte-Carlo draws) on Dask, resumable
    characterize  bias/dark/flat calibration frames -> camera parameters (+ a scene that reproduces it)
    effects       the catalogue of optional effects, their parameters and units
    compare       model vs measured frame: chi2, residuals per region/row/column/source, HTML report
    diagnose      which physical effect the model lacks, ranked by delta BIC; --apply adds it
    optics        vignetting | psf | pst: ray tracing of the telescope (Mitsuba 3, llvm)
    """


@cli.command()
@click.argument("scene")
@click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False), help="output FITS file")
@click.option("--seed", type=int, default=None, help="frame seed (noise); default: scene's exposure.seed or random")
@click.option("--noiseless", is_flag=True, help="write expected electrons (float32) before any random draw")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a scene key, e.g. exposure.time_s=150")
@click.option("--png/--no-png", default=True, help="also write OUTPUT.png, a quick-look (default on)")
@click.option("--expected", is_flag=True, help="add the expected electrons as extension EXPECTED")
@click.option("--workers", type=int, default=None, help="threads (default: CPUs, at most 4)")
@click.option("--json", "json_out", default=None, help="write a JSON summary here ('-' for stdout)")
def render(scene, output, seed, noiseless, sets, png, expected, workers, json_out):
    """Render SCENE (a TOML file or a built-in name such as 'default') to a FITS frame."""
    from .quicklook import write_png
    from .render import render as do_render
    from .scene import load_scene

    sc = load_scene(scene, list(sets))
    summary = do_render(sc, output, seed=seed, noiseless=noiseless, expected=expected, workers=workers)
    for w in summary["warnings"]:
        click.echo(f"newtsim: warning: {w}", err=True)
    if png:
        summary["png"] = str(write_png(output, Path(output).with_suffix(".png")))
    if json_out:
        _write_json(summary, json_out)
    else:
        click.echo(f"wrote {summary['path']} ({summary['shape'][1]}x{summary['shape'][0]}, seed {summary['seed']})"
                   + (f" and {summary['png']}" if png else ""), err=True)


@cli.command()
@click.option("--bias", "bias", multiple=True, required=True, type=click.Path(), help="bias frames (two or more)")
@click.option("--dark", "dark", multiple=True, required=True, type=click.Path(), help="dark frames, several exposures")
@click.option("--flat", "flat", multiple=True, type=click.Path(), help="a pair of flats (photon transfer)")
@click.option("--json", "json_out", default=None, help="write the numbers as JSON here ('-' for stdout)")
@click.option("--emit-scene", "emit_scene", default=None,
              help="write a scene TOML of this camera (its bias, dark-rate and flat maps as FITS beside it)")
@click.option("--population", is_flag=True,
              help="with --emit-scene: the statistical description instead (no maps), for sensors like it")
@click.option("--plots", "plots", default=None, type=click.Path(file_okay=False), help="folder for the plots")
@click.option("--sigma", default=5.0, show_default=True, help="outlier (hot pixel) threshold [robust sigma]")
def characterize(bias, dark, flat, json_out, emit_scene, population, plots, sigma):
    """Calibration-frame analysis: bias, read noise, dark current, hot pixels, gain and PRNU.

    Accepts shell-style multiple files after one option: --bias b1.fits b2.fits --dark d1.fits ...
    """
    from detector.characterize import characterize as run
    from detector.characterize import emit_scene_dict

    result = run(list(bias), list(dark), list(flat) or None, hot_sigma=sigma)
    if plots:
        from detector.calplots import write_plots

        Path(plots).mkdir(parents=True, exist_ok=True)
        result["plots"] = [str(p) for p in write_plots(result, plots)]
    if emit_scene:
        import tomli_w

        from detector.characterize import camera_twin, emit_population_dict, write_twin

        out = Path(emit_scene)
        if not out.parent.is_dir():
            raise DetectorError("folder does not exist", key="--emit-scene", file=str(out),
                                expected="a TOML path in an existing folder")
        maps, info = camera_twin(result, list(bias), list(dark), list(flat) or None, nsigma=sigma)
        result["camera"] = info
        scene = emit_population_dict(result, info) if population else write_twin(out, result, maps, info)
        out.write_text(tomli_w.dumps(scene))
    _write_json(result if json_out else _summary(result), json_out)
    if json_out not in (None, "-"):
        click.echo(f"wrote {json_out}" + (f", {emit_scene}" if emit_scene else "")
                   + (f", plots in {plots}" if plots else ""), err=True)


def _summary(result: dict) -> dict:
    keep = ("bias", "read_noise", "dark", "gain", "hot_pixels")
    return {k: result[k] for k in keep if k in result}


@cli.command()
@click.argument("name", required=False)
def effects(name):
    """List the optional effects (or describe NAME: stages, parameters, units, bounds)."""
    from detector import registry

    reg = registry()
    if name is None:
        for n, cls in sorted(reg.items()):
            first = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
            click.echo(f"{n:16s} {first}")
        return
    if name not in reg:
        raise DetectorError(f"unknown effect {name!r}", key="effects", expected="one of " + ", ".join(sorted(reg)))
    _write_json(reg[name].describe(), None)


cli.add_command(compare_cmd, name="compare")
cli.add_command(diagnose_cmd, name="diagnose")
cli.add_command(optics_group, name="optics")
cli.add_command(batch_command, name="batch")


_MULTI_FILE_OPTIONS = ("--bias", "--dark", "--flat")


def expand_multi_file_options(argv: list[str]) -> list[str]:
    """``--bias a b --dark c d`` (the contract's form) -> ``--bias a --bias b --dark c --dark d`` for click."""
    out, current = [], None
    for tok in argv:
        if tok in _MULTI_FILE_OPTIONS:
            current = tok
            out.append(tok)
        elif current and not tok.startswith("-") and out[-1] != current:
            out += [current, tok]
        else:
            if tok.startswith("-"):
                current = None
            out.append(tok)
    return out


def main(argv=None):
    """Console-script entry point."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["characterize"]:
        argv = expand_multi_file_options(argv)
    try:
        cli.main(args=argv, prog_name="newtsim", standalone_mode=True)
    except KeyboardInterrupt:
        click.echo("newtsim: interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()
