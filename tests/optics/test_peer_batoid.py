"""Rays through the ART design (field corrector included) and the bare Newtonian against batoid.

The reference (``tests/data/peers/batoid/rays.json``) was traced by batoid itself from the design files,
with the script beside it (its own environment; batoid is not needed here). Same pupil points, field
angles and wavelengths through newtsim's tracer without mechanical obstructions (batoid models none):
every ray must land where batoid's does within 1e-6 um, leave in the same direction, carry the same
optical path and be stopped by the same optical apertures (primary rim, diagonal outline, lens rims,
detector edge)."""

import json
from pathlib import Path

import numpy as np
import pytest

from optics import load_design
from optics.sequential import SequentialTracer

REF = Path(__file__).parents[1] / "data" / "peers" / "batoid" / "rays.json"
TOL_UM = 1e-6


@pytest.fixture(scope="module")
def reference():
    return json.loads(REF.read_text())


def test_reference_records_the_peer_and_its_command(reference):
    assert reference["peer"] == "batoid" and reference["version"]
    assert "make_ray_reference.py" in reference["command"]
    assert set(reference["designs"]) == {"art", "bare"}
    for d in reference["designs"].values():
        assert len(d["cases"]) >= 4 and d["px_mm"][0] == 0.0 and d["py_mm"][0] == 0.0   # chief ray first


@pytest.mark.parametrize("name", ["art", "bare"])
def test_rays_land_where_batoid_puts_them(mi, reference, name):
    d = reference["designs"][name]
    tracer = SequentialTracer(load_design(name), mi, obstruct="none")
    px, py = np.asarray(d["px_mm"]), np.asarray(d["py_mm"])
    fields = {tuple(c["field_deg"]) for c in d["cases"]}
    assert len(fields) == 4
    for c in d["cases"]:
        r = tracer.trace(c["field_deg"], px, py, wavelength_nm=c["wavelength_nm"])
        ok = np.asarray(c["reaches_detector"])
        where = f"{name} field {c['field_deg']} deg, {c['wavelength_nm']} nm"
        assert np.array_equal(r.ok, ok), where
        assert ok[0], f"{where}: the chief ray must reach the detector"
        for key, ours in (("u_mm", r.u), ("v_mm", r.v), ("opl_mm", r.opl)):
            err_um = np.max(np.abs(ours[ok] - np.asarray(c[key])[ok])) * 1e3
            assert err_um < TOL_UM, f"{where}: {key} differs from batoid by {err_um:.3g} um"
        for key, ours in (("du", r.du), ("dv", r.dv), ("dw", r.dw)):
            assert np.max(np.abs(ours[ok] - np.asarray(c[key])[ok])) < 1e-12, (where, key)
