"""``newtsim batch``: many frames (sweeps, sequences, Monte-Carlo draws) on Dask (``docs/scenes_batch.md``).

Exit status: 0 when every frame is done, 1 when some frame failed (each named in the summary and the
manifest), 2 for a user error in the batch file, its base scene or the options (one line, no traceback).
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from detector import DetectorError
from scenes.app import interrupts
from scenes.app.batch import frame_sets, load_batch, plan, run_batch
from scenes.scene import load_scene

from .common import Outputs, json_target, write_json

EXIT_FRAMES_FAILED = 1



def _dry_run(batch, force: bool) -> dict:
    """The frames, each with what a run would do: skip (done), render, or invalid (and why)."""
    todo = {s.index for s in plan(batch, force)[0]}
    frames = []
    for spec in batch.frames:
        row = {"index": spec.index, "file": Path(spec.file).name, "overrides": spec.overrides, "step": spec.step,
               "draw": spec.draw, "seed": spec.seed, "split": spec.split,
               "action": "render" if spec.index in todo else "skip"}
        if spec.index in todo:
            try:
                load_scene(spec.scene, frame_sets(spec))
            except DetectorError as exc:
                row.update(action="invalid", error=str(exc))
        frames.append(row)
    counts = {a: sum(f["action"] == a for f in frames) for a in ("render", "skip", "invalid")}
    return {"batch_file": batch.path, "scene": batch.scene, "output_dir": str(batch.output_dir),
            "root_seed": batch.cfg.batch.seed, "frames": len(frames), "counts": counts, "plan": frames}


def _no_second_cluster_close() -> None:
    """After an interrupt, run_batch has closed (or abandoned) its local cluster: Dask's own exit handler
    would close it again and print a traceback about the stopped event loop. Drop that handler."""
    import atexit

    try:
        from distributed.deploy.spec import close_clusters
    except ImportError:
        return
    atexit.unregister(close_clusters)


def _check_output_dir(folder: Path) -> None:
    """The frames' folder (created with its parents): not a file, and below no file."""
    folder = Path(folder).absolute()
    for p in (folder, *folder.parents):
        if p.exists():
            if not p.is_dir():
                raise DetectorError(f"{p} is not a folder", key="output_dir", file=str(folder),
                                    expected="a folder for the frames (existing or new)")
            if not os.access(p, os.W_OK | os.X_OK):
                raise DetectorError(f"folder {p} is not writable", key="output_dir", file=str(folder),
                                    expected="a folder this user can write")
            return


def _overrides_text(overrides: dict) -> str:
    return " ".join(f"{k}={v!r}" for k, v in overrides.items())


@click.command()
@click.argument("batch_file", metavar="BATCH.toml")
@click.option("--scheduler", default=None, metavar="ADDR",
              help="a running Dask scheduler (tcp://HOST:8786) or its scheduler file; default: a local cluster")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="local cluster: worker processes, one thread each (default: the cores)")
@click.option("-o", "--output-dir", "output_dir", default=None, type=click.Path(file_okay=False),
              help="output folder (replaces [batch] output_dir)")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="override a key of the base scene")
@click.option("--force", is_flag=True, help="re-render frames that are already done")
@click.option("--dry-run", is_flag=True, help="list the frames (and check their scenes) without rendering")
@click.option("--json", "json_out", default=None, help="write the summary (or the plan) as JSON ('-' for stdout)")
@click.option("--labels", "labels", default=None, metavar="FORMAT[,FORMAT]",
              help="write a labelled dataset: coco, satnet, yolo, fits (replaces [batch] labels); "
                   "docs/detection_bench.md")
@click.pass_context
def batch(ctx, batch_file, scheduler, workers, output_dir, sets, force, dry_run, json_out, labels):
    """Render the frames of BATCH.toml (sweeps x sequence x Monte-Carlo draws) on Dask, resumably.

    Frames go to OUTPUT_DIR/frame_IIII.fits with OUTPUT_DIR/manifest.json; a re-run skips the frames
    that are done. Each frame equals `newtsim render SCENE --seed S --set ...` with the seed and
    overrides of its manifest entry. With --labels, each frame's label files, one annotation file per
    format for the dataset (dataset.coco.json, dataset.satnet.json), and each frame's split (train/val/test
    from its seed) in the manifest and train.txt, val.txt, test.txt.
    """
    if scheduler and workers:
        raise DetectorError("--workers sets the size of the local cluster", key="--workers",
                            expected="no --workers with --scheduler (the scheduler's workers are used)")
    b = load_batch(batch_file, list(sets), output_dir, labels)
    _check_output_dir(b.output_dir)
    if dry_run:
        with Outputs(inputs=[batch_file]) as outs:
            json_path = json_target(outs, json_out)
            result = _dry_run(b, force)
            if json_path is not None:
                write_json(result, json_path)
        if json_out == "-":
            write_json(result, None)
        elif not json_out:
            for f in result["plan"]:
                click.echo(f"{f['file']}  seed {f['seed']:>20d}  step {f['step']:>3d}  draw {f['draw']:>3d}  "
                           f"{f['action']:7s}  {_overrides_text(f['overrides'])}  {f.get('error', '')}".rstrip())
        c = result["counts"]
        click.echo(f"dry run: {result['frames']} frames -> {result['output_dir']}: {c['render']} to render, "
                   f"{c['skip']} done, {c['invalid']} invalid", err=True)
        ctx.exit(EXIT_FRAMES_FAILED if c["invalid"] else 0)
    # frames are committed one by one (each atomic, listed in the manifest: a re-run resumes); the summary
    # JSON is checked now and written at the end
    with Outputs(inputs=[batch_file]) as outs:
        json_path = json_target(outs, json_out)
        try:
            summary = run_batch(b, scheduler=scheduler, workers=workers, force=force)
        except KeyboardInterrupt as exc:
            outs.discard()
            _no_second_cluster_close()
            click.echo(f"newtsim: interrupted; {b.manifest_path} lists the frames done: the same command resumes",
                       err=True)
            interrupts.reported()
            ctx.exit(interrupts.exit_code(exc))
        if json_path is not None:
            write_json(summary, json_path)
    for f in summary["failures"]:
        click.echo(f"newtsim: frame {f['index']} ({f['file']}; {_overrides_text(f['overrides'])}) failed: "
                   f"{f['error']}", err=True)
    if json_out == "-":
        write_json(summary, None)
    click.echo(f"batch: {summary['frames']} frames: {summary['rendered']} rendered, {summary['skipped']} already "
               f"done, {summary['failed']} failed in {summary['wall_s']:.1f} s -> {summary['manifest']}", err=True)
    for fmt, path in summary.get("dataset", {}).items():
        click.echo(f"batch: dataset {fmt} labels -> {path}", err=True)
    if summary["failed"]:
        ctx.exit(EXIT_FRAMES_FAILED)
