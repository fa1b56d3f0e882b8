"""Real data: the PANOPTES star field (Canon DSLR, Mauna Loa, 2016-09-09) against a scene set up from it.

The frame (``../shared/realdata/starfield/panoptes_solved.fits.fz``, tile-compressed HDU 1, never copied)
is a 700 x 700 raw cutout of a Canon EOS 100D frame behind an 85 mm f/1.4 lens (a PANOPTES unit): 120 s at
ISO 100, raw Bayer (RGGB) data, an astrometry.net TAN-SIP WCS (10.3"/px) and KIC 8462852 in the field.
The scene takes from the file:

* **geometry**: pointing = CRVAL (the WCS reference pixel is the cutout's centre, so the 700 x 700 cutout
  is the scene's whole sensor), roll and scale from the CD matrix, the header's order-2 SIP plus the CD
  matrix's small non-conformal part as the scene's ``[telescope.sip]`` (exact: the scene's WCS equals the
  header's to < 1e-3 px over the frame);
* **detector**: a CMOS read as a monochrome sensor: black level 2048 ADU (Canon), 14 bits, saturation at
  the frame's own clip level (13583 ADU), gain 2.2 e-/ADU and read noise 8 e- assumed (full well ~25 ke- of
  a 4.3 um Canon pixel over the 11535 ADU above black; not measurable here: the sky noise is dominated by
  unresolved stars, see the docs), no dark (degenerate with the sky at one exposure: the sky absorbs it);
* **band**: the Bayer-averaged response of a Canon sensor behind its IR-cut filter, scaled to the frame's
  zero point with the built-in catalogue's unsaturated stars (the model cannot know lens transmission,
  aperture and colour response);
* **sky** from the frame's median, **PSF** from Moffat fits on the channel-equalised frame, **stars**: the
  built-in catalogue (Gaia DR3 to G = 10, matched on the frame: this is the real test of the WCS) plus the
  faint population down to the detection limit.

The Bayer pattern is a real effect the model lacks: the diagnosis is run as it is, and the channels'
residual means and the residual power at the Nyquist frequency are measured on the full-resolution z map.
Usage::

    python examples/diagnose/real_panoptes.py [OUT_DIR] [--rounds N] [--write-scene]

writes ``OUT_DIR`` (default ``out/realdata/panoptes``) like ``real_astride.py``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from detector.jsonable import jsonable

sys.path.insert(0, str(Path(__file__).resolve().parent))
import real_astride as ra

ROOT = ra.ROOT
DATA = ra.REALDATA / "starfield" / "panoptes_solved.fits.fz"
SCENE = ROOT / "examples" / "diagnose" / "scenes" / "panoptes.toml"

BLACK_ADU = 2048.0  #: Canon's 14-bit black level
GAIN_E_PER_ADU = 2.2  #: assumed (see the module docstring)
READ_NOISE_E = 8.0  #: assumed, ISO 100
PIXEL_PITCH_UM = 4.30  #: EOS 100D: 22.3 mm / 5184 px
#: Bayer-averaged (R + 2G + B) / 4 response of a Canon CMOS behind its IR-cut filter (coarse, shape only:
#: the zero point scales it)
CFA_MEAN = ([380, 400, 425, 450, 475, 500, 525, 550, 575, 600, 625, 650, 675, 700, 720],
            [0.0, 0.05, 0.11, 0.16, 0.18, 0.20, 0.23, 0.23, 0.20, 0.17, 0.14, 0.09, 0.04, 0.01, 0.0])


def cfa_levels(img: np.ndarray) -> dict:
    """Median level above black of the four Bayer cells ((row % 2, col % 2) -> ADU)."""
    return {f"{oy}{ox}": float(np.median(img[oy::2, ox::2]) - BLACK_ADU) for oy in (0, 1) for ox in (0, 1)}


def equalised(img: np.ndarray) -> np.ndarray:
    """The frame above black with each Bayer cell divided by its sky level relative to the mean (for
    detection and PSF measurement only; the comparison uses the raw frame)."""
    lv = cfa_levels(img)
    mean = np.mean(list(lv.values()))
    out = img - BLACK_ADU
    for k, v in lv.items():
        oy, ox = int(k[0]), int(k[1])
        out[oy::2, ox::2] *= mean / v
    return out


def scene_sip(header, roll_deg: float, scale_arcsec: float) -> dict:
    """The header's SIP and the non-conformal part of its CD matrix in the scene's convention: with
    M = CD_scene^-1 CD_file, the scene's ideal offsets are M (x + A(x, y)), i.e. linear terms M - I and
    the second-order coefficient vectors mapped by M (pixel offsets about CRPIX = the sensor's centre)."""
    from scenes.projection import tan_wcs

    geom = ra.wcs_geometry(header)
    w = geom["wcs"]
    cd_file = np.array(geom["cd"])
    cd_scene = tan_wcs(0.0, 0.0, roll_deg, scale_arcsec, (2, 2)).wcs.cd
    m = np.linalg.solve(cd_scene, cd_file)
    out = {"order": int(w.sip.a_order) if w.sip is not None else 1}
    a = w.sip.a if w.sip is not None else np.zeros((2, 2))
    b = w.sip.b if w.sip is not None else np.zeros((2, 2))
    for p in range(a.shape[0]):
        for q in range(a.shape[1]):
            if 1 <= p + q:
                lin = (m - np.eye(2)) if p + q == 1 else np.zeros((2, 2))
                ex, ey = (1.0 if (p, q) == (1, 0) else 0.0), (1.0 if (p, q) == (0, 1) else 0.0)
                va = m[0, 0] * a[p, q] + m[0, 1] * b[p, q] + lin[0, 0] * ex + lin[0, 1] * ey
                vb = m[1, 0] * a[p, q] + m[1, 1] * b[p, q] + lin[1, 0] * ex + lin[1, 1] * ey
                if p + q <= out["order"] and (va != 0 or vb != 0):
                    out[f"a_{p}_{q}"] = float(f"{va:.10g}")
                    out[f"b_{p}_{q}"] = float(f"{vb:.10g}")
    out["reverse_order"] = out["order"] + 2
    return out


def measure(path=DATA, work: Path | None = None) -> tuple[dict, dict]:
    """Measure the frame and set up the scene (zero point from the catalogue stars). Returns (scene, meas)."""
    from scenes.app.compare import build_model, run_compare

    work = Path(work or ROOT / "out" / "realdata" / "panoptes")
    work.mkdir(parents=True, exist_ok=True)
    img, header = ra.read_frame(path)
    h, w = img.shape
    t = float(header["EXPTIME"])
    vals, counts = np.unique(img[img > np.percentile(img, 99.5)], return_counts=True)
    clip = float(vals[np.argmax(counts)])  # the most frequent high value: the saturation plateau
    eq = equalised(img)
    sigma_eq = ra.robust_std(eq)
    bg = ra.background_map(eq, 21)
    det = ra.detect_sources(eq, bg, sigma_eq, nsigma=5.0, smooth=0.8)
    psf = ra.fit_psf(eq, bg, det, peak_range=(150.0, 0.8 * (clip - BLACK_ADU)), radius=6,
                     saturation=0.9 * (clip - BLACK_ADU))
    geom = ra.wcs_geometry(header)
    scale, roll = geom["scale_arcsec"], geom["roll_deg"]
    sip = scene_sip(header, roll, scale)
    band = ra.band_table(CFA_MEAN, ([300, 1100], [1.0, 1.0]), step=20.0)
    sky = float(np.median(img))
    scene = {
        "telescope": {"design": "art", "pixel_scale_arcsec": round(scale, 5), "distortion": "sip", "sip": sip},
        "detector": {"preset": "imx411", "name": "canon-eos100d-raw", "kind": "cmos", "shutter": "global",
                     "line_time_s": 0.0, "pixel_pitch_um": PIXEL_PITCH_UM, "sensor_width_px": w,
                     "sensor_height_px": h, "bit_depth": 14, "gain_e_per_adu": GAIN_E_PER_ADU,
                     "bias_adu": BLACK_ADU, "read_noise_e": READ_NOISE_E, "dark_current_e_per_s": 0.0,
                     "full_well_e": round((clip - BLACK_ADU) * GAIN_E_PER_ADU, 1), "temperature_c": 13.0,
                     "qe_wavelength_nm": band[0], "qe": band[1]},
        "pointing": {"ra_deg": round(geom["crval"][0], 9), "dec_deg": round(geom["crval"][1], 9),
                     "roll_deg": round(roll, 5), "epoch": str(header["DATE-OBS"])[:19]},
        "exposure": {"time_s": t, "frame": "light", "tracking": "sidereal", "seed": 1},
        "sky": {"background_mag_arcsec2": 20.0, "stars": True, "star_mag_limit": 10.0, "star_seed": 0,
                "catalog": "builtin"},
        "psf": {"model": "moffat", "fwhm_arcsec": round(psf["fwhm_px"] * scale, 3),
                "beta": round(min(max(psf["beta"], 1.5), 50.0), 3)},
    }
    sky_e = (sky - BLACK_ADU) * GAIN_E_PER_ADU / t
    scene["sky"]["background_mag_arcsec2"] = round(ra.sky_mag_arcsec2(sky_e, scene), 4)
    # zero point: catalogue stars (G <= 10), unsaturated and isolated: first with aperture photometry at the
    # header's WCS positions, then refined on the comparison itself (whose saturation flags depend on it)
    zp0 = catalogue_zero_point(img, header, scene, clip, t)
    scene["detector"]["qe"] = [round(q * zp0["scale"], 6) for q in scene["detector"]["qe"]]
    scene["sky"]["background_mag_arcsec2"] = round(ra.sky_mag_arcsec2(sky_e, scene), 4)
    zp_passes = [zp0]
    for _ in range(2):
        sc = ra.load_scene_dict(scene, work / "_zp_probe.toml")
        cmp = run_compare(sc, str(path), workers=2)
        chk = ra.star_check(cmp, radius=3.0, min_snr=20.0)
        ratio = chk.get("median_flux_ratio", float("nan"))
        zp_passes.append({"n": chk.get("n", 0), "scale": ratio})
        if not math.isfinite(ratio) or abs(ratio - 1) < 0.02:
            break
        scene["detector"]["qe"] = [round(q * ratio, 6) for q in scene["detector"]["qe"]]
        scene["sky"]["background_mag_arcsec2"] = round(ra.sky_mag_arcsec2(sky_e, scene), 4)
    fwhm = psf["fwhm_px"]
    scene["sky"]["star_mag_limit"] = round(ra.limiting_mag(scene, sigma_eq, GAIN_E_PER_ADU, fwhm, t, nsigma=2.0), 2)
    sc = ra.load_scene_dict(scene, work / "_sky_probe.toml")
    model = build_model(sc, workers=2, realisation=False)
    excess_e = (float(np.median(model.mean_adu)) - sky) * GAIN_E_PER_ADU / t
    scene["sky"]["background_mag_arcsec2"] = round(ra.sky_mag_arcsec2(
        ra.sky_e_from_mag(scene, scene["sky"]["background_mag_arcsec2"]) - excess_e, scene), 4)
    lv = cfa_levels(img)
    meas = {"frame": str(path), "shape": [h, w], "exptime_s": t, "epoch_start": scene["pointing"]["epoch"],
            "black_adu": BLACK_ADU, "clip_adu": clip, "gain_e_per_adu_assumed": GAIN_E_PER_ADU,
            "gain_e_per_adu": GAIN_E_PER_ADU, "read_noise_e_assumed": READ_NOISE_E,
            "sky_median_adu": sky, "sky_robust_std_adu": ra.robust_std(img), "sky_e_per_s": sky_e,
            "sky_mag_arcsec2": scene["sky"]["background_mag_arcsec2"], "cfa_sky_levels_adu": lv,
            "cfa_sky_noise_adu": {f"{oy}{ox}": ra.robust_std(img[oy::2, ox::2] - ra.background_map(img[oy::2, ox::2], 15))
                                  for oy in (0, 1) for ox in (0, 1)},
            "equalised_sigma_adu": sigma_eq, "n_detected_5sigma": int(det["x"].size),
            "psf": {k: v for k, v in psf.items() if k != "stars"}, "wcs": {k: v for k, v in geom.items() if k != "wcs"},
            "sip": sip, "zero_point_passes": zp_passes, "band_peak": max(scene["detector"]["qe"]),
            "star_mag_limit": scene["sky"]["star_mag_limit"], "focal_length_mm": PIXEL_PITCH_UM / 1000 / math.radians(
                scale / 3600)}
    # the noise the sky should have (Poisson + read) against the measured one, per Bayer cell
    meas["cfa_expected_noise_adu"] = {k: math.sqrt(v / GAIN_E_PER_ADU + (READ_NOISE_E / GAIN_E_PER_ADU) ** 2)
                                      for k, v in lv.items()}
    return scene, meas


def catalogue_zero_point(img: np.ndarray, header, scene_dict: dict, clip_adu: float, exptime_s: float,
                         radius: float = 3.0) -> dict:
    """Band scale from the built-in catalogue's stars: aperture flux [e-] at the header WCS's positions
    over the scene band's electrons for each star's G and Teff. Saturated stars (a pixel within 10 % of
    the clip level) and stars with another catalogue star within 4 radii are left out."""
    from optics.design import load_design
    from scenes.catalog import star_electron_rate, stars_in_field

    geom = ra.wcs_geometry(header)
    w = geom["wcs"]
    h, wd = img.shape
    ra_c, dec_c = w.all_pix2world([[(wd - 1) / 2.0, (h - 1) / 2.0]], 0)[0]
    st = stars_in_field(ra_c, dec_c, radius_deg=0.75 * math.hypot(h, wd) * geom["scale_arcsec"] / 3600,
                        mag_limit=10.0, epoch=scene_dict["pointing"]["epoch"], catalog="builtin", seed=0)
    cat = st.source != "synthetic"
    x, y = w.all_world2pix(st.ra_deg[cat], st.dec_deg[cat], 0)
    flux, _ = ra.aperture_flux(img - BLACK_ADU, x, y, radius, radius + 2, radius + 5)
    d = load_design(scene_dict["telescope"]["design"])
    det = scene_dict["detector"]
    model_e = np.asarray(star_electron_rate(st.mag_g[cat], st.teff_k[cat], det["qe_wavelength_nm"], det["qe"],
                                            d.collecting_area_m2, optics_throughput=d.mirror_throughput)) * exptime_s
    ok = np.isfinite(flux) & (flux > 0)
    for k in np.flatnonzero(ok):
        xi, yi = round(x[k]), round(y[k])
        R = int(radius) + 1
        if img[yi - R:yi + R + 1, xi - R:xi + R + 1].max() >= 0.9 * clip_adu + 0.1 * BLACK_ADU:
            ok[k] = False
        near = np.hypot(x - x[k], y - y[k])
        if np.any((near > 0.1) & (near < 4 * radius)):
            ok[k] = False
    ratio = flux[ok] * scene_dict["detector"]["gain_e_per_adu"] / model_e[ok]
    lo, med, hi = np.percentile(ratio, [16, 50, 84])
    return {"n": int(ok.sum()), "scale": float(med), "scale_16": float(lo), "scale_84": float(hi),
            "g_range": [float(st.mag_g[cat][ok].min()), float(st.mag_g[cat][ok].max())]}


def wcs_match(scene_dict: dict, header, work: Path, shape: tuple[int, int]) -> dict:
    """The scene's WCS against the header's over the frame [px]: max distance of the same sky position."""
    w_file = ra.wcs_geometry(header)["wcs"]
    w_scene = ra.scene_wcs(scene_dict, work)
    ny, nx = shape
    yy, xx = np.mgrid[0:ny:25, 0:nx:25]
    ra_, dec_ = w_file.all_pix2world(xx.ravel(), yy.ravel(), 0)
    x2, y2 = w_scene.all_world2pix(ra_, dec_, 0)
    d = np.hypot(x2 - xx.ravel(), y2 - yy.ravel())
    return {"max_px": float(d.max()), "median_px": float(np.median(d))}


def cfa_check(cmp: dict) -> dict:
    """The Bayer pattern in the residuals: mean residual [ADU] and mean z of each cell over the sky pixels
    (no model source above 1 sigma), and the full-resolution z power at the Nyquist frequencies (0.5, 0.5),
    (0.5, 0), (0, 0.5) relative to the median power (white noise: ~1, a checkerboard: >> 1). The analysis's
    own spectrum is of a block-averaged map (3 x 3 here) and cannot show it."""
    res = cmp["_residuals"]
    src, _ = ra.source_maps(cmp)
    sky = res.fit & (src < np.sqrt(res.var_adu2))
    r = res.data_adu - res.model_adu
    z = np.where(res.fit, r / np.sqrt(res.var_adu2), 0.0)
    out = {"cells": {}}
    for oy in (0, 1):
        for ox in (0, 1):
            m = np.zeros_like(sky)
            m[oy::2, ox::2] = True
            m &= sky
            out["cells"][f"{oy}{ox}"] = {"mean_residual_adu": float(r[m].mean()), "mean_z": float(z[m].mean()),
                                         "std_z": float(z[m].std())}
    h, w = z.shape
    p = np.abs(np.fft.fft2(z - z.mean())) ** 2 / z.size
    med = float(np.median(p))
    out["nyquist_power"] = {"(0.5,0.5)": float(p[h // 2, w // 2] / med), "(0.5,0)": float(p[h // 2, 0] / med),
                            "(0,0.5)": float(p[0, w // 2] / med)}
    out["nyquist_rank"] = int(np.sum(p > p[h // 2, w // 2]))  # 0: the strongest frequency of the map
    out["cfa_fit"] = cfa_gain_fit(res)
    return out


def cfa_gain_fit(res) -> dict:
    """What a colour-filter-array effect would explain: one response factor per Bayer cell multiplying the
    model's photo-signal (sky and stars), fitted by weighted least squares on the compared pixels; chi2/dof
    before and after (the missing effect's signature, which the effect catalogue does not have)."""
    fit = res.fit
    r = (res.data_adu - res.model_adu)[fit].astype(np.float64)
    wgt = 1.0 / res.var_adu2[fit].astype(np.float64)
    t = []
    for oy in (0, 1):
        for ox in (0, 1):
            m = np.zeros(res.data_adu.shape)
            m[oy::2, ox::2] = 1.0
            t.append((m * res.photo_adu)[fit])
    t = np.array(t)
    a = (t * wgt) @ t.T
    c = np.linalg.solve(a, (t * wgt) @ r)
    r2 = r - c @ t
    n = r.size
    return {"response": {f"{oy}{ox}": float(1 + c[2 * oy + ox]) for oy in (0, 1) for ox in (0, 1)},
            "chi2_per_dof_before": float(np.sum(r * r * wgt) / n), "chi2_per_dof_after": float(np.sum(r2 * r2 * wgt) / n),
            "delta_chi2": float(np.sum(r2 * r2 * wgt) - np.sum(r * r * wgt))}


def extra(cmp: dict) -> dict:
    stars = ra.star_check(cmp, radius=3.0, min_snr=20.0)
    cfa = cfa_check(cmp)
    return {"star_check": {k: v for k, v in stars.items() if k != "table"}, "cfa": cfa, **ra.star_rows(stars),
            "row_nyquist_power": cfa["nyquist_power"]["(0.5,0.5)"],
            "row_cfa_mean_z": {k: v["mean_z"] for k, v in cfa["cells"].items()},
            "row_cfa_fit": cfa["cfa_fit"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="out/realdata/panoptes")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--write-scene", action="store_true", help="refresh examples/diagnose/scenes/panoptes.toml")
    args = ap.parse_args(argv)
    if not DATA.is_file():
        print(f"real data not found at {DATA}: nothing to do", file=sys.stderr)
        return 1
    out = Path(args.out).resolve()  # absolute: the scenes name their catalogue relative to themselves
    out.mkdir(parents=True, exist_ok=True)
    scene, meas = measure(DATA, out)
    img, header = ra.read_frame(DATA)
    meas["wcs_match"] = wcs_match(scene, header, out, img.shape)
    if args.write_scene:
        import tomli_w

        SCENE.parent.mkdir(parents=True, exist_ok=True)
        SCENE.write_text("# written by examples/diagnose/real_panoptes.py --write-scene: every value measured from\n"
                         "# ../shared/realdata/starfield/panoptes_solved.fits.fz or stated there as an assumption\n"
                         + tomli_w.dumps(scene))
    lv, nz, ez = meas["cfa_sky_levels_adu"], meas["cfa_sky_noise_adu"], meas["cfa_expected_noise_adu"]
    print(f"setup: black {BLACK_ADU:.0f} ADU, clip {meas['clip_adu']:.0f} ADU, gain {GAIN_E_PER_ADU} e-/ADU and RN "
          f"{READ_NOISE_E} e- assumed; sky {meas['sky_median_adu']:.0f} ADU = {meas['sky_mag_arcsec2']:.2f} mag/arcsec2 "
          f"(AB, calibrated band); Bayer cells above black " + ", ".join(f"{k}: {v:.0f}" for k, v in lv.items())
          + " ADU, sky noise " + ", ".join(f"{nz[k]:.1f} (Poisson+read {ez[k]:.1f})" for k in lv)
          + f"; PSF FWHM {meas['psf']['fwhm_major_px']:.2f} x {meas['psf']['fwhm_minor_px']:.2f} px, beta "
          f"{meas['psf']['beta']:.1f}; zero-point passes {meas['zero_point_passes']}; G limit {meas['star_mag_limit']};"
          f" scene WCS vs header: max {meas['wcs_match']['max_px']:.2g} px", flush=True)
    summary = {"setup": meas}
    summary["builtin"] = ra.rounds(scene, str(DATA), out, "panoptes_builtin", args.rounds, extra=extra)
    sb, info = frame_catalogue_scene(scene, meas, img, out)
    summary["frame_catalogue"] = {"catalogue": info, "rounds": ra.rounds(sb, str(DATA), out, "panoptes_framecat",
                                                                         args.rounds, extra=extra)}
    (out / "setup.json").write_text(json.dumps(jsonable(meas), indent=1, default=str))
    (out / "summary.json").write_text(json.dumps(jsonable(summary), indent=1, default=str))
    for name, table in (("builtin catalogue", summary["builtin"]), ("frame's own stars", summary["frame_catalogue"]["rounds"])):
        print(f"\n{name}: round  chi2/dof   misfit  stars(n, flux, offset px, size)  Nyquist power  cell mean z  "
              "best candidates (dBIC)")
        for r in table:
            print(f"{'':{len(name)}}  {r['round']:5d}  {r['chi2_per_dof']:8.4g}  {r['misfit']:7.4g}  "
                  f"{r.get('row_star_n', 0):3d} {ra._f(r.get('row_star_flux_ratio'))} {ra._f(r.get('row_star_offset_px'))} "
                  f"{ra._f(r.get('row_star_size_ratio'))}  {ra._f(r.get('row_nyquist_power'))}  "
                  + "/".join(f"{v:+.2f}" for v in r.get("row_cfa_mean_z", {}).values()) + "  "
                  + ", ".join(f"{e} {d:.3g}" for e, d, _ in r["candidates"][:3]))
    print(f"wrote {out}/summary.json, setup.json and the per-round scenes, JSON, ledgers and reports")
    return 0


def frame_catalogue_scene(scene: dict, meas: dict, img: np.ndarray, out: Path) -> tuple[dict, dict]:
    """Scene B: the frame's own detections (on the channel-equalised frame) as the star catalogue,
    magnitudes from raw-frame aperture fluxes (the Bayer-averaged flux that the model's band describes)."""
    from scenes.app.compare import build_model

    eq = equalised(img)
    bg = ra.background_map(eq, 21)
    det = ra.detect_sources(eq, bg, meas["equalised_sigma_adu"], nsigma=5.0, smooth=0.8)
    csv = out / "panoptes_frame_stars.csv"
    m2 = dict(meas, psf=dict(meas["psf"], fwhm_px=max(meas["psf"]["fwhm_px"], 1.2)))
    info = ra.frame_catalogue(img - BLACK_ADU, det, scene, m2, csv, sharp_max=0.7)
    sb = json.loads(json.dumps(scene))
    sb["sky"].update(catalog=csv.name, star_mag_limit=round(min(25.0, info["g_max"] + 0.5), 2))
    sc = ra.load_scene_dict(sb, out / "_panoptes_sky_probe.toml")
    model = build_model(sc, workers=2, realisation=False)
    g, t = meas["gain_e_per_adu"], meas["exptime_s"]
    sky_e = (ra.sky_e_from_mag(sb, sb["sky"]["background_mag_arcsec2"])
             - (float(np.median(model.mean_adu)) - meas["sky_median_adu"]) * g / t)
    sb["sky"]["background_mag_arcsec2"] = round(ra.sky_mag_arcsec2(sky_e, sb), 4)
    return sb, info


if __name__ == "__main__":
    sys.exit(main())
