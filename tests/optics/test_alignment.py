"""Alignment from the stars: synthetic star moments from a perturbed design, fitted back."""

import numpy as np
import pytest

from optics import load_design
from optics.alignment import FAMILIES, explain, fit_perturbations, rank_perturbations
from optics.design import with_perturbation
from optics.gradients import spot_moments
from optics.sequential import SequentialTracer

FAST = {"nodes": 8, "n_rays": 1500}


def _stars(mi, design, truth, n=200, seed=1):
    """Measured stars of ``design`` perturbed by ``truth``: moments from an independent ray sample (another
    seed, more rays) plus an isotropic 3 um rms rest (seeing, diffraction), 1 um position noise and 5 %
    moment noise."""
    rng = np.random.default_rng(seed)
    f = design.primary.focal_length_mm
    hu, hv = design.focal_plane.width_mm / 2 * 0.95, design.focal_plane.height_mm / 2 * 0.95
    u, v = rng.uniform(-hu, hu, n), rng.uniform(-hv, hv, n)
    fields = np.degrees(np.arctan(-np.stack([u, v], -1) / f))
    d = with_perturbation(design, **truth) if truth else design
    m = spot_moments(SequentialTracer(d, mi), fields, n_rays=3000, seed=5)
    rest = 3e-3 ** 2
    sm = 0.05 * (m.get("muu_mm2") + m.get("mvv_mm2")) / 2 + 0.05 * rest
    sp = 1e-3
    meas = {"cu_mm": m.get("cu_mm") + rng.normal(0, sp, n), "cv_mm": m.get("cv_mm") + rng.normal(0, sp, n),
            "muu_mm2": m.get("muu_mm2") + rest + rng.normal(0, 1, n) * sm,
            "mvv_mm2": m.get("mvv_mm2") + rest + rng.normal(0, 1, n) * sm,
            "muv_mm2": m.get("muv_mm2") + rng.normal(0, 1, n) * sm}
    sigma = {"cu_mm": sp, "cv_mm": sp, "muu_mm2": sm, "mvv_mm2": sm, "muv_mm2": sm}
    return fields, meas, sigma


def _recovered(value, error, truth):
    return abs(value - truth) <= max(0.2 * abs(truth), 2 * error)


def test_diagonal_tilt_is_recovered_by_the_joint_fit(mi):
    art = load_design("art")
    fields, meas, sigma = _stars(mi, art, {"diagonal_tilt_x_deg": 0.1})
    fit = fit_perturbations(art, mi, fields, meas, sigma, **FAST)
    i = fit.names.index("diagonal_tilt_x_deg")
    assert _recovered(fit.values[i], fit.errors[i], 0.1), (fit.values, fit.errors)
    assert int(np.argmax(fit.significance)) == i
    assert fit.explanation.startswith("diagonal tilted +0.") and "about x: coma" in fit.explanation
    assert fit.nuisances["extra_moment_mm2"] == pytest.approx(3e-3 ** 2, rel=0.3)


def test_nominal_stars_give_no_significant_perturbation(mi):
    art = load_design("art")
    fields, meas, sigma = _stars(mi, art, {})
    fit = fit_perturbations(art, mi, fields, meas, sigma, **FAST)
    assert np.all(fit.significance < 3.0), dict(zip(fit.names, fit.significance))
    assert fit.explanation.startswith("no significant misalignment")
    cands, _ = rank_perturbations(art, mi, fields, meas, sigma, families=["defocus", "diagonal_tilt", "sensor_tilt"],
                                  **FAST)
    assert all(c.p_value > 1e-4 for c in cands)


@pytest.mark.slow
@pytest.mark.parametrize("truth", [{"sensor_piston_um": 40.0}, {"sensor_piston_um": -25.0},
                                   {"diagonal_tilt_x_deg": 0.1}, {"diagonal_tilt_y_deg": 0.05},
                                   {"sensor_tilt_y_deg": 0.2}, {"sensor_tilt_x_deg": -0.1},
                                   {"primary_decenter_x_mm": 1.0}, {"primary_tilt_x_deg": 0.05}])
def test_the_right_family_is_named_first_and_its_value_recovered(mi, truth):
    art = load_design("art")
    fields, meas, sigma = _stars(mi, art, truth)
    cands, _ = rank_perturbations(art, mi, fields, meas, sigma)
    (name, value), = truth.items()
    best = cands[0]
    assert name in FAMILIES[best.family], [(c.family, c.delta_chi2) for c in cands[:3]]
    assert best.p_value < 1e-4
    i = best.fit.names.index(name)
    assert _recovered(best.fit.values[i], best.fit.errors[i], value)


def test_explanations_use_optical_words():
    assert explain("sensor_piston_um", 40.0, 3.0).startswith("sensor 40 +- 3 um beyond focus")
    assert "inside focus" in explain("sensor_piston_um", -40.0, 3.0)
    assert explain("diagonal_tilt_x_deg", 0.12, 0.02).startswith("diagonal tilted +0.12 +- 0.02 deg about x: coma")
