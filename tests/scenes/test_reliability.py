"""Issue 16: bad input, bad paths and interrupts give one clear line; nothing is lost, nothing overwritten.

Every failure class of docs/reliability.md: output paths (empty, a directory, a FIFO, a socket, a symlink
written through, a link loop, an input as output, a missing folder, a ``.png`` sibling that is a folder),
outputs committed together or not at all, strict scene types, NaN/inf measured pixels, interrupts at several
moments (SIGINT, SIGTERM, a second SIGINT) and a full disk (RLIMIT_FSIZE). The property-based suite is
tests/scenes/test_reliability_props.py. Special files are made by the tests (os.mkfifo, a socket, links):
never a real device.
"""

from __future__ import annotations

import io
import json
import os
import re
import resource
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from helpers import SMALL_SKY_TOML, write_scene

from scenes.app.cli import main
from scenes.app.outputs import STAGE_SUFFIX, OutputError, Outputs

ROOT = Path(__file__).resolve().parents[2]

#: the smallest useful scene: a 64 x 48 ML11002 dark window (renders in well under a second)
TINY = {"detector": {"preset": "ml11002", "width": 64, "height": 48},
        "exposure": {"time_s": 1.0, "frame": "dark", "seed": 3}}


def run(*args) -> tuple[int, str, str]:
    """``newtsim ARGS`` in this process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return code, out.getvalue(), err.getvalue()


def newtsim_proc(*args, cwd=None, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "scenes.app.cli", *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def leftovers(folder: Path) -> list[str]:
    """Temporary files or staging folders anywhere below ``folder``."""
    return [str(p) for p in Path(folder).rglob("*") if p.name.endswith(STAGE_SUFFIX) or ".part" in p.name]


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture()
def scene(tmp_path):
    return write_scene(tmp_path / "scene.toml", TINY)


# --- output paths --------------------------------------------------------------------------------------------

def test_render_writes_fits_png_and_json_together(scene, tmp_path):
    code, _, err = run("render", scene, "-o", tmp_path / "f.fits", "--json", tmp_path / "f.json")
    assert code == 0, err
    assert fits.getdata(tmp_path / "f.fits").shape == (48, 64)
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((tmp_path / "f.json").read_text())
    assert summary["path"] == str(tmp_path / "f.fits") and summary["png"] == str(tmp_path / "f.png")
    assert not leftovers(tmp_path)
    # a replaced file keeps its permission bits
    os.chmod(tmp_path / "f.fits", 0o640)
    assert run("render", scene, "-o", tmp_path / "f.fits", "--no-png")[0] == 0
    assert stat.S_IMODE(os.stat(tmp_path / "f.fits").st_mode) == 0o640


@pytest.mark.parametrize("case", ["empty", "directory", "fifo", "socket", "missing_folder", "input", "png_is_dir",
                                  "json_missing_folder", "trailing_slash", "link_loop", "same_twice"])
def test_unusable_output_is_one_line_before_any_work_and_nothing_is_touched(scene, tmp_path, case):
    before = scene.read_bytes()
    extra = []
    if case == "empty":
        out = ""
    elif case == "directory":
        out = tmp_path / "adir"
        out.mkdir()
    elif case == "fifo":
        out = tmp_path / "pipe.fits"
        os.mkfifo(out)
    elif case == "socket":  # AF_UNIX paths are short: a folder of its own under the system temp
        short = Path(tempfile.mkdtemp(prefix="nts"))
        out = short / "s.fits"
        sock = socket.socket(socket.AF_UNIX)
        sock.bind(str(out))
    elif case == "missing_folder":
        out = tmp_path / "nope" / "f.fits"
    elif case == "input":
        out = scene
    elif case == "png_is_dir":
        out = tmp_path / "f.fits"
        (tmp_path / "f.png").mkdir()
    elif case == "json_missing_folder":
        out = tmp_path / "f.fits"
        extra = ["--json", tmp_path / "nope" / "f.json"]
    elif case == "trailing_slash":
        out = str(tmp_path / "f.fits") + "/"
    elif case == "link_loop":
        out = tmp_path / "loop.fits"
        os.symlink(tmp_path / "loop2.fits", out)
        os.symlink(out, tmp_path / "loop2.fits")
    elif case == "same_twice":
        out = tmp_path / "f.fits"
        extra = ["--json", tmp_path / "f.png"]
    try:
        code, _, err = run("render", scene, "-o", out, *extra)
        line = one_line(err)
        assert code == 2, err
        assert line.startswith("newtsim: error: ")
        if case not in ("empty",):
            named = {"png_is_dir": "f.png", "json_missing_folder": "nope", "missing_folder": "nope",
                     "same_twice": "f.png"}.get(case, Path(str(out).rstrip("/")).name)
            assert named in line, line
        assert re.search(r"'-o|--output|--json|-o \(its", line), line
        # nothing written, nothing replaced
        assert scene.read_bytes() == before
        assert not (tmp_path / "f.fits").exists()
        assert not leftovers(tmp_path)
        if case == "fifo":
            assert stat.S_ISFIFO(os.lstat(out).st_mode)
        if case == "socket":
            assert stat.S_ISSOCK(os.lstat(out).st_mode)
        if case in ("directory", "png_is_dir"):
            assert (tmp_path / ("adir" if case == "directory" else "f.png")).is_dir()
    finally:
        if case == "socket":
            sock.close()
            out.unlink()
            short.rmdir()


def test_a_symlink_is_written_through_and_stays_a_link(scene, tmp_path):
    real = tmp_path / "data" / "frame.fits"
    real.parent.mkdir()
    real.write_bytes(b"old")
    link = tmp_path / "link.fits"
    os.symlink(real, link)
    code, _, err = run("render", scene, "-o", link, "--no-png")
    assert code == 0, err
    assert os.path.islink(link) and os.readlink(link) == str(real)
    assert fits.getdata(real).shape == (48, 64)
    # a dangling link creates its target (its folder must exist)
    dangling = tmp_path / "dangling.fits"
    os.symlink(tmp_path / "data" / "new.fits", dangling)
    assert run("render", scene, "-o", dangling, "--no-png")[0] == 0
    assert os.path.islink(dangling) and fits.getdata(tmp_path / "data" / "new.fits").shape == (48, 64)
    assert not leftovers(tmp_path)


def test_an_input_reached_through_a_link_is_not_overwritten(scene, tmp_path):
    link = tmp_path / "alias.fits"
    os.symlink(scene, link)
    code, _, err = run("render", scene, "-o", link, "--no-png")
    assert code == 2 and "is an input" in one_line(err)
    assert tomllib_load(scene)["detector"]["width"] == 64


def tomllib_load(p):
    import tomllib

    return tomllib.loads(Path(p).read_text())


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders: the check cannot be seen")
def test_read_only_folder_is_one_line(scene, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o555)
    try:
        code, _, err = run("render", scene, "-o", ro / "f.fits")
        assert code == 2 and "not writable" in one_line(err)
    finally:
        os.chmod(ro, 0o755)


def test_outputs_commit_all_or_nothing(tmp_path):
    """The layer itself: an error after the work removes every staged file; a later target that became a
    folder stops the commit before any rename."""
    with pytest.raises(RuntimeError), Outputs() as outs:
        a = outs.file(tmp_path / "a.json", "--json")
        b = outs.file(tmp_path / "b.html", "--report")
        a.write_text("{}")
        b.write_text("<html>")
        raise RuntimeError("the report failed")
    assert sorted(os.listdir(tmp_path)) == []
    with pytest.raises(OutputError, match="is a directory"), Outputs() as outs:
        a = outs.file(tmp_path / "a.json", "--json")
        b = outs.file(tmp_path / "b.html", "--report")
        a.write_text("{}")
        b.write_text("<html>")
        (tmp_path / "b.html").mkdir()  # meanwhile
    assert sorted(os.listdir(tmp_path)) == ["b.html"] and not (tmp_path / "a.json").exists()


@pytest.mark.parametrize("args, needle", [
    (["--seed", "-1"], "--seed"),
    (["--workers", "-3"], "--workers"),
    (["--workers", "0"], "--workers"),
])
def test_bad_option_values_are_one_line(scene, tmp_path, args, needle):
    code, _, err = run("render", scene, "-o", tmp_path / "f.fits", *args)
    assert code == 2 and needle in one_line(err)
    assert not (tmp_path / "f.fits").exists()


def test_other_commands_check_their_outputs_before_the_work(tmp_path):
    missing = tmp_path / "nope"
    bias = tmp_path / "b.fits"  # never read: the outputs are refused first
    cases = [
        (["characterize", "--bias", bias, bias, "--dark", bias, "--json", missing / "c.json"], "--json"),
        (["characterize", "--bias", bias, bias, "--dark", bias, "--emit-scene", missing / "c.toml"], "--emit-scene"),
        (["characterize", "--bias", bias, bias, "--dark", bias, "--plots", missing / "plots"], "--plots"),
        (["characterize", "--bias", bias, bias, "--dark", bias, "--json", ""], "--json"),
        (["optics", "layout", "art", "--plot", missing / "l.png"], "--plot"),
        (["optics", "vignetting", "art", "--json", tmp_path], "--json"),
        (["compare", "default", bias, "--report", missing / "r.html"], "--report"),
        (["diagnose", "default", bias, "--apply", missing / "s.toml"], "--apply"),
    ]
    for args, needle in cases:
        code, _, err = run(*args)
        assert code == 2, (args, err)
        assert needle in one_line(err), (args, err)
    assert sorted(os.listdir(tmp_path)) == []


def test_diagnose_refuses_to_apply_over_its_own_scene(tmp_path):
    sc = write_scene(tmp_path / "s.toml", TINY)
    code, _, err = run("diagnose", sc, tmp_path / "m.fits", "--apply", sc)
    assert code == 2 and "is an input" in one_line(err)


# --- strict scene types and messages ------------------------------------------------------------------------

@pytest.mark.parametrize("setting, key, expected", [
    ("detector.width=true", "detector.width", "an integer, not true/false"),
    ("exposure.time_s='2'", "exposure.time_s", "a number, not text"),
    ("sky.stars='yes'", "sky.stars", "true or false"),
    ("sky.stars=1", "sky.stars", "true or false"),
    ("exposure.time_s=nan", "exposure.time_s", "a finite number"),
    ("exposure.time_s=-inf", "exposure.time_s", "a finite number"),
    ("detector.gain_e_per_adu=nan", "detector.gain_e_per_adu", "a finite number"),
    ("detector.binning=2.5", "detector.binning", "an integer"),
    ("exposure.tracking='rate'", "exposure.rate_ra_deg_s", "tracking = 'rate'"),
    ("pointing.epoch='last tuesday'", "pointing.epoch", "ISO UTC time"),
    ("telescope.parity=true", "telescope.parity", ""),
])
def test_strict_scene_values_are_one_line_naming_file_and_key(scene, tmp_path, setting, key, expected):
    code, _, err = run("render", scene, "-o", tmp_path / "f.fits", "--set", setting)
    line = one_line(err)
    assert code == 2, err
    assert "scene.toml" in line and f"key '{key}'" in line and expected in line, line
    assert "Value error" not in line and "{" not in line  # no pydantic prefix, no dump of a table
    assert not (tmp_path / "f.fits").exists()


@pytest.mark.parametrize("text, needle", [
    ("", "empty"),
    ("# only a comment\n\n", "empty"),
])
def test_an_empty_scene_is_refused_not_the_default(tmp_path, text, needle):
    p = tmp_path / "s.toml"
    p.write_text(text)
    code, _, err = run("render", p, "-o", tmp_path / "f.fits")
    assert code == 2 and needle in one_line(err) and "s.toml" in err


def test_a_directory_as_scene_or_frame_is_named_a_directory(tmp_path):
    d = tmp_path / "dir.toml"
    d.mkdir()
    code, _, err = run("render", d, "-o", tmp_path / "f.fits")
    assert code == 2 and "is a directory" in one_line(err)
    fd = tmp_path / "frame.fits"
    fd.mkdir()
    sc = write_scene(tmp_path / "s.toml", TINY)
    code, _, err = run("compare", sc, fd)
    assert code == 2 and "is a directory" in one_line(err)


def test_a_truncated_vignetting_map_is_one_line(tmp_path):
    h = fits.Header()
    for k, v in (("CRVAL1", -10.0), ("CDELT1", 1.0), ("CRVAL2", -10.0), ("CDELT2", 1.0)):
        h[k] = v
    fits.PrimaryHDU(np.ones((21, 21)), h).writeto(tmp_path / "v.fits")
    (tmp_path / "cut.fits").write_bytes((tmp_path / "v.fits").read_bytes()[:4000])
    sc = write_scene(tmp_path / "s.toml", {**TINY, "effects": {"vignetting": {"map_file": "cut.fits"}}})
    code, _, err = run("render", sc, "-o", tmp_path / "f.fits")
    line = one_line(err)
    assert code == 2 and "effects.vignetting.map_file" in line and "truncated" in line


def test_impossible_designs_are_one_line(tmp_path):
    import tomli_w
    import tomllib

    base = tomllib.loads((ROOT / "optics" / "designs" / "bare.toml").read_text())
    for change, needle in (({"spider": {"vanes": 4, "width_mm": 500.0}}, "wider than the aperture"),
                           ({"spider": {"vanes": 16, "width_mm": 150.0}}, "cover the whole aperture"),
                           ({"baffle": {"vanes": 5, "vane_inner_diameter_mm": 300.0}}, "closes the aperture")):
        d = {**base, **{k: {**base.get(k, {}), **v} for k, v in change.items()}}
        p = tmp_path / "d.toml"
        p.write_text(tomli_w.dumps(d))
        code, _, err = run("optics", "layout", p, "--plot", tmp_path / "l.png")
        line = one_line(err)
        assert code == 2 and needle in line and "Value error" not in line, line


def test_a_far_epoch_warns_once_in_plain_words_or_not_at_all(scene, tmp_path):
    code, _, err = run("render", scene, "-o", tmp_path / "f.fits", "--no-png", "--set",
                       "pointing.epoch='2400-01-01T00:00:00'")
    assert code == 0, err
    lines = err.strip().splitlines()
    assert all(ln.startswith(("newtsim: warning:", "wrote ")) for ln in lines), err
    assert len([ln for ln in lines if "warning" in ln]) == len({ln for ln in lines if "warning" in ln})


# --- measured frames with NaN / inf pixels ----------------------------------------------------------------

@pytest.fixture(scope="module")
def sky_frame(tmp_path_factory):
    from scenes.app.render import render
    from scenes.scene import load_scene

    d = tmp_path_factory.mktemp("nan")
    (d / "sky.toml").write_text(SMALL_SKY_TOML)
    render(load_scene(str(d / "sky.toml")), d / "sky.fits", seed=7)
    return d


def _with_nonfinite(src: Path, dst: Path, fraction: float, seed: int = 2) -> int:
    with fits.open(src) as hdul:
        data = hdul[0].data.astype(np.float32)
        header = hdul[0].header.copy()
    rng = np.random.default_rng(seed)
    bad = rng.random(data.shape) < fraction
    data[bad] = np.where(rng.random(int(bad.sum())) < 0.8, np.nan, np.inf)
    for k in ("BZERO", "BSCALE"):
        header.remove(k, ignore_missing=True)
    fits.PrimaryHDU(data, header).writeto(dst)
    return int(bad.sum())


def test_nan_pixels_are_counted_masked_and_reported_not_a_defect(sky_frame, tmp_path):
    """3 % NaN/inf pixels: diagnose names nothing (before: column_defects, and --apply wrote it)."""
    n = _with_nonfinite(sky_frame / "sky.fits", tmp_path / "nan.fits", 0.03)
    code, _, err = run("diagnose", sky_frame / "sky.toml", tmp_path / "nan.fits", "--json", tmp_path / "d.json",
                       "--apply", tmp_path / "next.toml", "--report", tmp_path / "r.html")
    assert code == 0, err
    out = json.loads((tmp_path / "d.json").read_text())
    assert out["baseline"]["nonfinite_pixels"] == n
    assert not out["significant"], [(c["effect"], c["delta_bic"]) for c in out["candidates"][:3]]
    assert out["applied"] is None and not (tmp_path / "next.toml").exists()
    assert all(c["effect"] != "column_defects" or not c["significant"] for c in out["candidates"])
    assert f"{n} measured pixels" in (tmp_path / "r.html").read_text()
    assert f"{n} non-finite" in err
    assert not leftovers(tmp_path) and not leftovers(sky_frame)
    # the chi2 of the masked frame agrees with the clean frame's
    code, _, _ = run("compare", sky_frame / "sky.toml", sky_frame / "sky.fits", "--json", tmp_path / "c.json")
    clean = json.loads((tmp_path / "c.json").read_text())
    assert abs(out["baseline"]["chi2_per_dof"] - clean["chi2_per_dof"]) < 0.05
    assert clean["nonfinite_pixels"] == 0


def test_a_mostly_nan_frame_is_refused_in_one_line(sky_frame, tmp_path):
    _with_nonfinite(sky_frame / "sky.fits", tmp_path / "nan.fits", 0.6)
    code, _, err = run("compare", sky_frame / "sky.toml", tmp_path / "nan.fits", "--json", tmp_path / "c.json")
    line = one_line(err)
    assert code == 2 and "NaN or infinite" in line and "nan.fits" in line
    assert not (tmp_path / "c.json").exists()


# --- interrupts and a full disk (subprocesses) -----------------------------------------------------------------

#: a render long enough to be interrupted at several moments (a full ML11002 frame with EXPECTED and PNG)
SLOW = {"detector": {"preset": "ml11002"}, "exposure": {"time_s": 1.0, "frame": "dark", "seed": 1}}


def _wait_for(proc, seconds):
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end and proc.poll() is None:
        time.sleep(0.02)


def _wait_for_staging(proc, folder: Path, seconds: float) -> bool:
    """Wait until the command has checked its outputs and started writing (its staging folder exists)."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end and proc.poll() is None:
        if leftovers(folder):
            return True
        time.sleep(0.02)
    return False


@pytest.mark.parametrize("sig, moment, twice", [
    (signal.SIGINT, "import", False),    # 0.5 s in: while Python imports numpy / astropy
    (signal.SIGINT, "work", False),      # the outputs are staged, the frame is being computed
    (signal.SIGTERM, "work", False),
    (signal.SIGINT, "late", False),      # 1.5 s into the work
    (signal.SIGINT, "work", True),       # a second Ctrl-C is respected
])
def test_an_interrupt_is_one_line_and_leaves_nothing(tmp_path, sig, moment, twice):
    sc = write_scene(tmp_path / "slow.toml", SLOW)
    proc = newtsim_proc("render", sc, "-o", tmp_path / "f.fits", "--expected", "--json", tmp_path / "f.json",
                        cwd=tmp_path)
    if moment == "import":
        _wait_for(proc, 0.5)
    else:
        assert _wait_for_staging(proc, tmp_path, 120), "the render never started writing"
        _wait_for(proc, 1.5 if moment == "late" else 0.2)
    if proc.poll() is not None:
        pytest.skip(f"the render finished before the {moment} signal: nothing to interrupt")
    proc.send_signal(sig)
    if twice:
        time.sleep(0.05)
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    left = sorted(os.listdir(tmp_path))
    done = ["f.fits", "f.json", "f.png", "slow.toml"]
    if proc.returncode == 0:  # the signal landed after the outputs were committed, in the last instants
        assert moment == "late" and left == done and not err.strip(), (left, err)
        return
    assert proc.returncode == 128 + sig, (proc.returncode, err)
    assert err.strip() == "newtsim: interrupted", err
    # nothing, or (a signal between the commit and the exit) the whole outputs, never a part of them
    assert left == ["slow.toml"] or (moment == "late" and left == done), left


def test_a_full_disk_is_one_line_and_leaves_nothing(tmp_path):
    sc = write_scene(tmp_path / "s.toml", {**TINY, "detector": {"preset": "ml11002", "width": 512, "height": 512}})
    limit = 200_000  # bytes: the 512 x 512 uint16 frame (512 kB) does not fit

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = newtsim_proc("render", sc, "-o", tmp_path / "f.fits", cwd=tmp_path, preexec_fn=small_files)
    _, err = proc.communicate(timeout=300)
    line = one_line(err)
    assert proc.returncode == 1, err
    assert "no room" in line and "nothing was written" in line
    assert sorted(os.listdir(tmp_path)) == ["s.toml"]


def test_a_folder_output_is_created_or_its_files_replaced(tmp_path):
    """``--plots``: a new folder appears whole at commit; an existing one gets its files replaced one by one
    (other files in it stay); nothing appears on an error."""
    with Outputs() as outs:
        d = outs.folder(tmp_path / "plots", "--plots")
        (d / "a.png").write_bytes(b"a1")
        assert not (tmp_path / "plots").exists()
    assert (tmp_path / "plots" / "a.png").read_bytes() == b"a1"
    (tmp_path / "plots" / "mine.txt").write_text("keep")
    with Outputs() as outs:
        d = outs.folder(tmp_path / "plots", "--plots")
        (d / "a.png").write_bytes(b"a2")
        (d / "b.png").write_bytes(b"b2")
    assert sorted(os.listdir(tmp_path / "plots")) == ["a.png", "b.png", "mine.txt"]
    assert (tmp_path / "plots" / "a.png").read_bytes() == b"a2"
    with pytest.raises(KeyboardInterrupt), Outputs() as outs:
        d = outs.folder(tmp_path / "new", "--plots")
        (d / "a.png").write_bytes(b"x")
        raise KeyboardInterrupt
    assert not (tmp_path / "new").exists() and not leftovers(tmp_path)
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="--plots"):
        Outputs().folder(tmp_path / "file", "--plots")


def test_staged_paths_are_reported_as_the_users(tmp_path):
    with Outputs() as outs:
        p = outs.file(tmp_path / "a.toml", "--apply")
        sibling = p.with_name("a.ledger.json")
        shown = outs.public({"scene": str(p), "ledger": [str(sibling)]})
        p.write_text("x = 1\n")
        sibling.write_text("{}")
    assert shown == {"scene": str(tmp_path / "a.toml"), "ledger": [str(tmp_path / "a.ledger.json")]}
    assert sorted(os.listdir(tmp_path)) == ["a.ledger.json", "a.toml"]


def test_a_field_angle_no_ray_reaches_is_one_line(mi, tmp_path):
    code, _, err = run("optics", "psf", "bare", "--field-deg", "45", "0", "--geometric", "--no-cache",
                       "--json", tmp_path / "p.json")
    line = one_line(err)
    assert code == 2 and "--field-deg" in line and "no ray reached" in line
    assert sorted(os.listdir(tmp_path)) == []


def test_a_file_the_scene_reads_is_not_overwritten(tmp_path):
    h = fits.Header()
    for k, v in (("CRVAL1", -20.0), ("CDELT1", 2.0), ("CRVAL2", -20.0), ("CDELT2", 2.0)):
        h[k] = v
    fits.PrimaryHDU(np.ones((21, 21)), h).writeto(tmp_path / "vig.fits")
    before = (tmp_path / "vig.fits").read_bytes()
    sc = write_scene(tmp_path / "s.toml", {**TINY, "effects": {"vignetting": {"map_file": "vig.fits"}}})
    code, _, err = run("render", sc, "-o", tmp_path / "vig.fits")
    assert code == 2 and "the scene reads" in one_line(err)
    assert (tmp_path / "vig.fits").read_bytes() == before and not leftovers(tmp_path)


def test_a_failing_report_leaves_no_json_and_no_applied_scene(sky_frame, tmp_path, monkeypatch):
    """One of several outputs fails (the HTML report): none of them is written (before: a JSON without its
    report, an --apply scene without its diagnosis)."""
    import scenes.app.cli.compare as cmp_cli
    from detector import DetectorError

    def broken(*a, **k):
        raise DetectorError("cannot write the report (No space left on device)", file="r.html")

    monkeypatch.setattr(cmp_cli, "write_report", broken)
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    out.mkdir()
    (src / "sky.toml").write_text((sky_frame / "sky.toml").read_text())
    code, _, err = run("compare", src / "sky.toml", sky_frame / "sky.fits", "--json", out / "c.json",
                       "--report", out / "r.html")
    assert code == 2 and "cannot write the report" in one_line(err)
    assert sorted(os.listdir(out)) == []
    code, _, err = run("diagnose", src / "sky.toml", sky_frame / "sky.fits", "--json", out / "d.json",
                       "--apply", out / "next.toml", "--report", out / "r.html")
    assert code == 2 and "cannot write the report" in one_line(err)
    assert sorted(os.listdir(out)) == [] and sorted(os.listdir(src)) == ["sky.toml"]


def test_sigterm_stops_a_batch_in_one_line_and_it_resumes(tmp_path):
    """A batch is committed frame by frame: SIGTERM keeps the frames done (in the manifest), leaves no
    temporary file, and says the same command resumes."""
    write_scene(tmp_path / "s.toml", SLOW)
    (tmp_path / "b.toml").write_text('[batch]\nscene = "s.toml"\noutput_dir = "out"\nseed = 3\n'
                                     '[[sweep]]\nkey = "exposure.time_s"\nvalues = [1, 2, 3, 4, 5, 6]\n')
    proc = newtsim_proc("batch", tmp_path / "b.toml", "--workers", "1", cwd=tmp_path)
    t_end = time.monotonic() + 180
    while time.monotonic() < t_end and proc.poll() is None and not (tmp_path / "out" / "manifest.json").exists():
        time.sleep(0.05)
    _wait_for(proc, 1.0)
    if proc.poll() is not None:
        pytest.skip("the batch finished before the signal")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    # newtsim's own line; Dask's worker processes may log their own shutdown around it (docs/reliability.md)
    ours = [ln for ln in err.strip().splitlines() if ln.startswith("newtsim:")]
    assert len(ours) == 1 and re.fullmatch(r"newtsim: interrupted; \S+manifest\.json lists the frames done: the "
                                           r"same command resumes", ours[0]), err
    names = sorted(os.listdir(tmp_path / "out"))
    assert "manifest.json" in names and not [n for n in names if n.startswith(".")], names
    entries = json.loads((tmp_path / "out" / "manifest.json").read_text())["frames"]
    done = {f"frame_{e['index']:04d}.fits" for e in entries if e["status"] == "done"}
    on_disk = {n for n in names if n.endswith(".fits")}
    assert done <= on_disk  # a frame finished as the signal came may be on disk, not yet marked done
    for n in on_disk:  # every frame on disk is complete (written aside, renamed when whole)
        assert fits.getdata(tmp_path / "out" / n).shape == (2672, 4008)
