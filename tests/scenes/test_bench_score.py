"""The scorer (scenes.app.bench.score) against hand calculations on constructed sets."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from scenes.app.bench.score import (
    Item,
    average_precision,
    greedy_match,
    logistic_fit,
    match,
    score,
    wilson,
)
from scenes.app.cli import cli


def lab(x, y, snr=10.0, image="a", **kw):
    return Item(image, x, y, x, y, 1.0, None, (0, 0), {"x": x, "y": y, "snr": snr, **kw})


def det(x, y, s=1.0, image="a"):
    return Item(image, x, y, x, y, s)


def test_optimal_match_where_greedy_is_wrong():
    """Truths at x = 0 and 2.5, detections at 1.2 and -1.5, gate 2 px: nearest-first takes (1.2 -> 0) and
    leaves -1.5 unmatched (4.0 px from 2.5); the optimal match pairs (-1.5 -> 0, 1.5 px) and (1.2 -> 2.5,
    1.3 px): two matches, centre RMSE sqrt((1.5^2 + 1.3^2) / 2)."""
    labels = [lab(0.0, 0.0), lab(2.5, 0.0)]
    dets = [det(1.2, 0.0, 0.9), det(-1.5, 0.0, 0.8)]
    assert [(i, j) for i, j, _ in greedy_match(labels, dets, 2.0)] == [(0, 0)]
    assert sorted((i, j) for i, j, _ in match(labels, dets, "centre", 2.0)) == [(0, 1), (1, 0)]
    r = score(labels, dets, mode="centre", gate_px=2.0, images={"a": (100, 100)})
    assert r["matched"] == 2 and r["completeness"] == 1.0 and r["purity"] == 1.0 and r["false_alarms"] == 0
    assert r["centre_rmse_px"] == pytest.approx(math.sqrt((1.5 ** 2 + 1.3 ** 2) / 2))
    assert r["average_precision"] == pytest.approx(1.0)


def test_hand_calculated_set():
    """3 labels, 4 detections on 2 frames of 100 x 200 px: 2 matched (1 false alarm beyond the gate, 1 on
    the other frame), one label missed."""
    labels = [lab(10, 10, 20.0), lab(50, 50, 5.0), lab(30, 30, 8.0, image="b")]
    dets = [det(10.5, 10, 0.9), det(80, 80, 0.95), det(31, 30, 0.5, image="b"), det(5, 90, 0.2, image="b")]
    r = score(labels, dets, mode="centre", gate_px=3.0, images={"a": (100, 200), "b": (100, 200)})
    assert r["matched"] == 2 and r["labels"] == 3 and r["detections"] == 4
    assert r["completeness"] == pytest.approx(2 / 3) and r["purity"] == pytest.approx(2 / 4)
    assert r["false_alarms"] == 2 and r["false_alarms_per_frame"] == 1.0
    assert r["false_alarms_per_megapixel"] == pytest.approx(2 / 0.04)
    assert r["centre_rmse_px"] == pytest.approx(math.sqrt((0.5 ** 2 + 1.0 ** 2) / 2))
    # PR by score: 0.95 F, 0.9 T, 0.5 T, 0.2 F -> precision 0, 1/2, 2/3, 1/2 at recall 0, 1/3, 2/3, 2/3;
    # envelope 2/3 from recall 0 to 2/3: AP = 2/3 * 2/3
    assert r["average_precision"] == pytest.approx(4 / 9)
    assert wilson(2, 3) == pytest.approx(tuple(r["completeness_interval"]))
    # Wilson (z = 1) by hand for 2/3
    p, n = 2 / 3, 3
    c = (p + 1 / (2 * n)) / (1 + 1 / n)
    h = math.sqrt(p * (1 - p) / n + 1 / (4 * n * n)) / (1 + 1 / n)
    assert wilson(2, 3) == pytest.approx((c - h, c + h))


def test_endpoints_order_free_and_mask_iou():
    a = Item("a", 0, 0, 10, 0)
    b = Item("a", 10.5, 0, 0.5, 0)  # reversed, 0.5 px off at each end
    (m,) = match([a], [b], "endpoints", 1.0)
    assert m[2] == pytest.approx(0.5)
    ma = np.ones((2, 4), bool)
    mb = np.ones((2, 4), bool)
    la = Item("a", 0, 0, 0, 0, mask=ma, mask_xy=(0, 0))
    lb = Item("a", 0, 0, 0, 0, mask=mb, mask_xy=(2, 0))  # overlap 2 x 2 = 4 of union 12
    assert match([la], [lb], "mask", min_iou=0.3)[0][2] == pytest.approx(1 - 4 / 12)
    assert match([la], [lb], "mask", min_iou=0.5) == []


def test_snr50_logistic_and_bootstrap():
    """Draws from a known logistic (SNR50 = 6, w = 1): the fit recovers SNR50 within 3 bootstrap errors."""
    rng = np.random.default_rng(4)
    snr = rng.uniform(1, 15, 600)
    hit = rng.random(600) < 1 / (1 + np.exp(-(snr - 6.0)))
    s50, w = logistic_fit(snr, hit)
    assert s50 == pytest.approx(6.0, abs=0.4) and w == pytest.approx(1.0, abs=0.3)
    labels = [lab(float(i), 0.0, float(s)) for i, s in enumerate(snr)]
    dets = [det(float(i), 0.0) for i in np.flatnonzero(hit)]
    r = score(labels, dets, mode="centre", gate_px=0.1)
    e = r["snr50"]["bootstrap_error"]
    assert 0.02 < e < 0.5 and abs(r["snr50"]["value"] - 6.0) < 3 * e + 0.05
    assert r["snr50"]["value"] == pytest.approx(s50, rel=1e-6)


def test_logistic_newton_equals_direct_likelihood_maximum_and_degenerate_cases():
    """The Newton/IRLS fit is the likelihood's maximum: equal to a derivative-free (Nelder-Mead) maximisation
    of the same likelihood to 1e-5; separated data give the gap's middle and w = 0; completeness falling
    with SNR (b <= 0) gives NaN rather than a number."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(7)
    snr = rng.uniform(1, 30, 300)
    hit = rng.random(300) < 1 / (1 + np.exp(-(snr - 9.0) / 2.5))

    def nll(p):
        z = (snr - p[0]) / math.exp(p[1])
        return float(np.sum(np.logaddexp(0, -z) * hit + np.logaddexp(0, z) * (1 - hit)))

    ref = minimize(nll, [10.0, 0.0], method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-12, "maxiter": 20000})
    s50, w = logistic_fit(snr, hit)
    assert s50 == pytest.approx(ref.x[0], rel=1e-5) and w == pytest.approx(math.exp(ref.x[1]), rel=1e-5)
    assert logistic_fit([1.0, 2.0, 5.0, 6.0], [False, False, True, True]) == (3.5, 0.0)
    assert math.isnan(logistic_fit(snr, snr < 10)[0])  # falls with SNR
    assert math.isnan(logistic_fit([1.0, 2.0, 3.0], [True, True, True])[0])


def test_ap_all_points():
    ap, rec, prec = average_precision(np.array([0.9, 0.8, 0.7]), np.array([True, False, True]), 2)
    assert ap == pytest.approx(0.5 * 1 + 0.5 * (2 / 3))


def test_cli_score_csv_against_coco(tmp_path):
    """newtsim score: a CSV of centres against a COCO labels file; JSON holds the figures, HTML the plots."""
    coco = {"images": [{"id": 1, "file_name": "f.fits", "width": 50, "height": 40}],
            "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "kind": "object", "bbox": [9, 9, 3, 3],
                             "x": 10.0, "y": 10.0, "x0": 8.0, "y0": 10.0, "x1": 12.0, "y1": 10.0, "snr": 12.0,
                             "iscrowd": 0, "area": 9},
                            {"id": 2, "image_id": 1, "category_id": 2, "kind": "star", "bbox": [30, 30, 3, 3],
                             "x": 31.0, "y": 31.0, "x0": 31.0, "y0": 31.0, "x1": 31.0, "y1": 31.0, "snr": 50.0}],
            "categories": [{"id": 1, "name": "object"}, {"id": 2, "name": "star"}]}
    (tmp_path / "l.json").write_text(json.dumps(coco))
    (tmp_path / "d.csv").write_text("x0,y0,x1,y1,score\n12.2,10,8.1,10,0.7\n40,5,41,5,0.1\n")
    res = CliRunner().invoke(cli, ["score", str(tmp_path / "d.csv"), str(tmp_path / "l.json"), "--json",
                                   str(tmp_path / "s.json"), "--html", str(tmp_path / "r.html")])
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["labels"] == 1 and s["matched"] == 1 and s["false_alarms"] == 1  # the star is not scored
    assert s["endpoint_rmse_px"] == pytest.approx(0.15)
    assert "completeness_vs_snr" in s["figures"] and "precision_recall" in s["figures"]
    assert "data:image/png;base64," in (tmp_path / "r.html").read_text()
    bad = CliRunner().invoke(cli, ["score", str(tmp_path / "d.csv"), str(tmp_path / "d.csv")])
    assert bad.exit_code == 2


def test_label_fits_scores_as_its_coco_file(tmp_path):
    """A frame written with --labels coco,fits: scoring against the FITS (TRUTH + LABELS + LABELCAT) gives
    the COCO file's numbers; without LABELCAT the matches are the same (SNR unknown); without LABELS: exit 2."""
    from astropy.io import fits
    from helpers import write_scene

    from scenes.app.render import render
    from scenes.scene import load_scene

    objs = [{"ra_deg": 120.0, "dec_deg": -29.0 + dd, "rate_ra_deg_s": 0.0008, "rate_dec_deg_s": -0.0005,
             "photons": p} for p, dd in ((3000, -0.006), (800, 0.0), (20000, 0.006))]  # ~9 px streaks, 11 px apart
    sc = load_scene(str(write_scene(tmp_path / "s.toml", {
        "detector": {"preset": "ml11002", "width": 128, "height": 128}, "exposure": {"time_s": 5.0, "frame": "light"},
        "sky": {"stars": False, "background_mag_arcsec2": 20.0}, "psf": {"model": "gaussian", "fwhm_arcsec": 3.0},
        "pointing": {"ra_deg": 120.0, "dec_deg": -29.0, "epoch": "2023-02-01T22:00:00"}, "objects": objs})))
    f, coco = tmp_path / "f.fits", tmp_path / "f.coco.json"
    render(sc, f, seed=2, progress=False, workers=1, labels=["coco", "fits"], label_paths={"coco": coco})
    t = fits.getdata(f, "TRUTH")
    # detections: streaks 0 and 2 with ends 0.3 px off (swapped order for 2), a false alarm; streak 1 missed
    rows = ["x0,y0,x1,y1,score", f"{t['x0'][0] + 0.3},{t['y0'][0]},{t['x1'][0] + 0.3},{t['y1'][0]},0.9",
            f"{t['x1'][2]},{t['y1'][2] + 0.3},{t['x0'][2]},{t['y0'][2] + 0.3},0.8", "10,10,20,20,0.5"]
    dets = tmp_path / "d.csv"
    dets.write_text("\n".join(rows) + "\n")
    runner = CliRunner()

    def run(labels, *extra):
        r = runner.invoke(cli, ["score", str(dets), str(labels), "--json", "-", *extra])
        assert r.exit_code == 0, r.output
        return json.loads(r.stdout if hasattr(r, "stdout") else r.output)

    a, b = run(coco), run(f)
    for k in ("labels", "matched", "completeness", "purity", "false_alarms", "endpoint_rmse_px", "bins", "snr50"):
        assert a[k] == b[k], k
    assert (b["labels"], b["matched"], b["false_alarms"]) == (3, 2, 1)
    assert b["endpoint_rmse_px"] == pytest.approx(0.3, abs=1e-6)
    m = run(f, "--match", "mask")  # the LABELS pixels of each row: a detection at the label mask matches
    assert m["labels"] == 3
    # a LABELS image written by other code (no LABELCAT): the same matches, the SNR unknown
    with fits.open(f) as h:
        fits.HDUList([h[0], h["TRUTH"], h["LABELS"]]).writeto(tmp_path / "g.fits")
    c = run(tmp_path / "g.fits")
    assert (c["labels"], c["matched"], c["endpoint_rmse_px"]) == (3, 2, b["endpoint_rmse_px"])
    assert c["snr50"]["value"] is None
    with fits.open(f) as h:
        fits.HDUList([h[0], h["TRUTH"]]).writeto(tmp_path / "n.fits")
    r = runner.invoke(cli, ["score", str(dets), str(tmp_path / "n.fits")])
    assert r.exit_code == 2 and "no LABELS extension" in r.output
