"""The model of a measured frame: the scene's mean frame and per-pixel variance, and the measurement read
and checked against it.

The model is the detector chain's moments (:meth:`detector.Detector.moments`): the expected ADU of every
pixel and its variance from the chain's own noise model (Poisson, read, kTC and row noise, quantisation),
with the hardware patterns a real camera does not share (PRNU, DSNU, defect positions) as variance or as
outlier statistics. One noisy realisation of the model gives the expected outlier counts (spikes, outlier
columns) that the measurement's are compared with.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from detector.errors import DetectorError
from detector.signatures import Residuals, SpikeStats, spike_stats
from detector.significance import EXPLAINS_MOST
from detector.stats import median3x3
from scenes.app.render import Setup, prepare
from scenes.image.signal import Samples, SourceSignal, Trails
from scenes.measured import measured_wcs, read_measured
from scenes.projection import axis_crpix
from scenes.scene import Scene

#: seed of the model realisation used for outlier statistics (fixed: the comparison is reproducible)
REALISATION_SEED = 20231101
#: a measured frame with more non-finite (NaN, inf) pixels than this fraction is refused: a diagnosis of a frame
#: speaks on most of its pixels (EXPLAINS_MOST), else it describes a part, not the frame
MAX_NONFINITE_FRACTION = EXPLAINS_MOST


@dataclass
class ModelFrame:
    """The scene's prediction of a frame, in output pixels."""

    setup: Setup
    mean_adu: np.ndarray
    var_adu2: np.ndarray
    flag: np.ndarray  #: near saturation: compared statistically
    photo_adu: np.ndarray
    dark_e: np.ndarray
    #: the photo-signal before the full-well clip [ADU]: what image-plane effects (blur, shift) transform
    photo_field_adu: np.ndarray | None = None
    #: the mean frame of the background alone [ADU]: sky (or flat screen) and straylight through the whole
    #: chain, dark signal and bias; the sources' photometry subtracts it from data and model
    background_adu: np.ndarray | None = None
    realisation: np.ndarray | None = None  #: one noisy frame of the model [ADU], for the outlier statistics
    spikes: SpikeStats | None = None
    extra: dict = field(default_factory=dict)
    #: variance [ADU^2] the pixels of one output row share (their covariance: per-row offsets of row noise)
    row_var_adu2: float = 0.0

    @property
    def sensor(self):
        return self.setup.detector.sensor

    def pixel_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Sensor coordinates (ys, xs) of the output pixel centres."""
        s = self.sensor
        b = s.binning
        h, w = s.output_shape
        return s.roi_y0 + b * np.arange(h) + (b - 1) / 2.0, s.roi_x0 + b * np.arange(w) + (b - 1) / 2.0


def build_model(scene: Scene, workers: int | None = None, realisation: bool = True) -> ModelFrame:
    """Render the scene's mean frame, variance and photo/dark parts (and a realisation for the outliers)."""
    setup = prepare(scene, workers=workers)
    det, t = setup.detector, setup.exptime_s
    s = det.sensor
    mean, var, flag = det.moments(setup.signal_e, t)
    mean0, _, _ = det.moments(0.0, t)
    adu_sum = (s.binning ** 2 if s.binning_mode == "sum" else 1) if s.kind != "ccd" else 1
    photo = mean - mean0
    dark_e = np.maximum(mean0 - np.float32(s.bias_adu * adu_sum), 0) * np.float32(s.gain_e_per_adu)
    unclipped = det.expose(setup.signal_e, t, 0, noiseless=True) - det.expose(0.0, t, 0, noiseless=True)
    bg = background_signal(setup.signal_e)
    background = mean if bg is setup.signal_e else det.moments(bg, t)[0]
    model = ModelFrame(setup, mean, var, flag, photo, dark_e, unclipped / np.float32(s.gain_e_per_adu), background)
    model.row_var_adu2 = row_offset_var_adu2(det)
    if realisation:  # its outliers are counted with the data's (:func:`residuals`)
        model.realisation = det.expose(setup.signal_e, t, REALISATION_SEED).astype(np.float32)
    return model


def data_and_realisation_spikes(data: np.ndarray, usable: np.ndarray, real: np.ndarray, flag: np.ndarray,
                                mean: np.ndarray, var: np.ndarray, sensor, threads: int = 1
                                ) -> tuple[SpikeStats, np.ndarray, SpikeStats]:
    """The local outliers of the measured frame (:func:`detector.signatures.spike_stats`: its statistics and its
    statistical-only mask) and of the model's own realisation ``real`` (what the scene's own hot pixels, cosmic
    rays and noise give, against which the data's are counted; its flagged and saturated pixels left out). With
    ``threads`` > 1 the realisation's are counted in a thread while the data's are (the same statistics)."""
    gain = sensor.gain_e_per_adu
    real_usable = ~flag & (real < saturation_adu(sensor))
    with ThreadPoolExecutor(max_workers=1) as pool:
        later = pool.submit(spike_stats, real, mean, var, real_usable, gain) if threads > 1 else None
        spikes, statistical = spike_stats(data, mean, var, usable, gain)
        model_spikes = (later.result() if later is not None else spike_stats(real, mean, var, real_usable, gain))[0]
    return spikes, statistical, model_spikes


def row_offset_var_adu2(det) -> float:
    """Covariance [ADU^2] of two output pixels of one output row: the variance of the per-row offsets of
    ``row_noise`` (``sigma_e`` per read-out row). A CCD reads a binned row once; an output row of a CMOS sums
    b sensor rows over b columns each (b^3 offsets' variance); average binning divides by b^4."""
    eff = next((e for e in det.effects if e.name == "row_noise"), None)
    if eff is None:
        return 0.0
    s = det.sensor
    b = s.binning
    rows = (1 if s.kind == "ccd" else b ** 3) / (b ** 4 if s.binning_mode == "average" else 1)
    return float(rows * (eff.params.sigma_e / s.gain_e_per_adu) ** 2)


def background_signal(signal):
    """The expected photo-electrons without the sources: the uniform background (sky, flat screen) and the
    straylight of a :class:`scenes.image.signal.SourceSignal`; any other signal is all background."""
    if isinstance(signal, SourceSignal):
        return replace(signal, samples=Samples.empty(), trails=Trails.empty())
    return signal


def read_measurement(path: str | Path, model: ModelFrame) -> tuple[np.ndarray, dict]:
    """The measured frame as float32 ADU, checked against the model's size, binning and WCS.

    Returns the data and a dict of warnings/notes. Size or binning mismatches are errors naming the file.

    Non-finite pixels (NaN, +-inf: a camera's or a pipeline's mark for bad or missing data) are counted
    (``notes["nonfinite_pixels"]``, a warning line), set to the model's mean (a zero residual, so that no
    row, column or region statistic sees them) and masked: ``model.extra["nonfinite"]`` is the mask, which
    :func:`residuals` removes from the fit and every statistic. A frame with more than
    :data:`MAX_NONFINITE_FRACTION` of them is refused (one line naming the file).
    """
    data, header, read_notes = read_measured(path, model.setup.scene, dtype=np.float32)
    s = model.sensor
    notes: dict = {"warnings": [], "masked_pixels": read_notes["masked_pixels"]}
    if data.shape != s.output_shape:
        raise DetectorError(f"measured frame is {data.shape[1]}x{data.shape[0]} pixels", key="detector",
                            file=str(path), expected=f"{s.output_shape[1]}x{s.output_shape[0]} as the scene's "
                            f"[detector] (preset, width/height, binning {s.binning}) produces")
    for card in ("XBINNING", "YBINNING"):
        if card in header and int(header[card]) != s.binning:
            raise DetectorError(f"measured frame has {card} = {header[card]}", key="detector.binning",
                                file=str(path), expected=f"{s.binning} as the scene")
    bad = ~np.isfinite(data)
    n_bad = int(bad.sum())
    if n_bad - read_notes["masked_pixels"] > MAX_NONFINITE_FRACTION * data.size:
        raise DetectorError(f"{100 * n_bad / data.size:.0f} % of the measured pixels are NaN or infinite",
                            key="MEASURED", file=str(path), expected="a frame with at most "
                            f"{100 * MAX_NONFINITE_FRACTION:.0f} % non-finite pixels")
    notes["nonfinite_pixels"] = n_bad
    model.extra["nonfinite"] = bad if n_bad else None
    model.extra["nonfinite_pixels"] = n_bad
    if read_notes["masked_pixels"]:
        notes["warnings"].append(f"{read_notes['masked_pixels']} measured pixels masked by [mask] "
                                 f"({100 * read_notes['masked_pixels'] / data.size:.3g} %)")
    if n_bad > read_notes["masked_pixels"]:
        notes["warnings"].append(f"{n_bad} measured pixels ({100 * n_bad / data.size:.3g} %) are NaN or infinite: "
                                 "masked (left out of the fit and every statistic)")
        data = np.where(bad, model.mean_adu, data).astype(np.float32)
    sat = np.mean(data >= saturation_adu(s))
    if sat > 0.5:
        raise DetectorError(f"{100 * sat:.0f} % of the measured pixels are saturated (at or above "
                            f"{saturation_adu(s):.0f} ADU)", file=str(path), expected="a frame that is not mostly saturated")
    if np.nanmax(data) == np.nanmin(data):
        raise DetectorError(f"measured frame is constant ({float(np.nanmax(data))} ADU)", file=str(path),
                            expected="an image with signal and noise")
    notes["saturated_fraction"] = float(sat)
    notes["wcs_offset_px"] = _wcs_offset(header, model)
    if notes["wcs_offset_px"] is not None and notes["wcs_offset_px"] > 2:
        notes["warnings"].append(f"the measured WCS puts the scene's pointing {notes['wcs_offset_px']:.1f} px from "
                                 "the scene's optical axis: sources will not line up")
    exptime = header.get("EXPTIME")
    if exptime is not None and abs(float(exptime) - model.setup.exptime_s) > 1e-3 * max(1.0, float(exptime)):
        notes["warnings"].append(f"EXPTIME {exptime} s in the measured file, {model.setup.exptime_s} s in the scene")
    return data.astype(np.float32, copy=False), notes


def saturation_adu(s) -> float:
    """Measured level [ADU per output pixel] at or above which a pixel is saturated, less 5 read-noise sigma
    of the output pixel.

    As the chain makes it (:meth:`detector.Detector.process_tile`): a CCD sums the charge of ``b x b`` pixels
    (each clipped at the full well) before its one read, so the binned pixel is clipped at the ADC maximum
    (or ``b^2`` full wells); a CMOS reads every pixel (clipped at the ADC maximum or one full well) and sums
    the ``b^2`` digital values, up to ``b^2`` times one read, clipped again at the ADC maximum (the output
    word). Average binning divides the sum by ``b^2``.
    """
    n = s.binning ** 2
    top = float(s.adc_max_adu)
    ccd = s.kind == "ccd"
    read = min(top, s.bias_adu + (n if ccd else 1) * s.full_well_e / s.gain_e_per_adu)  # one read [ADU]
    average = s.binning_mode == "average"
    if average:
        level = read / n if ccd else read
    else:
        level = read if ccd else min(top, n * read)
    sigma = s.read_noise_e / s.gain_e_per_adu * (1 if ccd else s.binning)
    return float(level - 5 * sigma / (n if average else 1))


def _wcs_offset(header, model: ModelFrame) -> float | None:
    """Distance [output px] between the measured WCS's image of the scene pointing and the scene's optical
    axis, where the pointing lies (the full sensor's centre, which a read-out window moves:
    :func:`scenes.projection.axis_crpix`)."""
    if "CTYPE1" not in header or "CRVAL1" not in header:
        return None
    import warnings

    p = model.setup.scene.pointing
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            x, y = measured_wcs(header).all_world2pix([[p.ra_deg, p.dec_deg]], 0)[0]
    except Exception:  # noqa: BLE001  (a broken WCS is reported as absent, not fatal)
        return None
    ax, ay = axis_crpix(model.sensor)  # 1-based
    return float(np.hypot(x - (ax - 1), y - (ay - 1)))


def source_peaks(model: ModelFrame, nsigma: float = 3.0) -> np.ndarray:
    """:func:`source_peak_mask` of the model's photo-signal."""
    return source_peak_mask(model.photo_adu, model.var_adu2, nsigma)


def source_peak_mask(photo_adu: np.ndarray, var_adu2: np.ndarray, nsigma: float = 3.0) -> np.ndarray:
    """Pixels within two pixels of a place where the photo-signal [ADU] rises ``nsigma`` (of the noise,
    ``var_adu2``) above its 3x3 median (sources: stars, streaks)."""
    from scipy import ndimage

    peak = (photo_adu - median3x3(photo_adu)) > nsigma * np.sqrt(var_adu2)
    return ndimage.binary_dilation(peak, structure=np.ones((3, 3), bool), iterations=2)


def residuals(data: np.ndarray, model: ModelFrame) -> Residuals:
    """Everything the comparison and the signatures need: masks, spike statistics, model pieces."""
    s = model.sensor
    usable = ~model.flag & (data < saturation_adu(s)) & np.isfinite(data)
    if model.extra.get("nonfinite") is not None:  # NaN / inf in the measured file (read_measurement)
        usable &= ~model.extra["nonfinite"]
    if model.spikes is None and model.realisation is not None:
        spikes, statistical, model.spikes = data_and_realisation_spikes(
            data, usable, model.realisation, model.flag, model.mean_adu, model.var_adu2, s,
            model.setup.detector.workers or 1)
    else:
        spikes, statistical = spike_stats(data, model.mean_adu, model.var_adu2, usable, s.gain_e_per_adu)
    # where the model itself peaks (star cores) a local outlier is a source the model misplaces or mis-sizes,
    # not a defect: keep those pixels in the pixel-by-pixel comparison
    statistical &= ~source_peaks(model)
    ys, xs = model.pixel_centres()
    return Residuals(data, model.mean_adu, model.var_adu2, usable & ~statistical, model.photo_adu, model.dark_e,
                     ys, xs, s, model.setup.exptime_s, spikes, model.spikes or SpikeStats(0, 0, 0, 0, 0),
                     photo_field_adu=model.photo_field_adu, background_adu=model.background_adu,
                     row_var_adu2=model.row_var_adu2, light_source=light_source(model.setup.scene),
                     usable=usable, level_sd=level_sd(s))


def level_sd(sensor, outputs: float = 1.0) -> tuple[float, float]:
    """(bias offset [ADU per pixel of the residuals], relative dark level [1]) a scene may be off by: the
    default policy's tolerances of a refitted bias (per read, times the reads an output pixel holds and the
    ``outputs`` output pixels a pixel of the residuals sums) and of a refitted scale, by which
    :meth:`detector.signatures.Residuals.dark_share` splits a dark frame's one level between them. Used here as
    the one-sigma widths of the two priors (how far a scene's bias and dark current are known), not as decision
    bars: the residuals are built before a diagnosis's policy is read, so a ``--policy`` file does not move the
    split."""
    from .apply import bias_per_output_adu
    from .policy import DEFAULT_POLICY

    p = DEFAULT_POLICY
    return (p.parameter_bias_tolerance_adu * bias_per_output_adu(sensor) * outputs, p.parameter_scale_tolerance)


def light_source(scene) -> str:
    """Where the frame's light comes from: "flat" (a flat-field screen, which blocks the sky), "sky" (the
    sky, its stars and objects), "none" (a dark or bias frame)."""
    if scene.exposure.frame != "light":
        return "none"
    return "flat" if scene.sky.flat_e_per_s is not None else "sky"
