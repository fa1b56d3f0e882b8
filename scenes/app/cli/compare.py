"""``newtsim compare`` and ``newtsim diagnose`` (contract in DESIGN.md).

Every output (``--json``, ``--report``, ``--apply`` and the ledger beside it, or beside the input scene when
nothing is applied) is checked before the model is built and written together at the end
(:class:`scenes.app.outputs.Outputs`): a failing report leaves no JSON, an interrupted ``--apply`` no scene.
"""

from __future__ import annotations

from pathlib import Path

import click
from rich.progress import Progress

from scenes.app.compare import run_compare
from scenes.app.compare.ledger import ledger_path, plot_ledger, update_ledger
from scenes.app.compare.report import write_report
from scenes.app.compare.run import apply_best, run_diagnose

from .common import Outputs, json_target, load, warn, write_json


def _nonfinite_note(s: dict) -> str:
    n = s.get("nonfinite_pixels") or 0
    return f"; {n} non-finite measured pixels masked" if n else ""


@click.command()
@click.argument("scene")
@click.argument("measured", type=click.Path())
@click.option("--json", "json_out", default=None, help="write the comparison JSON here ('-' for stdout)")
@click.option("--report", "report", default=None, type=click.Path(dir_okay=False), help="write an HTML report")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a scene key")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="threads (default: CPUs, at most 4)")
def compare(scene, measured, json_out, report, sets, workers):
    """Model of SCENE vs the MEASURED frame: chi2/dof, residuals per region, row/column, source; report."""
    with Outputs(inputs=[scene, measured]) as outs:
        json_path = json_target(outs, json_out)
        report_path = outs.file(report, "--report") if report else None
        sc = load(scene, sets, outs)
        result = run_compare(sc, measured, workers=workers)
        s = result["summary"]
        if report_path is not None:
            write_report(result, report_path)
            s["report"] = report
        if json_path is not None:
            write_json(s, json_path)
    warn(s["warnings"])
    if json_out == "-":
        write_json(s, None)
    click.echo(f"chi2/dof {s['chi2_per_dof']:.4g} over {s['n_compared']} pixels ({s['n_statistical']} compared "
               f"statistically), misfit {s['misfit']:.3g}; worst regions: {', '.join(s['worst_regions'])}"
               + _nonfinite_note(s) + (f"; report {report}" if report else ""), err=True)
    _sampling_note(s.get("sampling"))


def _sampling_note(sampling: dict | None) -> None:
    """One line on how a large frame was compared (scenes.app.compare.fullframe)."""
    if sampling:
        click.echo(f"large frame: chi2/dof and profiles over every pixel; regions, spectra and smooth effects on "
                   f"{sampling['binning_k']}x{sampling['binning_k']} super-pixels; outliers and pixel-scale effects "
                   f"on {len(sampling['bands'])} full-resolution bands ({100 * sampling['sample_fraction']:.1f} % of "
                   "the rows); see \"sampling\" in the JSON", err=True)


@click.command()
@click.argument("scene")
@click.argument("measured", type=click.Path())
@click.option("--json", "json_out", default=None, help="write the diagnosis JSON here ('-' for stdout)")
@click.option("--apply", "apply_to", default=None, type=click.Path(dir_okay=False),
              help="write the scene with the best significant candidate added here")
@click.option("--report", "report", default=None, type=click.Path(dir_okay=False), help="write an HTML report")
@click.option("--prefer", "prefer", multiple=True, metavar="EFFECT",
              help="with --apply: add this effect instead of the best one when it is significant (repeatable)")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a scene key")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="threads (default: CPUs, at most 4)")
def diagnose(scene, measured, json_out, apply_to, report, prefer, sets, workers):
    """Rank the effects SCENE lacks by how much of the MEASURED frame they explain (delta BIC)."""
    with Outputs(inputs=[scene, measured]) as outs:
        json_path = json_target(outs, json_out)
        report_path = outs.file(report, "--report") if report else None
        apply_path = outs.file(apply_to, "--apply") if apply_to else None
        # the ledger (JSON + PNG) goes beside the applied scene, or beside the input scene when none is applied
        ledgers = {}
        for base, option in ([(apply_to, "--apply (its ledger)")] if apply_to else []) + [(scene, "ledger")]:
            lj = ledger_path(base)
            ledgers[base] = (outs.file(lj, option), outs.file(lj.with_suffix(".png"), option))
        sc = load(scene, sets, outs)
        with Progress(transient=True) as bar:
            task = bar.add_task("fitting candidate effects", total=None)
            out = run_diagnose(sc, measured, workers=workers, progress=lambda name: bar.update(task, description=name))
        # the map of an empirical apply goes beside the named scene, staged with the other outputs
        applied, best = apply_best(sc, out, apply_path, measured, tuple(prefer),
                                   reserve=lambda p: outs.file(Path(apply_to).with_name(p.name), "--apply (its map)"),
                                   public=outs.public)
        out["applied"] = {"effect": best["effect"], "params": best["params"], "scene": apply_to} if applied else None
        staged_json = ledgers[apply_to if applied else scene][0]
        ledger, rounds = update_ledger(scene, applied or staged_json.with_name(Path(scene).name), str(measured),
                                       out["baseline"], best if applied else None)
        plot = plot_ledger(rounds, Path(ledger).with_suffix(".png"))
        out["ledger"] = {"path": outs.public(str(ledger)), "rounds": rounds, "plot": outs.public(str(plot))}
        cmp = out.pop("_compare")
        if report_path is not None:
            write_report(cmp, report_path, diagnosis=out)
            out["report"] = report
        if json_path is not None:
            write_json(out, json_path)
    if apply_to and out["applied"] is None:
        click.echo("newtsim: nothing applied: no significant candidate", err=True)
    if json_out == "-":
        write_json(out, None)
    click.echo(f"baseline chi2/dof {out['baseline']['chi2_per_dof']:.4g}; {out['verdict']}"
               + _nonfinite_note(out["baseline"]), err=True)
    _sampling_note(out.get("sampling"))
    for c in out["candidates"][:5]:
        click.echo(f"  {c['effect']:15s} dBIC {c['delta_bic']:12.4g}  chi2/dof after {c['chi2_per_dof']:.4g}  "
                   f"{c['explanation']}", err=True)
    if out["applied"]:
        a = out["applied"]
        what = (f"objects[{a['params']['object']}].light_curve" if a["effect"] == "light_curve"
                else f"[effects.{a['effect']}]")
        click.echo(f"wrote {a['scene']} (+{what}); ledger {out['ledger']['path']}", err=True)
