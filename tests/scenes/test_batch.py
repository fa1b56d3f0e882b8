"""``newtsim batch``: schema, frame bookkeeping, sequences, reproducibility, resume, failures, Dask paths.

Frames are 64 x 64 pixels of the built-in default scene (~0.2 s each); most runs use one in-process
LocalCluster (threads); one test starts worker processes, one connects with ``--scheduler``.
"""

import hashlib
import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner

from scenes.app.batch import (
    MANIFEST,
    frame_seed,
    load_batch,
    run_batch,
    sequence_overrides,
    toml_inline,
)
from scenes.app.cli import cli
from scenes.objects.frames import angle_between_deg, radec_to_unit
from scenes.scene import SceneError, load_scene, parse_value

TINY = '[overrides]\ndetector.width = 64\ndetector.height = 64\n'
ROOT = Path(__file__).resolve().parents[2]


def write_batch(folder: Path, body: str, *, name="b.toml", seed=11, tiny=True, scene="default") -> Path:
    text = f'[batch]\nscene = "{scene}"\noutput_dir = "{folder / "out"}"\nseed = {seed}\n'
    p = folder / name
    p.write_text(text + (TINY if tiny else "") + textwrap.dedent(body))
    return p


@pytest.fixture(scope="module")
def client():
    """One in-process LocalCluster (2 threads) for the module."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as c:
        yield c


def manifest(folder: Path) -> dict:
    return json.loads((folder / "out" / MANIFEST).read_text())


# ------------------------------------------------------------------------------------------------ schema
@pytest.mark.parametrize("body, key, expected", [
    ('[batch]\nscene = "default"\n', "batch.seed", "a value"),
    ('[batch]\nscene = "default"\nseed = -1\n', "batch.seed", ">= 0"),
    ('[batch]\nscene = "default"\nseed = 1\nscen = "x"\n', "batch.scen", "one of the documented keys"),
    ('[batch]\nscene = "default"\nseed = 1\n[[sweep]]\nkey = "exposure.time_s"\nvalues = []\n', "sweep.0.values",
     "one value or more"),
    ('[batch]\nscene = "default"\nseed = 1\n[[sweep]]\nkey = "exposure..time_s"\nvalues = [1]\n', "sweep.0.key",
     "a key like exposure.time_s"),
    ('[batch]\nscene = "default"\nseed = 1\n[[sweep]]\nkey = ["psf.model", "psf.fwhm_arcsec"]\nvalues = [["moffat"]]\n',
     "sweep.0.values[0]", "one value per key of ['psf.model', 'psf.fwhm_arcsec']"),
    ('[batch]\nscene = "default"\nseed = 1\n[sequence]\nframes = 3\ncadence_s = 0\n', "sequence.cadence_s", "> 0"),
    ('[batch]\nscene = "default"\nseed = 1\n[montecarlo]\ndraws = 0\n', "montecarlo.draws", ">= 1"),
    (('[batch]\nscene = "default"\nseed = 1\n[[sweep]]\nkey = "exposure.time_s"\nvalues = [1]\n'
     '[[sweep]]\nkey = ["psf.model", "exposure.time_s"]\nvalues = [["moffat", 2]]\n'), "sweep.1.key", "in one [[sweep]]"),
    ('[batch]\nscene = "nosuch.toml"\nseed = 1\n', "batch.scene", "a scene TOML path relative to the batch file"),
])
def test_schema_errors_name_file_key_and_expectation(tmp_path, body, key, expected):
    p = tmp_path / "bad.toml"
    p.write_text(body)
    with pytest.raises(SceneError) as err:
        load_batch(p)
    msg = str(err.value)
    assert msg.startswith(str(p)) and f"key '{key}'" in msg and expected in msg, msg


def test_invalid_base_scene_names_batch_and_scene_key(tmp_path):
    p = write_batch(tmp_path, "[overrides]\nexposure.time_s = -3\n", tiny=False)
    with pytest.raises(SceneError) as err:
        load_batch(p)
    msg = str(err.value)
    assert msg.startswith(f"{p}: base scene: ") and "key 'exposure.time_s'" in msg and "(expected >= 0" in msg


def test_cli_user_error_is_one_line_exit_2(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('[batch]\nscene = "default"\nseed = "one"\n')
    r = CliRunner().invoke(cli, ["batch", str(p)])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert r.stderr.strip().count("\n") == 0 and "key 'batch.seed'" in r.stderr and str(p) in r.stderr
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------- bookkeeping
def test_frame_count_order_names_and_seeds(tmp_path):
    p = write_batch(tmp_path, """
        [[sweep]]
        key = "exposure.time_s"
        values = [1.0, 2.0, 5.0]
        [[sweep]]
        key = ["psf.model", "psf.fwhm_arcsec"]
        values = [["gaussian", 2.0], ["moffat", 3.5]]
        [sequence]
        frames = 4
        cadence_s = 10.0
        [montecarlo]
        draws = 5
        """, seed=1234)
    b = load_batch(p)
    assert len(b.frames) == 3 * 2 * 4 * 5 == 120
    assert [f.index for f in b.frames] == list(range(120))
    assert [Path(f.file).name for f in b.frames[:2]] == ["frame_0000.fits", "frame_0001.fits"]
    assert Path(b.frames[-1].file).name == "frame_0119.fits" and Path(b.frames[0].file).parent == tmp_path / "out"
    # i = (p * frames + k) * draws + d, first sweep slowest
    f = b.frames[(5 * 4 + 2) * 5 + 3]  # point 5 = (time 5.0, moffat 3.5), step 2, draw 3
    assert (f.step, f.draw) == (2, 3)
    assert f.overrides == {"exposure.time_s": 5.0, "psf.model": "moffat", "psf.fwhm_arcsec": 3.5}
    assert "exposure.time_s=5.0" in f.sets and 'psf.model="moffat"' in f.sets and "detector.width=64" in f.sets
    seeds = [f.seed for f in b.frames]
    assert len(set(seeds)) == 120 and all(0 <= s < 2 ** 63 for s in seeds)
    children = np.random.SeedSequence(1234).spawn(120)
    assert seeds[77] == int(children[77].generate_state(1, np.uint64)[0] >> np.uint64(1)) == frame_seed(1234, 77)


@pytest.mark.parametrize("value", [0.1, 1e-300, -2.5e17, float("inf"), 3, True, "a \"quoted\"\nline\\",
                                   [1, 2.5, "x"], {"a": 1, "b c": [0.3, {"d": False}]},
                                   [{"name": "x", "tle": "1 2\n2 3", "ra_deg": 120.95115000000001}]])
def test_toml_inline_round_trips_through_set(value):
    assert parse_value(toml_inline(value)) == value


# ------------------------------------------------------------------------------------------ sequences
def _scene(tmp_path, tracking, rates=(0.0, 0.0), objects=""):
    extra = f"rate_ra_deg_s = {rates[0]}\nrate_dec_deg_s = {rates[1]}\n" if tracking == "rate" else ""
    p = tmp_path / f"s_{tracking}.toml"
    p.write_text(f'[pointing]\nra_deg = 120.0\ndec_deg = -29.0\nepoch = "2023-02-01T22:00:00"\n'
                 f'[exposure]\ntime_s = 1.0\ntracking = "{tracking}"\n{extra}{objects}')
    return load_scene(str(p))


def test_sequence_moves_epoch_mount_and_rate_objects_along_great_circles(tmp_path):
    obj = ('[[objects]]\nra_deg = 120.0\ndec_deg = -29.0\nrate_ra_deg_s = 0.02\nrate_dec_deg_s = -0.01\nphotons = 1e4\n'
           '[[objects]]\nra_deg = 120.1\ndec_deg = -29.1\nrate_ra_deg_s = 0.3\nrate_dec_deg_s = 0.4\nphotons = 1e4\n')
    sc = _scene(tmp_path, "rate", (0.02, -0.01), obj)
    dt = 37.0
    o = sequence_overrides(sc, dt)
    assert o["pointing.epoch"] == "2023-02-01T22:00:37.000000"
    # the boresight moved speed x dt along its great circle, the rates keep the speed
    moved = angle_between_deg(radec_to_unit(120.0, -29.0), radec_to_unit(o["pointing.ra_deg"], o["pointing.dec_deg"]))
    assert moved == pytest.approx(math.hypot(0.02, 0.01) * dt, rel=1e-12)
    assert math.hypot(o["exposure.rate_ra_deg_s"], o["exposure.rate_dec_deg_s"]) == pytest.approx(math.hypot(0.02, 0.01))
    # an object with the tracking's rates at the boresight stays at the boresight
    a, b = o["objects"]
    assert (a["ra_deg"], a["dec_deg"]) == pytest.approx((o["pointing.ra_deg"], o["pointing.dec_deg"]), abs=1e-12)
    d = angle_between_deg(radec_to_unit(120.1, -29.1), radec_to_unit(b["ra_deg"], b["dec_deg"]))
    assert d == pytest.approx(0.5 * dt, rel=1e-12) and b["photons"] == 1e4
    # two steps of dt equal one of 2 dt (a great circle, not a rhumb line)
    sc2 = load_scene(sc.source, [f"{k}={toml_inline(v)}" for k, v in o.items()])
    two = sequence_overrides(sc2, dt)["objects"][1]
    once = sequence_overrides(sc, 2 * dt)["objects"][1]
    assert (two["ra_deg"], two["dec_deg"], two["rate_dec_deg_s"]) == pytest.approx(
        (once["ra_deg"], once["dec_deg"], once["rate_dec_deg_s"]), abs=1e-9)


def test_sequence_sidereal_and_drive_off(tmp_path):
    assert sequence_overrides(_scene(tmp_path, "sidereal"), 60.0) == {"pointing.epoch": "2023-02-01T22:01:00.000000"}
    o = sequence_overrides(_scene(tmp_path, "none"), 60.0)
    assert o["pointing.ra_deg"] - 120.0 == pytest.approx(360.0 / 86164.0905 * 60.0, rel=1e-9)
    assert "pointing.dec_deg" not in o and sequence_overrides(_scene(tmp_path, "none"), 0.0) == {}


# ---------------------------------------------------------------------------- rendering on the cluster
def test_batch_frames_equal_direct_render_bytes(tmp_path, client):
    p = write_batch(tmp_path, """
        [[sweep]]
        key = "exposure.time_s"
        values = [1.0, 3.0]
        [sequence]
        frames = 2
        cadence_s = 5.0
        """)
    s = run_batch(load_batch(p), client=client, progress=False)
    assert (s["rendered"], s["failed"], s["skipped"]) == (4, 0, 0)
    m = manifest(tmp_path)
    assert m["counts"] == {"done": 4, "failed": 0, "pending": 0} and m["root_seed"] == 11
    runner = CliRunner()
    for e in m["frames"]:
        batch_file = tmp_path / "out" / e["file"]
        direct = tmp_path / f"direct_{e['index']}.fits"
        args = ["render", "default", "-o", str(direct), "--seed", str(e["seed"]), "--no-png"]
        for item in e["set"]:
            args += ["--set", item]
        r = runner.invoke(cli, args)
        assert r.exit_code == 0, r.output
        assert direct.read_bytes() == batch_file.read_bytes(), e
        assert e["sha256"] == hashlib.sha256(batch_file.read_bytes()).hexdigest()
        assert e["bytes"] == batch_file.stat().st_size and e["wall_s"] > 0
    h3 = fits.getheader(tmp_path / "out" / "frame_0003.fits")
    assert h3["SEED"] == m["frames"][3]["seed"] and h3["EXPTIME"] == 3.0 and h3["DATE-OBS"].endswith("22:00:05.000000")
    assert "time_s = 3.0" in fits.getdata(tmp_path / "out" / "frame_0003.fits", "SCENE")["toml"][0]
    assert m["frames"][3]["command"].startswith("newtsim render default -o ")


def test_resume_skips_done_frames_and_redoes_changed_or_damaged(tmp_path, client):
    body = '[[sweep]]\nkey = "exposure.time_s"\nvalues = [1.0, 2.0, 4.0]\n'
    p = write_batch(tmp_path, body)
    assert run_batch(load_batch(p), client=client, progress=False)["rendered"] == 3
    out = tmp_path / "out"
    mtimes = {f.name: f.stat().st_mtime_ns for f in out.glob("frame_*.fits")}
    again = run_batch(load_batch(p), client=client, progress=False)
    assert (again["rendered"], again["skipped"]) == (0, 3)
    assert {f.name: f.stat().st_mtime_ns for f in out.glob("frame_*.fits")} == mtimes
    # a changed sweep value redoes its frame only; a truncated file and a killed render's leftover too
    p.write_text(p.read_text().replace("4.0]", "8.0]"))
    (out / "frame_0000.fits").write_bytes((out / "frame_0000.fits").read_bytes()[:2880])
    (out / ".frame_0001.fits.x1y2.part").write_bytes(b"half a frame")
    s = run_batch(load_batch(p), client=client, progress=False)
    assert (s["rendered"], s["skipped"]) == (2, 1)
    assert (out / "frame_0001.fits").stat().st_mtime_ns == mtimes["frame_0001.fits"]
    assert (out / "frame_0002.fits").stat().st_mtime_ns != mtimes["frame_0002.fits"]
    assert manifest(tmp_path)["frames"][2]["overrides"] == {"exposure.time_s": 8.0}
    assert not list(out.glob(".*.part"))
    # --force redoes everything
    assert run_batch(load_batch(p), client=client, progress=False, force=True)["rendered"] == 3


def test_failing_frame_is_reported_and_others_complete_via_scheduler(tmp_path, client):
    p = write_batch(tmp_path, """
        [[sweep]]
        key = "exposure.time_s"
        values = [1.0, -1.0, 2.0]
        [[sweep]]
        key = "sky.background_mag_arcsec2"
        values = [20.0]
        """)
    js = tmp_path / "summary.json"
    r = CliRunner().invoke(cli, ["batch", str(p), "--scheduler", client.scheduler.address, "--json", str(js)])
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output
    assert "frame 1 (frame_0001.fits; exposure.time_s=-1.0 sky.background_mag_arcsec2=20.0) failed:" in r.stderr
    assert "key 'exposure.time_s'" in r.stderr and "(expected >= 0" in r.stderr
    s = json.loads(js.read_text())
    assert s["scheduler"] == client.scheduler.address
    assert (s["rendered"], s["failed"]) == (2, 1) and [f["index"] for f in s["failures"]] == [1]
    m = manifest(tmp_path)
    assert [e["status"] for e in m["frames"]] == ["done", "failed", "done"]
    assert "exposure.time_s" in m["frames"][1]["error"] and "traceback" not in m["frames"][1]
    out = tmp_path / "out"
    assert sorted(f.name for f in out.glob("*.fits")) == ["frame_0000.fits", "frame_0002.fits"]
    assert not list(out.glob(".*"))
    # the failed frame is retried on the next run, the others are kept
    s2 = run_batch(load_batch(p), client=client, progress=False)
    assert (s2["skipped"], s2["failed"], s2["rendered"]) == (2, 1, 0)


def test_dry_run_lists_frames_and_flags_invalid_ones_without_writing(tmp_path):
    p = write_batch(tmp_path, '[[sweep]]\nkey = "psf.model"\nvalues = ["gaussian", "airy"]\n[montecarlo]\ndraws = 2\n')
    js = tmp_path / "plan.json"
    r = CliRunner().invoke(cli, ["batch", str(p), "--dry-run", "--json", str(js)])
    assert r.exit_code == 1
    plan = json.loads(js.read_text())
    assert [f["action"] for f in plan["plan"]] == ["render", "render", "invalid", "invalid"]
    assert "key 'psf.model'" in plan["plan"][2]["error"] and plan["counts"] == {"render": 2, "skip": 0, "invalid": 2}
    assert not (tmp_path / "out").exists()


def test_local_cluster_of_processes_from_the_command_line(tmp_path):
    p = write_batch(tmp_path, "[montecarlo]\ndraws = 2\n")
    proc = subprocess.Popen([sys.executable, "-m", "scenes.app.cli", "batch", str(p), "--workers", "2", "--set",
                             "exposure.time_s=0.5"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == 0, err
    assert "batch: 2 frames: 2 rendered, 0 already done, 0 failed" in err
    m = manifest(tmp_path)
    assert [e["status"] for e in m["frames"]] == ["done", "done"]
    assert all(e["pid"] != proc.pid for e in m["frames"])  # rendered in worker processes, not the client
    assert all("exposure.time_s=0.5" in e["set"] for e in m["frames"])
    a, b = (fits.getdata(tmp_path / "out" / e["file"]).astype(float) for e in m["frames"])
    assert a.shape == (64, 64) and not np.array_equal(a, b)  # two draws: other noise


def test_scheduler_file_is_accepted(tmp_path, client):
    sched = tmp_path / "scheduler.json"
    sched.write_text(json.dumps({"address": client.scheduler.address}))
    p = write_batch(tmp_path, "")
    js = tmp_path / "s.json"
    r = CliRunner().invoke(cli, ["batch", str(p), "--scheduler", str(sched), "--json", str(js)])
    assert r.exit_code == 0, r.output
    s = json.loads(js.read_text())
    assert s["scheduler"] == client.scheduler.address and (s["frames"], s["rendered"]) == (1, 1)
    assert fits.getheader(tmp_path / "out" / "frame_0000.fits")["SEED"] == frame_seed(11, 0)


def test_sequence_frames_after_an_object_left_the_field_render_without_it(tmp_path):
    """A sequence step's objects carry outside = "skip": the object crosses the 64-px window in step 0 and
    is 0.5 deg away 10 s later; that frame renders without it (no TRUTH row), while the base scene with the
    object placed there still refuses it (a typo in the rates is a user error)."""
    from scenes.app.render import prepare
    from scenes.scene import SceneError

    p = tmp_path / "s.toml"
    p.write_text('[detector]\npreset = "ml11002"\nwidth = 64\nheight = 64\n'
                 '[pointing]\nra_deg = 120.0\ndec_deg = -29.0\nepoch = "2023-02-01T22:00:00"\n'
                 '[exposure]\ntime_s = 0.1\n'
                 '[[objects]]\nra_deg = 120.0\ndec_deg = -29.0\nrate_ra_deg_s = 0.0\nrate_dec_deg_s = 0.05\n'
                 'photons = 1e5\n')
    sc = load_scene(str(p))
    assert int(np.sum(prepare(sc).truth["kind"] == b"object")) == 1
    o = sequence_overrides(sc, 10.0)
    assert o["objects"][0]["outside"] == "skip"
    later = load_scene(str(p), [f"{k}={toml_inline(v)}" for k, v in o.items()])
    assert int(np.sum(prepare(later).truth["kind"] == b"object")) == 0
    moved = {k: v for k, v in o["objects"][0].items() if k != "outside"}
    base = load_scene(str(p), [f"objects={toml_inline([moved])}", f"pointing.epoch={toml_inline(o['pointing.epoch'])}"])
    with pytest.raises(SceneError, match="stays outside the field"):
        prepare(base)
