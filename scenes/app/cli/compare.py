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
from scenes.app.compare.policy import DEFAULT_POLICY, load_policy
from scenes.app.compare.report import write_report
from scenes.app.compare.run import apply_best, run_diagnose
from scenes.app.compare.series import (
    apply_series,
    load_series,
    public_json,
    run_series_compare,
    run_series_diagnose,
    series_ledger,
)
from scenes.app.compare.series_report import write_series_report
from scenes.measured import with_mask

from .common import Outputs, json_target, load, scene_files, warn, write_json


def _nonfinite_note(s: dict) -> str:
    n = s.get("nonfinite_pixels") or 0
    return f"; {n} non-finite measured pixels masked" if n else ""


def _positional(scene, measured, series) -> None:
    """SCENE MEASURED, or --series SERIES.toml (not both)."""
    if series is not None and (scene is not None or measured is not None):
        raise click.UsageError("give SCENE MEASURED or --series SERIES.toml, not both")
    if series is None and (scene is None or measured is None):
        raise click.UsageError("missing SCENE and MEASURED (or --series SERIES.toml)")


def _series_inputs(path: str, sets) -> tuple:
    """The series and every file it reads (its scenes, their files, the measured frames): inputs no output may
    overwrite."""
    ser = load_series(path, tuple(sets))
    files = [path] + [str(f.file) for f in ser.frames]
    for f in ser.frames:
        files += scene_files(f.scene) + ([str(f.scene.source)] if f.scene.source else [])
    return ser, files


_SERIES_HELP = ("a series file (scene = ..., [[frames]] file = ..., set = {...}): compare / diagnose every frame "
                "together, hardware effects shared by the frames (instead of SCENE MEASURED)")


@click.command()
@click.argument("scene", required=False)
@click.argument("measured", type=click.Path(), required=False)
@click.option("--series", "series", default=None, type=click.Path(dir_okay=False), help=_SERIES_HELP)
@click.option("--json", "json_out", default=None, help="write the comparison JSON here ('-' for stdout)")
@click.option("--report", "report", default=None, type=click.Path(dir_okay=False), help="write an HTML report")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a scene key (every frame of a series)")
@click.option("--mask", "mask", default=None, type=click.Path(dir_okay=False),
              help="a FITS mask of the measured frame (non-zero = left out), added to the scene's [mask]")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="threads (default: CPUs, at most 4)")
def compare(scene, measured, series, json_out, report, sets, workers, mask):
    """Model of SCENE vs the MEASURED frame: chi2/dof, residuals per region, row/column, source; report.
    With --series, every frame of a series file against its model, side by side."""
    _positional(scene, measured, series)
    if series is not None:
        return _compare_series(series, json_out, report, sets, workers)
    with Outputs(inputs=[scene, measured]) as outs:
        json_path = json_target(outs, json_out)
        report_path = outs.file(report, "--report") if report else None
        sc = with_mask(load(scene, sets, outs), mask)
        if mask:
            outs.also_inputs([mask])
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


def _compare_series(series, json_out, report, sets, workers) -> None:
    ser, files = _series_inputs(series, sets)
    with Outputs(inputs=files) as outs:
        json_path = json_target(outs, json_out)
        report_path = outs.file(report, "--report") if report else None
        with Progress(transient=True) as bar:
            task = bar.add_task("series", total=None)
            result = run_series_compare(ser, workers=workers, progress=lambda t: bar.update(task, description=t))
        out = public_json(result)
        if report_path is not None:
            write_series_report(out, report_path, result["_compares"])
            out["report"] = report
        if json_path is not None:
            write_json(out, json_path)
    warn(out["baseline"]["warnings"])
    if json_out == "-":
        write_json(out, None)
    b = out["baseline"]
    click.echo(f"series of {b['n_frames']} frames: chi2/dof {b['chi2_per_dof']:.4g} ({b['chi2_per_dof_levels']:.4g} with "
               f"the levels refitted, shared: {', '.join(out['shared_levels']) or 'none'}), misfit {b['misfit']:.3g}"
               + (f"; report {report}" if report else ""), err=True)
    for f in out["frames"]:
        click.echo(f"  {f['label']:20s} {f['exposure_s']:8.3g} s  chi2/dof {f['chi2_per_dof']:.4g}  misfit "
                   f"{f['misfit']:.3g}", err=True)


def _sampling_note(sampling: dict | None) -> None:
    """One line on how a large frame was compared (scenes.app.compare.fullframe)."""
    if sampling:
        click.echo(f"large frame: chi2/dof and profiles over every pixel; regions, spectra and smooth effects on "
                   f"{sampling['binning_k']}x{sampling['binning_k']} super-pixels; outliers and pixel-scale effects "
                   f"on {len(sampling['bands'])} full-resolution bands ({100 * sampling['sample_fraction']:.1f} % of "
                   "the rows); see \"sampling\" in the JSON", err=True)


@click.command()
@click.argument("scene", required=False)
@click.argument("measured", type=click.Path(), required=False)
@click.option("--series", "series", default=None, type=click.Path(dir_okay=False), help=_SERIES_HELP)
@click.option("--json", "json_out", default=None, help="write the diagnosis JSON here ('-' for stdout)")
@click.option("--apply", "apply_to", default=None, type=click.Path(dir_okay=False),
              help="write the scene with the best significant candidate added here")
@click.option("--report", "report", default=None, type=click.Path(dir_okay=False), help="write an HTML report")
@click.option("--prefer", "prefer", multiple=True, metavar="EFFECT",
              help="with --apply: add this effect instead of the best one when it is significant (repeatable)")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a scene key (every frame of a series)")
@click.option("--mask", "mask", default=None, type=click.Path(dir_okay=False),
              help="a FITS mask of the measured frame (non-zero = left out), added to the scene's [mask]")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="threads (default: CPUs, at most 4)")
@click.option("--policy", "policy_file", default=None, type=click.Path(dir_okay=False),
              help="a TOML/JSON table overriding the judge's thresholds (docs/diagnosis_policy.md)")
def diagnose(scene, measured, series, json_out, apply_to, report, prefer, sets, workers, mask, policy_file):
    """Rank what SCENE gets wrong about the MEASURED frame: first the scene's own numbers (zero point, sky,
    PSF width, bias, dark), then the effects it lacks, by how much they explain (delta BIC, held-out pixels,
    against a description of the residual). With --series, the frames of a series file together: hardware
    effects shared, levels per frame."""
    _positional(scene, measured, series)
    policy = load_policy(policy_file)
    if series is not None:
        return _diagnose_series(series, json_out, apply_to, report, prefer, sets, workers, policy)
    with Outputs(inputs=[scene, measured] + ([policy_file] if policy_file else [])) as outs:
        json_path = json_target(outs, json_out)
        report_path = outs.file(report, "--report") if report else None
        apply_path = outs.file(apply_to, "--apply") if apply_to else None
        # the ledger (JSON + PNG) goes beside the applied scene, or beside the input scene when none is applied
        ledgers = {}
        for base, option in ([(apply_to, "--apply (its ledger)")] if apply_to else []) + [(scene, "ledger")]:
            lj = ledger_path(base)
            ledgers[base] = (outs.file(lj, option), outs.file(lj.with_suffix(".png"), option))
        sc = with_mask(load(scene, sets, outs), mask)
        if mask:
            outs.also_inputs([mask])
        with Progress(transient=True) as bar:
            task = bar.add_task("fitting candidate effects", total=None)
            out = run_diagnose(sc, measured, workers=workers, progress=lambda name: bar.update(task, description=name),
                               policy=policy)
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
                else "new values of " + ", ".join(a["params"]) if a["effect"] == "parameters"
                else f"[effects.{a['effect']}]")
        click.echo(f"wrote {a['scene']} (+{what}); ledger {out['ledger']['path']}", err=True)


def _diagnose_series(series, json_out, apply_to, report, prefer, sets, workers, policy=DEFAULT_POLICY) -> None:
    ser, files = _series_inputs(series, sets)
    with Outputs(inputs=files) as outs:
        json_path = json_target(outs, json_out)
        report_path = outs.file(report, "--report") if report else None
        apply_path = outs.file(apply_to, "--apply") if apply_to else None
        if apply_to:
            nxt = Path(apply_to).with_name(Path(apply_to).stem + ".series.toml")
            outs.file(nxt, "--apply (the next round's series)")
            lj = ledger_path(nxt)
            outs.file(lj, "--apply (its ledger)"), outs.file(lj.with_suffix(".png"), "--apply (its ledger)")
        lj = ledger_path(series)
        own_ledger = outs.file(lj, "ledger")
        outs.file(lj.with_suffix(".png"), "ledger")
        with Progress(transient=True) as bar:
            task = bar.add_task("series", total=None)
            out = run_series_diagnose(ser, workers=workers, progress=lambda t: bar.update(task, description=t),
                                      policy=policy)
        applied, new_series, best = apply_series(ser, out, apply_path, tuple(prefer), workers=workers)
        out["applied"] = ({"effect": best["effect"], "params": best["params"], "scene": apply_to,
                           "series": outs.public(str(new_series))} if applied else None)
        target = new_series if applied else own_ledger.with_name(Path(series).name)
        out["ledger"] = outs.public(series_ledger(ser, out, target if applied else None, best if applied else None,
                                                  target=None if applied else target))
        compares = out["_compare"]["_compares"]
        public = public_json(out)
        if report_path is not None:
            write_series_report(public, report_path, compares)
            public["report"] = report
        if json_path is not None:
            write_json(public, json_path)
    if apply_to and public["applied"] is None:
        click.echo("newtsim: nothing applied: no significant candidate", err=True)
    if json_out == "-":
        write_json(public, None)
    b = public["baseline"]
    click.echo(f"series of {b['n_frames']} frames: chi2/dof {b['chi2_per_dof_levels']:.4g} (levels refitted); "
               f"{public['verdict']}", err=True)
    for c in public["candidates"][:5]:
        click.echo(f"  {c['effect']:15s} {('shared' if c['shared'] else 'per frame'):9s} dBIC {c['delta_bic']:12.4g}  "
                   f"chi2/dof after {c['chi2_per_dof']:.4g}  {c['explanation']}", err=True)
    if public.get("separation"):
        click.echo(f"told apart: {public['separation']['statement']}", err=True)
    if public["applied"]:
        a = public["applied"]
        click.echo(f"wrote {a['scene']} (+[effects.{a['effect']}]) and {a['series']} (the next round: newtsim diagnose "
                   f"--series {a['series']}); ledger {public['ledger']['path']}", err=True)
