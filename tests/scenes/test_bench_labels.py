"""Labels of rendered frames (scenes.app.bench): exact on constructed streaks, SNR against noise draws, formats."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from helpers import write_scene

from scenes.app.bench import MASK_FRACTION_SIGMA, NoiseModel, SourceStamp, dominant_source_image, labels_from_sources
from scenes.app.bench.formats import (
    category_id,
    coco_document,
    dumps_indent1,
    rle_of,
    satnet_frame,
    yolo_corners,
    yolo_endpoints,
    yolo_lines,
)
from scenes.app.bench.frame import frame_labels, gaussian_star_stamps, render_one_sample
from scenes.app.render import prepare, render
from scenes.image.psf import GaussianPSF, MoffatPSF
from scenes.image.signal import Samples, render_samples
from scenes.scene import load_scene

RA, DEC, T = 120.0, -29.0, 5.0
N_DRAWS = 1000
RATE = (0.0008, -0.0005)  # deg/s: d(RA)/dt cos(Dec), d(Dec)/dt


def scene_table(size=96, objects=None, **sky):
    return {"detector": {"preset": "ml11002", "width": size, "height": size},
            "exposure": {"time_s": T, "frame": "light"},
            "sky": {"stars": False, "background_mag_arcsec2": 20.0, **sky},
            "pointing": {"ra_deg": RA, "dec_deg": DEC, "epoch": "2023-02-01T22:00:00"},
            "psf": {"model": "gaussian", "fwhm_arcsec": 3.0},
            "objects": objects or []}


def streak(photons, ra=RA, dec=DEC):
    return {"ra_deg": ra, "dec_deg": dec, "rate_ra_deg_s": RATE[0], "rate_dec_deg_s": RATE[1], "photons": photons}


def great_circle(ra, dec, rate, t):
    """Position after t seconds along the great circle tangent to the rates (independent of the track code)."""
    a, d = math.radians(ra), math.radians(dec)
    u0 = np.array([math.cos(d) * math.cos(a), math.cos(d) * math.sin(a), math.sin(d)])
    east = np.array([-math.sin(a), math.cos(a), 0.0])
    north = np.array([-math.sin(d) * math.cos(a), -math.sin(d) * math.sin(a), math.cos(d)])
    v = east * rate[0] + north * rate[1]
    speed = math.radians(float(np.hypot(*rate)))
    u = math.cos(speed * t) * u0 + math.sin(speed * t) * v / np.linalg.norm(v)
    return math.degrees(math.atan2(u[1], u[0])) % 360.0, math.degrees(math.asin(u[2]))


@pytest.fixture(scope="module")
def bright(tmp_path_factory):
    """A noiseless 96 x 96 frame with one bright streak wholly inside, its labels in every format."""
    d = tmp_path_factory.mktemp("bright")
    p = write_scene(d / "s.toml", scene_table(objects=[streak(60000)]))
    sc = load_scene(str(p), ["effects={}"])
    out = d / "f.fits"
    paths = {"coco": d / "f.coco.json", "satnet": d / "f.satnet.json", "yolo": d / "f.yolo.txt"}
    render(sc, out, seed=1, noiseless=True, progress=False, workers=1, labels=["coco", "satnet", "yolo", "fits"],
           label_paths=paths)
    fl = frame_labels(prepare(sc, workers=1))
    return out, paths, fl


def test_noiseless_streak_endpoints_flux_and_mask(bright):
    """Endpoints within 0.05 px of the great-circle positions at t = 0 and T through the file's WCS; flux
    within 0.1 % of the frame's own light; the mask at MASK_FRACTION_SIGMA holds >= 99 % of it."""
    out, _, fl = bright
    (lab,) = fl.labels
    with fits.open(out) as h:
        img = h[0].data.astype(float)
        hdr = h[0].header
    w = WCS(hdr)
    for (x, y), t in (((lab.x0, lab.y0), 0.0), ((lab.x1, lab.y1), T)):
        ra, dec = great_circle(RA, DEC, RATE, t)
        xe, ye = w.all_world2pix([ra], [dec], 0)
        assert math.hypot(x - xe[0], y - ye[0]) < 0.05
    assert (lab.t0_s, lab.t1_s) == (0.0, T)
    bg = (hdr["SKYRATE"] + hdr["DARKCUR"]) * hdr["EXPTIME"]
    light = img - bg
    assert lab.flux_e == pytest.approx(light.sum(), rel=1e-3)
    assert lab.flux_e == pytest.approx(lab.flux_truth_e, rel=1e-3)
    mask = lab.full_mask(img.shape)
    assert light[mask].sum() >= 0.99 * light.sum()
    assert lab.mask_flux_fraction >= 0.99
    # the rule holds pixel by pixel: in the mask exactly where s > k sigma_local (sigma from the header's noise)
    sigma = math.sqrt(bg + hdr["RDNOISE"] ** 2 + hdr["GAIN"] ** 2 / 12.0)
    assert np.array_equal(mask, light > MASK_FRACTION_SIGMA * sigma)
    # rate and length from the endpoints; the angular rate is the scene's
    assert lab.rate_arcsec_s == pytest.approx(math.hypot(*RATE) * 3600.0, rel=1e-3)
    assert lab.length_px == pytest.approx(math.hypot(lab.x1 - lab.x0, lab.y1 - lab.y0))


def test_snr_matches_noise_draws(tmp_path):
    """The labelled matched-filter SNR equals the SNR of the matched-filter estimate over 1000 noise draws of
    the same frame (four separated faint streaks: 4000 estimates) within 3 %."""
    objs = [streak(4000, RA + dx / math.cos(math.radians(DEC)), DEC + dy) for dx, dy in
            ((-0.014, 0.014), (0.010, 0.014), (-0.014, -0.010), (0.010, -0.010))]
    p = write_scene(tmp_path / "s.toml", scene_table(size=112, objects=objs))
    sc = load_scene(str(p), ["effects={}"])
    st = prepare(sc, workers=1)
    fl = frame_labels(st)
    assert len(fl.labels) == 4 and not any(lab.edge for lab in fl.labels)
    s_ = st.detector.sensor
    bg_frame = st.detector.expose(st.signal_e, st.exptime_s, 0, noiseless=True)  # expected charge
    sky_dark = float(np.median(bg_frame))
    ratios = []
    draws = np.array([(st.detector.expose(st.signal_e, st.exptime_s, 1000 + k).astype(float) - s_.bias_adu + 0.5)
                      * s_.gain_e_per_adu for k in range(N_DRAWS)])
    for src, lab in zip(fl.sources, fl.labels):
        h, w = src.stamp_e.shape
        s = src.stamp_e.astype(float)
        var = fl.noise.background_var_e2(src.y0, src.y0 + h, src.x0, src.x0 + w) + s
        wgt = s / var
        d = draws[:, src.y0:src.y0 + h, src.x0:src.x0 + w] - sky_dark
        est = np.einsum("kij,ij->k", d, wgt)
        ratios.append((est.mean() / est.std(ddof=1)) / lab.snr)
        assert 5.0 < lab.snr < 30.0
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.03)


def test_coco_loads_and_evaluates(bright):
    """The COCO file loads in pycocotools, its RLE equals pycocotools' own encoding of the mask, and COCOeval
    runs (the labels scored against themselves: AP = 1)."""
    from pycocotools import mask as cmask
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    _, paths, fl = bright
    gt = COCO(str(paths["coco"]))
    (ann,) = gt.loadAnns(gt.getAnnIds())
    m = fl.labels[0].full_mask(fl.shape)
    assert np.array_equal(gt.annToMask(ann).astype(bool), m)
    ref = cmask.encode(np.asfortranarray(m.astype(np.uint8)))
    assert ann["segmentation"]["counts"] == ref["counts"].decode()
    dets = [{"image_id": ann["image_id"], "category_id": ann["category_id"], "segmentation": ann["segmentation"],
             "score": 1.0}]
    ev = COCOeval(gt, gt.loadRes(dets), "segm")
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    assert ev.stats[0] == pytest.approx(1.0)
    doc = json.loads(paths["coco"].read_text())
    assert doc["info"]["label_rule"]["mask_fraction_sigma"] == MASK_FRACTION_SIGMA
    sat = json.loads(paths["satnet"].read_text())
    (obj,) = sat["data"]["objects"]
    assert obj["x_start"] == pytest.approx((fl.labels[0].x0 + 0.5) / fl.shape[1])


def test_yolo_box_keeps_the_endpoints(bright):
    _, paths, fl = bright
    lab = fl.labels[0]
    vals = np.array(paths["yolo"].read_text().split()[1:], dtype=float).reshape(4, 2)
    corners = vals * [fl.shape[1], fl.shape[0]] - 0.5
    p0, p1 = yolo_endpoints(corners)
    assert np.allclose(p0, [lab.x0, lab.y0], atol=1e-4) and np.allclose(p1, [lab.x1, lab.y1], atol=1e-4)
    assert np.allclose(yolo_corners(lab), corners, atol=1e-4)


def test_fits_label_image_is_the_dominant_source(bright):
    out, _, fl = bright
    with fits.open(out) as h:
        lab_img = h["LABELS"].data
    assert np.array_equal(lab_img == 0, fl.labels[0].full_mask(fl.shape))
    assert set(np.unique(lab_img)) == {-1, 0}


def test_overlap_goes_to_the_brighter_source_and_rle_without_a_frame():
    """Two overlapping constructed stamps: each pixel to the larger expected signal; a measured noise model."""
    yy, xx = np.mgrid[0:20, 0:20]
    a = 100 * np.exp(-((xx - 8) ** 2 + (yy - 10) ** 2) / 8.0)
    b = 300 * np.exp(-((xx - 12) ** 2 + (yy - 10) ** 2) / 8.0)
    srcs = [SourceStamp(a, 5, 5, 0, "injected"), SourceStamp(b, 5, 5, 1, "injected")]
    labs = labels_from_sources(srcs, NoiseModel.measured(2.0), (40, 40))
    img = dominant_source_image(srcs, labs, (40, 40))
    both = labs[0].full_mask((40, 40)) & labs[1].full_mask((40, 40))
    expect = np.where(b > a, 1, 0)[yy[both[5:25, 5:25]], xx[both[5:25, 5:25]]]
    assert np.array_equal(img[both], expect)
    # centre from the centroid when none is given; SNR = sqrt(sum s^2 / (sigma^2 + s))
    assert labs[0].x == pytest.approx(5 + (xx * a).sum() / a.sum())
    assert labs[0].snr == pytest.approx(math.sqrt(np.sum(a * a / (4.0 + a))))
    from pycocotools import mask as cmask
    m = labs[1].full_mask((40, 40))
    assert rle_of(labs[1], (40, 40))["counts"] == cmask.encode(np.asfortranarray(m.astype(np.uint8)))["counts"].decode()


def constructed_labels():
    """Labels of constructed stamps: a streak along a diagonal, a star, a faint source with an empty mask, a
    mask spanning the image's full height (RLE runs continuing from one column into the next)."""
    yy, xx = np.mgrid[0:24, 0:24]
    streak_e = 200 * np.exp(-((xx - yy) ** 2) / 4.0) * ((xx > 3) & (xx < 20))
    star_e = 300 * np.exp(-((xx - 12) ** 2 + (yy - 12) ** 2) / 6.0)
    column_e = np.zeros((40, 3))
    column_e[:, 1:] = 50.0
    srcs = [SourceStamp(streak_e, 2, 2, 0, "object", 13.5, 13.5, 6.0, 6.0, 21.0, 21.0, 0.0, 5.0, 4000.0, 11.2),
            SourceStamp(star_e, 10, 14, 1, "star", 26.0, 22.0, t0_s=0.0, t1_s=5.0, flux_e=5000.0, mag=10.5),
            SourceStamp(np.full((3, 3), 1e-6), 30, 30, 2, "synthetic", 31.0, 31.0),
            SourceStamp(column_e, 0, 35, 3, "star", 36.0, 19.5)]
    return srcs, labels_from_sources(srcs, NoiseModel.measured(2.0), (40, 40))


def numpy_default(v):
    """What the label files' JSON makes of numpy values (the standard encoder's ``default``)."""
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v))


def test_label_files_equal_the_standard_encoders():
    """The label files' own encoders (indented JSON, YOLO boxes of all labels at once, RLE counts) write the
    same bytes as the standard json module, the label-by-label corners and pycocotools."""
    from pycocotools import mask as cmask

    _, labs = constructed_labels()
    assert [lab.mask_pixels == 0 for lab in labs] == [False, False, True, False]
    docs = [coco_document([{"file_name": "f.fits", "shape": (40, 40), "labels": labs, "seed": 7}], 0.1),
            satnet_frame(labs, (40, 40), "f.fits", {"seed": np.int64(7)}),
            {"a": [], "b": {}, "c": (1, 2.5, None, True, False, 'q"\\\u00e9', [], [1, {}], 3), 1: np.float32(0.1),
             2.5: np.int64(3), None: [np.arange(3), {"z": [[]]}], False: np.float64(1e-5), "n": np.float32("nan")},
            [], "x", 1.5]
    for doc in docs:
        assert dumps_indent1(doc) == json.dumps(doc, indent=1, allow_nan=False, default=numpy_default)
    for bad in (math.nan, {"x": [1, -math.inf]}):
        with pytest.raises(ValueError):
            dumps_indent1(bad)
    ref = "".join(f"{category_id(lab.kind) - 1} " + " ".join(f"{cx / 40:.7f} {cy / 40:.7f}"
                                                             for cx, cy in yolo_corners(lab) + 0.5) + "\n"
                  for lab in labs)
    assert yolo_lines(labs, (40, 40)) == ref
    for lab in labs:
        m = np.asfortranarray(lab.full_mask((40, 40)).astype(np.uint8))
        assert rle_of(lab, (40, 40))["counts"] == cmask.encode(m)["counts"].decode()


@pytest.mark.parametrize("psf", [GaussianPSF(2.5), MoffatPSF(3.0, 2.5)], ids=["gaussian", "moffat"])
def test_one_sample_stamp_equals_render_samples(psf):
    """A static star's stamp drawn alone (render_one_sample) holds render_samples' numbers bit for bit: inside
    the box, cut by each of its edges, outside it, with a rolling-shutter window, and with no flux."""
    box = (10, 30, 20, 45)
    cases = [(30.3, 18.7, np.inf), (21.0, 10.2, np.inf), (44.6, 29.9, np.inf), (18.0, 8.0, np.inf),
             (31.2, 20.4, 0.3), (80.0, 20.0, np.inf), (31.0, 20.0, np.inf)]
    for k, (x, y, t_hi) in enumerate(cases):
        e = 0.0 if k == len(cases) - 1 else 5e4
        t_lo = 0.1 if np.isfinite(t_hi) else -np.inf
        part = Samples(np.array([x]), np.array([y]), np.array([e]), np.array([t_lo]), np.array([t_hi]),
                       np.array([6], dtype=np.int64))
        for row_time_s in (0.0, 0.01):
            ref = render_samples(part, psf, *box, row_time_s, 5.0)
            got = render_one_sample(part, psf, *box, row_time_s, 5.0)
            assert got.tobytes() == ref.tobytes(), (x, y, t_hi, row_time_s)


def test_gaussian_stars_together_equal_one_by_one():
    """Static stars with a Gaussian PSF drawn together (gaussian_star_stamps) hold render_samples' numbers bit
    for bit; those it leaves to be drawn alone (a rolling-shutter window, outside the box, no flux) are not
    returned."""
    rng = np.random.default_rng(5)
    psf = GaussianPSF(2.5)
    items, alone = [], set()
    for k in range(300):
        x, y = rng.uniform(-5, 3000), rng.uniform(-5, 2000)
        w = int(rng.choice([4, 6, 9]))
        cx, cy = int(np.rint(x)), int(np.rint(y))
        box = (max(0, cy - w + int(rng.integers(0, 3))), cy + w + 1 - int(rng.integers(0, 3)),
               max(0, cx - w + int(rng.integers(0, 3))), cx + w + 1)
        t_lo, e = -np.inf, rng.uniform(1e3, 1e5)
        if k % 50 == 1:
            t_lo = 0.2  # a rolling-shutter window
        if k % 50 == 2:
            e = 0.0
        if k % 50 == 3:
            box = (box[0] + 40, box[1] + 40, box[2], box[3])  # the star outside its box
        if t_lo > -np.inf or e == 0 or k % 50 == 3:
            alone.add(k)
        part = Samples(np.array([x]), np.array([y]), np.array([e]), np.array([t_lo]), np.array([t_lo + 1.0]),
                       np.array([w], dtype=np.int64))
        items.append((k, part, box))
    got = gaussian_star_stamps(items, psf)
    assert not alone & set(got) and len(got) >= 250
    for k, part, box in items:
        if k in got:
            assert got[k].tobytes() == render_samples(part, psf, *box).tobytes(), k
