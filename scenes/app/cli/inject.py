"""``newtsim inject`` (objects drawn into a measured frame) and ``newtsim detect`` (the baseline detector);
docs/detection_bench.md."""

from __future__ import annotations

import click

from .common import Outputs, json_target, warn, write_json
from .render import label_formats, label_path


def _range(text: str, option: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(":"))
    except ValueError:
        raise click.BadParameter(f"{text!r} is not MIN:MAX (two numbers)", param_hint=option) from None
    if not 0 <= lo <= hi:
        raise click.BadParameter(f"{text!r}: need 0 <= MIN <= MAX", param_hint=option)
    return lo, hi


@click.command()
@click.argument("frame", type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="output FITS file")
@click.option("--objects", type=click.Path(exists=True, dir_okay=False), default=None,
              help="objects TOML ([[objects]] with x0,y0,x1,y1 | x,y | ra_deg,dec_deg[,rates] and flux_e | snr)")
@click.option("--random", "n_random", type=click.IntRange(min=1), default=None, help="N random objects")
@click.option("--snr", "snr_range", default=None, metavar="MIN:MAX", help="random objects: matched-filter SNR range")
@click.option("--rate", "rate_range", default=None, metavar="MIN:MAX",
              help="random objects: angular rate range [arcsec/s] (0: points)")
@click.option("--psf", default="measured", show_default=True,
              help="measured (from the frame's stars), a FWHM in arcsec (2.5) or in pixels (3.2px)")
@click.option("--gain", type=click.FloatRange(min=0, min_open=True), default=None,
              help="[e-/ADU] (default: header EGAIN/GAIN/GAINA+B, else 1 with a warning)")
@click.option("--saturation", type=float, default=None, help="[ADU] (default: header SATURATE..., else the data type's maximum)")
@click.option("--exptime", type=click.FloatRange(min=0, min_open=True), default=None, help="[s] (default: header EXPTIME)")
@click.option("--pixel-scale", type=click.FloatRange(min=0, min_open=True), default=None,
              help="[arcsec/px]: for a frame without a WCS (objects then in pixels)")
@click.option("--hdu", default=None, help="image HDU (index or EXTNAME; default: the first image with a WCS)")
@click.option("--bayer", default=None, help="CFA pattern RGGB|GRBG|GBRG|BGGR|none (default: header BAYERPAT...)")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="seed of the random objects and the shot noise")
@click.option("--labels", "labels", default=None, metavar="FORMAT[,FORMAT]",
              help="coco, satnet, yolo (OUTPUT.coco.json ...), fits (a LABELS extension)")
@click.option("--json", "json_out", default=None, help="write a JSON summary here ('-' for stdout)")
def inject(frame, output, objects, n_random, snr_range, rate_range, psf, gain, saturation, exptime, pixel_scale,
           hdu, bayer, seed, labels, json_out):
    """Inject streaks and points into a measured FRAME (its WCS, PSF, gain, noise); every other pixel and HDU
    is left as it was. Labels as for a render, the SNR against the frame's own noise."""
    from scenes.app.bench.inject import inject_file

    if (objects is None) == (n_random is None):
        raise click.UsageError("give --objects FILE or --random N (with --snr MIN:MAX and --rate MIN:MAX)")
    random = None
    if n_random is not None:
        if snr_range is None or rate_range is None:
            raise click.UsageError("--random needs --snr MIN:MAX and --rate MIN:MAX")
        random = (n_random, _range(snr_range, "--snr"), _range(rate_range, "--rate"))
    with Outputs(inputs=[frame] + ([objects] if objects else [])) as outs:
        out_path = outs.file(output, "-o")
        fmts = label_formats(labels)
        paths = {f: outs.file(label_path(output, f), f"--labels {f}") for f in fmts if f != "fits"}
        json_path = json_target(outs, json_out)
        summary = inject_file(frame, out_path, objects, random=random, hdu=hdu, psf=psf, gain=gain,
                              saturation=saturation, exptime=exptime, pixel_scale=pixel_scale, bayer=bayer,
                              seed=seed, labels=fmts, label_paths=paths)
        summary["output"] = output
        if json_path is not None:
            write_json(summary, json_path)
    warn(summary["warnings"])
    if json_out == "-":
        write_json(summary, None)
    elif not json_out:
        click.echo(f"wrote {output}: {len(summary['objects'])} objects into HDU {summary['hdu']} "
                   f"(FWHM {summary['fwhm_px']:.2f} px {summary['psf'].split(' (')[0]}, gain "
                   f"{summary['gain_e_per_adu']:g} e-/ADU from {summary['sources']['gain']})", err=True)


@click.command()
@click.argument("frames", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="detections: .json (COCO results) or .ecsv/.csv (one row per detection)")
@click.option("--psf", default="measured", show_default=True,
              help="measured (the frame's stars; 2.5 px without stars), a FWHM in arcsec or in pixels (3px)")
@click.option("--hdu", default=None, help="image HDU (index or EXTNAME; default: the first image with a WCS)")
@click.option("--min-snr", type=click.FloatRange(min=0), default=None,
              help="smallest integrated SNR of a kept streak (default 7)")
@click.option("--points", is_flag=True, help="also report compact sources (stars and slow objects) as points")
@click.option("--labels", "labels_file", default=None, type=click.Path(exists=True, dir_okay=False),
              help="a COCO labels file: take the image ids from it (by file name)")
@click.option("--json", "json_out", default=None, help="write a JSON summary here ('-' for stdout)")
def detect(frames, output, psf, hdu, min_snr, points, labels_file, json_out):
    """The baseline streak detector on FRAMES (photutils background and segmentation, scikit-image
    probabilistic Hough; endpoints at the visible ends of each trail). docs/detection_bench.md."""
    import json

    from scenes.app.bench.detect import MIN_SNR, detect_file, write_detections

    with Outputs(inputs=list(frames) + ([labels_file] if labels_file else [])) as outs:
        out_path = outs.file(output, "-o")
        json_path = json_target(outs, json_out)
        ids = None
        if labels_file:
            with open(labels_file) as fh:
                doc = json.load(fh)
            ids = {im["file_name"]: im["id"] for im in doc.get("images", [])}
        dets, per_frame = [], []
        for f in frames:
            d, s = detect_file(f, hdu=hdu, psf=psf, min_snr=MIN_SNR if min_snr is None else min_snr, points=points)
            dets += d
            per_frame.append(s)
        write_detections(dets, out_path, image_ids=ids)
        summary = {"output": output, "frames": per_frame, "detections": len(dets)}
        if json_path is not None:
            write_json(summary, json_path)
    if json_out == "-":
        write_json(summary, None)
    elif not json_out:
        click.echo(f"wrote {output}: {len(dets)} detections in {len(frames)} frame(s)", err=True)
