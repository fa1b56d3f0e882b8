"""Write your own detector effect in a few dozen lines, without editing newtsim.

The effect below is *charge persistence* ("residual image"): a fraction of the charge a pixel held in the
previous frame is released during this one, decaying exponentially (Smith et al. 2008, SPIE 7021, for
HgCdTe; also seen in deep-depletion CCDs). Here the previous frame is a user-given image of electrons.

Register it with ``@register_effect`` (in code), or from an installed package through the entry-point group
``newtsim.effects`` in its pyproject.toml::

    [project.entry-points."newtsim.effects"]
    persistence = "mypackage.effects:Persistence"

then switch it on from any scene with ``[effects.persistence]``.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from detector import Detector, Effect, EffectParams, Stage, build_effects, make_sensor, register_effect


def persistence_e(previous_e: np.ndarray, fraction: float, tau_s: float, exptime_s: float) -> np.ndarray:
    """Electrons released during an exposure of ``t`` [s] by a trapped charge ``f Q`` decaying with time
    constant ``tau`` [s]: ``f Q (1 - exp(-t / tau))``."""
    return previous_e * fraction * (1.0 - np.exp(-exptime_s / tau_s))


class PersistenceParams(EffectParams):
    fraction: float = Field(1e-3, ge=0, le=1, description="trapped fraction of the previous charge [1]")
    tau_s: float = Field(30.0, gt=0, description="release time constant [s]")
    level_e: float = Field(50000.0, ge=0, description="charge of the previous frame's bright pixels [e-]")
    box: list[int] = Field([100, 140, 100, 140], description="row0, row1, col0, col1 of the previous bright area")


@register_effect
class Persistence(Effect):
    """Residual image of the previous frame: f Q (1 - exp(-t/tau)) electrons added to the mean."""

    name = "persistence"
    stages = (Stage.DARK,)
    Params = PersistenceParams

    def apply(self, stage, tile, data):
        p = self.params
        ys, xs = tile.pixel_centres()
        rows = (ys >= p.box[0]) & (ys < p.box[1])
        cols = (xs >= p.box[2]) & (xs < p.box[3])
        prev = np.outer(rows, cols) * p.level_e
        data += persistence_e(prev, p.fraction, p.tau_s, tile.exptime_s).astype(np.float32)


if __name__ == "__main__":
    s = make_sensor("ml11002", {"width": 256, "height": 256, "x0": 0, "y0": 0})
    det = Detector(s, build_effects({"persistence": {"fraction": 0.002}}, s))
    frame = det.expose(0.0, exptime_s=30.0, frame_seed=1, noiseless=True)
    print(f"residual in the old bright box: {frame[120, 120]:.1f} e- "
          f"(expected {50000 * 0.002 * (1 - np.exp(-1)) + 0.05 * 30:.1f}); elsewhere {frame[10, 10]:.2f} e-")
