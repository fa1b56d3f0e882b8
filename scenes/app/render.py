"""The main job: a scene in, a FITS frame (and its truth) out.

The expected photo-electrons per pixel are the uniform background (sky, or a flat screen) plus the stars
and debris streaks of :mod:`scenes.image` (PSF-integrated samples, rolling-shutter row windows) plus the
straylight of the Sun and the Moon (:mod:`scenes.straylight`), handed to the detector chain as a tile
callable; vignetting, the pixel response, dark signal and every detector effect are the chain's. The frame's
WCS carries the SIP distortion of ``[telescope] distortion`` (:mod:`scenes.projection`), and the sources
are drawn where it puts them; ``[psf] model = "optics"`` draws them with the design's PSF grid
(:mod:`scenes.image.gridpsf`). The TRUTH extension lists every source (``scenes.image.build.TRUTH_DTYPE``).
Optics products (SIP, PSF grid, straylight maps) come from the optics' on-disk cache: a render traces
nothing that was traced before.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from detector import Detector, build_effects
from detector.config import validate
from detector.effects.optical import VignettingParams, relative_illumination
from detector.fits_io import primary_header, table_hdu, write_streamed
from detector.rng import fresh_seed
from optics.design import OpticsError, load_design
from optics.distortion import cached_sip
from optics.vignetting import cached_map_fits
from scenes.image import TRUTH_DTYPE, build_sources, frame_wcs
from scenes.image.signal import Samples, SourceSignal
from scenes.photometry import sky_electron_rate_per_pixel
from scenes.projection import REVERSE_WARN_PX, Sip, axis_crpix, sip_from_optics, sip_from_table, with_radial
from scenes.scene import Scene, SceneError
from scenes.straylight import straylight_signal

#: SIP order of the optics' distortion fit: the art corrector's distortion has 7th-order terms (order 5
#: leaves 0.03-0.07 px, order 7 below 0.01 px; docs/optics_psf.md)
OPTICS_SIP_ORDER = 7

__all__ = ["TRUTH_DTYPE", "Setup", "header_cards", "prepare", "render", "scene_hdu"]


@dataclass
class Setup:
    """Everything resolved from a scene that a render needs."""

    scene: Scene
    detector: Detector
    exptime_s: float
    signal_e: object  # expected photo-electrons per unbinned pixel: a float, or a tile callable with sources
    pixel_scale_arcsec: float
    sky_e_per_s: float
    warnings: list[str]
    truth: np.ndarray | None = None
    source_cards: dict | None = None
    distortion: Sip | None = None
    straylight: object = None
    per_source: list | None = None  # each TRUTH row's samples alone (scenes.image.build.SourceModel.per_source)
    psf: object = None  # the sources' pixel-integrated PSF
    effect_tables: dict | None = None  # the scene's [effects] tables as resolved for the chain


def resolve_distortion(scene: Scene, sensor, design) -> Sip | None:
    """The frame's SIP distortion from ``[telescope] distortion`` (unbinned sensor pixels about the axis).

    ``"optics"`` asks the optics for the design's SIP fit over the full sensor
    (``optics.distortion.cached_sip``, cached on disk by the design's hash). ``[telescope.sip]
    radial_k_per_px2`` and ``decentering_p1/p2_per_px`` (what ``[effects.distortion]`` becomes,
    :func:`scenes.scene.resolve_effect_keys`) are composed with either (:func:`scenes.projection.with_radial`, fitted over the read-out window).
    """
    tel = scene.telescope
    if tel.distortion == "none":
        return None
    t = sip_from_table(tel.sip or {}, file=scene.source, allow_coefficients=tel.distortion == "sip")
    if tel.distortion == "sip":
        sip = Sip(t["order"], t["a"], t["b"], t["reverse_order"], "scene") if (t["a"] or t["b"]) else None
    else:
        shape = (sensor.sensor_height_px, sensor.sensor_width_px)
        try:
            fit = cached_sip(design, float(sensor.pixel_pitch_um), shape, order=t["order"] or OPTICS_SIP_ORDER)
            sip = sip_from_optics(fit, sensor, reverse_order=t["reverse_order"], parity=scene.telescope.parity)
        except (OpticsError, ImportError, ValueError, KeyError) as exc:
            raise SceneError(f"cannot get the SIP distortion of design '{design.name}': {exc}",
                             key="telescope.distortion", file=scene.source) from None
    if t["radial_k"] or any(t["decentering"]):
        (h, w), (cx, cy) = sensor.shape, axis_crpix(sensor, binned=False)
        margin = RADIAL_FIT_MARGIN_PX
        sip = with_radial(sip, t["radial_k"], (-0.5 - cx + 1 - margin, w - 0.5 - cx + 1 + margin),
                          (-0.5 - cy + 1 - margin, h - 0.5 - cy + 1 + margin), file=scene.source,
                          decentering=t["decentering"])
        if t["reverse_order"] is not None:
            sip = Sip(sip.order, sip.a, sip.b, max(t["reverse_order"], sip.order), sip.source, sip.info)
    return sip


#: the radial term's SIP is fitted over the read-out window plus this margin [sensor px] (sources just off it)
RADIAL_FIT_MARGIN_PX = 64.0


def _straylight(scene: Scene, sensor, design, tables: dict, exptime_s: float):
    """The scene's ray-traced straylight (``scene.parts.straylight``) -> (StraylightSignal, header cards).

    The straylight map is already focal-plane irradiance; the chain's vignetting multiplies all the light
    it is handed, so the map goes in divided by the vignetting's relative illumination, which is passed as
    data: :func:`detector.effects.optical.relative_illumination` of the scene's ``[effects.vignetting]``
    table (``tables``, its ``map_file = "optics"`` resolved).
    """
    vig = tables.get("vignetting")
    ri = (relative_illumination(validate(VignettingParams, vig, prefix="effects.vignetting", file=scene.source),
                                sensor) if vig is not None else None)
    try:
        return straylight_signal(scene.parts.straylight, scene, sensor, design, exptime_s, scene.parts.observer,
                                 ri=ri)
    except (OpticsError, ImportError) as exc:
        raise SceneError(f"cannot ray-trace the straylight of design '{design.name}': {exc}",
                         key="effects.straylight.pst", file=scene.source) from None


def _resolve_optics_maps(effects: dict, design, scene: Scene) -> dict:
    """``[effects.vignetting] map_file = "optics"``: ray-trace the scene's design (cached) for the map."""
    vig = effects.get("vignetting")
    if not vig or vig.get("map_file") != "optics":
        return effects

    try:
        path = cached_map_fits(design)
    except (OpticsError, ImportError) as exc:
        raise SceneError(f"cannot ray-trace the vignetting of design '{design.name}': {exc}",
                         key="effects.vignetting.map_file", file=scene.source) from None
    return {**effects, "vignetting": {**vig, "map_file": str(path)}}


def prepare(scene: Scene, workers: int | None = None, psf=None) -> Setup:
    """Resolve a scene: sensor, effects, plate scale, background, and the sources (stars, objects).

    ``psf`` replaces the scene's ``[psf]`` by any pixel-integrated PSF (the hook of
    :mod:`scenes.image.psf`, e.g. a field-dependent optics PSF).
    """
    parts = scene.parts
    sensor = scene.sensor()
    try:
        design = load_design(scene.telescope.design)
    except OpticsError as exc:
        raise SceneError(str(exc), key="telescope.design", file=scene.source) from None
    traced = parts.straylight is not None
    tables = _resolve_optics_maps(parts.effect_tables, design, scene)
    effects = build_effects(tables, sensor, file=scene.source)
    scale = scene.telescope.pixel_scale_arcsec or design.pixel_scale_arcsec(sensor.pixel_pitch_um)
    exp = scene.exposure
    exptime = 0.0 if exp.frame == "bias" else exp.time_s
    warnings = [w for w in [sensor.summed_bias_saturates()] if w]
    sky_rate = 0.0
    flat_rate = 0.0
    if exp.frame == "light":
        if scene.sky.flat_e_per_s is None and scene.sky.background_mag_arcsec2 is not None:
            sky_rate = sky_electron_rate_per_pixel(scene.sky.background_mag_arcsec2, scale, design.collecting_area_m2,
                                                   design.mirror_throughput, sensor.qe_wavelength_nm, sensor.qe)
        flat_rate = scene.sky.flat_e_per_s or 0.0  # a flat screen blocks the sky
        if scene.sky.flat_e_per_s is not None and (scene.sky.stars or scene.objects):
            warnings.append("sky.flat_e_per_s (a flat screen) blocks the sky: stars and objects are not rendered")
    background = (sky_rate + flat_rate) * exptime
    signal: object = background
    truth, cards = np.zeros(0, dtype=TRUTH_DTYPE), {}
    per_source, src_psf = [], None
    distortion = resolve_distortion(scene, sensor, design)
    stray = None
    if exp.frame == "light" and traced and scene.sky.flat_e_per_s is None:
        stray, stray_cards = _straylight(scene, sensor, design, tables, exptime)
        cards.update(stray_cards)
    if exp.frame == "light" and (scene.sky.stars or scene.objects):
        model = build_sources(scene, sensor, design, scale, exptime, background_e=background, psf=psf,
                              distortion=distortion, extra=stray)
        truth = model.truth
        per_source, src_psf = model.per_source, model.psf
        cards = {**model.cards, **cards}
        warnings += model.warnings
        if model.signal.n_samples or stray is not None:
            signal = model.signal
    elif stray is not None:
        signal = SourceSignal(Samples.empty(), None, background, sensor.roi_y0, sensor.roi_x0, extra=stray)
    return Setup(scene, Detector(sensor, effects, workers=workers), exptime, signal, scale, sky_rate, warnings,
                 truth, cards, distortion, stray, per_source, src_psf, tables)


def header_cards(setup: Setup, seed: int, noiseless: bool) -> fits.Header:
    """The contract's cards (GAIN, BIAS, RDNOISE, EXPTIME, FULLWELL, BITDEPTH, ROWTIME) and the WCS."""
    s = setup.detector.sensor
    sc = setup.scene
    b = s.binning
    h = fits.Header()
    h["BUNIT"] = ("electron", "expected electrons, before any random draw") if noiseless else ("adu", "")
    h["EXPTIME"] = (setup.exptime_s, "[s] exposure time")
    h["GAIN"] = (s.gain_e_per_adu, "[e-/ADU] conversion gain")
    h["BIAS"] = (s.bias_adu, "[ADU] bias level")
    h["RDNOISE"] = (s.read_noise_e, "[e-] read noise")
    h["FULLWELL"] = (s.full_well_e, "[e-] full-well capacity")
    h["BITDEPTH"] = (s.bit_depth, "ADC bits")
    h["ROWTIME"] = (s.row_time_s * b, "[s] row start delay (0: global shutter)")
    h["DARKCUR"] = (s.dark_current_e_per_s, "[e-/s/pixel] mean dark current")
    h["SHUTTER"] = (s.shutter, "rolling (CMOS) or global")
    h["DETECTOR"] = (s.name, "sensor preset")
    h["SENSKIND"] = (s.kind, "ccd or cmos")
    h["XPIXSZ"] = (s.pixel_pitch_um * b, "[um] pixel size incl. binning")
    h["YPIXSZ"] = (s.pixel_pitch_um * b, "[um] pixel size incl. binning")
    h["XBINNING"] = (b, "binning factor")
    h["YBINNING"] = (b, "binning factor")
    h["BINMODE"] = (s.binning_mode, "sum or average")
    h["ROIX0"] = (s.roi_x0, "first sensor column of the window (0-based)")
    h["ROIY0"] = (s.roi_y0, "first sensor row of the window (0-based)")
    h["CCD-TEMP"] = (s.temperature_c, "[C] sensor temperature")
    h["IMAGETYP"] = ({"light": "Light Frame", "dark": "Dark Frame", "bias": "Bias Frame"}[sc.exposure.frame], "")
    h["FRAMETYP"] = (sc.exposure.frame, "light, dark or bias")
    h["DATE-OBS"] = (sc.pointing.epoch, "start of exposure (UTC)")
    h["TELESCOP"] = (sc.telescope.design, "telescope design")
    h["PIXSCALE"] = (setup.pixel_scale_arcsec * b, "[arcsec/pixel] incl. binning")
    h["SKYRATE"] = (setup.sky_e_per_s, "[e-/s/unbinned pixel] sky background")
    h["SEED"] = (seed, "frame seed (noise)")
    h["HWSEED"] = (s.hardware_seed, "hardware seed (fixed pattern)")
    h["NOISELES"] = (bool(noiseless), "expected electrons, no random draw")
    names = [e.name for e in setup.detector.effects] + (["straylight"] if setup.straylight is not None else [])
    h["EFFECTS"] = (",".join(names) or "none", "optional effects on")
    h["CREATOR"] = ("newtsim", "")
    h["NOBJECTS"] = (len(sc.objects) if sc.exposure.frame == "light" else 0, "debris/satellite objects")
    h["NSTARS"] = (0, "stars with their centre on the frame (TRUTH)")
    for k, v in (setup.source_cards or {}).items():
        h[k] = v
    wcs = frame_wcs(sc, s, setup.pixel_scale_arcsec, distortion=setup.distortion)
    h.update(wcs.to_header(relax=True))
    if setup.distortion is not None:
        d = setup.distortion
        h["SIPSRC"] = (d.source, "SIP distortion from the scene or the optics")
        h["SIPRRMS"] = (float(wcs.sip_reverse_rms_px), "[pixel] rms residual of the fitted AP/BP")
        h["SIPRMAX"] = (float(wcs.sip_reverse_max_px), "[pixel] largest residual of the fitted AP/BP")
        if "rms_px" in d.info:
            h["SIPFRMS"] = (float(d.info["rms_px"]), "[sensor pixel] optics forward-fit rms residual")
        if d.info.get("radial_fit_max_px", 0.0) > REVERSE_WARN_PX:
            h.add_history(f"radial distortion fitted to {d.info['radial_fit_max_px']:.3g} px: SIP order too low")
        if wcs.sip_reverse_max_px > REVERSE_WARN_PX:
            h.add_history(f"SIP reverse fit off by up to {wcs.sip_reverse_max_px:.3g} px: raise reverse_order")
    for w in setup.warnings:
        h.add_history(w[:70])
    for n in sc.resolution_notes:  # what a short form of the scene file became (the SCENE extension too)
        h.add_history(f"scene: {n}"[:70])
    return h


def scene_hdu(scene: Scene) -> fits.BinTableHDU:
    """The resolved scene as TOML text in a one-row table (extension ``SCENE``)."""
    text = scene.resolved_text()
    col = fits.Column(name="toml", format=f"{max(len(text), 1)}A", array=np.array([text]))
    return fits.BinTableHDU.from_columns([col], name="SCENE")


def truth_hdu(truth: np.ndarray, setup: Setup) -> fits.BinTableHDU:
    """The ``TRUTH`` extension: one row per source, with the column units and the source counts."""
    hdu = table_hdu("TRUTH", truth)
    units = {"ra_deg": "deg", "dec_deg": "deg", "x": "pixel", "y": "pixel", "x0": "pixel", "y0": "pixel",
             "x1": "pixel", "y1": "pixel", "flux_e": "electron", "mag": "mag"}
    for i, name in enumerate(truth.dtype.names, start=1):
        if name in units:
            hdu.header[f"TUNIT{i}"] = units[name]
    hdu.header["COMMENT"] = "x, y: 0-based pixel centres of the written frame at mid-exposure (of the recorded"
    hdu.header["COMMENT"] = "part); x0,y0 / x1,y1: start / end of the recorded path; flux_e: electrons over the"
    hdu.header["COMMENT"] = "exposure before vignetting; kind: star, synthetic or object"
    for k in ("NOBJECTS", "NSTARS", "NSTARCAT", "NSTARSYN"):
        if setup.source_cards and k in setup.source_cards:
            hdu.header[k] = setup.source_cards[k]
    return hdu


def render(scene: Scene, out: str | Path, *, seed: int | None = None, noiseless: bool = False,
           expected: bool = False, progress: bool = True, workers: int | None = None, psf=None,
           labels: list[str] | None = None, label_paths: dict | None = None, label_meta: dict | None = None) -> dict:
    """Render ``scene`` to the FITS file ``out``; return a summary (path, seed, shape, warnings).

    Parameters
    ----------
    seed : frame seed; default the scene's ``exposure.seed`` or a fresh one (written to ``SEED``)
    noiseless : write the expected electrons (float32) instead of ADU
    expected : also write the expected electrons as extension ``EXPECTED``
    psf : a pixel-integrated PSF replacing the scene's ``[psf]`` (hook of :mod:`scenes.image.psf`)
    labels : label formats (``scenes.app.bench.formats.FORMATS``): "fits" adds the ``LABELS`` extension,
        the others are written to ``label_paths[format]`` (docs/detection_bench.md); ``label_meta``: extra
        image keys of the COCO/SatNet files (seed, split, scene)
    """
    setup = prepare(scene, workers, psf=psf)
    det = setup.detector
    s = det.sensor
    seed = seed if seed is not None else (scene.exposure.seed if scene.exposure.seed is not None else fresh_seed())
    dtype = np.float32 if noiseless else (np.uint16 if s.bit_depth <= 16 else np.uint32)
    header = primary_header(s.output_shape, dtype, header_cards(setup, seed, noiseless))
    truth = setup.truth if setup.truth is not None else np.zeros(0, dtype=TRUTH_DTYPE)
    ext = [scene_hdu(scene), truth_hdu(truth, setup)]
    state = det.frame_state(setup.exptime_s, seed)  # per-frame draws (cosmic rays), shared by truth and image
    ext += [table_hdu(name, t) for name, t in det.truth(setup.exptime_s, seed, state).items()]
    frame_lab = None
    if labels:
        from scenes.app.bench.formats import labels_hdu, labels_table_hdu
        from scenes.app.bench.frame import frame_labels, write_label_files

        frame_lab = frame_labels(setup)
        if "fits" in labels:
            ext.append(labels_hdu(frame_lab.sources, frame_lab.labels, frame_lab.shape, frame_lab.mask_fraction_sigma))
            ext.append(labels_table_hdu(frame_lab.labels))
        write_label_files(frame_lab, {f: p for f, p in (label_paths or {}).items() if f in labels}, Path(out).name,
                          dict(label_meta or {}, seed=seed))
    if expected and not noiseless:
        img = det.expose(setup.signal_e, setup.exptime_s, seed, noiseless=True, state=state)
        ext.append(fits.ImageHDU(img, name="EXPECTED"))
    bands = det.iter_frame(setup.signal_e, setup.exptime_s, seed, noiseless=noiseless, state=state)
    if progress and sys.stderr.isatty():
        bands = _with_progress(bands, len(det.tiles(setup.exptime_s, seed, state)), str(out))
    path = write_streamed(out, header, bands, s.output_shape, dtype, ext)
    cards = setup.source_cards or {}
    return {"path": str(path), "seed": seed, "shape": list(s.output_shape), "exptime_s": setup.exptime_s,
            "sky_e_per_s": setup.sky_e_per_s, "warnings": setup.warnings,
            "sources": {"stars": cards.get("NSTARS", (0,))[0], "objects": cards.get("NOBJECTS", (0,))[0],
                        # of the stars on the frame: catalogue (Gaia/Hipparcos) stars and faint-star model stars
                        "catalogue_stars": int(np.sum(truth["kind"] == b"star")),
                        "model_stars": int(np.sum(truth["kind"] == b"synthetic"))},
            **({"labels": len(frame_lab.labels)} if frame_lab is not None else {})}


def _with_progress(bands, total: int, label: str):
    with Progress(TextColumn("[bold]render[/bold] {task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total} bands"),
                  TimeElapsedColumn(), transient=True) as prog:
        task = prog.add_task(label, total=total)
        for item in bands:
            prog.advance(task)
            yield item
