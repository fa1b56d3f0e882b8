"""``newtsim compare`` and ``newtsim diagnose`` (contract in DESIGN.md)."""

from __future__ import annotations

import click
from rich.progress import Progress

from scenes.app.compare import diagnose_round, run_compare
from scenes.app.compare.report import write_report

from .common import load, warn, write_json


@click.command()
@click.argument("scene")
@click.argument("measured", type=click.Path())
@click.option("--json", "json_out", default=None, help="write the comparison JSON here ('-' for stdout)")
@click.option("--report", "report", default=None, type=click.Path(dir_okay=False), help="write an HTML report")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a scene key")
@click.option("--workers", type=int, default=None, help="threads (default: CPUs, at most 4)")
def compare(scene, measured, json_out, report, sets, workers):
    """Model of SCENE vs the MEASURED frame: chi2/dof, residuals per region, row/column, source; report."""
    sc = load(scene, sets)
    result = run_compare(sc, measured, workers=workers)
    s = result["summary"]
    warn(s["warnings"])
    if report:
        s["report"] = str(write_report(result, report))
    if json_out:
        write_json(s, json_out)
    click.echo(f"chi2/dof {s['chi2_per_dof']:.4g} over {s['n_compared']} pixels ({s['n_statistical']} compared "
               f"statistically), misfit {s['misfit']:.3g}; worst regions: {', '.join(s['worst_regions'])}"
               + (f"; report {report}" if report else ""), err=True)
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
@click.option("--workers", type=int, default=None, help="threads (default: CPUs, at most 4)")
def diagnose(scene, measured, json_out, apply_to, report, prefer, sets, workers):
    """Rank the effects SCENE lacks by how much of the MEASURED frame they explain (delta BIC)."""
    sc = load(scene, sets)
    with Progress(transient=True) as bar:
        task = bar.add_task("fitting candidate effects", total=None)
        out = diagnose_round(sc, scene, measured, apply_to=apply_to, workers=workers,
                             progress=lambda name: bar.update(task, description=name), prefer=tuple(prefer))
    cmp = out.pop("_compare")
    if apply_to and out["applied"] is None:
        click.echo("newtsim: nothing applied: no significant candidate", err=True)
    if report:
        out["report"] = str(write_report(cmp, report, diagnosis=out))
    if json_out:
        write_json(out, json_out)
    click.echo(f"baseline chi2/dof {out['baseline']['chi2_per_dof']:.4g}; {out['verdict']}", err=True)
    _sampling_note(out.get("sampling"))
    for c in out["candidates"][:5]:
        click.echo(f"  {c['effect']:15s} dBIC {c['delta_bic']:12.4g}  chi2/dof after {c['chi2_per_dof']:.4g}  "
                   f"{c['explanation']}", err=True)
    if out["applied"]:
        a = out["applied"]
        what = (f"objects[{a['params']['object']}].light_curve" if a["effect"] == "light_curve"
                else f"[effects.{a['effect']}]")
        click.echo(f"wrote {a['scene']} (+{what}); ledger {out['ledger']['path']}", err=True)
