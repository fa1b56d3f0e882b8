"""Compare a measured frame with the scene's model, and diagnose which physical effect the model lacks.

``run_compare(scene, measured)`` builds the model (:mod:`.model`), the residual statistics
(:mod:`.analysis`); ``run_diagnose`` adds the ranked candidates (:mod:`.diagnose`). The CLI commands
``newtsim compare`` and ``newtsim diagnose`` (``scenes/cli_compare.py``) and the HTML report
(:mod:`.report`) are thin layers over these two functions.
"""

from __future__ import annotations

import time
from pathlib import Path

from detector.errors import DetectorError

from .analysis import compare, summary
from .diagnose import (
    SIGNIFICANT_DELTA_BIC,
    candidates,
    rank,
    source_candidates,
    verdict,
)
from .model import ModelFrame, build_model, read_measurement, residuals

__all__ = ["SIGNIFICANT_DELTA_BIC", "ModelFrame", "build_model", "run_compare", "run_diagnose"]


def run_compare(scene, measured: str | Path, workers: int | None = None) -> dict:
    """Model vs measurement: the full result (arrays included) with ``summary`` (the contract's JSON)."""
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
                             seconds={"model": t1 - t0, "compare": time.perf_counter() - t1})
    result["_residuals"], result["_model"] = res, model
    return result


def run_diagnose(scene, measured: str | Path, workers: int | None = None, progress=None) -> dict:
    """compare + every absent effect fitted and ranked: ``{"baseline", "candidates", "verdict", ...}``."""
    cmp = run_compare(scene, measured, workers=workers)
    t0 = time.perf_counter()
    truth = cmp["_model"].setup.truth
    cands, problems = candidates(cmp["_residuals"], set(scene.effects), progress=progress, truth=truth)
    cands = rank(cands + source_candidates(cmp["_residuals"], truth, scene))
    out = {"baseline": cmp["summary"], "candidates": [c.to_json() for c in cands], "problems": problems,
           "verdict": verdict(cands), "seconds": time.perf_counter() - t0, "_compare": cmp}
    out["significant"] = [c["effect"] for c in out["candidates"] if c["significant"]]
    return out
