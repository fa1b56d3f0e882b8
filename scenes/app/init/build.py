"""``newtsim init``: a scene from a measured frame, its calibration frames and its header.

Order of work: the header's conventions (:mod:`.header`), the raw frame's overscan (:mod:`.calib`), the camera
from the calibration frames (:mod:`.calib`), the WCS (:mod:`.wcs`), the background, the stars and their PSF
(:mod:`.stars`), the mask (:mod:`.mask`), the optics (:mod:`.optics`), the catalogue, then the scene and the
files it names (:mod:`.writer`). Every value carries its source (measured | header | assumed).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from detector.errors import DetectorError
from detector.effects.image_plane import displaced_halo_transfer
from scenes.measured import parse_section, read_hdu

from . import calib
from . import mask as maskmod
from . import stars as starmod
from .header import Value, read_header
from .optics import airy_fwhm_arcsec, design_dict
from .wcs import has_wcs, scene_geometry

#: read noise assumed when nothing measures it [e-]: a CCD / a CMOS of the classes seen
ASSUMED_READ_NOISE_E = {"ccd": 10.0, "cmos": 3.0}
#: ellipticity (1 - minor/major) above which the measured PSF's elongation goes into the scene
ELONGATED = 0.05
#: a median Moffat beta at or above this is a Gaussian (the fits' upper bound is 20)
GAUSSIAN_BETA = 15.0
_CMOS_WORDS = ("zwo", "qhy", "canon", "nikon", "sony", "cmos", "imx", "seestar", "asi", "eos", "dslr", "touptek", "playerone")


@dataclass
class InitResult:
    scene: dict
    sources: dict  # dotted scene key -> "source (card / note)"
    summary: dict
    files: dict = field(default_factory=dict)  # file name (beside the scene) -> ("csv"|"fits"|"toml", payload)


def _v(value, source, card=None, note=None) -> Value:
    return Value(value, source, card, note)


def _pick(*cands: Value, default: Value) -> Value:
    for c in cands:
        if c is not None and c.value is not None:
            return c
    return default


def init_scene(frame: str, scene_name: str = "scene", *, bias=(), dark=(), flat=(), catalog: str = "frame",
               design: str | None = None, focal_length_mm: float | None = None, f_number: float | None = None,
               obstruction: float = 0.0, hdu=None, log=lambda s: None) -> InitResult:
    """Measure ``frame`` and set up its scene. ``scene_name``: the stem of the files written beside the scene."""
    t0 = time.perf_counter()
    n_cal = {"bias_frames": len(bias), "dark_frames": len(dark), "flat_frames": len(flat)}
    raw, header = read_hdu(frame, hdu, role="measured", key="FRAME", dtype=np.float64)
    hv = read_header(header, raw)
    sources: dict[str, str] = {}
    notes: list[str] = []
    files: dict = {}

    def src(key: str, v: Value) -> None:
        text = v.source + (f" ({v.card})" if v.card else "") + (f": {v.note}" if v.note else "")
        sources[key] = text

    # ---- raw frame: overscan
    ov = calib.find_overscan(raw, header)
    trim = ov["trim"] if ov else None
    data = raw[parse_section(trim)] if trim else raw
    h, w = data.shape
    rolloff_mask = np.zeros((h, w), bool)
    rolloff = None
    if ov:
        notes.append(f"overscan {ov['bias_section']} ({ov['source']}): level {ov['level_adu']:.1f} ADU, noise "
                     f"{ov['noise_adu']:.2f} ADU; compared pixels {trim}")
        rolloff = calib.edge_rolloff(data, trim, ov["bias_section"], ov["level_adu"])
        if rolloff:
            k = rolloff["n"]
            lines = slice(0, k) if rolloff["side"] == "low" else slice(-k, None)
            if rolloff["axis"] == "columns":
                rolloff_mask[:, lines] = True
            else:
                rolloff_mask[lines, :] = True
            ex = rolloff["excess_adu"]
            notes.append(f"the first {k} {rolloff['axis']} beside the overscan depart from the frame's level "
                         f"(+{ex[0]:.0f} ADU down to {ex[-1]:+.0f} ADU against {rolloff['reference_adu']:.0f} ADU: an "
                         "edge roll-off the scene does not model): masked")
    # ---- camera from the calibration frames
    hgain = hv["gain_e_per_adu"]
    # a flat frame and a flat given: the two make the photon-transfer pair (the map comes from the other one)
    pair = [*flat, frame] if (hv["frame_type"].value == "flat" or "flat" in Path(str(frame)).name.lower()) and flat else flat
    cam = calib.camera_from_calibration(bias, dark, pair, trim=trim, shape=(h, w), header_gain=hgain.value)
    notes += cam["notes"]
    kind_words = " ".join(str(hv[k].value or "") for k in ("instrument", "telescope")).lower()
    kind = "cmos" if (hv["bayer"].value or any(word in kind_words for word in _CMOS_WORDS)) else "ccd"
    kind_v = _v(kind, "assumed", note="from the instrument's name / the colour filter array" if kind == "cmos" else
                "no sign of a CMOS in the header: a CCD")
    frame_type = hv["frame_type"].value
    name = Path(str(frame)).name.lower()
    if frame_type == "light":  # cameras that write every frame as a "Light Frame": the file name decides
        for word, kind_ in (("flat", "flat"), ("dark", "dark"), ("bias", "bias"), ("zero", "bias")):
            if word in name:
                notes.append(f"the file name says {kind_!r} ({hv['frame_type'].card or 'no IMAGETYP'} = "
                             f"{header.get(hv['frame_type'].card or 'IMAGETYP', 'absent')!r}): taken as a {kind_} frame")
                frame_type = kind_
                break
    exptime = _pick(hv["exptime_s"], default=_v(1.0, "assumed", note="no EXPTIME"))
    t = float(exptime.value)
    # bias level
    bias_v = _pick(cam.get("bias_adu"), _v(ov["level_adu"], "measured", "overscan", ov["bias_section"]) if ov else None,
                   hv["bias_adu"], default=None)
    # gain
    g_meas = cam.get("gain_e_per_adu")
    if g_meas is not None and "gain_se" in cam:
        gain_v = g_meas
    else:
        gain_v = _pick(hgain if hgain.value else None, g_meas, default=None)
    # read noise
    rn_adu = _pick(cam.get("read_noise_adu"), _v(ov["noise_adu"], "measured", "overscan") if ov else None, default=None)
    rn_hdr = hv["read_noise_e"]
    # the frame's level and noise (sources masked coarsely) for what the rest does not give
    finite = np.isfinite(data)
    med = float(np.median(data[finite]))
    # the noise of a pixel about the smooth background (photutils Background2D: a gradient or the vignetting is
    # not noise; the stars are outliers of the robust std): it keeps the sky's structure between the pixel and
    # the background's box (a raw frame's column pattern, a CFA's checkerboard), so the gain of a light frame
    # comes from the white noise instead (:func:`calib.white_noise`)
    bkg0, rms0 = starmod.background(data, mask=~finite | (data >= float(hv["saturation_adu"].value)))
    res0 = (data - bkg0)[finite]
    noise_about = calib.robust_std(res0[:: max(1, res0.size // 2_000_000)])
    noise = noise_about
    integer = bool(np.allclose(data[finite][:1000], np.round(data[finite][:1000])))
    q_adu2 = 1.0 / 12.0 if integer else 0.0  # the quantisation's variance (the model has its own)
    bayer = bool(hv["bayer"].value)
    noise_info: dict = {"about_background_adu": noise_about}
    cfa_pt = None
    if frame_type == "light":
        sky_px = calib.sky_pixels(data, bkg0, rms0, bad=rolloff_mask | (data >= float(hv["saturation_adu"].value)))
        wn = calib.white_noise(data, sky_px, lag=2 if bayer else 1)
        noise_info.update(white_x_adu=wn["x_adu"], white_y_adu=wn["y_adu"], white_adu=wn["adu"], lag_px=wn["lag"],
                          sky_pixels=int(sky_px.sum()))
        if not bayer:  # neighbours correlated (a resampled or smoothed frame): the lag-1 noise below the lag-2 one
            noise_info["lag2_adu"] = calib.white_noise(data, sky_px, lag=2)["adu"]
        if math.isfinite(wn["adu"]) and wn["n"] >= 100:
            noise = wn["adu"]
        if bayer and not (g_meas is not None and "gain_se" in cam):
            cfa_pt = calib.cfa_photon_transfer(data, sky_px)
            noise_info["cfa_photon_transfer"] = cfa_pt
    noise_info["adopted_adu"] = noise
    var_w = max(noise ** 2 - q_adu2, 1e-9)
    if bias_v is None:
        low = float(np.percentile(data[finite], 0.1))
        if low <= 0.05 * med or med < 5 * noise:
            bias_v = _v(0.0, "assumed", note="the data reach zero: bias-subtracted (or black level removed in the camera)")
        elif cfa_pt is not None:
            # the photon-transfer line of the cells: var = RN^2 + (L - B) / K at the cells' mean level
            g = cfa_pt["gain_e_per_adu"]
            rn_e = rn_hdr.value or ASSUMED_READ_NOISE_E[kind]
            lv, vv = float(np.mean(cfa_pt["levels_adu"])), float(np.mean(cfa_pt["variances_adu2"]))
            b = lv - g * (vv - q_adu2 - (rn_e / g) ** 2)
            bias_v = _v(float(np.clip(b, 0, min(cfa_pt["levels_adu"]))), "measured",
                        note=f"black level from the colour cells' photon transfer (K = {g:.4g} e-/ADU, read noise "
                        f"{rn_e:g} e-): level - K (variance - RN^2) at the cells' mean level {lv:.1f} ADU")
        elif gain_v is not None and gain_v.value:
            rn_e = rn_hdr.value or ASSUMED_READ_NOISE_E[kind]
            g = float(gain_v.value)
            b = med - g * (var_w - (rn_e / g) ** 2)
            bias_v = _v(float(np.clip(b, 0, med)), "measured",
                        note="level minus gain x (variance - read noise^2): var = (S - B)/g + (RN/g)^2")
        else:
            bias_v = _v(0.0, "assumed", note="no bias frame, no overscan, no gain: the level is taken as all signal")
    bias = float(bias_v.value)
    # the gain the frame's white sky noise gives (Janesick 2007, eq. 4.7 on the sky: K = (S - B) / (var - RN^2))
    s_adu = max((float(np.median(bkg0[finite])) if frame_type == "light" else med) - bias, 1e-3)
    g_white = None
    if frame_type == "light" and bias_v.note != "level minus gain x (variance - read noise^2): var = (S - B)/g + (RN/g)^2":
        rn_e_guess = rn_hdr.value or ASSUMED_READ_NOISE_E[kind]
        if rn_adu is not None and rn_adu.value ** 2 < 0.8 * var_w:
            g_white = s_adu / (var_w - rn_adu.value ** 2)
        elif rn_adu is None:  # var g^2 - S g - RN^2 = 0 with the read noise in e- (header or assumed)
            g_white = (s_adu + math.sqrt(s_adu * s_adu + 4 * var_w * rn_e_guess ** 2)) / (2 * var_w)
        noise_info["gain_white_e_per_adu"] = g_white
    prnu_sigma = None
    gain_check = _gain_check(hgain, header, g_white, s_adu, var_w, rn_adu, rn_hdr, cfa_pt, trim is not None)
    if gain_check is not None:
        noise_info["gain_check"] = gain_check
        notes.append(gain_check["note"])
    if gain_v is not None and "gain_se" not in cam and gain_check is not None:
        if gain_check["adopted"] == "measured":
            gain_v = _v(gain_check["measured_e_per_adu"], "measured", note=gain_check["source_note"])
        elif gain_check.get("prnu_sigma"):
            prnu_sigma = gain_check["prnu_sigma"]
    if gain_v is None:
        if cfa_pt is not None:
            gain_v = _v(cfa_pt["gain_e_per_adu"], "measured",
                        note=f"photon transfer of the four colour cells' white sky noise against their levels "
                        f"{cfa_pt['levels_adu']} ADU (Janesick 2007, eq. 4.7), standard error {cfa_pt['gain_se']:.2g}")
        else:
            rn_e = rn_hdr.value or ASSUMED_READ_NOISE_E[kind]
            if rn_adu is not None and rn_adu.value ** 2 < 0.8 * var_w:  # var = S/g + rn_adu^2
                g = s_adu / (var_w - rn_adu.value ** 2)
            else:  # var g^2 - S g - RN^2 = 0
                g = (s_adu + math.sqrt(s_adu * s_adu + 4 * var_w * rn_e ** 2)) / (2 * var_w)
            which = (f"the white sky noise {noise:.3g} ADU (differences of neighbouring sky pixels / sqrt 2, lag "
                     f"{noise_info.get('lag_px', 1)} px)" if frame_type == "light" else f"the noise {noise:.3g} ADU")
            gain_v = _v(float(np.clip(g, 0.01, 999.0)), "measured",
                        note=f"{which}: var = S/g + (RN/g)^2 (Poisson sky and read noise); a raw frame's pixel "
                        "response pattern adds to it (the gain a lower bound)" if frame_type == "light" else
                        f"{which}: var = S/g + (RN/g)^2")
            if frame_type != "light":
                gain_v = _v(float(g), "measured", note=f"noise of the {frame_type} frame (Poisson + read noise)")
    gain = float(gain_v.value)
    if rn_adu is not None:
        rn_e_v = _v(rn_adu.value * gain, rn_adu.source, rn_adu.card, (rn_adu.note or "") + " x adopted gain")
    elif rn_hdr.value:
        rn_e_v = rn_hdr
    else:
        rn_e_v = _v(ASSUMED_READ_NOISE_E[kind], "assumed", note=f"typical of a {kind.upper()}")
    if rn_e_v.source != "measured" and noise * gain < float(rn_e_v.value):
        # the frame's whole noise is below the read noise said or assumed: the read noise cannot be that large
        notes.append(f"read noise {rn_e_v.value:g} e- ({rn_e_v.source}{' ' + rn_e_v.card if rn_e_v.card else ''}) is "
                     f"above the frame's own noise {noise * gain:.3g} e-: the frame's noise is adopted")
        rn_e_v = _v(noise * gain, "measured", note=f"the frame's robust noise (below the {rn_e_v.source} value {rn_e_v.value:g})")
    if hgain.note:
        notes.append(hgain.note)
    dark_v = cam.get("dark_rate_adu_s")
    dark_e_v = (_v(dark_v.value * gain, dark_v.source, dark_v.card, dark_v.note) if dark_v is not None
                else _v(0.0, "assumed", note="no dark frame"))
    if frame_type == "dark" and dark_v is None:
        dark_e_v = _v(max(med - bias, 0.0) * gain / max(t, 1e-9), "measured", note="the dark frame's median above the bias / t")
    sat_v = hv["saturation_adu"]
    depth_v = hv["bit_depth"]
    sat = float(sat_v.value)
    full_well = max((sat - bias) * gain, 1.0)
    fw_hdr = hv["full_well_e"]
    if fw_hdr.value and (sat_v.source != "measured" or fw_hdr.value < full_well):
        full_well = float(fw_hdr.value)
        sat = min(sat, bias + full_well / gain)
        sat_v = _v(sat, "header", fw_hdr.card, "full well from the header")
    temp_v = _pick(hv["temperature_c"], default=_v(20.0, "assumed"))
    binning = int(hv["binning"].value or 1)
    # ---- geometry
    geom = None
    if has_wcs(header):
        geom = scene_geometry(header, (h, w), binning=binning)
        if trim:  # the WCS refers to the raw frame's pixels: re-centre on the trimmed data
            rows, cols = parse_section(trim)
            geom = _trimmed_geometry(header, raw.shape, rows, cols, binning)
    fl_v = hv["focal_length_mm"]
    if focal_length_mm:
        fl_v = _v(float(focal_length_mm), "assumed", "--focal-length-mm", "given on the command line")
    ap_v = hv["aperture_mm"]
    if ap_v.value and fl_v.value and not 0.7 <= float(fl_v.value) / float(ap_v.value) <= 40:
        notes.append(f"{ap_v.card} = {ap_v.value:g} mm with a {fl_v.value:g} mm focal length is f/"
                     f"{float(fl_v.value) / float(ap_v.value):.3g}: not an aperture, ignored")
        ap_v = _v(None, "assumed")
    if f_number and fl_v.value:
        ap_v = _v(float(fl_v.value) / float(f_number), "assumed", "--f-number", "given on the command line")
    pitch_v = hv["pixel_pitch_um"]
    if pitch_v.value is None and geom is not None and fl_v.value:
        pitch_v = _v(geom["scale_arcsec"] / binning * float(fl_v.value) / 206.264806, "measured",
                     note="plate scale x focal length")
    if pitch_v.value is None:
        pitch_v = _v(5.0, "assumed", note="no XPIXSZ: 5 um (only the collecting area / design uses it)")
    pitch = float(pitch_v.value)
    if geom is not None:
        scale_v = _v(geom["scale_arcsec"] / binning, "header", "WCS", f"{geom['form']} ({geom['matrix']})")
    elif fl_v.value:
        scale_v = _v(206.264806 * pitch / float(fl_v.value), "measured", note="pixel pitch / focal length")
    else:
        scale_v = _v(2.0, "assumed", note="no WCS and no focal length: 2 arcsec/px")
    scale = float(scale_v.value)
    # ---- optics
    design_name = str(Path(design).resolve()) if design is not None and Path(design).is_file() else design
    if design is None:
        f_mm = float(fl_v.value) if fl_v.value else 206.264806 * pitch / scale
        n = float(f_number) if f_number else (f_mm / float(ap_v.value) if ap_v.value else 5.0)
        if not (f_number or ap_v.value) and frame_type == "light":
            notes.append("no aperture: f/5 assumed for the design (the zero point absorbs the collecting area)")
        table = design_dict(f_mm, n, obstruction, sensor_mm=(w * binning * pitch / 1000, h * binning * pitch / 1000),
                            name=f"{scene_name}_optics")
        design_name = f"{scene_name}_optics.toml"
        files[design_name] = ("toml", table)
        optics_info = {"focal_length_mm": f_mm, "f_number": n, "aperture_mm": f_mm / n, "obstruction": obstruction,
                       "airy_fwhm_arcsec_550nm": airy_fwhm_arcsec(f_mm / n)}
    else:
        optics_info = {"design": design}
    # ---- background, stars, PSF
    log("stars and PSF")
    # saturated as compare sees it: the clipped level less 5 read-noise sigma (scenes.app.compare.model.saturation_adu)
    sat_cut = sat - 5.0 * float(rn_e_v.value) / gain
    # a colour (Bayer) frame: the stars are measured on the frame divided by its cells' responses (measured on
    # the sky), so that a star's pixels follow its PSF and not the filter mosaic: on the raw mosaic the cells
    # of a star differ by their responses (PANOPTES: 0.68 to 1.21 of the mean), which distorts the PSF fits
    # and makes a bright star's checkerboard look like several stars to the deblending
    cfa_resp = None
    sdata, sat_px = data, sat_cut
    if hv["bayer"].value and frame_type == "light":
        cfa_resp = _cfa_response(data - bias, sky_px)
        rmap = np.tile(np.array(cfa_resp).reshape(2, 2), (h // 2 + 1, w // 2 + 1))[:h, :w]
        sdata = bias + (data - bias) / rmap
        sat_px = bias + (sat_cut - bias) / rmap  # the clip of each cell, divided alike
    bad = ~np.isfinite(data) | (data >= sat_cut) | rolloff_mask
    bkg, rms = starmod.background(sdata, mask=bad)
    seg, cols = None, {}
    if frame_type == "light":  # a dark, bias or flat frame has no stars (its outliers are hot pixels)
        seg, cols = starmod.detect(sdata, bkg, rms, fwhm_px=3.0, nsigma=5.0, mask=~np.isfinite(data))
    psf = {"ok": False, "n": 0}
    if seg is not None and len(cols.get("label", [])):
        seg, cols = starmod.detect(sdata, bkg, rms, fwhm_px=float(np.clip(np.nanmedian(cols["fwhm"]), 1.5, 20)),
                                   nsigma=5.0, mask=~np.isfinite(data), deblend=True)
        psf = starmod.fit_psf_stars(sdata, bkg, seg, cols, sat_px, rms=rms)
    if psf.get("ok"):
        fwhm_px, beta = psf["fwhm_px"], float(np.clip(psf["beta"], 1.2, 50))
        if psf["beta"] >= GAUSSIAN_BETA:  # the Moffat's beta -> infinity limit: a Gaussian core without wings
            beta = math.inf
        psf_src = _v(fwhm_px, "measured", note=f"median of elliptical Moffat fits of {psf['n']} stars")
    else:
        fwhm_px, beta = 3.0, 4.765
        psf_src = _v(fwhm_px, "assumed", note="no isolated star to fit")
    # the measured elongation goes into the scene ([effects.psf_elongation], below): the photometry fits the
    # stars with that same PSF, so the catalogue's fluxes are those of the scene's own stars
    elongated = bool(psf.get("ok") and psf["n"] >= 5 and psf["ellipticity"] > ELONGATED)
    cov_px2 = starmod.elongation_cov_px2(psf, fwhm_px) if elongated else None
    phot, halo_info, halo = None, None, None
    if seg is not None and frame_type == "light":
        sharp = cols["fwhm"] < 0.5 * fwhm_px
        phot = starmod.photometry(sdata, bkg, cols, fwhm_px, min(beta, 1000.0), sat_px, rms, keep=~sharp,
                                  gain=gain, cov_px2=cov_px2)
    # ---- mask
    # `drop`: what removes the sources under it from the catalogue (extended and broad sources, bleeds, the edge
    # roll-off); `mask`: that and the saturated cores (the stars whose cores they are stay in the catalogue,
    # their fluxes fitted from their wings)
    drop = np.zeros((h, w), bool)
    cores = np.zeros((h, w), bool)
    minfo = {"extended": [], "bleeds": [], "saturated_cores": [], "masked_fraction": 0.0}
    if frame_type == "light":
        sxyf = (phot["x"], phot["y"], phot["flux_adu"]) if phot is not None and phot["x"].size else None
        drop, minfo = maskmod.extended_and_bleeds(sdata, bkg, rms, fwhm_px, sat_px, sxyf)
        cores = minfo.pop("core_mask")
        if seg is not None and len(cols.get("label", [])):
            broad, minfo["broad"] = maskmod.broad_sources(sdata, bkg, rms, seg, cols, fwhm_px, sat_px, gain=gain)
            drop |= broad
            for b in minfo["broad"]["sources"]:
                notes.append(f"the source at ({b['x']:.1f}, {b['y']:.1f}) is {b['size_ratio']:.2f} x as broad as the "
                             f"frame's stars ({b['excess_sigma']:.1f} sigma): not a point source (a galaxy, an "
                             "unresolved double, a nebulous object): masked")
    if rolloff:
        drop |= rolloff_mask
        minfo["edge_rolloff"] = rolloff
    mask = drop | cores
    minfo["masked_fraction"] = float(mask.mean())
    # the PSF's displaced halo (the flare of a fast lens off its axis): measured on the whole frame with the stars
    # as fitted, the mask left out; when it is kept, the stars are measured again with that PSF
    if phot is not None and psf.get("ok") and phot["x"].size:
        halo_info = starmod.fit_psf_halo(sdata, bkg, phot, fwhm_px, min(beta, 1000.0), cov_px2, rms, gain=gain,
                                         saturation=sat_px, mask=mask)
    if halo_info is not None and halo_info["kept"]:
        halo = (halo_info["halo_frac"], halo_info["halo_sigma_px"], halo_info["halo_dx_px"], halo_info["halo_dy_px"])
        phot = starmod.photometry(sdata, bkg, cols, fwhm_px, min(beta, 1000.0), sat_px, rms, keep=~sharp,
                                  gain=gain, cov_px2=cov_px2, extra=displaced_halo_transfer(*halo))
        notes.append(f"the PSF has a displaced halo: {100 * halo[0]:.1f} % of each star's light in a Gaussian of "
                     f"{halo[1]:.2f} px rms centred ({halo[2]:+.2f}, {halo[3]:+.2f}) px from its core (the frame's "
                     f"chi2 {halo_info['chi2_without_halo']:.0f} -> {halo_info['chi2_with_halo']:.0f}): the flare of a "
                     "fast lens off its axis; in the scene as effects.psf_elongation's halo")
    # the stars the detection missed (a neighbour kept in a brighter star's segment): found in the residual of the
    # fitted stars and fitted (iterative PSF photometry)
    if phot is not None and phot["x"].size and psf.get("ok"):
        phot = starmod.residual_stars(sdata, bkg, phot, fwhm_px, min(beta, 1000.0), cov_px2, rms, gain=gain,
                                      saturation=sat_px, mask=mask,
                                      extra=None if halo is None else displaced_halo_transfer(*halo))
        if phot["added"]:
            notes.append(f"{phot['added']} stars found in the residual of the fitted ones (missed by the detection: "
                         "neighbours of brighter stars) and fitted")
    # ---- sky: the background of the frame without the scene's own stars (their wings and halos are the stars')
    sky_map = bkg
    if phot is not None and phot["x"].size and psf.get("ok"):
        sky_map = starmod.sky_without_stars(sdata, phot, fwhm_px, min(beta, 1000.0), cov_px2,
                                            None if halo is None else displaced_halo_transfer(*halo),
                                            mask=mask | (data >= sat_cut))
    sky_adu = float(np.median(sky_map[~mask])) if (~mask).any() else float(np.median(sky_map))
    sky_e_s = max((sky_adu - bias) * gain / max(t, 1e-9) - float(dark_e_v.value), 0.0)
    # ---- the scene
    preset = "ml11002" if kind == "ccd" else "imx411"
    det = {"preset": preset, "name": str(hv["instrument"].value or "camera")[:60], "kind": kind,
           "shutter": "global", "line_time_s": 0.0, "pixel_pitch_um": round(pitch, 4),
           "sensor_width_px": w * binning, "sensor_height_px": h * binning,
           "bit_depth": int(depth_v.value), "gain_e_per_adu": round(gain, 5), "bias_adu": round(bias, 3),
           "read_noise_e": round(float(rn_e_v.value), 4), "dark_current_e_per_s": round(float(dark_e_v.value), 6),
           "full_well_e": round(full_well, 1), "temperature_c": round(float(temp_v.value), 3)}
    if binning > 1:
        det["binning"] = binning
    for k, v in (("kind", kind_v), ("pixel_pitch_um", pitch_v), ("bit_depth", depth_v), ("gain_e_per_adu", gain_v),
                 ("bias_adu", bias_v), ("read_noise_e", rn_e_v), ("dark_current_e_per_s", dark_e_v),
                 ("temperature_c", temp_v), ("binning", hv["binning"])):
        src(f"detector.{k}", v)
    src("detector.full_well_e", _v(full_well, sat_v.source, sat_v.card, (f"(saturation {sat:.0f} - bias) x gain; " if sat_v.card != "FULLWELL" else "") + (sat_v.note or "")))
    sources["detector.sensor_width_px"] = "measured (the frame's size" + (f", trimmed to {trim})" if trim else ")")
    sources["detector.preset"] = f"assumed: a generic {kind.upper()} for the QE curve (the zero point calibrates the band)"
    win = hv["window_origin"]
    if win.source == "header" and any(win.value):
        notes.append(f"window origin {win.value} ({win.card}): the scene's sensor is the frame (optical axis at its centre)")
    scene: dict = {
        "telescope": {"design": design_name, "pixel_scale_arcsec": round(scale, 7)},
        "detector": det,
        "pointing": {}, "exposure": {"time_s": t, "frame": "light" if frame_type in ("light", "flat") else frame_type,
                                      "tracking": "sidereal", "seed": 1},
        "sky": {}, "psf": ({"model": "moffat", "fwhm_arcsec": round(fwhm_px * scale * binning, 4), "beta": round(beta, 3)}
                           if math.isfinite(beta) else {"model": "gaussian", "fwhm_arcsec": round(fwhm_px * scale * binning, 4)}),
    }
    src("telescope.pixel_scale_arcsec", scale_v)
    src("exposure.time_s", exptime)
    src("psf.fwhm_arcsec", psf_src)
    if math.isfinite(beta):
        src("psf.beta", _v(beta, psf_src.source))
    else:
        sources["psf.model"] = f"measured: the Moffat fits' beta reaches {GAUSSIAN_BETA:g} (no wings): a Gaussian"
    if geom is not None:
        scene["telescope"]["parity"] = int(geom["parity"])
        if geom["sip"]:
            scene["telescope"]["distortion"] = "sip"
            scene["telescope"]["sip"] = geom["sip"]
            sources["telescope.distortion"] = f"header (WCS {geom['form']}): max {geom['max_distortion_px']:.2f} px from TAN"
        scene["pointing"] = {"ra_deg": round(geom["ra_deg"], 8), "dec_deg": round(geom["dec_deg"], 8),
                             "roll_deg": round(geom["roll_deg"], 6)}
        for k in ("ra_deg", "dec_deg", "roll_deg"):
            sources[f"pointing.{k}"] = f"header (WCS {geom['form']}, {geom['matrix']}): the frame centre"
        sources["telescope.parity"] = "header (WCS): sign of det CD"
    else:
        ra = _first_angle(header, ("RA", "OBJCTRA", "RA_OBJ", "TELRA"), hours_if_str=True)
        dec = _first_angle(header, ("DEC", "OBJCTDEC", "DEC_OBJ", "TELDEC"))
        scene["pointing"] = {"ra_deg": round(ra if ra is not None else 0.0, 8) % 360, "dec_deg": round(dec if dec is not None else 0.0, 8),
                             "roll_deg": 0.0}
        sources["pointing.ra_deg"] = "header (RA/OBJCTRA)" if ra is not None else "assumed: no WCS and no RA card"
        sources["pointing.roll_deg"] = "assumed: no WCS (north up)"
        if frame_type == "light":
            notes.append("no WCS in the header: the frame's own catalogue only (positions through the scene's assumed WCS)")
        if catalog != "frame" and frame_type == "light":
            raise DetectorError("the frame has no WCS", key="--catalog", file=str(frame),
                                expected="--catalog frame (the frame's own stars) for a frame without a WCS")
    scene["pointing"]["epoch"] = hv["date_obs"].value
    src("pointing.epoch", hv["date_obs"])
    if hv["site"].value:
        s = hv["site"].value
        scene["observer"] = {"lat_deg": round(s["lat_deg"], 6), "lon_deg": round(s["lon_deg"], 6),
                             "alt_m": round(float(s["height_m"]), 1)}
        src("observer.lat_deg", hv["site"])
    if ov:
        scene["measured"] = {"trim": trim}
        sources["measured.trim"] = f"{ov['source']} ({ov.get('card') or 'flat, dark edge columns'}): overscan {ov['bias_section']}"
    if hdu is not None:
        scene.setdefault("measured", {})["hdu"] = hdu
    # effects from calibration maps
    effects: dict = {}
    if prnu_sigma:
        effects["prnu"] = {"sigma": round(float(prnu_sigma), 5)}
        sources["effects.prnu"] = ("measured: the sky's white noise above the header gain's Poisson and read noise, "
                                   "as a pixel response non-uniformity (see notes)")
    if cam.get("flat") is not None:
        files[f"{scene_name}_flat.fits"] = ("fits", cam["flat"])
        effects["flat_map"] = {"path": f"{scene_name}_flat.fits", "sigma_hdu": 1}
        sources["effects.flat_map"] = "measured: the normalised (first) flat, its standard error in HDU 1"
    if cam.get("dark_rate_map") is not None and frame_type != "bias":
        rate, se = cam["dark_rate_map"]
        files[f"{scene_name}_dark.fits"] = ("fits", [rate * gain, se * gain])
        effects["dark_map"] = {"path": f"{scene_name}_dark.fits", "sigma_hdu": 1}
        sources["effects.dark_map"] = ("measured: per-pixel slope of bias and darks against time [e-/s] (adopted gain), "
                                       "its standard error in HDU 1")
    if halo is not None:
        dc = (cov_px2 if cov_px2 is not None else np.zeros((2, 2))) * binning ** 2
        effects["psf_elongation"] = {"dcxx_px2": round(float(dc[0, 0]), 5), "dcyy_px2": round(float(dc[1, 1]), 5),
                                     "dcxy_px2": round(float(dc[0, 1]), 5), "halo_frac": round(halo[0], 5),
                                     "halo_sigma_px": round(halo[1] * binning, 4),
                                     "halo_dx_px": round(halo[2] * binning, 4), "halo_dy_px": round(halo[3] * binning, 4)}
        sources["effects.psf_elongation"] = (
            (f"measured: FWHM {psf['fwhm_major_px']:.2f} x {psf['fwhm_minor_px']:.2f} px, major axis at "
             f"{psf['pa_major_deg']:.0f} deg from +x (median of {psf['n']} stars); " if elongated else "measured: ")
            + f"the halo from the whole frame's residual (chi2 {halo_info['chi2_without_halo']:.0f} without it, "
            f"{halo_info['chi2_with_halo']:.0f} with it)")
    elif elongated:
        # the measured elliptical PSF as the round one plus a second-moment change dC (Gaussian-equivalent
        # variances of the major and minor axes about the quadratic-mean FWHM, rotated to the major axis), in
        # sensor pixels: the scene's [psf] has no ellipticity key, the renderer's elongation is this effect
        dc = cov_px2 * binning ** 2
        effects["psf_elongation"] = {"dcxx_px2": round(float(dc[0, 0]), 5), "dcyy_px2": round(float(dc[1, 1]), 5),
                                     "dcxy_px2": round(float(dc[0, 1]), 5)}
        sources["effects.psf_elongation"] = (f"measured: FWHM {psf['fwhm_major_px']:.2f} x {psf['fwhm_minor_px']:.2f} px, "
                                             f"major axis at {psf['pa_major_deg']:.0f} deg from +x (median of {psf['n']} stars)")
    if hv["bayer"].value and frame_type == "light":
        resp = cfa_resp
        effects["cfa"] = {"pattern": hv["bayer"].value, "response": [round(r, 5) for r in resp]}
        sources["effects.cfa"] = f"header ({hv['bayer'].card}) pattern; response measured from the sky level of each cell"
    if effects:
        scene["effects"] = effects
    if mask.any():
        files[f"{scene_name}_mask.fits"] = ("fits", mask.astype(np.uint8))
        scene["mask"] = {"file": f"{scene_name}_mask.fits"}
        n_broad = len(minfo.get("broad", {}).get("sources", []))
        sources["mask.file"] = (f"measured: {len(minfo['extended'])} extended source(s), "
                                + (f"{n_broad} source(s) broader than the PSF, " if n_broad else "")
                                + f"{len(minfo['saturated_cores'])} saturated core(s), {len(minfo['bleeds'])} bleed(s), "
                                + (f"{rolloff['n']} edge {rolloff['axis']} beside the overscan, " if rolloff else "")
                                + f"{100 * minfo['masked_fraction']:.2g} % of the pixels")
    # ---- sky and catalogue, through the scene's band
    band = _Band(scene, design_name, files)
    if frame_type == "flat":
        rate = max((med - bias) * gain / t - float(dark_e_v.value), 0.0)
        scene["sky"] = {"background_mag_arcsec2": None, "stars": False, "flat_e_per_s": round(rate, 4)}
        sources["sky.flat_e_per_s"] = "measured: the flat's median above the bias x gain / t - dark"
    elif frame_type in ("dark", "bias"):
        scene["sky"] = {"background_mag_arcsec2": None, "stars": False}
        if frame_type == "bias":
            scene["exposure"]["time_s"] = 0.0
    else:
        scene["sky"] = {"background_mag_arcsec2": None, "stars": True, "star_seed": 0}
        sources["sky.background_mag_arcsec2"] = (f"measured: background {sky_adu:.2f} ADU (photutils Background2D"
                                                 + (" of the frame less the scene's stars" if sky_map is not bkg else "")
                                                 + ") above the bias, through the scene's band")
    cat_info = {}
    if scene["sky"].get("stars"):
        cat_info = _catalogue(catalog, scene, band, phot, cols, fwhm_px, drop, data.shape, gain, t, geom, header,
                              files, scene_name, sources, notes)
    scale = cat_info.get("band_scale")
    if scale:  # real magnitudes: the matched stars' zero point goes into the aperture (when assumed) or the QE
        if design is None and not (f_number or ap_v.value):
            n_new = max(optics_info["f_number"] / math.sqrt(scale), 0.7)
            f_mm = optics_info["focal_length_mm"]
            fp = files[design_name][1]["focal_plane"]
            files[design_name] = ("toml", design_dict(f_mm, n_new, obstruction, sensor_mm=(fp["width_mm"], fp["height_mm"]),
                                                      name=f"{scene_name}_optics"))
            optics_info.update(f_number=n_new, aperture_mm=f_mm / n_new, aperture_source="measured: zero point")
            sources["telescope.design"] = (f"measured: the clear aperture {f_mm / n_new:.1f} mm that gives the zero point "
                                           f"of {cat_info['n_matched']} matched catalogue stars (focal length {f_mm:.0f} mm)")
        else:
            scene["detector"]["qe_wavelength_nm"] = band.wl
            peak = max(band.qe) * scale
            scene["detector"]["qe"] = [round(q * scale / max(peak / 0.95, 1.0), 6) for q in band.qe]
            if peak > 0.95:
                notes.append(f"zero point needs a band peak {peak:.2f} > 0.95: QE capped, the rest left to the diagnosis")
            sources["detector.qe"] = f"measured: the preset's curve x {scale:.3g} from {cat_info['n_matched']} matched stars"
        band = _Band(scene, design_name, files)
    if "background_mag_arcsec2" in scene["sky"]:
        scene["sky"]["background_mag_arcsec2"] = round(band.sky_mag(sky_e_s), 4)
    scene["sky"] = {k: v for k, v in scene["sky"].items() if v is not None}
    summary = {
        "frame": str(frame), "shape": [h, w], "raw_shape": list(raw.shape), "frame_type": frame_type,
        "values": {k: sources[k] for k in sorted(sources)},
        "header": {k: v.to_json() for k, v in hv.items()},
        "calibration": {"missing": cam["missing"], **n_cal},
        "overscan": ov, "wcs": {k: v for k, v in (geom or {}).items() if k != "sip"} or None,
        "psf": {**{k: v for k, v in psf.items() if k != "rows"}, "halo": halo_info}, "optics": optics_info,
        "sky": {"background_adu": sky_adu, "e_per_s_per_px": sky_e_s, "noise_adu": float(np.median(rms))},
        "noise": noise_info,
        "mask": minfo, "catalogue": cat_info, "notes": notes, "seconds": time.perf_counter() - t0,
    }
    return InitResult(scene, sources, summary, files)


#: a gain measured from the frame within this fraction of the header's (or its amplifiers' range) agrees with it
GAIN_TOLERANCE = 0.05
#: the largest pixel response non-uniformity [fraction] a header gain's excess white noise is put down to
MAX_PRNU = 0.03


def _gain_check(hgain: Value, header, g_white, s_adu: float, var_w: float, rn_adu, rn_hdr: Value, cfa_pt,
                raw: bool) -> dict | None:
    """The header's gain (and its amplifiers') against the one the frame's own noise gives, and which one the
    scene adopts (the issue: never hide a disagreement).

    The white sky noise var = (S - B)/K + RN^2 (+ (p S)^2 on a frame whose pixel response pattern p is not
    flat-fielded out) gives K when p is negligible and a lower bound on K otherwise. So:
    * within :data:`GAIN_TOLERANCE` of the header's (any amplifier's): they agree, the header's is adopted;
    * below it (the frame noisier than the header's gain allows): the excess, if it is a pixel response pattern
      p <= :data:`MAX_PRNU` (0.5-1.5 % is usual for a raw CCD), goes into the scene as ``effects.prnu`` and the
      header's gain (the camera's calibration) is kept; a larger excess means the header's gain is wrong;
    * above it (the frame quieter than the header's gain allows): no process lowers a Poisson noise, so the
      header's gain does not describe these pixels (a processed frame rescaled, a card left at a default):
      the measured one is adopted;
    * the photon transfer of a colour frame's cells (a slope, the bias and PRNU aside) is adopted when it
      disagrees, as a flat pair's would be."""
    from .header import amplifier_gains

    if not hgain.value:
        return None
    g_meas = cfa_pt["gain_e_per_adu"] if cfa_pt is not None else g_white
    if g_meas is None or not math.isfinite(g_meas) or g_meas <= 0:
        return None
    hdr = float(hgain.value)
    amps = amplifier_gains(header)
    lo, hi = (min(amps.values()), max(amps.values())) if amps else (hdr, hdr)
    method = ("photon transfer of the colour cells" if cfa_pt is not None else
              f"white sky noise {math.sqrt(var_w):.3g} ADU at {s_adu:.1f} ADU above the bias")
    hdr_text = (f"{hgain.card} = {hdr:.4g} e-/ADU" + (" (amplifiers " + ", ".join(f"{k} = {v:g}" for k, v in amps.items())
                                                      + ")" if amps else ""))
    out = {"header_e_per_adu": hdr, "header_card": hgain.card, "amplifiers": amps or None,
           "measured_e_per_adu": float(g_meas), "method": method, "ratio_measured_to_header": float(g_meas / hdr)}
    if lo * (1 - GAIN_TOLERANCE) <= g_meas <= hi * (1 + GAIN_TOLERANCE):
        out.update(adopted="header", note=f"gain: {hdr_text} and {g_meas:.4g} e-/ADU from the {method} agree "
                   f"(within {100 * GAIN_TOLERANCE:g} %): the header's adopted")
        return out
    if g_meas < lo * (1 - GAIN_TOLERANCE) and cfa_pt is None:
        rn2 = rn_adu.value ** 2 if rn_adu is not None else ((rn_hdr.value or 0.0) / hdr) ** 2
        excess = var_w - s_adu / hdr - rn2
        p = math.sqrt(max(excess, 0.0)) / s_adu
        out["excess_variance_adu2"] = float(excess)
        if p <= MAX_PRNU:
            out.update(adopted="header", prnu_sigma=float(p),
                       note=f"gain: {hdr_text} against {g_meas:.4g} e-/ADU from the {method} "
                       f"({100 * (g_meas / hdr - 1):+.0f} %: the sky is noisier than the header's gain allows): the "
                       f"excess {excess:.3g} ADU^2 is a pixel response non-uniformity of {100 * p:.2g} % "
                       f"({'a raw frame, not flat-fielded' if raw else 'the flat-field pattern left in the frame'}), "
                       "put in the scene as effects.prnu; the header's gain adopted")
            return out
        out.update(adopted="measured", note=f"gain: {hdr_text} DISAGREES with {g_meas:.4g} e-/ADU from the {method} "
                   f"({100 * (g_meas / hdr - 1):+.0f} %; as a pixel response pattern it would be {100 * p:.2g} %, "
                   f"above {100 * MAX_PRNU:g} %): the measured gain adopted")
        out["source_note"] = f"{method}: var = S/g + RN^2 (the header's {hgain.card} = {hdr:.4g} disagrees)"
        return out
    why = ("the colour cells' photon transfer (a slope: neither the bias nor a pixel pattern moves it)" if cfa_pt is not None
           else "the frame is quieter than the header's gain allows (no process lowers a Poisson noise: the header's "
           "value does not describe these pixels, e.g. a processed frame rescaled)")
    out.update(adopted="measured", note=f"gain: {hdr_text} DISAGREES with {g_meas:.4g} e-/ADU from the {method} "
               f"({100 * (g_meas / hdr - 1):+.0f} %): {why}; the measured gain adopted")
    out["source_note"] = f"{method}: var = S/g + RN^2 (the header's {hgain.card} = {hdr:.4g} disagrees)"
    return out


def _cfa_response(img: np.ndarray, ok: np.ndarray) -> list[float]:
    """Relative response of the four cells (row parity, column parity) from their median sky levels."""
    lv = []
    for r in (0, 1):
        for c in (0, 1):
            v = img[r::2, c::2][ok[r::2, c::2]]
            lv.append(max(float(np.median(v)), 1e-6) if v.size else 1.0)
    m = float(np.mean(lv))
    return [float(np.clip(x / m, 0.05, 4.0)) for x in lv]


def _first_angle(header, cards, hours_if_str: bool = False) -> float | None:
    from .header import number, sexagesimal

    for c in cards:
        if c in header:
            v = header[c]
            f = number(v)
            if f is not None:
                return f
            s = sexagesimal(v)
            if s is not None:
                return s * 15.0 if hours_if_str else s
    return None


def _trimmed_geometry(header, raw_shape, rows, cols, binning):
    """The WCS of the trimmed frame: CRPIX moved by the trimmed columns and rows."""
    from .wcs import clean_header

    hh = clean_header(header)
    if "CRPIX1" in hh:
        hh["CRPIX1"] = float(hh["CRPIX1"]) - cols.start
        hh["CRPIX2"] = float(hh["CRPIX2"]) - rows.start
    return scene_geometry(hh, (rows.stop - rows.start, cols.stop - cols.start), binning=binning)


class _Band:
    """The scene's band (QE x design) for star and sky rates: a star of G = 0 at Teff 5000 K, and the sky."""

    def __init__(self, scene: dict, design_name: str, files: dict):
        from detector.presets import PRESETS
        from optics.design import Design, load_design

        if design_name in files:
            self.design = Design.model_validate(files[design_name][1])
        else:
            self.design = load_design(design_name)
        p = PRESETS[scene["detector"]["preset"]]
        self.wl = list(scene["detector"].get("qe_wavelength_nm", p["qe_wavelength_nm"]))
        self.qe = list(scene["detector"].get("qe", p["qe"]))
        self.scene = scene

    def star_e_s(self, mag_g):
        from scenes.catalog import star_electron_rate

        m = np.atleast_1d(np.asarray(mag_g, float))
        return np.asarray(star_electron_rate(m, np.full(m.size, 5000.0), self.wl, self.qe,
                                             self.design.collecting_area_m2,
                                             optics_throughput=self.design.mirror_throughput), float)

    def sky_mag(self, sky_e_s: float) -> float:
        from scenes.photometry import sky_electron_rate_per_pixel

        b = self.scene["detector"].get("binning", 1)
        zero = sky_electron_rate_per_pixel(0.0, self.scene["telescope"]["pixel_scale_arcsec"], self.design.collecting_area_m2,
                                           self.design.mirror_throughput, self.wl, self.qe) * b * b
        return float(np.clip(-2.5 * math.log10(max(sky_e_s, 1e-9) / zero), 5.0, 35.0))


def _catalogue(catalog, scene, band, phot, cols, fwhm_px, mask, shape, gain, t, geom, header, files, scene_name,
               sources, notes) -> dict:
    """The scene's catalogue: the frame's own stars (a CSV beside the scene), a user table, gaia or builtin (with
    the zero point from the stars matched in the frame)."""
    h, w = shape
    if phot is None or phot["x"].size == 0:
        scene["sky"]["stars"] = False
        notes.append("no star found: stars = false")
        return {"n": 0}
    snr = phot["flux_adu"] / np.maximum(phot["flux_err_adu"], 1e-9)
    xi = np.clip(np.round(phot["x"]).astype(int), 0, w - 1)
    yi = np.clip(np.round(phot["y"]).astype(int), 0, h - 1)
    ok = (snr > 5) & ~mask[yi, xi] & (phot["flux_adu"] > 0)
    if not ok.any():
        scene["sky"]["stars"] = False
        notes.append("no star above 5 sigma outside the mask: stars = false")
        return {"n": 0}
    rate0 = float(band.star_e_s(0.0)[0])
    if catalog == "frame":
        x, y, f = phot["x"][ok], phot["y"][ok], phot["flux_adu"][ok]
        g = -2.5 * np.log10(f * gain / (rate0 * t))
        ra, dec = _scene_world(scene, band, files, x, y)
        lines = ["ra_deg,dec_deg,mag_g,teff_k,source_id,x_px,y_px,flux_adu"]
        lines += [f"{a:.9f},{d:.9f},{m:.5f},5000,{i + 1},{xx:.3f},{yy:.3f},{ff:.2f}"
                  for i, (a, d, m, xx, yy, ff) in enumerate(zip(ra, dec, g, x, y, f))]
        name = f"{scene_name}_stars.csv"
        files[name] = ("csv", "\n".join(lines) + "\n")
        scene["sky"].update(catalog=name, star_mag_limit=round(float(min(25.0, g.max() + 0.5)), 3))
        zp = 2.5 * math.log10(rate0 * t / gain)
        sources["sky.catalog"] = (f"measured: {x.size} stars found and PSF-fitted in the frame (photutils); "
                                  f"G = {zp:.4f} - 2.5 log10(flux_adu) (the scene's band at 5000 K)")
        return {"kind": "frame", "n": int(x.size), "g_min": float(g.min()), "g_max": float(g.max()),
                "zero_point_mag_at_1_adu": zp, "file": name}
    # a catalogue with real magnitudes: match and calibrate the band's scale
    from scenes.catalog import stars_in_field

    if geom is None:
        raise DetectorError("the frame has no WCS", key="--catalog", expected="--catalog frame")
    radius = 0.5 * math.hypot(h, w) * scene["telescope"]["pixel_scale_arcsec"] * scene["detector"].get("binning", 1) / 3600 * 1.05
    cat_arg = catalog
    st = stars_in_field(geom["ra_deg"], geom["dec_deg"], radius_deg=radius, mag_limit=21.0 if catalog == "gaia" else 25.0,
                        epoch=scene["pointing"]["epoch"], catalog=cat_arg, seed=0, fill_faint=False) \
        if catalog not in ("builtin",) else stars_in_field(geom["ra_deg"], geom["dec_deg"], radius_deg=radius,
                                                             mag_limit=10.0, epoch=scene["pointing"]["epoch"], catalog="builtin", seed=0)
    real = st.source != "synthetic"
    x, y = _scene_pixels(scene, band, files, st.ra_deg[real], st.dec_deg[real])
    mags = st.mag_g[real]
    px, py, pf = phot["x"][ok], phot["y"][ok], phot["flux_adu"][ok]
    ratios = []
    for xx, yy, m in zip(x, y, mags):
        if not (0 <= xx < w and 0 <= yy < h):
            continue
        d = np.hypot(px - xx, py - yy)
        j = int(np.argmin(d)) if d.size else -1
        if j >= 0 and d[j] < max(2.0, fwhm_px):
            ratios.append(pf[j] * gain / t / float(band.star_e_s(m)[0]))
    info = {"kind": catalog, "n_catalogue": int(real.sum()), "n_matched": len(ratios)}
    if len(ratios) >= 3:
        scale = float(np.median(ratios))
        info.update(band_scale=scale, band_scale_spread=float(np.std(np.log(ratios))))
    else:
        notes.append(f"{len(ratios)} catalogue stars matched in the frame: the band's zero point is the preset's (assumed)")
    scene["sky"].update(catalog=catalog if catalog in ("builtin", "gaia") else str(Path(catalog).resolve()),
                        star_mag_limit=round(float(min(25.0, -2.5 * math.log10(max(np.percentile(pf, 2), 1e-3) * gain / (rate0 * t)) + 0.5)), 2))
    sources["sky.catalog"] = f"given (--catalog {catalog})"
    return info


def _scene_wcs(scene, band, files):
    """The WCS the scene gives its frame (the scene's own convention), without writing the scene."""
    from scenes.projection import Sip, sip_from_table, tan_wcs

    b = scene["detector"].get("binning", 1)
    tel = scene["telescope"]
    sip = None
    if tel.get("distortion") == "sip":
        t = sip_from_table(tel["sip"])
        sip = Sip(t["order"], t["a"], t["b"], t["reverse_order"]).binned(b)
    p = scene["pointing"]
    h, w = scene["detector"]["sensor_height_px"] // b, scene["detector"]["sensor_width_px"] // b
    return tan_wcs(p["ra_deg"], p["dec_deg"], p["roll_deg"], tel["pixel_scale_arcsec"] * b, (h, w), sip=sip,
                   parity=tel.get("parity", -1))


def _scene_world(scene, band, files, x, y):
    w = _scene_wcs(scene, band, files)
    return w.all_pix2world(x, y, 0)


def _scene_pixels(scene, band, files, ra, dec):
    import warnings

    w = _scene_wcs(scene, band, files)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return w.all_world2pix(ra, dec, 0, quiet=True)
