"""``newtsim demo``: the showcase frame with its quick-look, then one compare / diagnose round (``make demo``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
from rich.console import Console

from detector.jsonable import jsonable
from scenes.app.demo import HiddenRound, run_demo


@click.command()
@click.option("-o", "--output", "out_dir", default="out", show_default=True, type=click.Path(file_okay=False),
              help="folder for the frame, its quick-look and the round's files")
@click.option("--no-frame", is_flag=True, help="skip the full-frame render (only the compare/diagnose round)")
@click.option("--window", type=click.IntRange(min=64), default=HiddenRound.width, show_default=True,
              help="side of the window of the round [pixels]")
@click.option("--workers", type=int, default=None, help="threads (default: CPUs, at most 4)")
@click.option("--json", "json_out", default=None, help="also write the demo's summary JSON here")
def demo(out_dir, no_frame, window, workers, json_out):
    """Render the built-in 'showcase' scene (OUT/demo.fits + OUT/demo.png with insets on the streak and a
    star), then hide an effect in a window of it and let diagnose name it (OUT/round_*)."""
    console = Console(highlight=False)
    err = Console(stderr=True, highlight=False, log_path=False)
    t0 = time.perf_counter()
    with err.status("newtsim demo") as status:
        def log(msg: str) -> None:
            err.log(msg)
            status.update(f"[bold]newtsim demo[/bold]: {msg}")

        res = run_demo(Path(out_dir), frame=not no_frame, cfg=HiddenRound(width=window, height=window),
                       workers=workers, log=log)
    for line in res["lines"]:
        console.print(line, soft_wrap=True)
    r = res["round"]
    files = [f for f in (r["files"]["measured"], r["files"]["diagnosis"], r["files"]["report"],
                         r["files"]["applied_scene"]) if f]
    err.print(f"[dim]also written: {', '.join(files)}; {time.perf_counter() - t0:.0f} s in all[/dim]")
    if json_out:
        Path(json_out).write_text(json.dumps(jsonable(res), indent=1, default=str) + "\n")
