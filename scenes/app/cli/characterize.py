"""``newtsim characterize``: calibration frames (bias, dark, flat) -> the camera's parameters and a scene."""

from __future__ import annotations

from pathlib import Path

import click
import tomli_w

from detector import DetectorError
from detector.calplots import write_plots
from detector.characterize import camera_twin, emit_population_dict, write_twin
from detector.characterize import characterize as run

from .common import Outputs, json_target, progress_bar, write_json


@click.command()
@click.option("--bias", "bias", multiple=True, type=click.Path(), help="bias frames (two or more)")
@click.option("--dark", "dark", multiple=True, type=click.Path(), help="dark frames, several exposures")
@click.option("--flat", "flat", multiple=True, type=click.Path(), help="a pair of flats (photon transfer)")
@click.option("--json", "json_out", default=None, help="write the numbers as JSON here ('-' for stdout)")
@click.option("--emit-scene", "emit_scene", default=None,
              help="write a scene TOML of this camera (its bias, dark-rate and flat maps as FITS beside it)")
@click.option("--population", is_flag=True,
              help="with --emit-scene: the statistical description instead (no maps), for sensors like it")
@click.option("--plots", "plots", default=None, help="folder for the plots (created; its parent must exist)")
@click.option("--sigma", type=float, default=5.0, show_default=True, help="outlier (hot pixel) threshold [robust sigma]")
def characterize(bias, dark, flat, json_out, emit_scene, population, plots, sigma):
    """Calibration-frame analysis: bias, read noise, dark current, hot pixels, gain and PRNU.

    Accepts shell-style multiple files after one option: --bias b1.fits b2.fits --dark d1.fits ...
    The JSON, the scene and its maps and the plots are written together at the end (or not at all).
    """
    if not (bias or dark or flat):
        raise DetectorError("no calibration frame given", key="--bias/--dark/--flat",
                            expected="any of bias, dark and flat frames")
    if not _full_set(bias, dark):
        return _subset(bias, dark, flat, json_out, emit_scene, plots)
    with Outputs(inputs=[*bias, *dark, *flat]) as outs:
        json_path = json_target(outs, json_out)
        plots_dir = outs.folder(plots, "--plots") if plots else None
        scene_path = outs.file(emit_scene, "--emit-scene") if emit_scene else None
        if emit_scene and not population:  # the maps beside it (detector.characterize.write_twin)
            stem = Path(emit_scene).with_suffix("")
            for part in ("bias", "dark") + (("flat",) if flat else ()):
                outs.file(f"{stem}_{part}.fits", "--emit-scene (its maps)")
        with _Progress() as progress:
            result = _run_bounded(lambda: run(list(bias), list(dark), list(flat) or None, hot_sigma=sigma,
                                              progress=progress), bias)
            if scene_path is not None:
                maps, info = _run_bounded(lambda: camera_twin(result, list(bias), list(dark), list(flat) or None,
                                                              nsigma=sigma, progress=progress), bias)
                result["camera"] = info
                scene = emit_population_dict(result, info) if population else \
                    _run_bounded(lambda: write_twin(scene_path, result, maps, info), bias)
                scene_path.write_text(tomli_w.dumps(scene))
        if plots_dir is not None:
            result["plots"] = [str(Path(plots) / Path(p).name) for p in write_plots(result, plots_dir)]
        if json_path is not None:
            write_json(result, json_path)
    if json_out in (None, "-"):
        write_json(result if json_out else _summary(result), None)
    else:
        click.echo(f"wrote {json_out}" + (f", {emit_scene}" if emit_scene else "")
                   + (f", plots in {plots}" if plots else ""), err=True)


def _full_set(bias, dark) -> bool:
    """Bias frames and darks at two exposure times or more: the full analysis."""
    if not bias or not dark:
        return False
    if not all(Path(p).is_file() for p in [*bias, *dark]):
        return True  # the full path checks the outputs first, then names the first missing input
    from scenes.app.init.calib import _exptime

    return len({_exptime(p) for p in dark}) >= 2


def _subset(bias, dark, flat, json_out, emit_scene, plots) -> None:
    """Any other subset: what it measures, and one line for each thing it cannot."""
    from scenes.app.init.calib import characterize_subset

    if emit_scene or plots:
        raise DetectorError("--emit-scene / --plots need the full analysis", key="--emit-scene/--plots",
                            expected="bias frames and darks at two exposure times or more (or `newtsim init` "
                            "for a scene from a light frame and any calibration frames)")
    with Outputs(inputs=[*bias, *dark, *flat]) as outs:
        json_path = json_target(outs, json_out)
        result = characterize_subset(bias, dark, flat)
        if json_path is not None:
            write_json(result, json_path)
    if json_out in (None, "-"):
        write_json(result, None)
    for line in result["not_measured"]:
        click.echo(f"not measured: {line}", err=True)
    for line in result["warnings"]:
        click.echo(f"warning: {line}", err=True)


def _run_bounded(fn, bias):
    """``fn()``, with running out of memory turned into one line (exit 2) instead of a traceback."""
    try:
        return fn()
    except MemoryError:
        raise DetectorError("out of memory", key="characterize", file=str(bias[0]) if bias else None,
                            expected="more free memory (the analysis needs about 1 GiB for a 151-Mpixel "
                                     "set), or smaller frames") from None


class _Progress:
    """A rich progress bar on stderr for the band passes (one task per pass), only when stderr is a terminal."""

    def __init__(self):
        import sys

        self.bar = progress_bar("[bold]characterize[/bold] {task.description}") if sys.stderr.isatty() else None
        self.tasks: dict = {}

    def __enter__(self):
        if self.bar:
            self.bar.__enter__()
            return self
        return None

    def __exit__(self, *exc):
        if self.bar:
            self.bar.__exit__(*exc)
        return False

    def __call__(self, label: str, done: int, total: int) -> None:
        if total <= 1:  # one band: a small frame, done in a moment
            return
        if label not in self.tasks:
            self.tasks[label] = self.bar.add_task(label, total=total)
        self.bar.update(self.tasks[label], completed=done)


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
