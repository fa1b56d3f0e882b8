"""``diagnose --apply``: write the scene with the chosen candidate added, and the global levels that go with it.

The diagnosis fits every candidate together with the global levels the model only knows roughly (light,
sky, bias offset, dark level; :meth:`detector.signatures.Residuals.levels`). The new scene carries those
levels, refitted on the measured frame with the new effect in the model, in the scene keys that hold them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tomli_w
from astropy.io import fits

from detector.signatures import LEVEL_DEGENERACY, independent_columns, template_at
from scenes.scene import load_scene

from .model import build_model, read_measurement, residuals
from .optics_candidates import OPTICS_CANDIDATES


def parameter_bundle(significant: list[dict]) -> dict:
    """The applied entry of a round whose best candidate is a number of the scene: every significant parameter
    candidate (JSON dicts) written at once (they were fitted together), the effects waiting for the next round."""
    params = [c for c in significant if c.get("kind") == "parameter"]
    return {"effect": "parameters", "kind": "parameter", "params": {c["key"]: c["value"] for c in params},
            "parameters": params, "delta_bic": min(c["delta_bic"] for c in params),
            "explanation": "; ".join(c["explanation"] for c in params)}


def apply_candidate(scene, cand: dict, path: str | Path, measured: str | Path | None = None) -> Path:
    """Write ``scene`` with the candidate's effect and fitted parameters added (a new scene TOML).

    The diagnosis fits every candidate together with the global levels the model only knows roughly
    (:meth:`detector.signatures.Residuals.levels`: light, sky background, bias offset, dark level). The new
    scene therefore carries the levels that go with the effect: with ``measured`` given, the levels that
    frame measures are refitted with the new effect in the model (weighted least squares,
    :func:`refit_levels`) and written to the scene keys that hold them (``[sky] flat_e_per_s``,
    ``[sky] background_mag_arcsec2``, ``[detector] bias_adu``); each change is noted in the file's header
    comment. A multiplicative effect such as vignetting would otherwise lower the whole model."""
    data = scene.model_dump(mode="json", exclude_none=True, exclude_unset=True)
    if cand.get("kind") == "parameter":  # numbers of the scene: written in place
        from .parameters import apply_parameters

        changed = apply_parameters(data, cand.get("parameters") or [cand])
        added = "new values of " + ", ".join(c.split(" ")[0] for c in changed)
    elif cand["effect"] == "light_curve":  # a source's property: into its [[objects]] table
        data["objects"][cand["params"]["object"]]["light_curve"] = cand["params"]["light_curve"]
        added = f"objects[{cand['params']['object']}].light_curve"
    elif cand["effect"] in OPTICS_CANDIDATES:  # the telescope's alignment: a new design file beside the scene
        design = write_perturbed_design(scene, cand["params"], Path(path))
        data.setdefault("telescope", {})["design"] = design.name
        added = f"[perturbation] of the design in {design.name}"
    else:
        data.setdefault("effects", {})[cand["effect"]] = cand["params"]
        added = f"[effects.{cand['effect']}]"
    p = Path(path)
    notes = []
    if measured is not None:
        # a PSF change moves each star's light between its core and its wings, and a response (a non-linearity,
        # a gain) scales the stars' light as it scales the sky's: the sources' scale that goes with it (which
        # the diagnosis profiled when it scored the change) is refitted with the sky
        psf = cand.get("kind") == "parameter" and any(
            str(c.get("key", "")).startswith("psf.") for c in (cand.get("parameters") or [cand]))
        data, notes = carry_levels(data, refit_levels(p, data, measured, with_sources=psf or _scales_light(cand)),
                                   scene)
    p.write_text(f"# written by newtsim diagnose --apply: added {added}\n"
                 f"# {cand['explanation']}\n" + "".join(f"# and {n}\n" for n in notes) + tomli_w.dumps(data))
    return p


def _scales_light(cand: dict) -> bool:
    """Whether the candidate is a response to the light (a multiplicative field: vignetting, gains, a flat; or
    a law of the collected signal applied at read-out: a non-linearity), which changes the stars' level as it
    changes the sky's."""
    from detector import registry
    from detector.effects.base import Stage

    eff = registry().get(cand.get("effect", "")) if cand.get("kind", "effect") == "effect" else None
    if eff is None:
        return False
    return eff.field_kind == "multiplicative" or (tuple(eff.stages) == (Stage.READ,) and eff.scaling == "signal")


def write_perturbed_design(scene, params: dict, scene_path: Path) -> Path:
    """Write the scene's design with the fitted ``[perturbation]`` entries of ``params`` (names of
    :data:`optics.design.PERTURBATION_NAMES`; other keys such as ``errors`` are ignored) as
    ``NEW_SCENE_design.toml`` beside the new scene; returns its path. The design's other perturbations are
    kept. With ``[psf] model = "optics"`` the new scene's PSF grid and (``distortion = "optics"``) SIP are
    traced for the perturbed design (cached by its hash); with another PSF model only the SIP follows."""
    from optics.design import PERTURBATION_NAMES, load_design, with_perturbation

    values = {k: float(v) for k, v in params.items() if k in PERTURBATION_NAMES}
    design = with_perturbation(load_design(scene.telescope.design), **values)
    out = scene_path.with_name(scene_path.stem + "_design.toml")
    data = design.model_dump(mode="json", exclude_none=True)
    data["name"] = out.stem
    out.write_text(f"# written by newtsim diagnose --apply: {scene.telescope.design} with the fitted perturbation\n"
                   + tomli_w.dumps(data))
    return out


#: level changes below these are not written back (relative for scales, ADU for the bias offset)
LEVEL_SCALE_TOL, LEVEL_OFFSET_TOL_ADU = 1e-4, 0.01


def refit_levels(path: Path, data: dict, measured, with_sources: bool = False) -> dict[str, float]:
    """The global levels the scene ``data`` (written to ``path``) needs to match ``measured``.

    With ``with_sources`` (a light frame with stars whose PSF has just changed), the sources' scale and the sky are
    refitted together on every fitted pixel: ``source_scale`` (the photo-signal's level) and
    ``background_scale`` (the sky's, the light level included), as the diagnosis profiled them.

    A level is refitted from the frame that measures it, on the pixels where the model's sources add less
    than one sigma to its background (misplaced or mis-sized stars would pull a sky level): the light level
    (flat screen) or the sky level from a light frame, the bias offset and the dark level from a dark or bias frame (a light frame cannot
    separate a bias offset from its light: on a vignetted flat screen the least squares trade hundreds of
    ADU of bias against a per cent of light). Weighted least squares of the residual on those templates,
    degenerate ones dropped in :attr:`Residuals.LEVELS` order. Returns ``{level name: coefficient}``
    (scales are relative changes, the offset is in ADU)."""
    path.write_text(tomli_w.dumps(data))
    sc = load_scene(str(path))
    res, per_offset = _level_residuals(sc, measured)
    idx, r, w = res.flat()
    if with_sources and sc.exposure.frame == "light" and sc.sky.stars and sc.sky.background_mag_arcsec2 is not None:
        keep, c = _solve_levels(res, idx, r, w, [0, 1])  # every fitted pixel: the sources' too
        if len(keep) == 2:
            return {"source_scale": float(c[0]), "background_scale": float(c[0] + c[1])}
    if res.background_adu is not None:  # the levels from the background's pixels: a misfit star is not sky
        sources = (res.model_adu - res.background_adu).ravel()[idx] * np.sqrt(w)
        keep = sources < 1.0
        idx, r, w = idx[keep], r[keep], w[keep]
    if not idx.size:
        return {}
    if sc.exposure.frame == "light":
        if sc.sky.flat_e_per_s:
            wanted = [0]  # the flat screen: the whole photo-signal
        elif sc.sky.background_mag_arcsec2 is not None:
            wanted = [1]  # the sky: the uniform part of the light
        else:
            return {}
    else:
        # a dark or bias frame: the bias offset. A uniform dark level is the same change of the mean in one
        # dark frame; it is written as the bias (the dark template holds glow, DSNU and bias structure too:
        # scaling the dark current by its fit would be wrong). The judge gives the offset's dark part its shot
        # noise by the priors' split (Residuals.dark_share); that split is a prior, not a measurement, so the
        # value written is the measured sum, and a rediagnosis of the applied scene starts near a zero offset
        wanted = [2]
    keep, coef = _solve_levels(res, idx, r, w, wanted)
    return {res.LEVELS[wanted[k]]: float(c) / (per_offset if wanted[k] == 2 else 1.0) for k, c in zip(keep, coef)}


def _solve_levels(res, idx, r, w, wanted: list[int]) -> tuple[list[int], np.ndarray]:
    """Weighted least squares of the residual ``r`` (weights ``w``, at flat pixels ``idx``) on the level templates
    ``wanted`` (indices of :attr:`Residuals.LEVELS`): (the positions in ``wanted`` kept, degenerate ones dropped
    in order, and their coefficients)."""
    temps = res.level_templates()
    x = np.stack([template_at(temps[i], res.data_adu.shape, idx) for i in wanted])
    xw = x * w
    g = xw @ x.T
    keep = independent_columns(g, tol=LEVEL_DEGENERACY)
    if not keep:
        return [], np.zeros(0)
    return keep, np.linalg.solve(g[np.ix_(keep, keep)], (xw @ r)[keep])


def _level_residuals(sc, measured):
    """The residuals the levels are refitted on, and how many output pixels' bias one unit of its offset
    template holds: the whole frame, or a large frame's binned frame (:mod:`.fullframe`; ``k^2`` output
    pixels summed per binned pixel)."""
    from . import fullframe

    if fullframe.is_large(sc):
        out = fullframe.run_compare_large(sc, measured)
        res = out["_residuals"]
        k = out["sampling"]["binning_k"]
        return res, (float(k * k) if res.sensor.binning_mode == "sum" else 1.0)
    model = build_model(sc, realisation=False)
    d, _ = read_measurement(measured, model)
    return residuals(d, model), 1.0


def carry_levels(data: dict, levels: dict[str, float], scene) -> tuple[dict, list[str]]:
    """Write refitted global levels into the keys of the scene ``data`` (a dump of ``scene``, with the applied
    candidate in it) that hold them. The levels were refitted on ``data`` (:func:`refit_levels`), so they scale
    the values ``data`` holds (a sky level a parameter candidate has just set), not the old scene's. Returns
    (scene data, notes)."""
    notes, sensor = [], scene.sensor()
    sky, det = data.setdefault("sky", {}), data.setdefault("detector", {})
    c = levels.get("light_scale", 0.0)
    if abs(c) > LEVEL_SCALE_TOL and sky.get("flat_e_per_s") and 1 + c > 0:
        sky["flat_e_per_s"] = round(float(sky["flat_e_per_s"]) * (1 + c), 6)
        notes.append(f"the flat-screen level refitted: flat_e_per_s x {1 + c:.5f}")
    c = levels.get("source_scale", 0.0)
    if abs(c) > LEVEL_SCALE_TOL and 1 + c > 0:
        old = float(sky.get("source_flux_scale", scene.sky.source_flux_scale))
        sky["source_flux_scale"] = round(old * (1 + c), 6)
        notes.append(f"the sources' scale refitted with the change: source_flux_scale {old:.5g} -> "
                     f"{sky['source_flux_scale']:.6g}")
    c = levels.get("background_scale", 0.0)
    if abs(c) > LEVEL_SCALE_TOL and 1 + c > 0.05:
        mag = sky.get("background_mag_arcsec2", scene.sky.background_mag_arcsec2)
        # within the scene file's range [5, 35] mag/arcsec^2 (a sky fainter than 35 is no sky)
        sky["background_mag_arcsec2"] = round(min(max(float(mag) - 2.5 * float(np.log10(1 + c)), 5.0), 35.0), 5)
        notes.append(f"the sky level refitted: x {1 + c:.5f} ({mag:.4g} -> {sky['background_mag_arcsec2']:.5g} "
                     "mag/arcsec^2)")
    c = levels.get("offset_adu", 0.0) / bias_per_output_adu(sensor)
    if abs(c) > LEVEL_OFFSET_TOL_ADU:
        bias = float(det.get("bias_adu", sensor.bias_adu))
        det["bias_adu"] = round(max(bias + c, 0.0), 3)
        notes.append(f"the bias level refitted: {bias:.4g} -> {det['bias_adu']:.6g} ADU")
    return data, notes


def bias_per_output_adu(sensor) -> float:
    """Output ADU per ADU of ``bias_adu``: a CMOS sums (or averages) ``b^2`` digitised reads, each with the
    bias; a CCD reads a binned pixel once (and an average divides that by ``b^2``)."""
    b2 = sensor.binning ** 2
    if sensor.binning_mode == "sum":
        return float(b2) if sensor.kind != "ccd" else 1.0
    return 1.0 if sensor.kind != "ccd" else 1.0 / b2


#: the effect an empirical map is applied through, by the kind of the residual (and the frame type)
EMPIRICAL_EFFECTS = {"multiplicative": "flat_map", "additive": "dark_map", "additive_bias": "bias_map",
                     "noise": "noise_map"}


def apply_empirical(scene, empirical: dict, morphology: dict, path: str | Path, measured: str | Path | None = None,
                    public=None) -> tuple[Path, dict] | None:
    """Write ``scene`` with the residual's own smooth pattern added as a measured map, when no catalogue
    effect explains it (the verdict says so): extra noise as a ``noise_map`` (the sigma of a read [e-]), a
    multiplicative pattern as a ``flat_map`` (relative response),
    an additive one as a ``dark_map`` (charge that grows with the exposure and carries its shot noise: light
    the model lacks) or, on a bias frame, a ``bias_map`` [ADU]. The map (unbinned read-out window, FITS) is
    written beside the new scene as ``NAME_empirical.fits``. Returns (scene path, the applied entry) or None
    when the scene already has that map effect. ``public`` maps a staged path to the path the user named
    (:meth:`scenes.app.outputs.Outputs.public`)."""
    sensor = scene.sensor()
    kind = empirical["kind"]
    if kind == "additive" and scene.exposure.frame == "bias":
        kind = "additive_bias"
    effect = EMPIRICAL_EFFECTS.get(kind)
    if effect is None or effect in scene.effects:
        return None
    p = Path(path)
    b = sensor.binning
    out_map = np.asarray(empirical["map"], np.float64)  # per output pixel: relative (x light) or ADU
    full = np.repeat(np.repeat(out_map, b, axis=0), b, axis=1)  # unbinned read-out window
    gain = float(sensor.gain_e_per_adu)
    per_sensor_px = float(b * b) if sensor.binning_mode == "sum" else 1.0  # output value = sum of b^2 pixels
    if kind == "multiplicative":  # the map is the relative change of the light
        data, params, unit = 1.0 + full, {}, "relative response"
        if float(np.min(data)) <= 0.0:  # a response cannot be negative: the pattern is not a flat field
            return None
    elif kind == "noise":  # the map is the extra variance of an output pixel [ADU^2]: the sigma of one read [e-]
        if sensor.kind == "ccd":
            reads = 1.0  # one read of the binned charge
        else:  # b^2 reads summed (or averaged) digitally
            reads = 1.0 / per_sensor_px if sensor.binning_mode == "sum" else float(b * b)
        data = np.sqrt(np.maximum(full, 0.0) * reads) * gain
        params, unit = {}, "e- rms per read"
    elif kind == "additive_bias":
        reads = per_sensor_px if sensor.kind != "ccd" else 1.0  # a CMOS sums b^2 digitised reads
        data, params, unit = full / reads, {}, "ADU"
    else:
        t = max(float(scene.exposure.time_s), 1e-6)
        data = float(sensor.dark_current_e_per_s) + full * gain / per_sensor_px / t
        params, unit = {}, "e-/s"
    map_path = p.with_name(p.stem + "_empirical.fits")
    hdu = fits.PrimaryHDU(np.asarray(data, np.float32))
    hdu.header["BUNIT"] = unit
    hdu.header["COMMENT"] = "empirical map of a residual no catalogue effect explains (newtsim diagnose --apply)"
    hdu.writeto(map_path, overwrite=True)
    where = str(map_path.resolve())
    explanation = ("an empirical map of the residual (" + morphology["explanation"] + "); no catalogue effect "
                   "explains it")
    # the levels are refitted with the map where it is now (staged); the scene names it where it will be
    written = apply_candidate(scene, {"effect": effect, "params": {"path": where, **params},
                                      "explanation": explanation}, p, measured)
    final = public(where) if public is not None else where
    if final != where:
        text = written.read_text()
        written.write_text(text.replace(tomli_w.dumps({"p": where}).split("=", 1)[1].strip(),
                                        tomli_w.dumps({"p": final}).split("=", 1)[1].strip()))
    cand = {"effect": effect, "params": {"path": final, **params}, "explanation": explanation}
    return written, cand

