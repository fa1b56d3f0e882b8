"""Run a comparison, a diagnosis, one compare / diagnose / apply round, or several rounds.

``run_compare(scene, measured)`` builds the model (:mod:`.model`) and the residual statistics
(:mod:`.statistics`); ``run_diagnose`` adds the ranked candidates (:mod:`.candidates`); ``diagnose_round``
applies the best one (:mod:`.apply`) and updates the ledger (:mod:`.ledger`); ``run_rounds`` repeats the
round until nothing significant is left. The CLI commands ``newtsim compare`` / ``newtsim diagnose``
(:mod:`scenes.app.cli.compare`) and the HTML report (:mod:`.report`) are thin layers over these.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable
from pathlib import Path

import tomli_w

from detector.allocator import reuse_freed_memory
from detector.errors import DetectorError
from detector.jsonable import jsonable
from detector.morphology import describe
from detector.signatures import single_blas_thread
from scenes.scene import load_scene

from . import fullframe
from .apply import apply_candidate, apply_empirical, parameter_bundle
from .candidates import SIGNIFICANT_DELTA_BIC, blind_rivals, candidates, source_candidates
from .catch_all import compare_with_catch_all, outliers_after_catch_all
from .floors import HOT_EFFECTS, hot_in_dark
from .judge import judge_json, kind_gate, rank, verdict
from .ledger import best_candidate, plot_ledger, round_row, update_ledger
from .model import ModelFrame, build_model, read_measurement, residuals
from .optics_candidates import field_pattern_check, optics_candidates
from .parameters import explained_away, parameter_candidates
from .policy import DEFAULT_POLICY, DiagnosisPolicy
from .report import write_report
from .star_table import star_table
from .statistics import compare, summary

__all__ = ["SIGNIFICANT_DELTA_BIC", "ModelFrame", "best_candidate", "build_model", "diagnose_round", "run_compare",
           "run_diagnose", "run_rounds"]


@single_blas_thread
@reuse_freed_memory
def run_compare(scene, measured: str | Path, workers: int | None = None, *, large_px: int | None = None,
                progress=None) -> dict:
    """Model vs measurement: the full result (arrays included) with ``summary`` (the contract's JSON).

    A frame of more than ``large_px`` output pixels (default :data:`.fullframe.LARGE_FRAME_PX`) takes the
    bounded-memory path of :mod:`.fullframe` (binned frame, band sample; ``summary["sampling"]``)."""
    if fullframe.is_large(scene, large_px):
        try:
            return fullframe.run_compare_large(scene, measured, workers=workers, progress=progress)
        except MemoryError as exc:
            raise fullframe.out_of_memory(measured, exc) from None
    try:
        return _run_compare(scene, measured, workers)
    except MemoryError as exc:
        raise fullframe.out_of_memory(measured, exc) from None


def _run_compare(scene, measured: str | Path, workers: int | None = None) -> dict:
    t0 = time.perf_counter()
    model = build_model(scene, workers=workers)
    data, notes = read_measurement(measured, model)
    t1 = time.perf_counter()
    res = residuals(data, model)
    if res.n_fit == 0:
        raise DetectorError("no pixel of the measured frame can be compared pixel by pixel (all saturated, "
                            "flagged or outliers)", file=str(measured), expected="a frame the model predicts")
    result = compare(res, model.setup.truth, model.realisation)
    result["summary"] = summary(result)
    result["summary"].update(scene_file=scene.source, measured_file=str(measured), warnings=notes["warnings"] +
                             model.setup.warnings, wcs_offset_px=notes["wcs_offset_px"],
                             nonfinite_pixels=notes.get("nonfinite_pixels", 0),
                             seconds={"model": t1 - t0, "compare": time.perf_counter() - t1})
    result["summary"]["star_table"] = star_table(res, model.setup.truth, usable=res.fit)
    result["_residuals"], result["_model"] = res, model
    return result


@single_blas_thread
@reuse_freed_memory
def run_diagnose(scene, measured: str | Path, workers: int | None = None, progress=None, *,
                 large_px: int | None = None, policy: DiagnosisPolicy = DEFAULT_POLICY) -> dict:
    """compare + every absent effect fitted and ranked: ``{"baseline", "candidates", "verdict", ...}``.

    Large frames (``large_px``, see :func:`run_compare`) take :func:`.fullframe.run_diagnose_large`. Every
    threshold of the judge comes from ``policy`` (:mod:`.policy`), recorded in the result."""
    try:
        if fullframe.is_large(scene, large_px):
            return fullframe.run_diagnose_large(scene, measured, workers=workers, progress=progress, policy=policy)
        return _run_diagnose(scene, measured, workers, progress, policy)
    except MemoryError as exc:
        raise fullframe.out_of_memory(measured, exc) from None


def _run_diagnose(scene, measured: str | Path, workers: int | None = None, progress=None,
                  policy: DiagnosisPolicy = DEFAULT_POLICY) -> dict:
    cmp = _run_compare(scene, measured, workers=workers)
    t0 = time.perf_counter()
    truth = cmp["_model"].setup.truth
    res = cmp["_residuals"]
    cands, problems = candidates(res, set(scene.effects), progress=progress, truth=truth, policy=policy,
                                 threads=cmp["_model"].setup.detector.workers)
    optical, optical_problems = optics_candidates(res, truth, scene, progress=progress, model=cmp["_model"])
    for c in optical:
        c.policy = policy
    field_pattern_check(cands, optical)  # a uniform blur/jitter that varies over the field as the optics predicts
    if progress is not None:
        progress("the scene's parameters")
    threads = cmp["_model"].setup.detector.workers
    with ThreadPoolExecutor(max_workers=1) as pool:  # the residual's description while the parameters are fitted
        described = pool.submit(describe, res) if threads > 1 else None
        params = parameter_candidates(res, scene, cmp["_model"], truth, policy, problems)
        problems = problems + optical_problems
        if progress is not None:
            progress("residual morphology")
        morph = describe(res) if described is None else described.result()
    for c in cands:
        if c.fit.effect in HOT_EFFECTS and c.contender:
            why = hot_in_dark(res, scene, policy)
            if why:
                c.refuse("dark", why)
    effects = cands + source_candidates(res, truth, scene, policy) + optical
    kind_gate(effects, morph)
    if progress is not None:
        progress("the catch-all (held out)")
    catch_all = compare_with_catch_all(res, effects, morph, threads)
    outliers_after_catch_all(res, effects, morph, morph.get("empirical"))
    blind_rivals(res, effects, policy)
    explained_away(params, rank(effects, res.light_source), res, scene)
    cands = rank(params + effects, res.light_source)
    out = finish_diagnosis(cmp, cands, problems, morph, policy, t0, catch_all)
    best = next((c for c in cands if c.significant and c.kind == "effect"), None)
    if best is not None and best.fit.delta_adu is not None:
        remaining = describe(res, best.fit.delta_adu)
        remaining.pop("empirical")
        out["remaining_morphology"] = remaining
    return out


def finish_diagnosis(cmp: dict, cands: list, problems: list, morph: dict, policy: DiagnosisPolicy, t0: float,
                     catch_all: float | None = None) -> dict:
    """The diagnosis JSON every path writes (single frame, large frame; the series adds its own keys): the
    baseline, the candidates as the judge ranked them, the verdict, the morphology (its empirical map kept
    aside for ``--apply``), the policy and gate registry (:func:`.judge.judge_json`)."""
    empirical = morph.pop("empirical", None)
    out = {"baseline": cmp["summary"], "candidates": [c.to_json() for c in cands], "problems": problems,
           "verdict": verdict(cands, morph), "residual_morphology": morph, "seconds": time.perf_counter() - t0,
           "catch_all_heldout": catch_all, "_compare": cmp}
    cmp["_empirical"] = empirical  # the smooth fit of the residual's pattern (an array: not for the JSON)
    out.update(judge_json(cands, policy))
    return out


def apply_best(scene, diagnosis: dict, apply_to: str | Path | None, measured: str | Path,
               prefer: tuple[str, ...] = (), reserve=None, public=None) -> tuple[Path | None, dict | None]:
    """``--apply``: the best significant candidate of ``diagnosis`` (or the first of ``prefer``) added to
    ``scene`` at ``apply_to``; when none is significant but the residual is, its empirical map
    (:func:`.apply.apply_empirical`). Returns (the written scene or None, the applied entry or the best
    candidate). ``reserve(path)`` is called with the empirical map's path before it is written, ``public``
    maps a staged path to the user's (the command line's output layer)."""
    best = best_candidate(diagnosis, prefer)
    if apply_to is None:
        return None, best
    if best is not None and best.get("kind") == "parameter":
        # a number of the scene is wrong: every significant parameter is written at once (they were fitted
        # together), the effects wait for the next round
        best = parameter_bundle([c for c in diagnosis["candidates"] if c["significant"]])
        return apply_candidate(scene, best, apply_to, measured), best
    if best is not None:
        return apply_candidate(scene, best, apply_to, measured), best
    empirical = diagnosis["_compare"].get("_empirical")
    if not (diagnosis["residual_morphology"]["significant"] and empirical):
        return None, None
    if reserve is not None:
        reserve(Path(apply_to).with_name(Path(apply_to).stem + "_empirical.fits"))
    done = apply_empirical(scene, empirical, diagnosis["residual_morphology"], apply_to, measured, public=public)
    if done is None:
        return None, None
    applied, entry = done
    return applied, {**entry, "delta_bic": None}


def diagnose_round(scene, scene_path: str | Path, measured: str | Path, apply_to: str | Path | None = None,
                   workers: int | None = None, progress=None, prefer: tuple[str, ...] = (),
                   large_px: int | None = None) -> dict:
    """One round: the diagnosis of ``scene`` (loaded from ``scene_path``) against ``measured``; with
    ``apply_to``, the best significant candidate (or the first of ``prefer`` that is significant) added
    there. The ledger continues the scene's own.

    Returns the diagnosis (``run_diagnose``) with ``applied`` (or None), ``ledger`` and the comparison under
    ``_compare``."""
    out = run_diagnose(scene, measured, workers=workers, progress=progress, large_px=large_px)
    applied, best = apply_best(scene, out, apply_to, measured, prefer)
    out["applied"] = {"effect": best["effect"], "params": best["params"], "scene": str(applied)} if applied else None
    ledger, rounds = update_ledger(scene_path, applied, str(measured), out["baseline"], best if applied else None)
    out["ledger"] = {"path": str(ledger), "rounds": rounds,
                     "plot": str(plot_ledger(rounds, Path(ledger).with_suffix(".png")))}
    return out


def run_rounds(scene: dict, measured: str | Path, out: Path, name: str, n_rounds: int = 3, *,
               workers: int | None = None, extra: Callable[[dict], dict] | None = None, report: bool = True,
               log: Callable[[str], None] | None = print, prefer: tuple[str, ...] = ()) -> list[dict]:
    """compare / diagnose / apply until no candidate is significant (at most ``n_rounds`` diagnoses).

    ``scene`` is a scene table (written to ``out/NAME_round1.toml``; relative paths in it are resolved
    against ``out``). Round ``k`` writes ``NAME_round{k}.json`` (baseline, candidates, verdict, problems and
    ``extra(comparison)``), ``NAME_round{k}.html`` (with ``report``) and, when a candidate is applied,
    ``NAME_round{k+1}.toml``; the ledger (``*.ledger.json`` / ``.png``) follows the last scene. ``prefer``:
    effects applied before the ranking's best whenever they are significant. Returns one :func:`round_row`
    per round."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}_round1.toml"
    path.write_text(tomli_w.dumps(scene))
    for stale in out.glob(f"{name}_round*.ledger.json"):
        stale.unlink()
    table = []
    for k in range(1, n_rounds + 1):
        nxt = out / f"{name}_round{k + 1}.toml" if k < n_rounds else None
        res = diagnose_round(load_scene(str(path)), path, measured, apply_to=nxt, workers=workers, prefer=prefer)
        cmp = res.pop("_compare")
        checks = extra(cmp) if extra else {}
        (out / f"{name}_round{k}.json").write_text(json.dumps(jsonable(
            {"baseline": res["baseline"], "candidates": res["candidates"][:10], "verdict": res["verdict"],
             "problems": res["problems"], "applied": res["applied"], **checks}), indent=1, default=str))
        if report:
            write_report(cmp, out / f"{name}_round{k}.html", diagnosis=res)
        row = round_row(k, res, checks)
        table.append(row)
        if log is not None:
            log(f"{name} round {k}: chi2/dof {row['chi2_per_dof']:.4g}, misfit {row['misfit']:.4g}; top: "
                + ", ".join(f"{e} ({d:.3g})" for e, d, _ in row["candidates"][:4])
                + (f"; applies {row['applied']} {row['params']}" if row["applied"] else f"; {res['verdict']}"))
        if res["applied"] is None:
            break
        path = nxt
    return table
