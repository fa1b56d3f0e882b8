"""One mechanism per effect, and the typed scene (issue 15).

* ``[psf] jitter_rms_arcsec`` is a short form of ``[effects.jitter]``: the loaded scene holds the effect, the
  frame is the same bytes as the scene written with the effect, and the stars' second moments grow by the
  jitter variance (moments of a convolution add).
* ``[effects.distortion]`` becomes ``[telescope.sip] radial_k_per_px2``: the sources sit at
  ``r (1 + k r^2)`` from the axis (independent: the undistorted frame's TRUTH moved by the formula), and
  the frame's WCS carries it.
* ``Scene.parts``: the tables parsed once at loading, the ray-traced straylight routed out of the registry's
  tables, a changed table re-checked.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from scenes.app.render import render
from scenes.projection import Sip, with_radial
from scenes.scene import SceneError, load_scene
from tests.helpers import star_field_toml


def _scene(tmp_path, name, extra="", psf=""):
    """The 160 px star field of tests.helpers with ``psf`` lines added to its ``[psf]`` and ``extra`` tables."""
    p = tmp_path / f"{name}.toml"
    p.write_text(star_field_toml(160, extra).replace('fwhm_arcsec = 3.0\n', 'fwhm_arcsec = 3.0\n' + psf, 1))
    return p


def _scale(sc) -> float:
    from optics.design import load_design

    return load_design("art").pixel_scale_arcsec(sc.sensor().pixel_pitch_um)


# ------------------------------------------------------------------------------------------------ jitter
def test_jitter_short_form_becomes_the_effect(tmp_path):
    sc = load_scene(str(_scene(tmp_path, "j", psf="jitter_rms_arcsec = 2.0\n")))
    scale = _scale(sc)
    assert sc.psf.jitter_rms_arcsec == 0.0
    j = sc.effects["jitter"]
    assert j["sigma_major_px"] == pytest.approx(2.0 / scale) and j["sigma_minor_px"] == pytest.approx(2.0 / scale)
    assert "jitter" in sc.parts.effect_tables
    assert any("psf.jitter_rms_arcsec" in n for n in sc.resolution_notes)
    assert sc.resolved()["psf"]["jitter_rms_arcsec"] == 0.0  # the saved scene says where it went
    assert sc.resolved_text().startswith("# psf.jitter_rms_arcsec")
    load_scene(str(tmp_path / "j.toml"))  # loading twice is the same (idempotent)


def test_jitter_short_form_adds_to_an_elongated_effect(tmp_path):
    extra = "[effects.jitter]\nsigma_major_px = 0.8\nsigma_minor_px = 0.3\nangle_deg = 30.0\n"
    sc = load_scene(str(_scene(tmp_path, "j2", extra, psf="jitter_rms_arcsec = 1.0\n")))
    s = 1.0 / _scale(sc)
    j = sc.effects["jitter"]
    # covariances add: R diag(a^2, b^2) R^T + s^2 I = R diag(a^2 + s^2, b^2 + s^2) R^T
    assert j["sigma_major_px"] == pytest.approx(math.hypot(0.8, s))
    assert j["sigma_minor_px"] == pytest.approx(math.hypot(0.3, s))
    assert j["angle_deg"] == 30.0


def test_jitter_short_form_same_frame_as_the_effect_and_moments_add(tmp_path):
    short = load_scene(str(_scene(tmp_path, "a", psf="jitter_rms_arcsec = 2.5\n")))
    j = short.effects["jitter"]
    long = load_scene(str(_scene(tmp_path, "b", "[effects.jitter]\n" + "".join(
        f"{k} = {v!r}\n" for k, v in j.items()))))
    none = load_scene(str(_scene(tmp_path, "c")))
    imgs = {}
    for name, sc in (("a", short), ("b", long), ("c", none)):
        render(sc, tmp_path / f"{name}.fits", seed=3, noiseless=True, progress=False)
        imgs[name] = fits.getdata(tmp_path / f"{name}.fits").astype(np.float64)
    np.testing.assert_array_equal(imgs["a"], imgs["b"])  # one mechanism: the same bytes
    truth = fits.getdata(tmp_path / "c.fits", "TRUTH")
    r = 10
    far = [np.hypot(truth["x"] - t["x"], truth["y"] - t["y"]) for t in truth]
    ok = [i for i, t in enumerate(truth) if r <= t["y"] < 160 - r - 1 and r <= t["x"] < 160 - r - 1
          and np.sort(far[i])[1] > 2 * r]  # inside, no other source within 2 r
    assert ok, "no isolated star in the field"
    t = truth[max(ok, key=lambda i: truth["flux_e"][i])]
    y, x = round(float(t["y"])), round(float(t["x"]))
    _, xx = np.mgrid[-r:r + 1, -r:r + 1]

    def var_x(img):
        s = img[y - r:y + r + 1, x - r:x + r + 1] - np.median(img)
        cx = (s * xx).sum() / s.sum()
        return (s * (xx - cx) ** 2).sum() / s.sum()

    # second moments of a convolution add: the jitter's variance along x (angle 0) [px^2]
    assert var_x(imgs["a"]) - var_x(imgs["c"]) == pytest.approx(j["sigma_major_px"] ** 2, rel=0.02)


def test_jitter_short_form_too_large_names_its_key(tmp_path):
    with pytest.raises(SceneError, match=r"key 'psf.jitter_rms_arcsec'.*expected at most 50"):
        load_scene(str(_scene(tmp_path, "big", psf="jitter_rms_arcsec = 500.0\n")))


# -------------------------------------------------------------------------------------------- distortion
def test_distortion_effect_becomes_the_scene_sip(tmp_path):
    sc = load_scene(str(_scene(tmp_path, "d", "[effects.distortion]\nk_per_px2 = 1e-9\n")))
    assert "distortion" not in sc.effects and "distortion" not in sc.parts.effect_tables
    assert sc.telescope.distortion == "sip" and sc.telescope.sip == {"radial_k_per_px2": 1e-9}
    text = star_field_toml(160, "[telescope.sip]\nradial_k_per_px2 = 5e-10\n[effects.distortion]\nk_per_px2 = 1e-9\n")
    (tmp_path / "d2.toml").write_text(text.replace('design = "art"', 'design = "art"\ndistortion = "sip"', 1))
    again = load_scene(str(tmp_path / "d2.toml"))
    assert again.telescope.sip["radial_k_per_px2"] == pytest.approx(1.5e-9)  # small radial terms add
    zero = load_scene(str(_scene(tmp_path, "d0", "[effects.distortion]\nk_per_px2 = 0.0\n")))
    assert zero.telescope.distortion == "none" and "distortion" not in zero.effects  # the identity


def _distorted_pair(tmp_path, table: str):
    """A star field off the axis rendered without and with ``[effects.distortion]`` ``table``: (the scene's
    sensor, the axis (xc, yc) in output px, the undistorted TRUTH rows of the stars in both, the distorted
    frame's TRUTH rows of the same stars, the distorted frame's primary header)."""
    base = star_field_toml(160).replace("[detector]", "[detector]\nx0 = 2600\ny0 = 1700", 1)
    (tmp_path / "n.toml").write_text(base)
    (tmp_path / "d.toml").write_text(base + "[effects.distortion]\n" + table)
    out = {}
    for name in ("n", "d"):
        render(load_scene(str(tmp_path / f"{name}.toml")), tmp_path / f"{name}.fits", seed=1, noiseless=True,
               progress=False)
        out[name] = fits.open(tmp_path / f"{name}.fits")
    s = load_scene(str(tmp_path / "n.toml")).sensor()
    xc, yc = (s.sensor_width_px - 1) / 2 - s.roi_x0, (s.sensor_height_px - 1) / 2 - s.roi_y0
    tn, td = out["n"]["TRUTH"].data, out["d"]["TRUTH"].data
    by_id = {int(i): j for j, i in enumerate(td["source_id"])}
    stars = np.isin(tn["kind"], ["star", "synthetic"]) & np.isin(tn["source_id"], td["source_id"])
    assert stars.sum() >= 3
    return s, (xc, yc), tn[stars], td[[by_id[int(i)] for i in tn["source_id"][stars]]], out["d"][0].header


def test_radial_sources_move_by_the_formula_and_the_wcs_says_so(tmp_path):
    k = 1e-8
    _, (xc, yc), tn, tk, h = _distorted_pair(tmp_path, f"k_per_px2 = {k}\n")
    # the distortion effect's mapping (detector.effects.image_plane.radial_distortion): the recorded pixel at
    # p (from the axis) holds the undistorted image at p / (1 + k |p|^2), i.e. r' = r (1 + k r^2) to first order
    dx, dy = tk["x"] - xc, tk["y"] - yc
    f = 1 + k * (dx ** 2 + dy ** 2)
    assert np.max(np.hypot(tk["x"] - tn["x"], tk["y"] - tn["y"])) > 3.0  # it moved them
    np.testing.assert_allclose(tn["x"], xc + dx / f, atol=0.01)
    np.testing.assert_allclose(tn["y"], yc + dy / f, atol=0.01)
    assert h["SIPSRC"] == "scene" and "A_ORDER" in h
    w = WCS(h)
    px, py = w.all_world2pix(tk["ra_deg"], tk["dec_deg"], 0)
    np.testing.assert_allclose(px, tk["x"], atol=0.02)
    np.testing.assert_allclose(py, tk["y"], atol=0.02)


def test_decentering_sources_move_by_browns_formula_as_the_resampler_does(tmp_path):
    """``[effects.distortion] p1_per_px, p2_per_px`` (Brown 1966 decentering): the sources sit where
    :func:`detector.effects.image_plane.radial_distortion` (what the diagnosis fits) moves them: the recorded
    pixel p (from the axis) holds the undistorted image at p - D(p), D = (p1 (r^2 + 2x^2) + 2 p2 x y,
    p2 (r^2 + 2y^2) + 2 p1 x y); and the WCS says so."""
    from detector.effects.image_plane import radial_distortion

    p1, p2 = 2e-6, -1e-6
    sc = load_scene(str(_scene(tmp_path, "p", f"[effects.distortion]\np1_per_px = {p1}\np2_per_px = {p2}\n")))
    assert sc.telescope.sip == {"decentering_p1_per_px": p1, "decentering_p2_per_px": p2}
    s, (xc, yc), tn, tp, h = _distorted_pair(tmp_path, f"p1_per_px = {p1}\np2_per_px = {p2}\n")
    x, y = tp["x"] - xc, tp["y"] - yc
    r2 = x * x + y * y
    assert np.max(np.hypot(tp["x"] - tn["x"], tp["y"] - tn["y"])) > 1.0  # it moved them
    np.testing.assert_allclose(tn["x"], xc + x - (p1 * (r2 + 2 * x * x) + 2 * p2 * x * y), atol=0.01)
    np.testing.assert_allclose(tn["y"], yc + y - (p2 * (r2 + 2 * y * y) + 2 * p1 * x * y), atol=0.01)
    # the resampler the diagnosis fits with moves a point source by the same amount
    ys = np.arange(s.roi_y0, s.roi_y0 + s.height, dtype=float)
    xs = np.arange(s.roi_x0, s.roi_x0 + s.width, dtype=float)
    gy, gx = np.mgrid[: s.height, : s.width]
    for k in range(3):
        img = np.zeros((s.height, s.width), np.float32)
        iy, ix = int(round(tn["y"][k])), int(round(tn["x"][k]))
        img[iy, ix] = 1.0
        moved = radial_distortion(img, ys, xs, (s.sensor_height_px - 1) / 2, (s.sensor_width_px - 1) / 2, 0.0,
                                  p1_per_px=p1, p2_per_px=p2)
        cx, cy = float((moved * gx).sum() / moved.sum()), float((moved * gy).sum() / moved.sum())
        np.testing.assert_allclose([cx - ix, cy - iy], [tp["x"][k] - tn["x"][k], tp["y"][k] - tn["y"][k]], atol=0.02)
    px, py = WCS(h).all_world2pix(tp["ra_deg"], tp["dec_deg"], 0)
    np.testing.assert_allclose(px, tp["x"], atol=0.02)
    np.testing.assert_allclose(py, tp["y"], atol=0.02)


def test_with_radial_composes_with_a_sip():
    base = Sip(3, {(2, 0): 1e-6, (0, 3): 2e-9}, {(1, 1): -1e-6}, None, "scene")
    k = 3e-10
    rng = ((-3000, 3000), (-2000, 2000))
    sip = with_radial(base, k, *rng)
    x, y = np.random.default_rng(1).uniform(-2000, 2000, (2, 200))
    f = 1 + k * (x * x + y * y)
    ex, ey = base.forward(x / f, y / f)  # the recorded pixel holds what the SIP put at p / (1 + k r^2)
    gx, gy = sip.forward(x, y)
    assert np.max(np.hypot(gx - ex, gy - ey)) < 1e-3
    assert sip.order == 7 and sip.info["radial_fit_max_px"] < 1e-3
    with pytest.raises(SceneError, match="radial_k_per_px2"):
        with_radial(None, -1e-7, *rng)  # 1 + k r^2 < 0.5: folds the field


# ----------------------------------------------------------------------------------------- typed scene
def test_parts_are_parsed_once(tmp_path, monkeypatch):
    import scenes.scene as scene_mod

    calls = []
    real = scene_mod.object_from_table
    monkeypatch.setattr(scene_mod, "object_from_table", lambda *a, **k: calls.append(1) or real(*a, **k))
    extra = ("[[objects]]\nra_deg = 120.95\ndec_deg = -29.25\nrate_ra_deg_s = 0.001\nrate_dec_deg_s = 0.0\n"
             "photons = 5000\n")
    sc = load_scene(str(_scene(tmp_path, "o", extra)))
    assert len(calls) == 1 and len(sc.parts.objects) == 1
    render(sc, tmp_path / "o.fits", seed=1, noiseless=True, progress=False)
    assert len(calls) == 1  # the render used the parsed object
    sc.objects[0]["photons"] = 6000  # a table changed after loading is checked again
    assert sc.parts.objects[0].brightness is not None and len(calls) == 2


def test_parts_route_straylight_by_form(tmp_path):
    traced = load_scene(str(_scene(tmp_path, "s", "[effects.straylight]\npst = 1e-6\n")))
    assert traced.parts.straylight is not None and traced.parts.straylight.pst == 1e-6
    assert "straylight" not in traced.parts.effect_tables and "straylight" in traced.effects
    field = load_scene(str(_scene(tmp_path, "f", "[effects.straylight]\nmodel = 'field'\ngx = 1.0\n")))
    assert field.parts.straylight is None and field.parts.effect_tables["straylight"]["gx"] == 1.0
    series = load_scene(str(_scene(tmp_path, "l", "[effects.straylight]\nmodel = 'legendre'\norder = 2\n"
                                   "coef = [0.1, 0.0, 0.0, 0.2, 0.0]\n")))
    assert series.parts.straylight is None and series.parts.effect_tables["straylight"]["order"] == 2
    assert traced.sensor() is traced.parts.sensor  # built once
    traced.detector["gain_e_per_adu"] = 2.5  # a changed [detector] is resolved again
    assert traced.sensor().gain_e_per_adu == 2.5
