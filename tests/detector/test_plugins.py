"""User effects: registered in code or through the ``newtsim.effects`` entry points, used from scenes."""

import runpy
from pathlib import Path

import numpy as np

from detector import Detector, build_effects, make_sensor, registry
from detector.effects import base

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "custom_effect.py"


def test_example_plugin_registers_and_follows_its_law():
    ns = runpy.run_path(str(EXAMPLE))
    assert "residual_image" in registry()
    s = make_sensor("ml11002", {"width": 256, "height": 256, "x0": 0, "y0": 0, "dark_current_e_per_s": 0.0})
    det = Detector(s, build_effects({"residual_image": {"fraction": 0.01, "tau_s": 10.0}}, s))
    m = det.expose(0.0, 20.0, 1, noiseless=True)
    assert np.isclose(m[120, 120], ns["persistence_e"](50000.0, 0.01, 10.0, 20.0)) and m[10, 10] == 0


def test_entry_point_effects_are_loaded(monkeypatch):
    class FakeEP:
        name = "ep_effect"

        def load(self):
            class EPEffect(base.Effect):
                """An effect from another package."""
                stages = (base.Stage.DARK,)

                def apply(self, stage, tile, data):
                    data += 1.0
            return EPEffect

    monkeypatch.setattr("importlib.metadata.entry_points", lambda group=None: [FakeEP()])
    reg = registry()
    assert "ep_effect" in reg
    s = make_sensor("ml11002", {"width": 240, "height": 240, "dark_current_e_per_s": 0.0})
    m = Detector(s, build_effects({"ep_effect": {}}, s)).expose(0.0, 1.0, 1, noiseless=True)
    assert (m == 1.0).all()
    base._REGISTRY.pop("ep_effect")


def test_entry_points_scanned_again_only_when_the_install_changes(monkeypatch):
    scans = []

    def fake_entry_points(group=None):
        scans.append(group)
        return []

    monkeypatch.setattr("importlib.metadata.entry_points", fake_entry_points)
    registry()
    registry()
    assert len(scans) == 1  # the same discovery function and import path: the scan is kept
    monkeypatch.setattr(base, "_SCANNED", None)
    registry()
    assert len(scans) == 2
