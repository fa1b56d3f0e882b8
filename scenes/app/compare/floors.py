"""Physical effect-size floors: sizes at which a fitted effect is not a finding, whatever its delta BIC.

A likelihood ratio can be enormous for an effect no camera has: a non-linearity of 0.02 % at full well
(what a textbook linear camera's rounding makes of a flat series), a third of a sensor's columns "hot" by
0.0003 e-/s, cosmic rays at a hundred times the physical rate. Each check returns one line when the fitted
size is beyond what physics allows (gate ``floor``), from the policy's fields
(:class:`~.policy.DiagnosisPolicy`: ``min_nonlinearity_at_full_well``, ``max_defect_fraction``,
``max_cosmic_rate_factor``). An effect without a rule here has no floor.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from detector.cosmics import ENVIRONMENTS
from detector.significance import DETECTION_SIGMA

from .policy import DEFAULT_POLICY, DiagnosisPolicy


def _num(params: dict, key: str, default: float = 0.0) -> float:
    v = params.get(key, default)
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else default


def response_ratio(params: dict, x: np.ndarray | float) -> np.ndarray:
    """S' / S of the ``nonlinearity`` effect's law at signals ``x`` [fraction of the full well]: the knee
    ``1 - knee_deficit max(x - knee, 0) / x``, then the polynomial ``1 - beta x - beta2 x^2`` of that signal,
    then the power law ``(S' / S_ref)^(gamma - 1)`` (S_ref ``gamma_reference`` of the well, half by default), as
    :class:`detector.effects.pixel_response.Nonlinearity` applies them."""
    x = np.maximum(np.asarray(x, np.float64), 1e-12)
    rk = 1.0 - _num(params, "knee_deficit") * np.maximum(x - _num(params, "knee", 1.0), 0.0) / x
    xk = x * rk
    r = rk * (1.0 - _num(params, "beta") * xk - _num(params, "beta2") * xk * xk)
    ref = _num(params, "gamma_reference", 0.5) or 0.5
    return r * np.maximum(x * r / ref, 1e-12) ** (_num(params, "gamma", 1.0) - 1.0)


def nonlinearity_floor(params: dict, sensor, policy: DiagnosisPolicy, exptime_s: float | None = None) -> str:
    """The response's relative deficit at full well: ``beta + beta2`` (the polynomial's terms) plus the power
    law's ``|1 - (1 / S_ref)^(gamma-1)|`` (the law equals the linear response at ``gamma_reference`` of the well)
    plus the knee's ``knee_deficit (1 - knee)``."""
    ref = _num(params, "gamma_reference", 0.5) or 0.5
    deficit = abs(_num(params, "beta") + _num(params, "beta2")) + abs(
        1.0 - (1.0 / ref) ** (_num(params, "gamma", 1.0) - 1.0)) + abs(
        _num(params, "knee_deficit") * (1.0 - _num(params, "knee", 1.0)))
    if deficit < policy.min_nonlinearity_at_full_well:
        return (f"a non-linearity of {100 * deficit:.3g} % at full well is below the "
                f"{100 * policy.min_nonlinearity_at_full_well:g} % any photon-transfer curve resolves")
    return ""


def reset_noise_floor(params: dict, sensor, policy: DiagnosisPolicy, exptime_s: float | None = None) -> str:
    """The extra noise per read, sqrt(k T C) / q (thesis eq. 33), against the camera's read noise."""
    from detector.effects.readout import ktc_noise_e

    c_ff = _num(params, "capacitance_ff")
    if c_ff <= 0:
        return ""
    sigma = ktc_noise_e(sensor.temperature_c + 273.15, c_ff * 1e-15)
    floor = policy.min_extra_noise_fraction * float(sensor.read_noise_e)
    if sigma < floor:
        return (f"an extra noise of {sigma:.3g} e- per read is below {100 * policy.min_extra_noise_fraction:g} % of "
                f"the {sensor.read_noise_e:.3g} e- read noise: no characterisation of a camera tells it apart")
    return ""


def _defects(count: float, total: float, what: str, policy: DiagnosisPolicy, seen: float | None = None) -> str:
    """Refuse ``count`` defects of ``total`` on the sensor beyond the policy's fraction. ``count`` is extrapolated
    from the ``seen`` units (pixels, columns) of the window when it is smaller than the sensor: the defects it
    holds are a count, judged on the lower end of its Poisson interval (as the cosmic-ray floor judges its
    tracks), since a window whose 256 columns hold 17 defects (6.6 %) is what a sensor of 5 % defective
    columns shows about one time in seven (binomial), not a rate beyond every camera."""
    if total <= 0:
        return ""
    lowest = count
    if seen is not None and 0 < seen < total and count > 0:
        from detector.effects.cosmic_rays import poisson_interval

        in_window = count * seen / total
        lowest = poisson_interval(round(in_window))[0] * total / seen
    if lowest > policy.max_defect_fraction * total:
        return (f"{count:.0f} {what} are {100 * count / total:.3g} % of the sensor's (at least "
                f"{100 * lowest / total:.3g} % from the window's count); no camera has more than "
                f"{100 * policy.max_defect_fraction:g} %: a pattern of many small deviations, not defects")
    return ""


def _window_px(sensor) -> float | None:
    w, h = getattr(sensor, "roi_shape", (0, 0))
    return float(w * h) if w and h else None


def _window_columns(sensor) -> float | None:
    w = getattr(sensor, "roi_shape", (0, 0))[0]
    return float(w) if w else None


def hot_pixels_floor(params: dict, sensor, policy: DiagnosisPolicy, exptime_s: float | None = None) -> str:
    return _defects(_num(params, "count"), sensor.sensor_width_px * sensor.sensor_height_px, "hot pixels", policy,
                    _window_px(sensor))


def dead_pixels_floor(params: dict, sensor, policy: DiagnosisPolicy, exptime_s: float | None = None) -> str:
    """The dead pixels on the sensor: its defects times the pixels of a cluster (the count is of clusters: the
    sensor's and the window's pixels are counted in clusters' areas)."""
    area = max(_num(params, "cluster_px", 1.0), 1.0) ** 2
    seen = _window_px(sensor)
    return _defects(_num(params, "count"), sensor.sensor_width_px * sensor.sensor_height_px / area,
                    "dead pixels (or clusters)", policy, seen / area if seen else None)


def column_defects_floor(params: dict, sensor, policy: DiagnosisPolicy, exptime_s: float | None = None) -> str:
    """Too many columns for defects, or hot columns whose excess dark current adds less than one electron per
    pixel over the exposure (a column 'above its neighbours' by no measurable charge is not a charge trap or
    a leaky gate: it is a pattern of the light or of the statistics)."""
    n = _num(params, "hot_columns") + _num(params, "dead_columns")
    why = _defects(n, sensor.sensor_width_px, "defective columns", policy, _window_columns(sensor))
    if why:
        return why
    hot, rate = _num(params, "hot_columns"), _num(params, "hot_rate_e_per_s")
    if exptime_s and hot > 0 and _num(params, "dead_columns") == 0 and rate * exptime_s < 1.0:
        return (f"{hot:.0f} hot columns whose excess dark current ({rate:.3g} e-/s) adds {rate * exptime_s:.3g} e- "
                "per pixel over the exposure: less than one electron is not a column defect")
    return ""


def cosmic_rays_floor(params: dict, sensor, policy: DiagnosisPolicy, exptime_s: float | None = None) -> str:
    """The fitted particle flux against the flux of the environment the fit names (ground by default). With the
    exposure, the flux is a count of tracks over the window's area and time: refused only when even the lower
    end of that count's Poisson interval (:func:`detector.effects.cosmic_rays.poisson_interval`) is beyond the
    policy's factor, since one track on a small window "measures" a flux hundreds of times the physical one
    while being what the physical flux makes a few times in a thousand frames."""
    from detector.effects.cosmic_rays import poisson_interval, window_area_cm2

    flux = _num(params, "flux_per_cm2_s", -1.0)
    env = ENVIRONMENTS.get(str(params.get("environment", "ground")), ENVIRONMENTS["ground"])
    lowest = flux
    if exptime_s and exptime_s > 0 and flux > 0:
        exposure = window_area_cm2(sensor) * exptime_s  # [cm^2 s]
        lowest = poisson_interval(round(flux * exposure))[0] / exposure
    if lowest > policy.max_cosmic_rate_factor * env.flux_per_cm2_s:
        return (f"{flux:.3g} particles /cm^2/s (at least {lowest:.3g} from the count) is "
                f"{lowest / env.flux_per_cm2_s:.3g}x the physical flux of the environment ({env.flux_per_cm2_s:.3g}); "
                f"more than {policy.max_cosmic_rate_factor:g}x is not cosmic rays")
    return ""


#: effect name -> its floor check ``(params, sensor, policy, exptime_s [s] or None) -> reason or ""``
FLOORS: dict[str, Callable[[dict, object, DiagnosisPolicy, float | None], str]] = {
    "nonlinearity": nonlinearity_floor,
    "reset_noise": reset_noise_floor,
    "hot_pixels": hot_pixels_floor,
    "dead_pixels": dead_pixels_floor,
    "column_defects": column_defects_floor,
    "cosmic_rays": cosmic_rays_floor,
}


def signal_range(res) -> tuple[float, float] | None:
    """(median, top) of a frame's signal per sensor pixel [e-] over its fitted pixels: the light and the dark
    charge of an output pixel over the pixels summed into it (None: no fitted pixel). The top is the model's
    brightest fitted pixel: the model's signal is noiseless, so no outlier sets it, and on a star frame the few
    cores that reach high in the well (ten pixels of 65 000 at half the well on an IMX411 window, above its
    99.9th percentile) are where a compressive response acts and is measured; how well the frame
    measures the law is the fit's significance, not this range's."""
    ok = res.fit
    if not np.any(ok):
        return None
    charge = (np.broadcast_to(res.photo_adu, ok.shape)[ok] * res.gain
              + np.broadcast_to(res.dark_e, ok.shape)[ok]) / res.pixel_sum
    return max(float(np.median(charge)), 0.0), float(charge.max())


def signal_range_floor(effect: str, res, policy: DiagnosisPolicy = DEFAULT_POLICY, params: dict | None = None,
                       signal: tuple[float, float] | None = None) -> str:
    """"" or why the frame's signal does not measure the fitted response law (gate ``floor``): a non-linearity is
    judged by what it changes within the frame's own signal range (:func:`signal_range`: from its median to its
    brightest fitted pixel; ``signal`` overrides it, e.g. a series' range across its frames): the law's response
    there, ``S'/S`` at the top over ``S'/S`` at the median (:func:`response_ratio`), must differ by the policy's
    ``min_nonlinearity_in_range``, however high the signal reaches: a law's size at full well, on a frame of a few
    per cent of the well, is an extrapolation the pixels cannot check; its change across the frame's signal is what
    they measure (a gamma law compresses every decade of signal alike; a quadratic deficit little at low signal).
    On a frame whose median is low and whose top reaches high in the well (stars on a faint sky) that change is
    close to the law's own deficit at the top (the floor at full well, ``min_nonlinearity_at_full_well``, asks the
    same size of it); a frame of a narrow range, however high (a flat at 40-44 % of the well: a 2 % deficit at full
    well changes its response by 0.08 %), and a frame without a range (a uniform flat: the law's change is a
    level the light's level takes) measure a law little or not at all, whatever its size at full well: a series
    of flats at several levels measures it (``signal`` across the frames)."""
    if effect != "nonlinearity":
        return ""
    got = signal if signal is not None else signal_range(res)
    if got is None:
        return ""
    lo, top = got
    fw = float(res.sensor.full_well_e)
    change = float(abs(response_ratio(params or {}, top / fw) / response_ratio(params or {}, lo / fw) - 1.0))
    if change < policy.min_nonlinearity_in_range:
        return (f"over the {'series' if signal is not None else 'frame'}'s own signal ({lo:.3g} to {top:.3g} e- per "
                f"pixel, {100 * top / fw:.2g} % of the {fw:.3g} e- full well at most) the fitted law changes the "
                f"response by {100 * change:.2g} %, less than the {100 * policy.min_nonlinearity_in_range:g} % a "
                "linearity measurement resolves: its size beyond that range is an extrapolation the pixels cannot "
                "check")
    return ""


def floor_reason(effect: str, params: dict, sensor, policy: DiagnosisPolicy = DEFAULT_POLICY,
                 exptime_s: float | None = None) -> str:
    """"" or why the fitted size of ``effect`` is not a finding (gate ``floor``); ``exptime_s`` [s] for the
    floors that weigh a rate over the exposure."""
    check = FLOORS.get(effect)
    return check(params, sensor, policy, exptime_s) if check is not None else ""


#: candidates whose evidence is pixels brighter than the model that stay put: hot in every frame
HOT_EFFECTS = ("hot_pixels", "dark_rate_tail")
#: a pixel is hot in the user's dark when its rate is this many robust sigmas above the map's median
HOT_IN_DARK_SIGMA = DETECTION_SIGMA


def hot_in_dark(res, scene, policy: DiagnosisPolicy = DEFAULT_POLICY) -> str:
    """"" or why hot pixels are not the finding when the scene holds the user's own dark (``[effects.dark_map]``):
    the frame's isolated bright pixels must be hot in that dark (its rate beyond HOT_IN_DARK_SIGMA robust
    sigmas of the map) for at least the policy's ``hot_in_dark_fraction`` of them; a hot pixel is hot in every
    frame, so bright pixels the dark does not have are something else (cosmic rays, a star the catalogue lacks)."""
    from detector.effects.maps import read_map, window_of
    from scenes.scene import resolve_path, scene_dir

    table = scene.effects.get("dark_map")
    idx = np.asarray(res.data_spikes.single_pos_index)
    if table is None or idx.size == 0:
        return ""
    path = resolve_path(str(table["path"]), scene_dir(scene))
    dark = window_of(read_map(path, table.get("hdu"), "effects.dark_map.path"), res.sensor, str(path),
                     "effects.dark_map.path")
    med = float(np.median(dark))
    sig = 1.4826 * float(np.median(np.abs(dark - med))) or 1e-12
    b = res.sensor.binning
    w = res.data_adu.shape[1]
    ys, xs = idx // w, idx % w
    hot = np.zeros(idx.size, bool)
    for i, (y, x) in enumerate(zip(ys, xs)):
        block = dark[y * b:(y + 1) * b, x * b:(x + 1) * b]
        hot[i] = block.size > 0 and float(block.max()) > med + HOT_IN_DARK_SIGMA * sig
    share = float(hot.mean())
    if share < policy.hot_in_dark_fraction:
        return (f"only {100 * share:.0f} % of the frame's {idx.size} isolated bright pixels are hot in the scene's own "
                f"dark ({path.name}); a hot pixel is hot in every frame")
    return ""
