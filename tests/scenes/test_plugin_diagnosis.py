"""A user's own effect (examples/custom_effect.py) is diagnosed like the catalogue's: named first, its
parameter recovered, and the error falls once it is added to the scene."""

import runpy
from pathlib import Path

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "custom_effect.py"


def test_diagnosis_picks_up_a_user_plugin_and_the_error_falls(tmp_path):
    ns = runpy.run_path(str(EXAMPLE))
    before, after, best = ns["diagnosis_demo"](str(tmp_path))
    assert best["effect"] == "residual_image" and best["significant"]
    assert abs(best["params"]["fraction"] / 0.003 - 1) < 0.05
    assert before > 1.5
    assert after - 1 < 0.1 * (before - 1)
