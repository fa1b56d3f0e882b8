"""compare / diagnose / apply, round by round: the loop a user runs by hand with ``newtsim diagnose --apply``.

:func:`diagnose_round` is one round (what the CLI does): diagnose the scene against the measurement, add the
best significant candidate to a new scene (with the global levels refitted, :func:`.diagnose.apply_candidate`)
and append the round to the ledger (JSON and plot). :func:`run_rounds` repeats it until no candidate is
significant, writing every round's scene, diagnosis JSON and HTML report to one folder, and returns one
table row per round.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from detector.jsonable import jsonable

from . import diagnose as dg


def best_candidate(diagnosis: dict, prefer: tuple[str, ...] = ()) -> dict | None:
    """The first significant (and not rejected) candidate of a diagnosis, or None; with ``prefer``, the
    first significant candidate named there (in that order) comes first: the user's physical judgement
    over the ranking (a raw DSLR frame: ``cfa`` before a blur that only hides the mosaic)."""
    sig = [c for c in diagnosis["candidates"] if c["significant"]]
    for name in prefer:
        chosen = next((c for c in sig if c["effect"] == name), None)
        if chosen is not None:
            return chosen
    return sig[0] if sig else None


def diagnose_round(scene, scene_path: str | Path, measured: str | Path, apply_to: str | Path | None = None,
                   workers: int | None = None, progress=None, prefer: tuple[str, ...] = ()) -> dict:
    """One round: the diagnosis of ``scene`` (loaded from ``scene_path``) against ``measured``; with
    ``apply_to``, the best significant candidate (or the first of ``prefer`` that is significant) added
    there. The ledger continues the scene's own.

    Returns the diagnosis (``run_diagnose``) with ``applied`` (or None), ``ledger`` and the comparison under
    ``_compare``."""
    from . import run_diagnose

    out = run_diagnose(scene, measured, workers=workers, progress=progress)
    best = best_candidate(out, prefer)
    applied = None
    if apply_to is not None and best is not None:
        applied = dg.apply_candidate(scene, best, apply_to, measured)
    out["applied"] = {"effect": best["effect"], "params": best["params"], "scene": str(applied)} if applied else None
    ledger, rounds = dg.update_ledger(scene_path, applied, str(measured), out["baseline"], best if applied else None)
    out["ledger"] = {"path": str(ledger), "rounds": rounds,
                     "plot": str(dg.plot_ledger(rounds, Path(ledger).with_suffix(".png")))}
    return out


def round_row(k: int, diagnosis: dict, extra: dict | None = None, top: int = 6) -> dict:
    """The table row of round ``k``: the baseline's errors, the top candidates, what was applied; the
    ``row_*`` keys of ``extra`` (a caller's own checks) are copied."""
    b, applied = diagnosis["baseline"], diagnosis.get("applied")
    best, stars = best_candidate(diagnosis), b.get("stars") or {}  # the ranking's best, whatever was applied
    return {"round": k, "chi2_per_dof": b["chi2_per_dof"], "chi2_per_dof_levels": b.get("chi2_per_dof_levels"),
            "misfit": b["misfit"], "worst_regions": b.get("worst_regions"), "n_stars": stars.get("n", 0),
            "star_flux_ratio": stars.get("median_flux_ratio"), "star_offset_px": stars.get("median_offset_px"),
            "star_size_ratio": stars.get("median_size_ratio"),
            "streak_flux_ratio": [s["total_flux_ratio"] for s in b.get("streaks") or []],
            "candidates": [(c["effect"], c["delta_bic"], c["chi2_per_dof"]) for c in diagnosis["candidates"][:top]],
            "best": best["effect"] if best else None, "delta_bic": best["delta_bic"] if best else None,
            "explanation": best["explanation"] if best else diagnosis["verdict"],
            "applied": applied["effect"] if applied else None, "params": applied["params"] if applied else None,
            "verdict": diagnosis["verdict"], **{k2: v for k2, v in (extra or {}).items() if k2.startswith("row_")}}


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
    import tomli_w

    from ..scene import load_scene

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
            from .report import write_report

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

