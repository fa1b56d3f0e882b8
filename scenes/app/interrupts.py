"""SIGINT / SIGTERM for the ``newtsim`` program: one line, exit 130 (143 for SIGTERM), nothing left behind.

Standard library only: :mod:`scenes.app.cli` installs the handlers before it imports anything heavy, so an
interrupt while numpy, astropy or Mitsuba load is the same one line as an interrupt during a render.

* The first signal raises :class:`Interrupted` (a ``KeyboardInterrupt``) in the main thread: the commands
  unwind, every :class:`scenes.app.outputs.Outputs` removes its temporary files, and the command line prints
  ``newtsim: interrupted`` and exits ``128 + signal`` (130 for SIGINT, 143 for SIGTERM: the shell's
  convention, which schedulers and ``timeout`` read).
* A signal swallowed on its way up (raised inside a finaliser, where Python can only print it, or caught by
  a library) is remembered: the outputs are not committed and the command ends as interrupted.
* A second signal while the first is still unwinding (a library that swallowed it, a slow clean-up) is
  respected at once: the registered clean-ups run (removing temporary files only; they never touch a
  committed output) and the process ends with ``os._exit``.

The handlers are installed only when newtsim runs as a program (:func:`running_as_program`), never when a
test or a user's script imports the package.
"""

from __future__ import annotations

import os
import signal
import sys

EXIT_INTERRUPTED = 130  #: 128 + SIGINT

_cleanups: dict[int, object] = {}
_count = 0
_first = 0  # the first signal's number (0: none yet)
_installed = False
_reported = False


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread; ``signum`` says which."""

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def exit_code(exc: BaseException | None = None) -> int:
    """``128 + signal``: 130 for SIGINT (and a plain KeyboardInterrupt), 143 for SIGTERM."""
    return 128 + getattr(exc, "signum", signal.SIGINT)


def register(obj) -> None:
    """Call ``obj.discard()`` on a second signal (temporary files only)."""
    _cleanups[id(obj)] = obj


def unregister(obj) -> None:
    _cleanups.pop(id(obj), None)


def discard_all() -> None:
    for obj in list(_cleanups.values()):
        try:
            obj.discard()
        except Exception:  # noqa: BLE001, S110  (a clean-up on the way out must not raise)
            pass


def _handler(signum, frame):
    global _count, _first
    _count += 1
    _first = _first or int(signum)
    if _count >= 2:  # the second signal: clean up and go, whatever the first one is still doing
        discard_all()
        try:
            if not _reported:
                os.write(2, b"newtsim: interrupted\n")
        finally:
            os._exit(128 + signum)
    raise Interrupted(signum)


def raise_if_pending() -> None:
    """Raise :class:`Interrupted` if a signal came and was swallowed on its way up (raised inside a
    finaliser, or caught by a library): the outputs are then not committed."""
    if _first:
        raise Interrupted(_first)


def _unraisable(info) -> None:
    """An interrupt raised inside a finaliser cannot propagate: it is remembered (``raise_if_pending``),
    not printed as a traceback."""
    if isinstance(info.exc_value, KeyboardInterrupt):
        return
    sys.__unraisablehook__(info)


def reported() -> None:
    """The command has printed its interrupt line (a second signal then prints nothing more)."""
    global _reported
    _reported = True


def install() -> None:
    """SIGINT and SIGTERM -> :class:`Interrupted` (main thread only; a no-op elsewhere)."""
    global _installed, _count, _first
    _count, _first = 0, 0
    try:
        signal.signal(signal.SIGINT, _handler)
        signal.signal(signal.SIGTERM, _handler)
        sys.unraisablehook = _unraisable
        _installed = True
    except ValueError:  # not the main thread
        pass


def installed() -> bool:
    return _installed


def running_as_program() -> bool:
    """True for ``newtsim ...`` and ``python -m scenes.app.cli ...`` (not for an import in a script or test)."""
    arg0 = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    return arg0 in ("newtsim", "-m") or sys.argv[0].endswith(os.path.join("scenes", "app", "cli", "__main__.py"))


def exit_interrupted(exc: BaseException | None = None) -> None:
    """Print the one line and exit 128 + signal (for interrupts outside a command, e.g. during imports)."""
    discard_all()
    try:
        if not _reported:
            sys.stderr.write("newtsim: interrupted\n")
        sys.stderr.flush()
    finally:
        os._exit(exit_code(exc))


def exit_now(code: int) -> None:
    """Flush the standard streams and end the process with ``code`` at once (no interpreter shutdown)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001, S110  (a closed stream: nothing to flush)
            pass
    os._exit(code)


def exit_on_signal(code: int) -> None:
    """From now on SIGINT / SIGTERM end the process at once with ``code`` (for the shutdown after an
    interrupt: libraries' exit handlers still run, a second signal does not wait for them)."""

    def _now(signum, frame):
        exit_now(code)

    try:
        signal.signal(signal.SIGINT, _now)
        signal.signal(signal.SIGTERM, _now)
    except ValueError:  # not the main thread
        pass


class blocked:
    """Hold SIGINT and SIGTERM for the duration (the rename of finished outputs is never cut in half);
    a signal that arrives meanwhile is delivered when the block ends."""

    _SIGS = frozenset({signal.SIGINT, signal.SIGTERM})

    def __enter__(self):
        try:
            self._old = signal.pthread_sigmask(signal.SIG_BLOCK, self._SIGS)
        except (AttributeError, ValueError, OSError):
            self._old = None
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, self._old)
        return False
