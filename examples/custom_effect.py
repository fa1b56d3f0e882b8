"""Write your own detector effect in a few dozen lines, without editing newtsim.

The effect below is *charge persistence* ("residual image"): a fraction of the charge a pixel held in the
previous frame is released during this one, decaying exponentially (Smith et al. 2008, SPIE 7021, for
HgCdTe; also seen in deep-depletion CCDs). Here the previous frame is a user-given image of electrons.

Register it with ``@register_effect`` (in code), or from an installed package through the entry-point group
``newtsim.effects`` in its pyproject.toml::

    [project.entry-points."newtsim.effects"]
    residual_image = "mypackage.effects:Persistence"

then switch it on from any scene with ``[effects.residual_image]``.

A ``signature`` tells ``newtsim diagnose`` how the effect shows in the residuals of a measured frame: here
a linear template (the released charge per unit trapped fraction), so the diagnosis can fit ``fraction``
by weighted least squares and rank the effect against the catalogue by delta BIC. Run this file to see
the diagnosis find the effect in a frame that has it and the error fall once it is added::

    python examples/custom_effect.py
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from detector import (
    Detector,
    Effect,
    EffectParams,
    Stage,
    build_effects,
    make_sensor,
    register_effect,
)
from detector.signatures import LinearSignature, Variant


def persistence_e(previous_e: np.ndarray, fraction: float, tau_s: float, exptime_s: float) -> np.ndarray:
    """Electrons released during an exposure of ``t`` [s] by a trapped charge ``f Q`` decaying with time
    constant ``tau`` [s]: ``f Q (1 - exp(-t / tau))``."""
    return previous_e * fraction * (1.0 - np.exp(-exptime_s / tau_s))


class PersistenceParams(EffectParams):
    fraction: float = Field(1e-3, ge=0, le=1, description="trapped fraction of the previous charge [1]")
    tau_s: float = Field(30.0, gt=0, description="release time constant [s]")
    level_e: float = Field(50000.0, ge=0, description="charge of the previous frame's bright pixels [e-]")
    box: list[int] = Field([100, 140, 100, 140], description="row0, row1, col0, col1 of the previous bright area")


def _box(p, ys, xs) -> np.ndarray:
    rows = (ys >= p.box[0]) & (ys < p.box[1])
    cols = (xs >= p.box[2]) & (xs < p.box[3])
    return np.outer(rows, cols).astype(np.float32)


def _persistence_variants(res):
    """Template: ADU released per unit trapped fraction, for the default box, level and time constant."""
    p = PersistenceParams()
    t = _box(p, res.ys, res.xs) * np.float32(persistence_e(p.level_e, 1.0, p.tau_s, res.exptime_s)
                                             * res.pixel_sum / res.gain)
    if t.any():
        yield Variant([t], lambda c: {"fraction": float(c[0])} if 0 < c[0] <= 1 else None)


@register_effect
class Persistence(Effect):
    """Residual image of the previous frame: f Q (1 - exp(-t/tau)) electrons added to the mean."""

    name = "residual_image"
    stages = (Stage.DARK,)
    Params = PersistenceParams
    signature = LinearSignature(
        _persistence_variants, extra_k=0, pattern="a faint copy of the previous frame's bright area",
        explain=lambda p, res: f"excess charge in the previous frame's bright area, {p['fraction']:.2g} of it: "
                               "persistence")

    def apply(self, stage, tile, data):
        p = self.params
        prev = _box(p, *tile.pixel_centres()) * np.float32(p.level_e)
        data += persistence_e(prev, p.fraction, p.tau_s, tile.exptime_s).astype(np.float32)


def diagnosis_demo(folder: str) -> tuple[float, float, dict]:
    """Measured frame with persistence, a scene without: diagnose, apply, compare again.

    Returns (chi2/dof before, chi2/dof after, best candidate)."""
    from pathlib import Path

    import tomli_w

    from scenes.app.compare import run_compare, run_diagnose
    from scenes.app.compare.apply import apply_candidate
    from scenes.app.render import render
    from scenes.scene import load_scene

    d = Path(folder)
    base = {"detector": {"preset": "ml11002", "width": 256, "height": 256, "x0": 0, "y0": 0},
            "exposure": {"time_s": 30.0, "frame": "dark"}}
    (d / "model.toml").write_text(tomli_w.dumps(base))
    (d / "truth.toml").write_text(tomli_w.dumps({**base, "effects": {"residual_image": {"fraction": 0.003}}}))
    render(load_scene(str(d / "truth.toml")), d / "measured.fits", seed=7)
    out = run_diagnose(load_scene(str(d / "model.toml")), d / "measured.fits")
    best = out["candidates"][0]
    apply_candidate(load_scene(str(d / "model.toml")), best, d / "model_round2.toml")
    after = run_compare(load_scene(str(d / "model_round2.toml")), d / "measured.fits")
    return out["baseline"]["chi2_per_dof"], after["summary"]["chi2_per_dof"], best


if __name__ == "__main__":
    import tempfile

    s = make_sensor("ml11002", {"width": 256, "height": 256, "x0": 0, "y0": 0})
    det = Detector(s, build_effects({"residual_image": {"fraction": 0.002}}, s))
    frame = det.expose(0.0, exptime_s=30.0, frame_seed=1, noiseless=True)
    print(f"residual in the old bright box: {frame[120, 120]:.1f} e- "
          f"(expected {50000 * 0.002 * (1 - np.exp(-1)) + 0.05 * 30:.1f}); elsewhere {frame[10, 10]:.2f} e-")
    with tempfile.TemporaryDirectory() as tmp:
        before, after, best = diagnosis_demo(tmp)
    print(f"diagnosis: {best['effect']} first (delta BIC {best['delta_bic']:.4g}, fraction {best['params']['fraction']:.3g}"
          f" vs 0.003 put in): {best['explanation']}")
    print(f"chi2/dof {before:.4g} -> {after:.4g} once the fitted effect is in the scene")
