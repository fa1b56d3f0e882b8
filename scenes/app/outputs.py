"""One output layer for every ``newtsim`` command: checked before the work, written aside, committed together.

Every file a command writes (a FITS frame and its PNG, a JSON summary, an HTML report, an ``--apply`` scene
and its ledger, the maps beside an ``--emit-scene`` TOML, a plots folder, an optics FITS/PNG/GLB) goes
through one :class:`Outputs`::

    with Outputs(inputs=[scene, measured]) as outs:      # before any work:
        fits_path = outs.file(output, "-o")              # the path is checked, a staged path returned
        png_path = outs.file(png, "--png")
        ...                                              # the writers write the staged paths
    # here every output is in place, or (an error, SIGINT, SIGTERM) none is and no temporary file is left

The rules (docs/reliability.md):

* **Checked before any work starts.** ``-o ''`` is refused; the folder must exist and be writable (a
  staging folder is created in it at once, so a read-only or full file system fails now, not after an hour of
  ray tracing); the target must be a regular file or absent: a directory, a device, a FIFO or a socket is
  refused (newtsim never replaces one); it must not be one of the command's inputs (``render scene.toml
  -o scene.toml``), and no two outputs may be the same file.
* **Symbolic links are written through.** ``-o link.fits`` writes the file the link points to (the link
  stays a link; a dangling link creates its target, whose folder must exist); the checks apply to that
  target. A link loop is refused.
* **Written aside.** Each output is written into a hidden staging folder ``.newtsim-*.part`` in its target's
  folder (the same file system), under its own name, so writers that add siblings (``<stem>_dark.fits``
  beside an ``--emit-scene`` TOML, a ledger beside an ``--apply`` scene) and writers that pick a format by
  the file suffix work unchanged.
* **Committed together.** When the command's work is done, every staged file is checked again (a target
  that became a directory meanwhile is refused before anything is renamed), then renamed over its target
  with SIGINT/SIGTERM held; a replaced file keeps its permission bits. On an error or an interrupt nothing is
  renamed and the staging folders are removed.
* **A full disk** (``ENOSPC``, ``EFBIG``: a file-size limit, ``EDQUOT``) while writing is one line, exit
  status 1 (the environment failed, not the input: the same command succeeds once there is room), and
  nothing is left.
"""

from __future__ import annotations

import errno
import os
import shutil
import stat
import tempfile
from pathlib import Path

from detector.errors import DetectorError

from . import interrupts

STAGE_PREFIX, STAGE_SUFFIX = ".newtsim-", ".part"

#: exit status of an output that could not be written for lack of room (see the module docstring)
EXIT_NO_SPACE = 1
NO_SPACE_ERRNOS = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}


class OutputError(DetectorError):
    """An output path that cannot be used (exit status 2, one line naming the option and the path)."""

    exit_status = 2


class NoSpaceError(DetectorError):
    """The disk (or a file-size limit, or a quota) was full while writing; nothing was written (exit 1)."""

    exit_status = EXIT_NO_SPACE


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _kind(mode: int) -> str | None:
    """What a non-regular file is, in words (None for a regular file)."""
    if stat.S_ISREG(mode):
        return None
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


class Outputs:
    """The outputs of one command (see the module docstring). Use as a context manager.

    Parameters
    ----------
    inputs : the command's input files (scene, measured frame, calibration frames, design ...): no output
        may be one of them. Names that are not files (a built-in scene such as ``default``) are ignored.
    """

    def __init__(self, inputs=()):
        self._inputs = [str(p) for p in inputs if p is not None and os.path.exists(str(p))]
        self._stages: dict[str, Path] = {}     # real folder -> its staging folder
        self._finals: dict[str, str] = {}      # final path -> the option that writes it
        self._shown: dict[str, str] = {}       # staged path -> the path as the user gave it
        self._folders: set[str] = set()        # final paths that are folders
        self._done = False

    # ------------------------------------------------------------------ context
    def __enter__(self):
        interrupts.register(self)
        return self

    def __exit__(self, exc_type, exc, tb):
        try:
            if exc_type is None:
                self.commit()
            else:
                self.discard()
                if isinstance(exc, OSError) and exc.errno in NO_SPACE_ERRNOS:
                    raise self.no_space(exc) from None
        finally:
            interrupts.unregister(self)
        return False

    # ------------------------------------------------------------------ declaring
    def file(self, path, option: str) -> Path:
        """Check ``path`` (the value of ``option``) as an output file now; return where to write it."""
        final = self._check(path, option)
        staged = self._stage(final.parent, option, path) / final.name
        self._shown[str(staged)] = os.fspath(path)
        return staged

    def optional(self, path, option: str) -> Path:
        """An output a writer may or may not make (a ledger written only when ...): checked like :meth:`file`."""
        return self.file(path, option)

    def folder(self, path, option: str) -> Path:
        """A folder of outputs (``--plots``): absent (created at commit) or an existing folder whose files
        are replaced one by one; its parent must exist. Returns the staged folder to write into."""
        s = os.fspath(path) if path is not None else ""
        if not s.strip():
            raise OutputError("empty output path", key=option, expected="a folder path")
        final = Path(os.path.abspath(Path(s.rstrip("/") or "/").expanduser()))
        if final.exists() and not final.is_dir():
            raise OutputError(f"is {_kind(os.stat(final).st_mode) or 'a file'}", key=option, file=s,
                              expected="a folder (existing or new)")
        parent = final.parent
        if not parent.is_dir():
            raise OutputError(f"folder {parent} does not exist", key=option, file=s,
                              expected="a path in an existing folder")
        self._claim(str(final), option, s)
        staged = self._stage(parent, option, s) / final.name
        staged.mkdir()
        self._folders.add(str(final))
        self._shown[str(staged)] = s
        return staged

    def also_inputs(self, paths) -> None:
        """More inputs, known only once the scene is loaded (its catalogue, maps, design, TLE files): an
        output already declared on one of them is refused now, still before the work."""
        new = [str(p) for p in paths if p is not None and os.path.isfile(str(p))]
        for final, option in self._finals.items():
            for inp in new:
                if _same_file(final, inp) if os.path.exists(final) else False:
                    raise OutputError(f"is a file the scene reads ({inp})", key=option, file=final,
                                      expected="an output path that is not one of the inputs")
        self._inputs += new

    def _claim(self, final: str, option: str, shown: str) -> None:
        if final in self._finals:
            raise OutputError(f"is also the output of {self._finals[final]}", key=option, file=shown,
                              expected="a different path for each output")
        for inp in self._inputs:
            if _same_file(final, inp) if os.path.exists(final) else os.path.realpath(final) == os.path.realpath(inp):
                raise OutputError(f"is an input of this command ({inp})", key=option, file=shown,
                                  expected="an output path that is not one of the inputs")
        self._finals[final] = option

    def _check(self, path, option: str) -> Path:
        s = os.fspath(path) if path is not None else ""
        if not s.strip():
            raise OutputError("empty output path", key=option, expected="a file path")
        if s.endswith(("/", os.sep)):
            raise OutputError("names a folder", key=option, file=s, expected="a file path")
        p = Path(os.path.abspath(Path(s).expanduser()))
        if os.path.islink(p):  # written through: the checks below apply to the link's target
            try:
                os.stat(p)
            except OSError as exc:
                if exc.errno == errno.ELOOP:
                    raise OutputError("is a symbolic link loop", key=option, file=s,
                                      expected="a regular file, a new path or a link to one") from None
            p = Path(os.path.realpath(p))
        folder = p.parent
        if not folder.is_dir():
            raise OutputError(f"folder {folder} does not exist", key=option, file=s,
                              expected="a path in an existing folder")
        try:
            st = os.stat(p)
        except FileNotFoundError:
            st = None
        except OSError as exc:
            raise OutputError(f"cannot be checked ({exc.strerror})", key=option, file=s) from None
        if st is not None and (kind := _kind(st.st_mode)):
            raise OutputError(f"is {kind}", key=option, file=s,
                              expected="a regular file or a new path (newtsim never replaces anything else)")
        self._claim(str(p), option, s)
        return p

    def _stage(self, folder: Path, option: str, shown) -> Path:
        key = str(folder)
        if key not in self._stages:
            try:
                self._stages[key] = Path(tempfile.mkdtemp(prefix=STAGE_PREFIX, suffix=STAGE_SUFFIX, dir=folder))
            except OSError as exc:
                if exc.errno in NO_SPACE_ERRNOS:
                    raise NoSpaceError(f"no room in {folder} ({exc.strerror})", key=option,
                                       file=os.fspath(shown)) from None
                raise OutputError(f"folder {folder} is not writable ({exc.strerror})", key=option,
                                  file=os.fspath(shown), expected="a folder this user can write") from None
        return self._stages[key]

    # ------------------------------------------------------------------ finishing
    def public(self, obj):
        """``obj`` (a path, a string, or a dict/list of them) with every staged path replaced by the final one
        (as the user named it for a declared output): for messages and JSON summaries."""
        if isinstance(obj, dict):
            return {k: self.public(v) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            return type(obj)(self.public(v) for v in obj)
        if isinstance(obj, Path):
            return Path(self.public(str(obj)))
        if isinstance(obj, str):
            if obj in self._shown:
                return self._shown[obj]
            for folder, stage in self._stages.items():
                s = str(stage)
                if obj.startswith(s + os.sep):
                    return folder + obj[len(s):]
        return obj

    def no_space(self, exc: OSError) -> NoSpaceError:
        where = ", ".join(sorted(self._stages)) or "the output folder"
        return NoSpaceError(f"no room to write the output ({exc.strerror}: the disk, a quota or a file-size limit "
                            f"is full); nothing was written", file=where)

    def _plan(self) -> list[tuple[Path, Path, int | None]]:
        """(staged, final, mode to keep) for every staged file, every final checked before any is renamed."""
        plan = []
        for folder, stage in self._stages.items():
            for name in sorted(os.listdir(stage)):
                src, dst = stage / name, Path(folder) / name
                if str(dst) in self._folders:
                    for sub in sorted(os.listdir(src)):
                        plan.append(self._item(src / sub, dst / sub))
                else:
                    plan.append(self._item(src, dst))
        return plan

    def _item(self, src: Path, dst: Path) -> tuple[Path, Path, int | None]:
        option = self._finals.get(str(dst), "output")
        if src.is_dir():
            raise OutputError("a writer made a folder where a file was expected", key=option, file=str(dst))
        if os.path.islink(dst) and str(dst) not in self._finals:
            raise OutputError("is a symbolic link (not declared as an output)", key=option, file=str(dst),
                              expected="a regular file or a new path")
        try:
            st = os.stat(dst)
        except FileNotFoundError:
            return src, dst, None
        if kind := _kind(st.st_mode):
            raise OutputError(f"is {kind}", key=option, file=str(dst),
                              expected="a regular file or a new path (newtsim never replaces anything else)")
        for inp in self._inputs:
            if _same_file(str(dst), inp):
                raise OutputError(f"is an input of this command ({inp})", key=option, file=str(dst),
                                  expected="an output path that is not one of the inputs")
        return src, dst, stat.S_IMODE(st.st_mode)

    def commit(self) -> None:
        """Rename every staged file over its target (signals held), then remove the staging folders."""
        if self._done:
            return
        try:
            with interrupts.blocked():
                interrupts.raise_if_pending()
                plan = self._plan()
                new_dirs = [Path(f) for f in self._folders if not Path(f).exists()]
                for d in new_dirs:
                    d.mkdir()
                default_mode = 0o666 & ~_umask()
                for src, dst, mode in plan:
                    os.chmod(src, mode if mode is not None else default_mode)
                    os.replace(src, dst)
                self._done = True
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove the staging folders (and whatever is still in them); committed outputs are not touched."""
        with interrupts.blocked():
            for stage in self._stages.values():
                shutil.rmtree(stage, ignore_errors=True)


def leftovers(folder) -> list[Path]:
    """Staging folders and ``.part`` files in ``folder`` (for tests and for operators' checks)."""
    return sorted(p for p in Path(folder).iterdir() if p.name.endswith(STAGE_SUFFIX))
