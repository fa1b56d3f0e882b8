"""Which physical effect does the model lack? Fit every absent effect's signature and rank by delta BIC.

For each registered effect (built-in catalogue and user plugins) that the scene does not switch on and
that declares a ``signature`` (:mod:`detector.diagnosis`), the signature fits the effect's own parameters
to the residuals under the model's noise; the fitted parameters are validated by the plugin's parameter
model. Candidates are ranked by ``delta_BIC = delta(-2 ln L) + k ln n`` (Schwarz 1978); the contract's
significance threshold is ``delta_BIC < -10`` ("very strong" evidence, Kass & Raftery 1995, JASA 90, 773).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detector import registry
from detector.diagnosis import Fit, Residuals

#: a candidate with delta BIC at or above this is not significant (DESIGN.md contract)
SIGNIFICANT_DELTA_BIC = -10.0


@dataclass
class Candidate:
    fit: Fit
    chi2_per_dof: float
    seconds: float

    def to_json(self) -> dict:
        f = self.fit
        return {"effect": f.effect, "params": f.params, "chi2_per_dof": self.chi2_per_dof,
                "delta_bic": f.delta_bic, "delta_m2lnl": f.delta_m2lnl, "k": f.k, "explanation": f.explanation,
                "kind": type(registry()[f.effect].signature).__name__ if f.effect in registry() else "",
                "significant": f.delta_bic < SIGNIFICANT_DELTA_BIC, "variant": f.note, "seconds": self.seconds}


def chi2_after(res: Residuals, fit: Fit) -> float:
    """chi2/dof over the fitted pixels once the candidate's mean change and added variance are in the model."""
    idx, r, w = res.flat()
    if fit.delta_adu is not None:
        r = r - np.asarray(fit.delta_adu, np.float64).ravel()[idx]
    if fit.extra_var_adu2 is not None:
        extra = np.broadcast_to(np.asarray(fit.extra_var_adu2, np.float64), res.data_adu.shape).ravel()[idx]
        w = 1.0 / (1.0 / w + extra)
    return float(np.dot(r * r, w) / max(idx.size, 1))


def candidates(res: Residuals, present: set[str], progress=None) -> tuple[list[Candidate], list[dict]]:
    """Fit every absent effect with a signature. Returns (candidates best first, problems)."""
    out, problems = [], []
    for name, cls in sorted(registry().items()):
        if name in present or cls.signature is None:
            continue
        t0 = time.perf_counter()
        try:
            fit = cls.signature.fit(res, name)
            if fit is not None:
                cls.Params.model_validate(fit.params)
        except Exception as exc:  # noqa: BLE001  (a plugin that raises is reported, the others still run)
            problems.append({"effect": name, "error": f"{type(exc).__name__}: {exc}"})
            continue
        finally:
            if progress is not None:
                progress(name)
        if fit is None or not np.isfinite(fit.delta_m2lnl):
            continue
        out.append(Candidate(fit, chi2_after(res, fit), time.perf_counter() - t0))
    out.sort(key=lambda c: c.fit.delta_bic)
    return out, problems


def verdict(cands: list[Candidate]) -> str:
    """One sentence for the report."""
    sig = [c for c in cands if c.fit.delta_bic < SIGNIFICANT_DELTA_BIC]
    if not sig:
        return "no missing effect was found: no candidate improves the fit significantly (delta BIC < -10)"
    best = sig[0].fit
    return f"most likely missing: {best.effect} (delta BIC {best.delta_bic:.4g}): {best.explanation}"


def apply_candidate(scene, cand: dict, path: str | Path, measured: str | Path | None = None) -> Path:
    """Write ``scene`` with the candidate's effect and fitted parameters added (a new scene TOML).

    The diagnosis fits every candidate together with the global levels the model only knows roughly (the
    light level among them). An effect that changes the mean light (vignetting, gain regions) therefore
    needs the level that went with it: with ``measured`` given and a flat-field screen in the scene
    (``[sky] flat_e_per_s``), the screen's level is refitted to the measurement with the new effect in the
    model (one weighted least-squares scale of the photo-signal)."""
    import tomli_w

    data = scene.model_dump(mode="json", exclude_none=True, exclude_unset=True)
    data.setdefault("effects", {})[cand["effect"]] = cand["params"]
    p = Path(path)
    note = ""
    flat = data.get("sky", {}).get("flat_e_per_s")
    if measured is not None and flat:
        scale = _light_scale(p, data, measured)
        if scale is not None and abs(scale - 1) > 1e-4:
            data["sky"]["flat_e_per_s"] = round(float(flat) * scale, 6)
            note = f"# and the flat-screen level refitted: flat_e_per_s x {scale:.5f}\n"
    p.write_text(f"# written by newtsim diagnose --apply: added [effects.{cand['effect']}]\n"
                 f"# {cand['explanation']}\n" + note + tomli_w.dumps(data))
    return p


def _light_scale(path: Path, data: dict, measured) -> float | None:
    """Weighted least-squares scale of the model's photo-signal that best matches the measurement."""
    import tomli_w

    from ..scene import load_scene
    from .model import build_model, read_measurement, residuals

    path.write_text(tomli_w.dumps(data))
    model = build_model(load_scene(str(path)), realisation=False)
    d, _ = read_measurement(measured, model)
    res = residuals(d, model)
    idx, r, w = res.flat()
    t = model.photo_adu.ravel()[idx].astype(np.float64)
    den = float(np.dot(t * t, w))
    return 1.0 + float(np.dot(t * r, w)) / den if den > 0 else None


# --- the ledger of rounds ------------------------------------------------------------------------------------

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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
