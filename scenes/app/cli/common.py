"""What every ``newtsim`` command shares: the error handling, JSON output and scene loading.

User mistakes (bad scene keys, missing files, out-of-range parameters, unusable output paths) raise
:class:`detector.DetectorError` or :class:`optics.design.OpticsError` anywhere below; :class:`Group` turns
them into one line naming the file, the key and what was expected, and exit status 2; never a traceback.
An operating-system error (a full disk, an I/O error) is one line and exit status 1; SIGINT / SIGTERM one
line and 130 / 143 (:mod:`scenes.app.interrupts`). Every output goes through :class:`scenes.app.outputs.Outputs`
(checked before the work, committed together). Third-party warnings (astropy, ERFA) are collected and, when
the command succeeds, reported once each in one line; deprecation and numerical-noise warnings are dropped.
The table of failure classes: docs/reliability.md.
"""

from __future__ import annotations

import json
import os
import warnings
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
from scenes.app import interrupts
from scenes.app.outputs import NO_SPACE_ERRNOS, Outputs
from scenes.scene import load_scene

EXIT_USER_ERROR = 2
EXIT_OS_ERROR = 1
EXIT_INTERRUPTED = interrupts.EXIT_INTERRUPTED

__all__ = ["EXIT_INTERRUPTED", "EXIT_OS_ERROR", "EXIT_USER_ERROR", "Group", "Outputs", "json_target", "load",
           "progress_bar", "warn", "write_json"]

#: warnings that carry nothing for the user of a command (library internals, numerical noise)
_SILENCED = (DeprecationWarning, PendingDeprecationWarning, FutureWarning, ResourceWarning, RuntimeWarning,
             ImportWarning, BytesWarning)


def os_error_line(exc: OSError) -> str:
    """One line for an operating-system error (no traceback)."""
    where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
    if exc.errno in NO_SPACE_ERRNOS:
        return (f"{where}no room to write ({exc.strerror}: the disk, a quota or a file-size limit is full); "
                "nothing was written")
    return f"{where}{exc.strerror or exc}"


def plain_warning(w: warnings.WarningMessage) -> str:
    """A third-party warning in one line of plain words."""
    text = str(w.message).strip().splitlines()[0] if str(w.message).strip() else type(w.message).__name__
    name = type(w.message).__name__
    if name == "ErfaWarning" and "dubious year" in text:
        return ("the epoch is outside the leap-second table (before 1960 or years ahead): its UTC is "
                "approximate (ERFA)")
    module = (w.filename or "").replace("\\", "/")
    lib = next((lib for lib in ("astropy", "erfa", "numpy", "scipy", "matplotlib", "mitsuba", "drjit", "dask")
                if f"/{lib}/" in module), None)
    return f"{lib}: {text}" if lib else text


class Group(click.Group):
    """Turns user errors raised anywhere below into one line on stderr (see the module docstring)."""

    def invoke(self, ctx):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for cat in _SILENCED:
                warnings.simplefilter("ignore", cat)
            try:
                result = super().invoke(ctx)
            except (DetectorError, OpticsError) as exc:
                click.echo(f"newtsim: error: {exc}", err=True)
                ctx.exit(getattr(exc, "exit_status", EXIT_USER_ERROR))
            except BrokenPipeError:  # `newtsim effects | head`: the reader is gone; say nothing more
                try:
                    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
                except OSError:
                    pass
                ctx.exit(EXIT_OS_ERROR)
            except OSError as exc:
                click.echo(f"newtsim: error: {os_error_line(exc)}", err=True)
                ctx.exit(EXIT_OS_ERROR)
            except KeyboardInterrupt as exc:
                click.echo("newtsim: interrupted", err=True)
                interrupts.reported()
                ctx.exit(interrupts.exit_code(exc))
        seen = set()
        for w in caught:
            line = plain_warning(w)
            if line not in seen:
                seen.add(line)
                click.echo(f"newtsim: warning: {line}", err=True)
        return result


def json_target(outs: Outputs, path: str | None, option: str = "--json"):
    """Where ``--json PATH`` goes: a staged file of ``outs`` (checked now), or None for stdout / no JSON."""
    return None if path in (None, "-") else outs.file(path, option)


def write_json(obj, path) -> None:
    """``obj`` as JSON (numpy values made plain) to ``path``, or to stdout for None or ``-``."""
    text = json.dumps(jsonable(obj), indent=2, allow_nan=False)
    if path is None or str(path) == "-":
        click.echo(text)
    else:
        Path(path).write_text(text + "\n")


def load(scene: str, sets, outs: Outputs | None = None) -> object:
    """The scene file (or built-in name) with the command's ``--set KEY=VALUE`` overrides; with ``outs``,
    the files the scene reads (catalogue, maps, design, TLEs) become inputs no output may overwrite."""
    sc = load_scene(scene, list(sets))
    if outs is not None:
        outs.also_inputs(scene_files(sc))
    return sc


def scene_files(scene) -> list[str]:
    """Every existing file a loaded scene names (its paths are absolute after :func:`load_scene`)."""
    found = []

    def walk(v):
        if isinstance(v, dict):
            for x in v.values():
                walk(x)
        elif isinstance(v, (list, tuple)):
            for x in v:
                walk(x)
        elif isinstance(v, str) and os.path.isabs(v) and os.path.isfile(v):
            found.append(v)

    walk(scene.model_dump(mode="json"))
    return found


def warn(lines) -> None:
    for w in lines:
        click.echo(f"newtsim: warning: {w}", err=True)


def progress_bar(label: str) -> Progress:
    """A transient rich progress bar on stderr: label, bar, done/total, elapsed and remaining time."""
    return Progress(TextColumn(label), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True), transient=True)
