"""The ``newtsim`` command line (contract in DESIGN.md): one module per command group.

* :mod:`.render`        ``render``, ``effects``
* :mod:`.characterize`  ``characterize``
* :mod:`.compare`       ``compare``, ``diagnose``
* :mod:`.batch`         ``batch``
* :mod:`.optics`        ``optics vignetting | psf | pst | layout``
* :mod:`.inject`        ``inject``, ``detect``
* :mod:`.common`        error handling, JSON output, scene loading, progress bars

The optics commands import Mitsuba only when they run, so ``newtsim render`` works without it.
"""

from __future__ import annotations

import atexit
import sys

# before anything heavy: SIGINT/SIGTERM while numpy, astropy or Mitsuba load is one line, not a traceback
from scenes.app import interrupts as _interrupts

if _interrupts.running_as_program() and not _interrupts.installed():
    _interrupts.install()

try:
    import click

    from .batch import batch as batch_command
    from .characterize import characterize as characterize_command
    from .characterize import expand_multi_file_options
    from .common import EXIT_USER_ERROR, Group
    from .compare import compare as compare_command
    from .compare import diagnose as diagnose_command
    from .demo import demo as demo_command
    from .inject import detect as detect_command
    from .inject import inject as inject_command
    from .init import init as init_command
    from .optics import optics as optics_group
    from .render import effects as effects_command
    from .render import render as render_command
    from .score import score as score_command
except KeyboardInterrupt as _exc:
    _interrupts.exit_interrupted(_exc)


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="newtsim")
def cli():
    """newtsim: what a Newtonian telescope with a CCD or CMOS camera records.

    \b
    render        a scene to a FITS frame (+ PNG quick-look)
    batch         many frames (sweeps, time sequences, Monte-Carlo draws) on Dask, resumable
    characterize  bias/dark/flat calibration frames -> camera parameters (+ a scene that reproduces it)
    effects       the catalogue of optional effects, their parameters and units
    compare       model vs measured frame: chi2, residuals per region/row/column/source, HTML report
    diagnose      which physical effect the model lacks, ranked by delta BIC; --apply adds it
    optics        vignetting | psf | pst: ray tracing of the telescope (Mitsuba 3, llvm)
    inject        synthetic streaks and points drawn into a measured frame (+ labels)
    detect        the baseline streak detector: a frame -> detections (COCO results JSON or ECSV)
    score         detections vs labels: completeness, purity, SNR of 50 %, PR curve (HTML, JSON)
    """


cli.add_command(render_command, name="render")
cli.add_command(characterize_command, name="characterize")
cli.add_command(effects_command, name="effects")
cli.add_command(compare_command, name="compare")
cli.add_command(diagnose_command, name="diagnose")
cli.add_command(optics_group, name="optics")
cli.add_command(batch_command, name="batch")
cli.add_command(demo_command, name="demo")
cli.add_command(inject_command, name="inject")
cli.add_command(detect_command, name="detect")
cli.add_command(score_command, name="score")
cli.add_command(init_command, name="init")


def _usage_line(exc: click.ClickException) -> str:
    """A click usage error (bad option value, missing argument) as one line with where to look."""
    msg = exc.format_message().replace("\n", " ").strip()
    ctx = getattr(exc, "ctx", None)
    hint = f" (see '{ctx.command_path} -h')" if ctx is not None else ""
    return f"newtsim: error: {msg}{hint}"


def main(argv=None):
    """Console-script entry point: exit 0, 1 (frames failed, or an operating-system error such as a full
    disk), 2 (a user error, one line), 130 / 143 (SIGINT / SIGTERM); never a traceback for any of them."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv[:1] == ["characterize"]:
            argv = expand_multi_file_options(argv)
        code = cli.main(args=argv, prog_name="newtsim", standalone_mode=False)
    except click.exceptions.Abort as exc:  # click's form of an interrupt at a prompt or while parsing
        _interrupts.exit_interrupted(exc.__context__)
    except KeyboardInterrupt as exc:
        _interrupts.exit_interrupted(exc)
    except click.ClickException as exc:
        click.echo(_usage_line(exc), err=True)
        sys.exit(exc.exit_code if exc.exit_code else EXIT_USER_ERROR)
    code = code if isinstance(code, int) else 0
    if argv[:1] == ["batch"]:  # Dask's worker processes need the interpreter's shutdown (threads, exit handlers)
        if code in (128 + 2, 128 + 15):
            _interrupts.exit_on_signal(code)
        sys.exit(code)
    if _interrupts.installed():
        # The outputs are committed (or discarded): leave now. The interpreter's shutdown would put the
        # default SIGINT action back for its last moments, and a Ctrl-C landing there would kill the process
        # silently with -SIGINT instead of this exit status.
        _interrupts.exit_on_signal(code)
        atexit._run_exitfuncs()
        _interrupts.exit_now(code)
    sys.exit(code)


if __name__ == "__main__":
    main()
