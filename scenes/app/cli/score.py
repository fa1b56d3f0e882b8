"""``newtsim score``: detections against labels (matching, completeness, purity, PR curve)."""

from __future__ import annotations

import click

from .common import Outputs, write_json


@click.command()
@click.argument("detections", type=click.Path(exists=True, dir_okay=False))
@click.argument("labels", type=click.Path(exists=True, dir_okay=False))
@click.option("--match", "mode", type=click.Choice(["endpoints", "mask", "centre"]), default="endpoints",
              show_default=True, help="matching: endpoint distance (ends' order free), mask IoU or centre distance")
@click.option("--gate", "gate_px", type=click.FloatRange(min=0), default=3.0, show_default=True,
              help="[px] largest endpoint or centre distance of a match")
@click.option("--min-iou", type=click.FloatRange(0, 1), default=0.5, show_default=True, help="smallest mask IoU of a match")
@click.option("--kinds", default="object", show_default=True,
              help="label kinds scored (comma-separated: object, star, synthetic, injected; 'all')")
@click.option("--html", "html_out", default=None, type=click.Path(dir_okay=False), help="write an HTML report with plots")
@click.option("--json", "json_out", default=None, help="write the metrics and every figure's data here ('-': stdout)")
def score(detections, labels, mode, gate_px, min_iou, kinds, html_out, json_out):
    """Score DETECTIONS (COCO results JSON, CSV/ECSV of endpoints or centres, or a mask FITS) against
    LABELS (the .coco.json of --labels coco, a dataset.coco.json, or a frame written with --labels fits:
    TRUTH + LABELS extensions). See docs/detection_bench.md."""
    from scenes.app.bench.score import ScoreError, html_report, score_files

    kind_list = None if kinds.strip().lower() == "all" else tuple(k.strip() for k in kinds.split(",") if k.strip())
    with Outputs(inputs=[detections, labels]) as outs:
        html_path = outs.file(html_out, "--html") if html_out else None
        json_path = outs.file(json_out, "--json") if json_out and json_out != "-" else None
        try:
            result = score_files(detections, labels, mode, gate_px, min_iou, kind_list)
        except ScoreError as exc:
            raise click.UsageError(str(exc)) from None
        if html_path is not None:
            html_path.write_text(html_report(result))
        if json_path is not None:
            write_json(result, json_path)
    if json_out == "-":
        write_json(result, None)
    else:
        c, p, s50 = result["completeness"], result["purity"], result["snr50"]["value"]
        click.echo(f"{result['matched']}/{result['labels']} labels matched (completeness {c if c is None else round(c, 4)}),"
                   f" purity {p if p is None else round(p, 4)}, SNR50 {s50 if s50 is None else round(s50, 3)}", err=True)
