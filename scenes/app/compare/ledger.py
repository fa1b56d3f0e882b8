"""The ledger of compare / diagnose / apply rounds: the error of each round, what was added after it.

Written next to the scene as ``NAME.ledger.json`` (and ``.png``); :func:`round_row` is one round's table row
for scripts that run several rounds (:func:`scenes.app.compare.run.run_rounds`).
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")


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


def ledger_path(scene_path: str | Path) -> Path:
    p = Path(scene_path)
    return p.with_name(p.stem + ".ledger.json")


def update_ledger(scene_path: str | Path, new_scene: str | Path | None, measured: str, compare_summary: dict,
                  best: dict | None) -> tuple[Path, list[dict]]:
    """Append this round to the ledger of the scene (continuing the input scene's ledger, if any) and write
    it next to the new scene (or the input scene when nothing is applied). Returns (path, rounds)."""
    src = ledger_path(scene_path)
    rounds = json.loads(src.read_text())["rounds"] if src.is_file() else []
    # the rounds of this measurement, up to (not including) a re-run of this scene
    rounds = [r for r in rounds if r.get("measured") == str(measured)]
    rounds = [r for r in rounds if r["scene"] != str(scene_path)]
    rounds.append({"round": len(rounds) + 1, "scene": str(scene_path), "measured": str(measured),
                   "chi2_per_dof": compare_summary["chi2_per_dof"], "misfit": compare_summary["misfit"],
                   "applied": best["effect"] if best else None, "params": best["params"] if best else None,
                   "delta_bic": best["delta_bic"] if best else None})
    out = ledger_path(new_scene) if new_scene else src
    out.write_text(json.dumps({"rounds": rounds}, indent=2) + "\n")
    return out, rounds


def plot_ledger(rounds: list[dict], path: str | Path) -> Path:
    """chi2/dof and misfit round by round, each point labelled with the effect added after it."""
    import matplotlib.pyplot as plt  # heavy: only when a plot is asked for

    n = [r["round"] for r in rounds]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4), dpi=90)
    for a, key, label in ((ax[0], "chi2_per_dof", "chi2 / dof"), (ax[1], "misfit", "misfit (standardised)")):
        a.plot(n, [max(r[key], 1e-3) for r in rounds], "o-")
        a.set_yscale("log")
        a.set_xlabel("round")
        a.set_ylabel(label)
        for r in rounds:
            if r.get("applied"):
                a.annotate(f"+{r['applied']}", (r["round"], max(r[key], 1e-3)), fontsize=7, xytext=(3, 3),
                           textcoords="offset points")
    ax[0].axhline(1.0, color="grey", lw=0.8, ls="--")
    fig.suptitle("compare / diagnose / apply: the error round by round", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)
