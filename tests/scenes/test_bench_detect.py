"""``newtsim detect``: the baseline streak detector (scenes/app/bench/detect.py).

- A constructed frame (noise, stars, trails drawn with the injection's own PSF-integrated stamps): the trails
  are found with their ends within 1 px of the drawn ends, a faint one (0.8 sigma per pixel, integrated SNR
  ~ 25) by the line finder; a frame of noise and stars alone gives no detection.
- The real Trailblazer frames of ../shared/realdata: every streak the provenance lists is found, along its
  angle, with its ends at the frame's edges (the streaks cross the cutouts) or, for the ASTRiDE frame, at the
  visible ends of the trail; the LBC cutout (no streak) gives no detection.
- The loop: inject into a frame, detect, score (the bench's scorer) -> the bright injected trails matched.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from astropy.io import fits

from scenes.app.bench.detect import Detection, detect_file, detect_image, write_detections
from scenes.app.bench.inject import expected_stamp, inject_file

FWHM = 2.5


def _trail(img, p0, p1, flux, fwhm=FWHM):
    n = int(math.hypot(p1[0] - p0[0], p1[1] - p0[1]) * 4) + 1
    x, y = np.linspace(p0[0], p1[0], n), np.linspace(p0[1], p1[1], n)
    r0, c0, st = expected_stamp(x, y, np.full(n, flux / n), fwhm)
    h, w = img.shape
    ra, ca = max(r0, 0), max(c0, 0)
    rb, cb = min(r0 + st.shape[0], h), min(c0 + st.shape[1], w)
    img[ra:rb, ca:cb] += st[ra - r0:rb - r0, ca - c0:cb - c0]


def _dist(p, a, b) -> float:
    ax, ay = b[0] - a[0], b[1] - a[1]
    u = max(0.0, min(1.0, ((p[0] - a[0]) * ax + (p[1] - a[1]) * ay) / max(ax * ax + ay * ay, 1e-12)))
    return math.hypot(p[0] - a[0] - u * ax, p[1] - a[1] - u * ay)


def _frame(rng, trails=(), stars=25, shape=(256, 256), sigma=10.0):
    """Noise, stars (2e3 to 2e5 ADU; none within 15 px of a trail: star confusion is the noise frame's
    test) and trails."""
    img = 500.0 + rng.normal(0.0, sigma, shape)
    n = 0
    while n < stars:
        x, y = rng.uniform(8, shape[1] - 8), rng.uniform(8, shape[0] - 8)
        if any(_dist((x, y), p0, p1) < 15.0 for p0, p1, _ in trails):
            continue
        _trail(img, (x, y), (x, y), rng.uniform(2e3, 2e5))
        n += 1
    for p0, p1, flux in trails:
        _trail(img, p0, p1, flux)
    return img


def _cost(d: Detection, p0, p1) -> float:
    a = (math.hypot(d.x0 - p0[0], d.y0 - p0[1]) + math.hypot(d.x1 - p1[0], d.y1 - p1[1])) / 2
    b = (math.hypot(d.x0 - p1[0], d.y0 - p1[1]) + math.hypot(d.x1 - p0[0], d.y1 - p0[1])) / 2
    return min(a, b)


def test_constructed_trails_found_with_their_ends():
    rng = np.random.default_rng(3)
    # per-pixel peak of a trail of flux F over L px: F / L / (sqrt(2 pi) sigma_psf) [ADU]
    trails = [((30.0, 40.0), (200.0, 90.0), 2.0e5),     # bright: ~110 sigma per px at the peak
              ((60.0, 220.0), (150.0, 150.0), 2.4e4),   # ~25 sigma
              ((220.0, 30.0), (170.0, 200.0), 1.6e4)]   # faint: ~8 ADU = 0.8 sigma per px
    img = _frame(rng, trails)
    dets = detect_image(img, fwhm_px=FWHM)
    streaks = [d for d in dets if d.kind == "streak"]
    assert len(streaks) == 3, [(round(d.x0), round(d.y0), round(d.x1), round(d.y1)) for d in streaks]
    for p0, p1, _ in trails:
        best = min(streaks, key=lambda d: _cost(d, p0, p1))
        assert _cost(best, p0, p1) < 1.0
    faint = min(streaks, key=lambda d: _cost(d, trails[2][0], trails[2][1]))
    assert 10.0 < faint.score < 60.0


def test_noise_and_stars_give_no_streak():
    rng = np.random.default_rng(4)
    for _ in range(3):
        img = _frame(rng, stars=40)
        assert [d for d in detect_image(img, fwhm_px=FWHM) if d.kind == "streak"] == []


def test_outputs_read_by_the_scorer(tmp_path):
    from scenes.app.bench.score import load_detections

    dets = [Detection("streak", 1.0, 2.0, 30.0, 40.0, 12.5, "f.fits"), Detection("streak", 5.0, 5.0, 50.0, 9.0, 8.0, "f.fits")]
    write_detections(dets, tmp_path / "d.json")
    write_detections(dets, tmp_path / "d.ecsv")
    for name in ("d.json", "d.ecsv"):
        items = load_detections(tmp_path / name, {"f.fits": (64, 64)})
        assert [(i.x0, i.y0, i.x1, i.y1, i.score) for i in items] == [(1.0, 2.0, 30.0, 40.0, 12.5), (5.0, 5.0, 50.0, 9.0, 8.0)]
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc[0]["image_id"] == 1 and doc[0]["category_id"] == 1 and len(doc[0]["bbox"]) == 4


def test_inject_detect_score_loop(tmp_path):
    """Bright injected trails in a constructed frame with a WCS come back through detect and score."""
    from astropy.wcs import WCS

    from scenes.app.bench.score import score_files

    rng = np.random.default_rng(9)
    img = _frame(rng, stars=8)  # a sparse field: a trail over a bright star is the harder case (docs)
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [10.0, 40.0]
    wcs.wcs.crpix = [128.0, 128.0]
    wcs.wcs.cdelt = [-1.0 / 3600, 1.0 / 3600]
    hdr = wcs.to_header()
    hdr["EXPTIME"] = 10.0
    hdr["GAIN"] = 1.5
    path = tmp_path / "frame.fits"
    fits.PrimaryHDU(np.rint(img).astype(np.uint16), hdr).writeto(path)
    out = tmp_path / "inj.fits"
    inject_file(path, out, random=(4, (40.0, 80.0), (4.0, 10.0)), seed=5, psf=f"{FWHM}px", labels=("coco",),
                label_paths={"coco": tmp_path / "inj.coco.json"})
    dets, _ = detect_file(out, psf=f"{FWHM}px")
    write_detections(dets, tmp_path / "det.json")
    res = score_files(tmp_path / "det.json", tmp_path / "inj.coco.json", kinds=("injected",))
    assert res["labels"] == 4 and res["matched"] >= 3 and res["false_alarms"] <= 1


# ----------------------------------------------------------------------------------------------- real frames
def _angle(d: Detection) -> float:
    return math.degrees(math.atan2(d.y1 - d.y0, d.x1 - d.x0)) % 180.0


def _load(realdata, rel, **kw):
    path = realdata / "streaks_trailblazer" / rel if "/" not in rel else realdata / rel
    if not path.exists():
        pytest.skip(f"{path} not found")
    dets, _ = detect_file(path, **kw)
    return [d for d in dets if d.kind == "streak"]


def _spans(d: Detection, shape, tol=3.0) -> bool:
    """Both ends at the frame's edges (a streak crossing the cutout)."""
    h, w = shape

    def at_edge(x, y):
        return min(x + 0.5, w - 0.5 - x, y + 0.5, h - 0.5 - y) <= tol

    return at_edge(d.x0, d.y0) and at_edge(d.x1, d.y1)


def test_trailblazer_vatt_faint_streak(realdata):
    """VATT: the faint wide streak (~4 sigma per px) at 30 deg, edge to edge."""
    (d,) = _load(realdata, "cutout_m20211212UT_image0110.new.fits")
    assert _angle(d) == pytest.approx(30.0, abs=1.5) and _spans(d, (200, 200))


@pytest.mark.slow
def test_trailblazer_lco_three_streaks(realdata):
    """LCO 0.4 m: the three parallel streaks at 150.8-151.2 deg, each edge to edge."""
    streaks = [d for d in _load(realdata, "cutout_bi327715.fits") if abs(_angle(d) - 151.0) < 1.0]
    assert len(streaks) == 3
    assert all(_spans(d, (400, 400)) for d in streaks)


def test_trailblazer_decam_raw_ccd(realdata):
    """DECam S28 (raw, with overscan and a read-out ramp): the streak at 134.6 deg, edge to edge; the ramp
    beside the overscan is not a streak."""
    streaks = _load(realdata, "cutout_c4d_200306_000415_ori.fits.fz", hdu="S28")
    assert len(streaks) == 1
    assert _angle(streaks[0]) == pytest.approx(134.6, abs=1.5) and _spans(streaks[0], (100, 100))


@pytest.mark.slow
def test_trailblazer_hsc_and_lbc(realdata):
    """HSC (raw): the bright wide streak at 110 deg, edge to edge, once (its halo is not a second trail; the
    other detections are short and faint: cosmic-ray tracks of the raw frame, < 60 px, < 1 % of its score);
    LBC: none."""
    found = _load(realdata, "cutout_HSCA21787010.fits")
    d = max(found, key=lambda s: s.score)
    assert _angle(d) == pytest.approx(110.0, abs=1.5) and _spans(d, (400, 400))
    assert all(o.length_px < 60.0 and o.score < 0.01 * d.score for o in found if o is not d)
    assert _load(realdata, "cutout_lbcb.20210407.120357.fits") == []


def test_astride_visible_ends(realdata):
    """ASTRiDE: the streak's visible ends, x ~ 20 and x ~ 342 (two collinear segments, y 309..338)."""
    streaks = _load(realdata, "streak/astride_long.fits")
    d = max(streaks, key=lambda s: s.length_px)
    xs = sorted((d.x0, d.x1))
    assert xs[0] == pytest.approx(20.0, abs=4.0) and xs[1] == pytest.approx(342.0, abs=4.0)
    assert 305.0 < min(d.y0, d.y1) < 315.0 and 330.0 < max(d.y0, d.y1) < 342.0
