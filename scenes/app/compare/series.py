"""Compare and diagnose a series of frames together (``newtsim compare|diagnose --series SERIES.toml``).

One frame cannot tell apart effects that make the same pattern in it: a compressive non-linearity on a flat
lowers the level like a dimmer lamp, a bias ramp on a dark looks like a dark-current gradient, a fixed glow
like a straylight gradient. A series can, because the effects change differently from frame to frame: each
effect declares its ``scaling`` (:attr:`detector.effects.base.Effect.scaling`): with exposure, with the
signal, with nothing (hardware the frames share, fitted with one set of parameters) or frame by frame (a
straylight that moves with the pointing).

The series file (contract, DESIGN.md "series")::

    scene = "camera.toml"                 # the base scene (relative to this file)
    [[frames]]
    file = "flat_1.fits"                  # the measured frame
    set = { "exposure.time_s" = 2.0 }     # per-frame overrides, as --set
    label = "flat 2 s"                    # optional
    [[frames]]
    file = "flat_2.fits"
    scene = "other.toml"                  # optional: a frame with a scene of its own
    [levels]                              # optional: "series" (one value for all frames) or "frame"
    light_scale = "series"

The levels a model knows only roughly (:meth:`detector.signatures.Residuals.levels`) are nuisance
parameters: by default the light level of flat-screen frames is one for the series (the lamp's calibration
is one number; its exposure times scale it), the dark level too (one sensor temperature), while the sky, the
light of sky frames (transparency) and the bias offset (drift) are per frame.

Linear candidates are fitted jointly (:mod:`detector.joint`); the others (added variance, counts, image
transforms) frame by frame, their delta(-2 ln L) summed and their parameters counted once per frame. The
ranking, the plausibility checks and the verdict are those of the single frame (:mod:`.candidates`); the
held-out score of a shared effect is its leave-one-frame-out score.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

from detector import registry
from detector.allocator import reuse_freed_memory
from detector.characterize import linear_fit, pair_noise, photon_transfer
from detector.errors import DetectorError
from detector.joint import (
    SampleGrams,
    fixed_score,
    frame_amplitude,
    frame_gram,
    leave_one_out,
    levels_chi2,
    solve_joint,
)
from detector.jsonable import jsonable
from detector.morphology import describe
from detector.signatures import (
    LINEAR_SEARCH_PIXELS,
    Fit,
    LinearSignature,
    Residuals,
    Variant,
    heldout_blind,
    heldout_delta,
    search_sample,
    single_blas_thread,
)
from scenes.errors import SceneError
from scenes.scene import load_scene, read_toml

from . import fullframe
from .apply import LEVEL_SCALE_TOL, apply_candidate, parameter_bundle
from .candidates import chi2_after, implausibility, overfit, stars_check, structure_share, support_share
from .floors import floor_reason, signal_range, signal_range_floor
from .judge import Candidate, judge_json, kind_gate, rank, verdict
from .ledger import plot_ledger, update_ledger
from .parameters import calibration_candidates
from .policy import DEFAULT_POLICY, DiagnosisPolicy
from .run import _run_compare

#: the scopes of the global levels (Residuals.LEVELS) by default: "series" for a flat-screen frame's light
#: (one lamp) and the dark level (one temperature); the rest per frame
LEVEL_SCOPES = ("series", "frame")
#: a series of frames larger than this (output pixels each) is refused: the joint fit holds every frame
MAX_SERIES_FRAME_PX = fullframe.LARGE_FRAME_PX
#: fitted pixels per frame the variant search of a joint linear fit uses (the winner is refitted on all)
MIN_SEARCH_PIXELS = 40_000


@dataclass
class SeriesFrame:
    file: Path
    scene: object  #: the loaded Scene (base or its own, with the overrides)
    label: str
    sets: dict = field(default_factory=dict)
    scene_file: Path | None = None  #: the frame's own scene file, if any


@dataclass
class Series:
    path: Path
    scene_file: Path | None
    frames: list[SeriesFrame]
    levels: dict[str, str]  #: explicit scopes from the file's [levels]

    @property
    def key(self) -> str:
        """What the ledger calls this series' measurement."""
        return "series:" + ",".join(str(f.file) for f in self.frames)


# --- the series file --------------------------------------------------------------------------------------

def toml_inline(v) -> str:
    """A value as inline TOML text (what ``--set KEY=VALUE`` parses)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_inline(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_inline(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _assignments(sets: dict, file: str, where: str) -> list[str]:
    if not isinstance(sets, dict):
        raise SceneError(f"{where}.set is a {type(sets).__name__}", key=f"{where}.set", file=file,
                         expected='a table of dotted scene keys, e.g. { "exposure.time_s" = 2.0 }')
    out = []
    for k, v in sets.items():
        try:
            out.append(f"{k}={toml_inline(v)}")
        except TypeError as exc:
            raise SceneError(str(exc), key=f"{where}.set.{k}", file=file, expected="a TOML value") from None
    return out


def load_series(path: str | Path, sets: tuple[str, ...] | list[str] = ()) -> Series:
    """Read and check a series file: every frame's scene loaded (base or own, with the frame's ``set`` and
    then the command line's ``--set`` overrides) and every frame of the same camera, size and binning.
    Errors are one line naming the file, the key and what is expected."""
    p = Path(path)
    file = str(p)
    if not p.is_file():
        raise SceneError("series file not found" if not p.exists() else "is not a regular file", file=file,
                         expected="a series TOML file (scene = ..., [[frames]] file = ...)")
    data = read_toml(p, "a series TOML file")
    unknown = set(data) - {"scene", "frames", "levels", "title"}
    if unknown:
        raise SceneError(f"unknown key(s) {', '.join(sorted(unknown))}", key=min(unknown), file=file,
                         expected="scene, [[frames]], [levels], title")
    base = p.parent
    frames_in = data.get("frames")
    if "frames" in data and not isinstance(frames_in, list):
        raise SceneError(f"frames is a {type(frames_in).__name__}", key="frames", file=file,
                         expected="[[frames]] tables, each with file = \"measured.fits\"")
    if not isinstance(frames_in, list) or len(frames_in) < 2:
        raise SceneError(f"{0 if not isinstance(frames_in, list) else len(frames_in)} frame(s)", key="frames",
                         file=file, expected="at least two [[frames]] tables, each with file = \"measured.fits\"")
    scene_file = None
    if "scene" in data:
        if not isinstance(data["scene"], str):
            raise SceneError("scene is not a string", key="scene", file=file, expected="a scene TOML path")
        scene_file = _resolve(base, data["scene"])
    levels = data.get("levels", {})
    if not isinstance(levels, dict):
        raise SceneError("[levels] is not a table", key="levels", file=file, expected="a table of level = scope")
    for k, v in levels.items():
        if k not in Residuals.LEVELS or v not in LEVEL_SCOPES:
            raise SceneError(f"levels.{k} = {v!r}", key=f"levels.{k}", file=file,
                             expected=f"one of {', '.join(Residuals.LEVELS)} = \"series\" or \"frame\"")
    frames = []
    for i, fr in enumerate(frames_in):
        where = f"frames[{i}]"
        if not isinstance(fr, dict) or not isinstance(fr.get("file"), str):
            raise SceneError("no file", key=f"{where}.file", file=file, expected='file = "measured.fits"')
        extra = set(fr) - {"file", "scene", "set", "label"}
        if extra:
            raise SceneError(f"unknown key(s) {', '.join(sorted(extra))}", key=f"{where}.{min(extra)}",
                             file=file, expected="file, scene, set, label")
        own = _resolve(base, fr["scene"]) if isinstance(fr.get("scene"), str) else None
        if "scene" in fr and own is None:
            raise SceneError("scene is not a string", key=f"{where}.scene", file=file, expected="a scene TOML path")
        sc_file = own or scene_file
        if sc_file is None:
            raise SceneError("no scene", key=f"{where}.scene", file=file,
                             expected="a top-level scene = \"...\" or one in every frame")
        frame_sets = fr.get("set", {})
        assigned = _assignments(frame_sets, file, where) + list(sets)
        try:
            sc = load_scene(str(sc_file), assigned)
        except DetectorError as exc:  # say which frame (and which of its overrides) made the scene invalid
            key = f"{where}.set.{exc.key}" if exc.key in frame_sets else (exc.key or where)
            where_file = f" (scene {exc.file})" if exc.file and exc.file != str(sc_file) else f" (scene {sc_file})"
            raise SceneError(f"frame {i} ({fr['file']}): {exc.message}{where_file}", key=key, file=file,
                             expected=exc.expected) from None
        measured = _resolve(base, fr["file"])
        if not measured.is_file():
            raise SceneError("measured frame is a directory" if measured.is_dir() else "measured frame not found",
                             key=f"{where}.file", file=file, expected=f"an existing FITS file ({measured})")
        frames.append(SeriesFrame(measured, sc, str(fr.get("label") or measured.stem), dict(frame_sets), own))
    _check_same_camera(frames, file)
    return Series(p, scene_file, frames, dict(levels))


def _resolve(base: Path, name: str) -> Path:
    q = Path(name).expanduser()
    return q if q.is_absolute() else (base / q).resolve()


def _check_same_camera(frames: list[SeriesFrame], file: str) -> None:
    """Every frame of one camera, size and binning (the joint fit shares its hardware); one line naming the
    first frame that differs from the first."""
    def ident(fr):
        s = fr.scene.sensor()
        return {"camera": s.kind, "size": f"{s.output_shape[1]}x{s.output_shape[0]}", "binning": s.binning,
                "sensor": f"{s.sensor_width_px}x{s.sensor_height_px}"}
    ref = ident(frames[0])
    for i, fr in enumerate(frames[1:], start=1):
        got = ident(fr)
        for k in ref:
            if got[k] != ref[k]:
                raise SceneError(f"frame {i} ({fr.file.name}) has {k} {got[k]}, frame 0 ({frames[0].file.name}) "
                                 f"{ref[k]}", key=f"frames[{i}]", file=file,
                                 expected="every frame of one camera, size and binning")
    s = frames[0].scene.sensor()
    if s.output_shape[0] * s.output_shape[1] > MAX_SERIES_FRAME_PX:
        raise SceneError(f"frames of {s.output_shape[1]}x{s.output_shape[0]} pixels", key="frames", file=file,
                         expected=f"frames of at most {MAX_SERIES_FRAME_PX / 1e6:.0f} Mpixel each (bin them or read "
                         "a window: --set detector.binning=... or detector.roi)")


# --- the levels ---------------------------------------------------------------------------------------------

def shared_levels(series: Series, frames: list[Residuals]) -> list[str]:
    """The global levels that are one for the whole series: the explicit [levels] scopes, else the light
    level when every lit frame is a flat screen (one lamp) and the dark level (one sensor temperature)."""
    out = []
    lit = [r.light_source for r in frames if r.light_source in ("flat", "sky")]
    for name in Residuals.LEVELS:
        scope = series.levels.get(name)
        if scope is None:
            scope = "series" if (name == "light_scale" and lit and all(s == "flat" for s in lit)) or \
                name == "dark_scale" else "frame"
        if scope == "series":
            out.append(name)
    return out


# --- compare ------------------------------------------------------------------------------------------------

@single_blas_thread
@reuse_freed_memory
def run_series_compare(series: Series, workers: int | None = None, progress: Callable[[str], None] | None = None
                       ) -> dict:
    """Every frame compared with its model (:func:`scenes.app.compare.run._run_compare`), and the series'
    figures: chi2/dof over all frames, with the levels fitted per frame and with the shared ones joint."""
    t0 = time.perf_counter()
    cmps = []
    for i, fr in enumerate(series.frames):
        if progress is not None:
            progress(f"model of frame {i + 1}/{len(series.frames)} ({fr.label})")
        cmps.append(_run_compare(fr.scene, fr.file, workers=workers))
    ress = [c["_residuals"] for c in cmps]
    shared = shared_levels(series, ress)
    grams = [_level_gram(r, shared) for r in ress]
    chi2_joint, coef = levels_chi2(grams)
    n = sum(r.n_fit for r in ress)
    chi2 = sum(r.chi2() for r in ress)
    frames = [_frame_row(fr, c) for fr, c in zip(series.frames, cmps)]
    baseline = {"chi2_per_dof": chi2 / max(n, 1), "chi2_per_dof_levels": chi2_joint / max(n, 1),
                "misfit": float(np.average([f["misfit"] for f in frames], weights=[max(f["n_compared"], 1)
                                                                                    for f in frames])),
                "n_compared": int(n), "n_frames": len(frames), "series_file": str(series.path),
                "levels": {"series": {k: float(v) for k, v in zip(shared, coef)},
                           "frame": [f["levels"] for f in frames]},
                "warnings": [f"{f['label']}: {w}" for f in frames for w in f["warnings"]],
                "seconds": {"compare": time.perf_counter() - t0}}
    return {"baseline": baseline, "frames": frames, "shared_levels": shared, "calibration": calibration(series, cmps),
            "_compares": cmps, "_series": series, "_level_grams": grams}


def _level_gram(res: Residuals, shared: list[str]):
    idx, _, w = res.flat_profiled()
    return frame_gram(res, idx, res.flat()[1], w, shared_levels=shared)


def _frame_row(fr: SeriesFrame, cmp: dict) -> dict:
    s, res = cmp["summary"], cmp["_residuals"]
    idx = res.flat()[0]
    charge = res.charge_e.ravel()[idx] if idx.size else np.zeros(1)
    return {"label": fr.label, "file": str(fr.file), "exposure_s": float(res.exptime_s),
            "light_source": res.light_source, "signal_e": float(np.median(charge)),
            "chi2_per_dof": s["chi2_per_dof"], "chi2_per_dof_levels": s.get("chi2_per_dof_levels"),
            "misfit": s["misfit"], "n_compared": s["n_compared"], "levels": s.get("levels", {}),
            "worst_regions": s.get("worst_regions"), "warnings": s.get("warnings", [])}


def calibration(series: Series, cmps: list[dict]) -> dict:
    """The series' own calibration regressions, as characterize computes them (:func:`detector.characterize
    .linear_fit`): the dark level against exposure time (the dark rate, EMVA 1288 sect. 8.1) over the dark
    frames and the flat signal against exposure time (the linearity, EMVA 1288 sect. 6.5) over the flats,
    measured and modelled side by side."""
    out = {}
    for kind, src in (("dark_regression", "none"), ("linearity", "flat")):
        rows = []
        for fr, c in zip(series.frames, cmps):
            res = c["_residuals"]
            if res.light_source != src:
                continue
            idx = res.flat()[0]
            if not idx.size:
                continue
            d = res.data_adu.ravel()[idx].astype(np.float64)
            m = res.model_adu.ravel()[idx].astype(np.float64)
            # beside the medians (the table), the means of the fitted pixels (spikes left out) for the dark rate
            # as a number of the scene: a median of integer ADU jumps between codes when the noise spans a few of
            # them (a 10-300 s IMX411 dark: 0.66 e- of dark charge), the mean stays continuous; its standard
            # error the residual's scatter / sqrt(n)
            se = float(np.std(d - m)) / math.sqrt(d.size)
            rows.append((res.exptime_s, float(np.median(d)), float(np.median(m)), fr.label, res.gain, se,
                         float(d.mean()), float(m.mean())))
        ts = np.array([r[0] for r in rows])
        if len(rows) < 2 or np.ptp(ts) == 0:
            continue
        meas, mod = linear_fit(ts, [r[1] for r in rows]), linear_fit(ts, [r[2] for r in rows])
        g = rows[0][4]
        entry = {"frames": [r[3] for r in rows], "exposure_s": ts.tolist(), "measured_adu": [r[1] for r in rows],
                 "model_adu": [r[2] for r in rows],
                 "measured_slope_adu_per_s": meas["slope"], "model_slope_adu_per_s": mod["slope"],
                 "measured_intercept_adu": meas["intercept"], "model_intercept_adu": mod["intercept"]}
        if kind == "dark_regression":
            entry["measured_rate_e_per_s"] = meas["slope"] * g
            entry["model_rate_e_per_s"] = mod["slope"] * g
            # from the means (weighted least squares, the means' own errors: slope se = 1 / sqrt(sum w (t - tw)^2))
            wts = 1.0 / np.maximum(np.array([r[5] for r in rows]), 1e-12) ** 2
            tw = float(np.sum(wts * ts) / np.sum(wts))
            sxx = float(np.sum(wts * (ts - tw) ** 2))
            for key, col in (("measured_mean_rate_e_per_s", 6), ("model_mean_rate_e_per_s", 7)):
                y = np.array([r[col] for r in rows])
                entry[key] = g * float(np.sum(wts * (ts - tw) * y) / sxx)
            entry["measured_mean_rate_se_e_per_s"] = g / math.sqrt(sxx)
        else:
            fit_y = meas["intercept"] + meas["slope"] * ts
            sig = np.maximum(np.abs(fit_y - meas["intercept"]), 1e-9)
            entry["max_linearity_deviation"] = float(np.max(np.abs(np.array(entry["measured_adu"]) - fit_y) / sig))
        out[kind] = entry
    out.update(_pairs(series, cmps))
    return out


def _pairs(series: Series, cmps: list[dict]) -> dict:
    """Pairs of frames taken alike (same kind, exposure and light), measured as characterize measures them:
    the read noise of two bias frames from their difference (:func:`detector.characterize.pair_noise`) and
    the gain of two flats by photon transfer (:func:`detector.characterize.photon_transfer`, Janesick 2007
    eq. 4.7, the model's bias and dark as the master), each against the scene's."""
    groups: dict = {}
    for fr, c in zip(series.frames, cmps):
        res = c["_residuals"]
        key = (res.light_source, round(res.exptime_s, 6), json.dumps(fr.sets.get("sky.flat_e_per_s")))
        groups.setdefault(key, []).append((fr.label, res))
    out: dict = {}
    for (src, t, _), members in groups.items():
        if len(members) < 2:
            continue
        (la, a), (lb, b) = members[:2]
        s = a.sensor
        if src == "none" and t == 0:
            pn = pair_noise(a.data_adu, b.data_adu)
            out.setdefault("read_noise", []).append(
                {"frames": [la, lb], "measured_e": pn["sigma_adu"] * s.gain_e_per_adu, "scene_e": s.read_noise_e,
                 "n_pixels": int(a.data_adu.size)})
        elif src == "flat":
            master = (a.model_adu - a.photo_adu).astype(np.float64)
            pt = photon_transfer(a.data_adu, b.data_adu, master, s.read_noise_e / s.gain_e_per_adu)
            out.setdefault("photon_transfer", []).append(
                {"frames": [la, lb], "signal_adu": pt["signal_adu"], "measured_gain_e_per_adu": pt["gain_e_per_adu"],
                 "gain_se": pt["gain_se"], "scene_gain_e_per_adu": s.gain_e_per_adu})
    return out


# --- diagnose -----------------------------------------------------------------------------------------------

@dataclass
class SeriesFit:
    """One candidate over the series: the combined :class:`Fit` (delta -2 ln L summed, parameters counted
    once when shared, once per frame otherwise), each frame's own fit, and the joint solution's pieces."""

    fit: Fit
    frames: list[Fit | None]
    mode: str  #: "shared" or "frame"
    per_frame_delta: list[float]
    chi2_before: float  #: the series' chi2 with the levels alone
    chi2_after: float  #: and with the candidate (levels refitted)
    grams: list | None = None  #: the final normal equations (shared linear fits: leave-one-out scores)
    solution: object = None  #: the joint solution (:class:`detector.joint.JointFit`) of a linear fit
    shared_names: list = field(default_factory=list)  #: the shared levels of that solution, in order


def _values(v, res):
    return lambda i: v.values(i, res.data_adu.shape)


def joint_linear(name: str, sig: LinearSignature, frames: list[Residuals], shared: list[str], mode: str,
                 chi2_base: float | None = None) -> SeriesFit | None:
    """A linear signature fitted to the whole series: one set of coefficients (``mode`` "shared") or one per
    frame ("frame"), jointly with the levels; variants searched on a subsample of every frame and the winner
    refitted on every fitted pixel. With ``chi2_base`` (the series' chi2 with the levels alone), a form
    whose search-sample delta BIC is positive is returned as it is, without per-frame fits."""
    # linear forms only: a variant with a fixed part is a non-linear model linearised on one frame
    variant_lists = _aligned([[v for v in sig.variants(r) if v.fixed is None] for r in frames], frames)
    if variant_lists is None:
        return None
    nsearch = max(MIN_SEARCH_PIXELS, LINEAR_SEARCH_PIXELS // len(frames))
    samples = []
    for r in frames:
        ctx = search_sample(r, nsearch)
        samples.append(SampleGrams(r, ctx["idx"], ctx["r"], ctx["w"], shared_levels=shared, scale=ctx["scale"]))

    def evaluate(vs):
        grams = []
        for v, r, smp in zip(vs, frames, samples):
            f = _values(v, r)
            grams.append(smp.gram(shared=f if mode == "shared" else None, own=f if mode == "frame" else None))
        return solve_joint(grams), grams

    def params_of(vs, sol, grams):
        # a frame the effect does not reach (a vignetting on a dark, a dark charge on a bias: its templates are
        # zero there) has no parameters of its own and is not asked for them
        if mode == "shared":
            return [v.to_params(sol.shared) if _concerned(g) else "-" for v, g in zip(vs, grams)]
        return [v.to_params(c) if _concerned(g) else "-" for v, c, g in zip(vs, sol.own, grams)]

    n_all = sum(r.n_fit for r in frames)

    def bic(vs, sol):
        """Variants of different sizes (a ramp, a series of 8 x 8 cosines) compared as a single frame's search
        compares them (:meth:`detector.signatures.LinearSignature._best`): chi2 plus their templates (once
        when shared, once per frame otherwise) times ln n (Schwarz 1978)."""
        k = len(vs[0].values(np.zeros(1, np.intp), frames[0].data_adu.shape)) + vs[0].extra_k
        return sol.delta_chi2 + k * (1 if mode == "shared" else len(frames)) * math.log(max(n_all, 2))

    def search(cands):
        best = None
        for vs in cands:
            sol, grams = evaluate(vs)
            ps = params_of(vs, sol, grams)
            if (mode == "shared" and any(p is None for p in ps)) or all(p in (None, "-") for p in ps):
                continue
            score = bic(vs, sol)
            if best is None or score < best[2]:
                best = (vs, sol, score)
        return best

    best = search(list(zip(*variant_lists)))
    if best is not None and sig.refine is not None:
        rebuild = getattr(sig, "rebuild", None)
        if rebuild is not None:
            # the form refined on the frame the best variant improves most, then that one form on every frame
            # (one centre, one scale for the whole series)
            top = int(np.argmin(best[1].per_frame_delta))
            labels = [v.label for v in sig.refine(best[0][top], frames[top])]
            refined = [[rebuild(lab, r) for r in frames] for lab in labels]
            best = search([best[0], *refined]) or best
        else:
            refined = _aligned([list(sig.refine(v, r)) if v.label != "(none)" else [] for v, r in
                                zip(best[0], frames)], frames)
            if refined is not None:
                best = search([best[0], *zip(*refined)]) or best
    if best is None:
        return None
    vs = best[0]
    sol = best[1]
    # a form that does not improve the search sample even before its parameters are counted is not refitted on
    # every pixel (the sample's estimate, scaled, is if anything optimistic: it also fits the sample's noise)
    k_est = len(vs[0].values(np.zeros(1, np.intp), frames[0].data_adu.shape)) + sig.extra_k
    k_est *= 1 if mode == "shared" else len(frames)
    n = sum(r.n_fit for r in frames)
    if chi2_base is not None and sol.delta_chi2 + k_est * math.log(max(n, 2)) > 0:
        fit = Fit(name, {}, sol.delta_chi2, k_est, n, "does not improve the fit of the series", note=vs[0].label)
        return SeriesFit(fit, [None] * len(frames), mode, list(sol.per_frame_delta), chi2_base,
                         chi2_base + sol.delta_chi2)

    def final_gram(v, r):
        idx, _, w = r.flat_profiled()
        f = _values(v, r)
        return frame_gram(r, idx, r.flat()[1], w, shared=f if mode == "shared" else None,
                          own=f if mode == "frame" else None, shared_levels=shared)

    grams = [final_gram(v, r) for v, r in zip(vs, frames)]
    sol = solve_joint(grams)
    coefs = [sol.shared] * len(frames) if mode == "shared" else sol.own
    if sig.of_light:  # a multiplicative effect's coefficients carry the light level (see LinearSignature)
        coefs = [c / (1.0 + _light_level(sol, i, shared, frames[i])) for i, c in enumerate(coefs)]
    ps = [v.to_params(c) if _concerned(g) else "-" for v, c, g in zip(vs, coefs, grams)]
    if (mode == "shared" and any(p is None for p in ps)) or all(p in (None, "-") for p in ps):
        return None
    def finish(v, r, c, p, d):
        if p is None or p == "-":
            return None
        fi = sig._finish(r, name, v, c, d, p)
        fi.state["coef"] = np.asarray(c, float)  # with the variant: what rebuilds the mean change (fit_delta)
        return fi

    fits: list[Fit | None] = [finish(*a) for a in zip(vs, frames, coefs, ps, sol.per_frame_delta)]
    # the shot noise of the added charge (with_shot_noise), frame by frame
    corr = sum(fi.delta_m2lnl - d for fi, d in zip(fits, sol.per_frame_delta) if fi is not None)
    first = next(f for f in fits if f is not None)
    k_one = first.k
    k = k_one if mode == "shared" else k_one * sum(f is not None for f in fits)
    n = sum(r.n_fit for r in frames)
    params = first.params if mode == "shared" else {"per_frame": [f.params if f else None for f in fits]}
    expl = first.explanation
    fit = Fit(name, params, sol.delta_chi2 + corr, k, n, expl, note=first.note)
    return SeriesFit(fit, fits, mode, list(sol.per_frame_delta), sol.chi2_levels, sol.chi2,
                     grams if mode == "shared" else None, sol, list(shared))


def _aligned(lists: list[list], frames: list[Residuals]) -> list[list] | None:
    """The frames' variant lists made parallel: a frame a signature has no variant for (a light pattern on a
    dark frame) gets zero templates of the same count (it is then not concerned, :func:`_concerned`); where
    frames are offered different variants, those they all have (by label: a variant's label names its basis,
    so two frames' variants are paired only under one label); None when they share none."""
    ref_i = next((i for i, v in enumerate(lists) if v), None)
    if ref_i is None:
        return None
    if any(v and [x.label for x in v] != [x.label for x in lists[ref_i]] for v in lists):
        # a variant some frames are not offered (a bias profile fitted on unlit frames only), or offered in
        # another basis (a smooth field over another window: its label names the box): the variants every
        # frame that has any shares, by label, in the first frame's order (never paired by position alone)
        common = set.intersection(*[{x.label for x in v} for v in lists if v])
        if len(common) == 0 or any(v and len({x.label for x in v}) != len(v) for v in lists):
            return None
        order = [x.label for x in lists[ref_i] if x.label in common]
        lists = [[{x.label: x for x in v}[name] for name in order] if v else [] for v in lists]
    ref, res = lists[ref_i], frames[ref_i]
    probe = np.zeros(1, dtype=np.intp)
    counts = [np.atleast_2d(v.values(probe, res.data_adu.shape)).shape[0] for v in ref] if any(
        not v for v in lists) else []
    return [v if v else [Variant([np.zeros(1, np.float32)] * k, lambda c: None, label="(none)")
                         for k in counts] for v in lists]


def fit_delta(fit: Fit, res: Residuals) -> np.ndarray | None:
    """A fit's mean change [ADU] on its frame: kept, or rebuilt from its variant and coefficients (a series
    drops the frames' maps once a candidate is judged, to stay in bounded memory)."""
    if fit.delta_adu is not None:
        return fit.delta_adu
    v, c = fit.state.get("variant"), fit.state.get("coef")
    if v is None or c is None:
        return None
    return sum(ci * np.asarray(t, np.float32) for ci, t in zip(c, v.maps()))


def _drop_maps(sf: SeriesFit) -> None:
    """Forget the frames' full-frame maps of a judged candidate (its mean change stays rebuildable when the
    fit's variant and coefficients are known, :func:`fit_delta`): ten frames of a few hundred candidates'
    maps would not fit in memory."""
    for f in sf.frames:
        if f is not None:
            f.delta_adu = None
            f.extra_var_adu2 = None
            f.state.pop("smooth_adu", None)  # a variance fit's smooth part (its cells' test is done)


def _concerned(g) -> bool:
    """Whether the candidate's templates reach the frame at all (not all zero on its fitted pixels)."""
    cols = g.cols("ts") + g.cols("tp")
    return bool(cols) and bool(np.any(np.diag(g.g)[cols] > 0))


def _light_level(sol, i: int, shared: list[str], res: Residuals) -> float:
    if "light_scale" in shared:
        return float(sol.shared_levels[shared.index("light_scale")]) if sol.shared_levels.size else 0.0
    names = [n for n in res.levels()["names"] if n not in shared]
    lv = sol.own_levels[i]
    return float(lv[names.index("light_scale")]) if "light_scale" in names and lv.size else 0.0


def per_frame(name: str, sig, frames: list[Residuals], params_model=None) -> SeriesFit | None:
    """A signature that is not linear, fitted frame by frame: delta(-2 ln L) and parameters summed over the
    frames it fits (a frame whose fit the effect's parameter model refuses counts as not fitted)."""
    def one(r):
        f = sig.fit(r, name)
        if f is not None and params_model is not None:
            try:
                params_model.model_validate(f.params)
            except ValueError:
                f = None
        return f if f is not None and np.isfinite(f.delta_m2lnl) else None

    fits = [one(r) for r in frames]
    got = [f for f in fits if f is not None]
    if not got:
        return None
    best = min(got, key=lambda f: f.delta_m2lnl)
    params = best.params if len(got) == 1 else {**best.params, "per_frame": [f.params if f else None for f in fits]}
    fit = Fit(name, params, float(sum(f.delta_m2lnl for f in got)), sum(f.k for f in got),
              sum(r.n_fit for r in frames), best.explanation, note=best.note)
    before = sum(r.chi2_profiled() for r in frames)
    after = sum(chi2_after(r, f) * r.n_fit if f is not None else r.chi2_profiled() for r, f in zip(frames, fits))
    return SeriesFit(fit, fits, "frame", [f.delta_m2lnl if f else 0.0 for f in fits], before, after)


def _mode(cls) -> str:
    return "frame" if (cls.scaling or "frame") == "frame" else "shared"


def series_candidates(frames: list[Residuals], labels: list[str], present: set[str], shared: list[str],
                      truths: list, progress=None, chi2_base: float | None = None, level_grams: list | None = None,
                      policy: DiagnosisPolicy = DEFAULT_POLICY) -> tuple[list[Candidate], list[dict], dict]:
    """Every absent effect with a signature, fitted to the series and judged by the same judge as one frame
    (:mod:`.judge`, the same policy): the structure, excess and support shares frame by frame (a candidate
    keeps the largest over the frames where it acts), the held-out score over the frames. Returns
    (candidates best first, problems, {effect: SeriesFit}). ``level_grams``: the frames' levels-only normal
    equations when the comparison has them (:func:`run_series_compare`), else built here."""
    out, problems, fits = [], [], {}
    for name, cls in sorted(registry().items()):
        if name in present or cls.signature is None:
            continue
        t0 = time.perf_counter()
        if progress is not None:
            progress(name)
        mode = _mode(cls)
        try:
            if isinstance(cls.signature, LinearSignature):
                sf = joint_linear(name, cls.signature, frames, shared, mode, chi2_base)
            else:
                sf = per_frame(name, cls.signature, frames, cls.Params)
            if sf is not None:
                for f in sf.frames:
                    if f is not None:
                        cls.Params.model_validate(f.params)
        except Exception as exc:  # noqa: BLE001  (a plugin that raises is reported, the others still run)
            problems.append({"effect": name, "error": f"{type(exc).__name__}: {exc}"})
            continue
        if sf is None or not np.isfinite(sf.fit.delta_m2lnl):
            continue
        fits[name] = sf
        why, implaus = "", ""
        for i, (lab, r, f, truth) in enumerate(zip(labels, frames, sf.frames, truths)):
            if f is None or sf.per_frame_delta[i] >= -1.0:  # judged where it changes something
                continue
            if not why:
                w = overfit(f, chi2_after(r, f), r, policy) or (stars_check(r, f, truth, policy)
                                                                if cls.signature.kind == "transform" else "")
                why = f"frame {lab}: {w}" if w else ""
            if not implaus:
                w = implausibility(cls, f, r)
                implaus = f"frame {lab}: {w}" if w else ""
        consistency = ""
        if not implaus and sf.mode == "frame" and _mode(cls) == "shared":
            consistency = _consistency(sf, labels, policy)
        n_all = sum(r.n_fit for r in frames)
        cand = Candidate(sf.fit, sf.chi2_after / max(n_all, 1), time.perf_counter() - t0, why, implaus,
                         policy=policy)
        if consistency:
            cand.refuse("consistency", consistency)
        floor = next((w for w in (floor_reason(name, f.params, r.sensor, policy, r.exptime_s)
                                  for r, f in zip(frames, sf.frames) if f is not None) if w), "")
        if not floor:  # the series measures a response law across the signal of all its frames
            spans = [g for g in (signal_range(r) for r in frames) if g is not None]
            fitted = next((f for f in sf.frames if f is not None), None)
            if spans and fitted is not None:
                floor = signal_range_floor(name, frames[0], policy, fitted.params,
                                           signal=(min(g[0] for g in spans), max(g[1] for g in spans)))
        if floor:
            cand.refuse("floor", floor)
        cand.scaling = cls.scaling or "frame"  # type: ignore[attr-defined]
        if cand.contender:
            _frame_shares(cand, sf, frames, policy)
        _drop_maps(sf)
        out.append(cand)
    _excess_shares(frames, out, fits, level_grams or [_level_gram(r, shared) for r in frames], policy)
    _heldout(frames, out, fits, progress, policy)
    return rank(out, series_light(frames)), problems, fits


def _frame_shares(cand: Candidate, sf: SeriesFit, frames: list[Residuals], policy: DiagnosisPolicy) -> None:
    """The single frame's structure and support shares (:func:`.candidates.structure_share`,
    :func:`.candidates.support_share`) in every frame where the candidate changes the mean; the candidate
    keeps the largest (an effect of the darks need not explain the flats' structure)."""
    explains, support = [], []
    for r, f, d in zip(frames, sf.frames, sf.per_frame_delta):
        if f is None or f.delta_adu is None or d >= -1.0:
            continue
        for share, into in ((support_share(r, f, policy), support), (structure_share(r, f.delta_adu, policy),
                                                                       explains)):
            if share is not None:
                into.append(share)
    if explains:
        cand.explains = max(explains)
    if support:
        cand.support_share = round(max(support), 4)


def _consistency(sf: SeriesFit, labels: list[str], policy: DiagnosisPolicy = DEFAULT_POLICY) -> str:
    vals = []
    for lab, f, d in zip(labels, sf.frames, sf.per_frame_delta):
        if f is None or d > policy.significant_delta_bic:
            continue
        num = next((v for v in f.params.values() if isinstance(v, (int, float)) and not isinstance(v, bool)), None)
        if num is not None and num != 0:
            vals.append((abs(float(num)), lab))
    if len(vals) < 2:
        return ""
    lo, hi = min(vals), max(vals)
    if hi[0] > policy.consistency_factor * lo[0]:
        return (f"a hardware effect, but its fitted strength differs {hi[0] / lo[0]:.3g}x between frames {lo[1]} "
                f"({lo[0]:.3g}) and {hi[1]} ({hi[0]:.3g}): not one property of the camera")
    return ""


def _excess_shares(frames: list[Residuals], cands: list[Candidate], fits: dict, grams: list,
                   policy: DiagnosisPolicy = DEFAULT_POLICY) -> None:
    """The excess-share rule of the single frame (:func:`.candidates.excess_shares`), frame by frame: in every
    frame whose excess chi2 (levels alone, the shared ones at their joint values) is large (``excess_sigma``),
    the share of it the candidate removes; a candidate keeps the largest (an effect of the darks need not
    remove a share of the flats' excess). None when no frame has a large excess. ``grams``: the frames'
    levels-only normal equations."""
    _, c_lv = levels_chi2(grams)
    excess = []
    for r, g in zip(frames, grams):
        e = fixed_score(g, g.cols("ls"), c_lv, g.cols("lf")) - r.n_fit
        excess.append(e if r.n_fit and e / math.sqrt(2 * r.n_fit) >= policy.excess_sigma else None)
    if all(e is None for e in excess):
        return
    for c in cands:
        sf = fits[c.fit.effect]
        shares = [-d / e for d, e in zip(sf.per_frame_delta, excess) if e is not None and np.isfinite(d)]
        if shares:
            c.excess_share = round(float(max(shares)), 4)


def _heldout(frames: list[Residuals], cands: list[Candidate], fits: dict, progress=None,
             policy: DiagnosisPolicy = DEFAULT_POLICY) -> None:
    """Held-out scores of the contenders: a shared linear effect's leave-one-frame-out score (fitted on the
    other frames, scored on each left-out frame), the others' block cross-validation in every frame
    (:func:`detector.signatures.heldout_delta`), summed."""
    reg = registry()
    for c in sorted((c for c in cands if c.contender), key=lambda c: c.fit.delta_bic)[:policy.heldout_candidates]:
        sf = fits[c.fit.effect]
        t0 = time.perf_counter()
        try:
            if sf.grams is not None:
                c.heldout = float(sum(leave_one_out(sf.grams)))
            else:
                sig = reg[c.fit.effect].signature
                total, scored = 0.0, False
                for r, f in zip(frames, sf.frames):
                    if f is None:
                        continue
                    h = heldout_delta(sig, r, c.fit.effect, f)
                    if h is None:
                        scored = False
                        break
                    total, scored = total + h, True
                c.heldout = total if scored else None
                # blind in every frame (one fold of each sees less than a detection of its change): the summed
                # held-out score tests it neither way, as a single frame's (a tie in the judge, not a refusal)
                c.heldout_blind = scored and all(heldout_blind(f, r) for r, f in zip(frames, sf.frames)
                                                 if f is not None)
        except Exception as exc:  # noqa: BLE001
            c.refuse("error", f"cannot be scored on held-out frames ({type(exc).__name__}: {exc})")
        c.seconds += time.perf_counter() - t0
        if progress is not None:
            progress(f"{c.fit.effect} (held out)")


def series_light(frames: list[Residuals]) -> str:
    """The series' light source for the judge's ranking: "flat" when every frame is a flat screen's."""
    return "flat" if all(r.light_source == "flat" for r in frames) else ""


@single_blas_thread
@reuse_freed_memory
def run_series_diagnose(series: Series, workers: int | None = None, progress=None,
                        policy: DiagnosisPolicy = DEFAULT_POLICY) -> dict:
    """compare + every absent effect fitted to the series and ranked (the single-frame JSON keys for the
    series as a whole, ``frames`` with each frame's own figures, ``separation``: what told the winner from
    its nearest rival)."""
    cmp = run_series_compare(series, workers=workers, progress=progress)
    t0 = time.perf_counter()
    cmps = cmp["_compares"]
    frames = [c["_residuals"] for c in cmps]
    labels = [f.label for f in series.frames]
    present = set().union(*(set(f.scene.effects) for f in series.frames))
    truths = [c["_model"].setup.truth for c in cmps]
    chi2_base = cmp["baseline"]["chi2_per_dof_levels"] * cmp["baseline"]["n_compared"]
    cands, problems, fits = series_candidates(frames, labels, present, cmp["shared_levels"], truths, progress,
                                              chi2_base, cmp["_level_grams"], policy)
    morphs = [describe(r, frames=len(frames)) for r in frames]  # the worst of n frames stands for the series
    for m in morphs:
        m.pop("empirical", None)
    worst = int(np.argmax([m.get("significance_sigma", 0.0) for m in morphs]))
    morph = {**morphs[worst], "frame": labels[worst]}
    kind_gate(cands, morph)
    base = series.frames[0].scene if series.scene_file is None else load_scene(str(series.scene_file))
    params = calibration_candidates(cmp["calibration"], frames[0].sensor, sum(r.n_fit for r in frames),
                                    cmp["baseline"]["chi2_per_dof"], base, policy)
    cands = rank(params + cands, series_light(frames))  # the kind gate may have refused the first
    out = {"baseline": cmp["baseline"], "candidates": [_cand_json(c, fits, labels) for c in cands],
           "problems": problems, "verdict": verdict(cands, morph), "residual_morphology": morph,
           "frames": cmp["frames"], "shared_levels": cmp["shared_levels"], "calibration": cmp["calibration"],
           "series": str(series.path), "_compare": cmp, "_fits": fits, "_candidates": cands}
    for fr, m in zip(out["frames"], morphs):
        fr["residual_morphology"] = m
    out.update(judge_json(cands, policy))
    out["separation"] = separation(frames, labels, cands, fits, series)
    out["seconds"] = time.perf_counter() - t0
    return out


def _cand_json(c: Candidate, fits: dict, labels: list[str]) -> dict:
    d = c.to_json()
    sf = fits.get(c.fit.effect)
    d["scaling"] = getattr(c, "scaling", "frame")
    d["shared"] = bool(sf is not None and sf.mode == "shared")
    if sf is not None:
        d["frames"] = [{"label": lab, "delta_chi2": round(float(dd), 4),
                        "params": (f.params if f is not None else None)} for lab, f, dd in
                       zip(labels, sf.frames, sf.per_frame_delta)]
    return d


# --- what told the winner apart ------------------------------------------------------------------------------

def separation(frames: list[Residuals], labels: list[str], cands: list[Candidate], fits: dict, series: Series
               ) -> dict | None:
    """What separated the best effect from its nearest rival (the next plausible, unrejected candidate of
    another effect with delta BIC < -10): frame by frame, each one's share of the improvement and, for a
    shared effect, its pattern fitted to that frame alone (amplitude relative to the joint fit, the shared
    levels held: 1 where the frame agrees). A shared effect of the right scaling keeps 1 in every frame; one
    of the wrong scaling drifts with exposure or signal (a bias ramp fitted to a dark-current gradient grows
    with exposure time, a lamp-level error fitted as a non-linearity shrinks with the signal)."""
    best = next((c for c in cands if c.significant and c.fit.effect in fits), None)  # effects (not numbers)
    if best is None:
        return None
    rival = next((c for c in cands if c is not best and c.fit.effect != best.fit.effect and c.plausible
                  and not c.rejected and c.fit.delta_bic < c.policy.significant_delta_bic
                  and c.fit.effect in fits), None)
    pair = [("best", best, fits[best.fit.effect])]
    if rival is not None:
        pair.append(("rival", rival, fits[rival.fit.effect]))
    rows = []
    for i, (r, lab) in enumerate(zip(frames, labels)):
        idx = r.flat()[0]
        row = {"label": lab, "exposure_s": float(r.exptime_s),
               "signal_e": float(np.median(r.charge_e.ravel()[idx])) if idx.size else 0.0}
        for key, _, sf in pair:
            row[f"delta_chi2_{key}"] = round(float(sf.per_frame_delta[i]), 3)
            if sf.grams is not None and sf.solution is not None:
                a, e = frame_amplitude(sf.grams[i], sf.solution)
                row[f"amplitude_{key}"] = a if np.isfinite(a) else None
                row[f"amplitude_error_{key}"] = e if np.isfinite(e) else None
        rows.append(row)
    total = {key: float(sum(sf.per_frame_delta)) for key, _, sf in pair}
    if rival is None:
        text = f"{best.fit.effect}: no plausible rival fits the series"
    else:
        text = (f"{best.fit.effect} (scaling: {getattr(best, 'scaling', '?')}) against {rival.fit.effect} "
                f"(scaling: {getattr(rival, 'scaling', '?')}): over the series chi2 falls by {-total['best']:.4g} "
                f"against {-total['rival']:.4g}")
        amps = [row.get("amplitude_rival") for row in rows if row.get("amplitude_rival") is not None]
        if len(amps) >= 2:
            text += (f"; the rival's pattern fitted frame by frame ranges from {min(amps):.3g} to {max(amps):.3g} "
                     "times its joint amplitude, the winner's stays near 1")
    return {"best": best.fit.effect, "rival": rival.fit.effect if rival is not None else None,
            "scaling": {key: getattr(c, "scaling", None) for key, c, _ in pair}, "frames": rows, "statement": text,
            "residual_vs_signal": residual_vs_signal(frames, labels, pair)}


def residual_vs_signal(frames: list[Residuals], labels: list[str], pair: list) -> list[dict] | None:
    """The lit frames' mean residual relative to their light, against their signal level, with the shared
    light level of the levels-only fit removed, and what each candidate predicts there (its mean change
    plus the change it makes to the shared light level): a non-linearity is a deficit growing with the
    signal, a lamp-level error a constant. None when the light level is not shared by the frames (then each
    frame's own level absorbs any such curve: one frame's level cannot tell them apart)."""
    _, _, sf = pair[0]
    sol = sf.solution
    if sol is None or not frames or "light_scale" not in _shared_names(sf):
        return None
    i_light = _shared_names(sf).index("light_scale")
    out = []
    for i, (r, lab) in enumerate(zip(frames, labels)):
        idx, res_, _ = r.flat()
        photo = r.photo_adu.ravel()[idx].astype(np.float64)
        total = float(photo.sum())
        if total <= 0:
            continue
        row = {"label": lab, "signal_e": float(np.median(r.charge_e.ravel()[idx])),
               "residual_rel": float(res_.sum()) / total - float(sol.levels_only[i_light])}
        for k, _, f in pair:
            fi = f.frames[i]
            delta = fit_delta(fi, r) if fi is not None and f.solution is not None else None
            if delta is None:
                continue
            names = _shared_names(f)
            dl = (float(f.solution.shared_levels[names.index("light_scale")] - f.solution.levels_only[names.index(
                "light_scale")]) if "light_scale" in names else 0.0)
            row[f"{k}_rel"] = float(np.asarray(np.broadcast_to(delta, r.data_adu.shape), np.float64).ravel()[idx].sum(
            )) / total + dl
        out.append(row)
    return out or None


def _shared_names(sf: SeriesFit) -> list[str]:
    return list(getattr(sf, "shared_names", []) or [])


# --- apply and the ledger -----------------------------------------------------------------------------------

def apply_series(series: Series, diagnosis: dict, apply_to: str | Path | None, prefer: tuple[str, ...] = (),
                 workers: int | None = None) -> tuple[Path | None, Path | None, dict | None]:
    """``--apply``: the best significant candidate added to the series' base scene at ``apply_to`` (one scene
    serving every frame), and ``APPLY.series.toml`` beside it: the series file of the next round (the new
    scene, the same frames; a per-frame effect's parameters as each frame's ``set``). The levels the series
    shares (the flat-screen level, the dark current) are then refitted with the new scene's model of every
    frame and written into it, as the single-frame ``--apply`` refits a frame's levels: the levels fitted
    jointly with a candidate are not those of its parameters when the two trade off (gain regions normalised to
    a mean gain of 1 against the light and dark levels). Returns (scene, series file, the applied candidate)
    or Nones."""
    sig = [c for c in diagnosis["candidates"] if c["significant"]]
    best = next((c for n in prefer for c in sig if c["effect"] == n), sig[0] if sig else None)
    if apply_to is None or best is None:
        return None, None, best
    if best.get("kind") == "parameter":  # numbers of the camera: every significant one written at once
        best = parameter_bundle(sig)
    base = series.frames[0].scene if series.scene_file is None else load_scene(str(series.scene_file))
    per = best["params"].get("per_frame") if isinstance(best["params"], dict) else None
    cand = dict(best)
    if per is not None:
        first = next(p for p in per if p is not None)
        cand = {**best, "params": first}
    scene_path = Path(apply_candidate(base, cand, apply_to, None))
    new_series = scene_path.with_name(scene_path.stem + ".series.toml")
    _write_next_series(series, best, per, scene_path, new_series, {}, [])
    # the shared levels with the new scene in the model of every frame
    refit = run_series_compare(load_series(new_series), workers=workers)
    levels = refit["baseline"]["levels"]["series"]
    new_base, notes = carry_series_levels(load_scene(str(scene_path)), levels)
    if notes:
        apply_candidate(new_base, cand, scene_path, None)
    light = levels.get("light_scale", 0.0)
    if abs(light) > LEVEL_SCALE_TOL and any("sky.flat_e_per_s" in fr.sets for fr in series.frames):
        notes.append(f"the frames' flat-screen levels refitted: sky.flat_e_per_s x {1 + light:.5f}")
    if notes:
        _write_next_series(series, best, per, scene_path, new_series, levels, notes)
    return scene_path, new_series, best


def _write_next_series(series: Series, best: dict, per: list | None, scene_path: Path, new_series: Path,
                       levels: dict, notes: list[str]) -> None:
    frames = []
    light = levels.get("light_scale", 0.0)
    for i, fr in enumerate(series.frames):
        entry = {"file": str(fr.file), "label": fr.label}
        sets = dict(fr.sets)
        if "sky.flat_e_per_s" in sets and abs(light) > LEVEL_SCALE_TOL and 1 + light > 0:
            sets["sky.flat_e_per_s"] = round(float(sets["sky.flat_e_per_s"]) * (1 + light), 6)
        if per is not None and best["effect"] != "light_curve":
            # the frame's own parameters; a frame the effect was not fitted on gets its zero strength
            own = per[i] if per[i] is not None else (registry()[best["effect"]].identity or {})
            for k, v in own.items():
                sets[f"effects.{best['effect']}.{k}"] = v
        if fr.scene_file is not None:
            entry["scene"] = str(fr.scene_file)
            if per is None and best.get("kind") != "parameter":
                for k, v in best["params"].items():
                    sets[f"effects.{best['effect']}.{k}"] = v
        if sets:
            entry["set"] = sets
        frames.append(entry)
    body = {"scene": scene_path.name, "frames": frames}  # beside it
    if series.levels:
        body["levels"] = series.levels
    new_series.write_text(f"# written by newtsim diagnose --series --apply: {best['effect']} added\n"
                          + "".join(f"# and {n}\n" for n in notes) + tomli_w.dumps(body))


def carry_series_levels(scene, levels: dict[str, float]):
    """The base scene with the levels the series shares written into the keys that hold them (the flat-screen
    level, the dark current), as the single-frame ``--apply`` carries a frame's levels
    (:func:`.apply.carry_levels`); per-frame levels (sky, bias drift) stay per frame. Returns (scene, notes)."""
    notes, update = [], {}
    c = levels.get("light_scale", 0.0)
    if abs(c) > LEVEL_SCALE_TOL and scene.sky.flat_e_per_s and 1 + c > 0:
        update["sky"] = scene.sky.model_copy(update={"flat_e_per_s": round(scene.sky.flat_e_per_s * (1 + c), 6)})
        notes.append(f"the series' flat-screen level refitted: flat_e_per_s x {1 + c:.5f}")
    c = levels.get("dark_scale", 0.0)
    if abs(c) > LEVEL_SCALE_TOL and 1 + c > 0:
        det = dict(scene.detector)
        rate = scene.sensor().dark_current_e_per_s
        det["dark_current_e_per_s"] = round(rate * (1 + c), 6)
        update["detector"] = det
        notes.append(f"the series' dark level refitted: dark current {rate:.4g} -> {det['dark_current_e_per_s']:.4g} e-/s")
    return (scene.model_copy(update=update) if update else scene), notes


def series_ledger(series: Series, diagnosis: dict, new_series: Path | None, best: dict | None,
                  target: Path | None = None) -> dict:
    """The ledger of the series' rounds (beside the new series file, else beside the series file): the
    series' chi2/dof with the levels refitted (shared ones joint: the lamp, sky and bias levels the scene
    only knows to a per cent are not the error) and the misfit, per round."""
    b = diagnosis["baseline"]
    ledger, rounds = update_ledger(series.path, new_series or target, series.key,
                                   {**b, "chi2_per_dof": b["chi2_per_dof_levels"]}, best if new_series else None)
    plot = plot_ledger(rounds, Path(ledger).with_suffix(".png"))
    return {"path": str(ledger), "rounds": rounds, "plot": str(plot)}


def public_json(diagnosis: dict) -> dict:
    """The diagnosis without its in-memory parts (arrays, residuals)."""
    return jsonable({k: v for k, v in diagnosis.items() if not k.startswith("_")})
