"""``newtsim init``: a scene (and the files it names, beside it) from a measured frame.

    newtsim init FRAME.fits -o SCENE.toml [--bias F ...] [--dark F ...] [--flat F ...]
        [--catalog frame|builtin|gaia|PATH] [--design DESIGN | --focal-length-mm F --f-number N [--obstruction R]]
        [--hdu N] [--json SUMMARY.json]

then ``newtsim compare SCENE.toml FRAME.fits``. Every value's source (measured | header | assumed) is a comment
in the scene and a line of the summary JSON.
"""

from __future__ import annotations

from pathlib import Path

import click

from scenes.app.init import init_scene, scene_text, write_file

from .common import Outputs, json_target, write_json

#: the files a scene written by init may name, beside it (suffixes of the scene's stem)
SIDE_FILES = ("_stars.csv", "_mask.fits", "_flat.fits", "_dark.fits", "_optics.toml")


def _hdu(value):
    if value is None:
        return None
    try:
        return int(value)
    except ValueError:
        return value


@click.command()
@click.argument("frame", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False), help="the scene TOML to write")
@click.option("--bias", multiple=True, type=click.Path(dir_okay=False), help="a bias frame (repeatable)")
@click.option("--dark", multiple=True, type=click.Path(dir_okay=False), help="a dark frame (repeatable)")
@click.option("--flat", multiple=True, type=click.Path(dir_okay=False), help="a flat frame (repeatable; two for the gain)")
@click.option("--catalog", default="frame", show_default=True,
              help="frame (the frame's own stars), builtin, gaia, or a star table (CSV/ECSV/FITS)")
@click.option("--design", default=None, help="a design TOML or built-in design (instead of --focal-length-mm)")
@click.option("--focal-length-mm", type=click.FloatRange(min=1.0), default=None, help="focal length [mm]")
@click.option("--f-number", type=click.FloatRange(min=0.5), default=None, help="focal ratio f/D")
@click.option("--obstruction", type=click.FloatRange(0.0, 0.9), default=0.0, show_default=True,
              help="central obstruction, fraction of the aperture diameter (0: lens or refractor)")
@click.option("--hdu", default=None, help="the image HDU of a multi-extension frame (index or EXTNAME)")
@click.option("--json", "json_out", default=None, help="write the summary JSON here ('-' for stdout)")
def init(frame, output, bias, dark, flat, catalog, design, focal_length_mm, f_number, obstruction, hdu, json_out):
    """A scene of FRAME (camera, WCS, sky, PSF, stars, mask) for `newtsim compare SCENE FRAME`."""
    if design and (focal_length_mm or f_number):
        raise click.UsageError("give --design or --focal-length-mm/--f-number, not both")
    inputs = [frame, *bias, *dark, *flat] + ([catalog] if catalog not in ("frame", "builtin", "gaia") else [])
    stem = Path(output).stem
    with Outputs(inputs=inputs) as outs:
        scene_path = outs.file(output, "-o")
        json_path = json_target(outs, json_out)
        side = {suf: outs.optional(Path(output).with_name(stem + suf), "-o (a file the scene names)") for suf in SIDE_FILES}
        res = init_scene(frame, stem, bias=bias, dark=dark, flat=flat, catalog=catalog, design=design,
                         focal_length_mm=focal_length_mm, f_number=f_number, obstruction=obstruction, hdu=_hdu(hdu))
        for name, (kind, payload) in res.files.items():
            write_file(kind, payload, side[name[len(stem):]])
        notes = res.summary["notes"] + res.summary["calibration"]["missing"]
        scene_path.write_text(scene_text(res.scene, res.sources, notes))
        _validate(scene_path, res)
        res.summary["scene"] = output
        if json_path is not None:
            write_json(res.summary, json_path)
    if json_out == "-":
        write_json(res.summary, None)
    s = res.summary
    psf = s["psf"]
    click.echo(f"wrote {output}: {s['shape'][1]}x{s['shape'][0]} px {s['frame_type']} frame, "
               f"{res.scene['detector']['kind']}, gain {res.scene['detector']['gain_e_per_adu']:.4g} e-/ADU, "
               f"PSF FWHM {psf.get('fwhm_px', float('nan')):.3g} px, catalogue {s['catalogue'].get('kind', '-')} "
               f"({s['catalogue'].get('n', s['catalogue'].get('n_matched', 0))} stars), "
               f"{100 * s['mask']['masked_fraction']:.2g} % masked; {s['seconds']:.1f} s", err=True)
    for line in s["calibration"]["missing"]:
        click.echo(f"  not measured: {line}", err=True)
    for line in s["notes"]:
        click.echo(f"  note: {line}", err=True)


def _validate(path: Path, res) -> None:
    """Load the written scene (in its staging folder, beside its files): an observer whose site puts the pointing
    below the horizon at the header's time is dropped with a note, anything else is an error."""
    from scenes.scene import load_scene

    try:
        load_scene(str(path))
    except Exception as exc:
        text = str(exc).lower()
        if "observer" in res.scene and ("observer" in text or "horizon" in text):
            res.scene.pop("observer", None)
            res.summary["notes"].append(f"[observer] left out: {str(exc).splitlines()[0]}")
            path.write_text(scene_text(res.scene, res.sources, res.summary["notes"]))
            load_scene(str(path))
        else:
            raise
