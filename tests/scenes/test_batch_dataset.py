"""``newtsim batch --labels``: a labelled dataset (frames, per-frame and dataset label files, splits, resume)."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner
from helpers import write_scene

from scenes.app.batch import SPLITS, frame_split, load_batch, run_batch
from scenes.app.cli import cli
from scenes.scene import SceneError

N_DRAWS = 6


def streak_scene(folder: Path) -> Path:
    """A 64 x 64 ML11002 window with one streak crossing it (one object label per frame) and no stars."""
    return write_scene(folder / "s.toml", {
        "detector": {"preset": "ml11002", "width": 64, "height": 64},
        "exposure": {"time_s": 2.0, "frame": "light"},
        "sky": {"stars": False, "background_mag_arcsec2": 20.0},
        "pointing": {"ra_deg": 120.0, "dec_deg": -29.0, "epoch": "2023-02-01T22:00:00"},
        "psf": {"model": "gaussian", "fwhm_arcsec": 3.0},
        "objects": [{"ra_deg": 120.0, "dec_deg": -29.0, "rate_ra_deg_s": 0.0008, "rate_dec_deg_s": -0.0005,
                     "photons": 40000}]})


def write_batch(folder: Path, extra: str = "") -> Path:
    streak_scene(folder)
    p = folder / "b.toml"
    p.write_text(textwrap.dedent(f"""\
        [batch]
        scene = "s.toml"
        output_dir = "{folder / 'out'}"
        seed = 3
        {extra}
        [montecarlo]
        draws = {N_DRAWS}
        """))
    return p


def test_split_is_a_function_of_the_seed_with_the_stated_fractions():
    seeds = np.random.default_rng(0).integers(0, 2 ** 62, 20000)
    splits = [frame_split(int(s), (0.7, 0.2, 0.1)) for s in seeds]
    frac = {k: splits.count(k) / len(splits) for k in SPLITS}
    # binomial scatter of 20000 draws: sigma <= 0.0033; 4 sigma
    assert abs(frac["train"] - 0.7) < 0.013 and abs(frac["val"] - 0.2) < 0.012 and abs(frac["test"] - 0.1) < 0.009
    assert all(frame_split(int(s), (0.7, 0.2, 0.1)) == k for s, k in zip(seeds[:50], splits[:50]))
    assert frame_split(5, (1.0, 0.0, 0.0)) == "train" and frame_split(5, (0.0, 0.0, 1.0)) == "test"


def test_bad_label_format_and_fractions_name_file_and_key(tmp_path):
    p = write_batch(tmp_path, "split = [0.5, 0.2, 0.2]")
    with pytest.raises(SceneError, match="batch.split") as e:
        load_batch(p)
    assert "summing to 1" in str(e.value)
    p = write_batch(tmp_path, 'labels = ["coco", "voc"]')
    with pytest.raises(SceneError, match="'voc'") as e:
        load_batch(p)
    assert "batch.labels" in str(e.value) and str(p) in str(e.value)
    r = CliRunner().invoke(cli, ["batch", str(write_batch(tmp_path)), "--labels", "coco,xml", "--dry-run"])
    assert r.exit_code == 2 and "--labels" in r.output and "'xml'" in r.output


def test_labelled_batch_writes_a_dataset_coco_loads_and_resumes(tmp_path):
    from distributed import Client, LocalCluster
    from pycocotools.coco import COCO

    p = write_batch(tmp_path)
    out = tmp_path / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        s = run_batch(load_batch(p, labels="coco,satnet,yolo,fits"), client=client, progress=False)
        assert (s["rendered"], s["failed"]) == (N_DRAWS, 0)
        m = json.loads((out / "manifest.json").read_text())
        assert m["split"]["fractions"] == {"train": 0.8, "val": 0.1, "test": 0.1}
        assert m["labels"]["formats"] == ["coco", "satnet", "yolo", "fits"]
        for e in m["frames"]:
            assert e["split"] == frame_split(e["seed"]) and e["scene"] == str((tmp_path / "s.toml").resolve())
            assert e["labels"]["count"] == 1 and "--labels coco,satnet,yolo,fits" in e["command"]
            assert (out / e["labels"]["files"]["yolo"]).read_text().startswith("0 ")  # class 0: the object
            with fits.open(out / e["file"]) as h:  # the LABELS image holds TRUTH row 0 where the streak is
                assert (h["LABELS"].data == 0).sum() > 20 and len(h["TRUTH"].data) == 1
        coco = COCO(str(out / "dataset.coco.json"))
        assert sorted(coco.getImgIds()) == [e["index"] + 1 for e in m["frames"]]
        assert len(coco.getAnnIds()) == N_DRAWS and len(set(coco.getAnnIds())) == N_DRAWS
        for e in m["frames"]:
            img = coco.loadImgs(e["index"] + 1)[0]
            assert (img["file_name"], img["seed"], img["split"]) == (e["file"], e["seed"], e["split"])
            (ann,) = coco.loadAnns(coco.getAnnIds(imgIds=img["id"]))
            mask = coco.annToMask(ann)
            assert mask.shape == (64, 64) and mask.sum() == ann["area"] > 0
            with fits.open(out / e["file"]) as h:  # the RLE mask and the FITS label image agree
                np.testing.assert_array_equal(mask.astype(bool), h["LABELS"].data == 0)
        sat = json.loads((out / "dataset.satnet.json").read_text())
        assert [f["data"]["file"]["filename"] for f in sat] == [e["file"] for e in m["frames"]]
        lists = {k: (out / f"{k}.txt").read_text().split() for k in SPLITS}
        assert sorted(f for k in SPLITS for f in lists[k]) == [e["file"] for e in m["frames"]]
        # resume: nothing redone; a frame whose label file is missing is redone, the dataset rebuilt the same
        before = (out / "dataset.coco.json").read_bytes()
        assert run_batch(load_batch(p, labels="coco,satnet,yolo,fits"), client=client, progress=False)["rendered"] == 0
        (out / "frame_0002.yolo.txt").unlink()
        s = run_batch(load_batch(p, labels="coco,satnet,yolo,fits"), client=client, progress=False)
        assert (s["rendered"], s["skipped"]) == (1, N_DRAWS - 1)
        assert (out / "frame_0002.yolo.txt").is_file() and (out / "dataset.coco.json").read_bytes() == before
