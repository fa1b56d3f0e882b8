"""``newtsim characterize``: calibration frames (bias, dark, flat) -> the camera's parameters and a scene."""

from __future__ import annotations

from pathlib import Path

import click
import tomli_w

from detector import DetectorError
from detector.calplots import write_plots
from detector.characterize import camera_twin, emit_population_dict, write_twin
from detector.characterize import characterize as run

from .common import write_json


@click.command()
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
    result = run(list(bias), list(dark), list(flat) or None, hot_sigma=sigma)
    if plots:
        Path(plots).mkdir(parents=True, exist_ok=True)
        result["plots"] = [str(p) for p in write_plots(result, plots)]
    if emit_scene:
        out = Path(emit_scene)
        if not out.parent.is_dir():
            raise DetectorError("folder does not exist", key="--emit-scene", file=str(out),
                                expected="a TOML path in an existing folder")
        maps, info = camera_twin(result, list(bias), list(dark), list(flat) or None, nsigma=sigma)
        result["camera"] = info
        scene = emit_population_dict(result, info) if population else write_twin(out, result, maps, info)
        out.write_text(tomli_w.dumps(scene))
    write_json(result if json_out else _summary(result), json_out)
    if json_out not in (None, "-"):
        click.echo(f"wrote {json_out}" + (f", {emit_scene}" if emit_scene else "")
                   + (f", plots in {plots}" if plots else ""), err=True)


def _summary(result: dict) -> dict:
    keep = ("bias", "read_noise", "dark", "gain", "hot_pixels")
    return {k: result[k] for k in keep if k in result}


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
