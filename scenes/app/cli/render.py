"""``newtsim render`` (a scene to a FITS frame and its quick-look) and ``newtsim effects`` (the catalogue)."""

from __future__ import annotations

from pathlib import Path

import click

from detector import DetectorError, registry
from scenes.app.quicklook import write_png
from scenes.app.render import render as do_render

from .common import Outputs, json_target, load, warn, write_json


@click.command()
@click.argument("scene")
@click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False), help="output FITS file")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="frame seed (noise); default: scene's exposure.seed or random")
@click.option("--noiseless", is_flag=True, help="write expected electrons (float32) before any random draw")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a scene key, e.g. exposure.time_s=150")
@click.option("--png/--no-png", default=True, help="also write OUTPUT.png, a quick-look (default on)")
@click.option("--expected", is_flag=True, help="add the expected electrons as extension EXPECTED")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="threads (default: CPUs, at most 4)")
@click.option("--json", "json_out", default=None, help="write a JSON summary here ('-' for stdout)")
@click.option("--labels", "labels", default=None, metavar="FORMAT[,FORMAT]",
              help="per-source labels: coco, satnet, yolo (OUTPUT.coco.json, .satnet.json, .yolo.txt), fits (a "
                   "LABELS extension); docs/detection_bench.md")
def render(scene, output, seed, noiseless, sets, png, expected, workers, json_out, labels):
    """Render SCENE (a TOML file or a built-in name such as 'default') to a FITS frame.

    The FITS file, its PNG and the JSON are written together when the frame is complete (or not at all).
    """
    with Outputs(inputs=[scene]) as outs:
        fits_path = outs.file(output, "-o")
        png_path = outs.file(Path(output).with_suffix(".png"), "-o (its .png quick-look)") if png else None
        json_path = json_target(outs, json_out)
        fmts = label_formats(labels)
        label_paths = {f: outs.file(label_path(output, f), f"--labels {f}") for f in fmts if f != "fits"}
        sc = load(scene, sets, outs)
        summary = do_render(sc, fits_path, seed=seed, noiseless=noiseless, expected=expected, workers=workers,
                            labels=fmts, label_paths=label_paths, label_meta={"scene": str(scene)})
        summary["path"] = output
        if png:
            write_png(fits_path, png_path)
            summary["png"] = str(Path(output).with_suffix(".png"))
        if json_path is not None:
            write_json(summary, json_path)
    warn(summary["warnings"])
    if json_out == "-":
        write_json(summary, None)
    elif not json_out:
        click.echo(f"wrote {summary['path']} ({summary['shape'][1]}x{summary['shape'][0]}, seed {summary['seed']})"
                   + (f" and {summary['png']}" if png else ""), err=True)


def label_formats(text):
    """--labels text -> formats, or a usage error naming the option."""
    from scenes.app.bench.formats import parse_formats

    try:
        return parse_formats(text)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--labels") from None


def label_path(output, fmt: str) -> Path:
    """OUTPUT.fits -> OUTPUT.coco.json, OUTPUT.satnet.json, OUTPUT.yolo.txt."""
    ext = {"coco": ".coco.json", "satnet": ".satnet.json", "yolo": ".yolo.txt"}[fmt]
    p = Path(output)
    return p.with_name(p.stem + ext)


@click.command()
@click.argument("name", required=False)
def effects(name):
    """List the optional effects (or describe NAME: stages, parameters, units, bounds)."""
    reg = registry()
    if name is None:
        for n, cls in sorted(reg.items()):
            first = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
            click.echo(f"{n:16s} {first}")
        return
    if name not in reg:
        raise DetectorError(f"unknown effect {name!r}", key="effects", expected="one of " + ", ".join(sorted(reg)))
    write_json(reg[name].describe(), None)
