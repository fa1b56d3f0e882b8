"""What every ``newtsim`` command shares: the error handling, JSON output and scene loading.

User mistakes (bad scene keys, missing files, out-of-range parameters) raise :class:`detector.DetectorError`
or :class:`optics.design.OpticsError` anywhere below; :class:`Group` turns them into one line naming the file,
the key and what was expected, and exit status 2; never a traceback.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
from rich.console import Console
from rich.progress import (
    BarColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from detector import DetectorError
from detector.jsonable import jsonable
from optics.design import OpticsError
from scenes.scene import load_scene

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130


class Group(click.Group):
    """Turns user errors raised anywhere below into one line on stderr."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (DetectorError, OpticsError) as exc:
            click.echo(f"newtsim: error: {exc}", err=True)
            ctx.exit(EXIT_USER_ERROR)


def write_json(obj, path: str | None) -> None:
    """``obj`` as JSON (numpy values made plain) to ``path``, or to stdout for None or ``-``."""
    text = json.dumps(jsonable(obj), indent=2, allow_nan=False)
    if path in (None, "-"):
        click.echo(text)
    else:
        Path(path).write_text(text + "\n")


def load(scene: str, sets) -> object:
    """The scene file (or built-in name) with the command's ``--set KEY=VALUE`` overrides."""
    return load_scene(scene, list(sets))


def warn(lines) -> None:
    for w in lines:
        click.echo(f"newtsim: warning: {w}", err=True)


def progress_bar(label: str) -> Progress:
    """A transient rich progress bar on stderr: label, bar, done/total, elapsed and remaining time."""
    return Progress(TextColumn(label), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True), transient=True)
