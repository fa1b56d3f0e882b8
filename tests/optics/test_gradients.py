"""Gradients of the spot moments and throughput (drjit forward-mode AD) against central finite differences."""

import numpy as np
import pytest

from optics import load_design
from optics.design import with_perturbation
from optics.gradients import (
    MOMENT_NAMES,
    default_steps,
    detector_field_points,
    finite_difference_jacobian,
    perturbation_names,
    spot_moments,
)
from optics.sequential import SequentialTracer


def _compare(ad, fd, rel=0.01):
    """Every entry of the Jacobian within ``rel`` of the finite difference; entries that vanish by symmetry
    (below 1e-3 of the largest of their moment and parameter over the field) within 1e-3 of that."""
    scale = np.abs(fd).max(axis=0, keepdims=True)                  # per (moment, parameter)
    big = np.abs(fd) > 1e-2 * scale
    err = np.abs(ad - fd)
    bad_rel = big & (err > rel * np.abs(fd))
    bad_abs = ~big & (err > 1e-3 * scale + 1e-15)
    return np.argwhere(bad_rel | bad_abs)


def test_perturbation_gradients_match_finite_differences_bare(mi):
    d = with_perturbation(load_design("bare"), sensor_piston_um=30.0, primary_tilt_x_deg=0.01)
    tr = SequentialTracer(d, mi)
    fields = detector_field_points(d, 3)
    wrt = perturbation_names(d)
    m = spot_moments(tr, fields, wrt, n_rays=1500)
    fd = finite_difference_jacobian(tr, fields, wrt, default_steps(wrt), n_rays=1500)
    bad = _compare(m.jacobian, fd)
    assert len(bad) == 0, [(i, MOMENT_NAMES[j], wrt[k], m.jacobian[i, j, k], fd[i, j, k]) for i, j, k in bad[:5]]
    # the values do not depend on whether a Jacobian was asked for
    assert np.allclose(m.values, spot_moments(tr, fields, n_rays=1500).values, rtol=1e-12, atol=1e-15)
    # throughput derivatives exist (soft edges): a decentred primary loses light at the diagonal's edge
    assert np.abs(m.jacobian[:, MOMENT_NAMES.index("throughput"), wrt.index("primary_tilt_x_deg")]).max() > 1e-3


def test_design_and_corrector_gradients_match_finite_differences_art(mi):
    d = load_design("art")
    tr = SequentialTracer(d, mi)
    fields = np.array([[0.0, 0.0], [1.2, -0.8], [-1.5, 1.0]])
    wrt = ("diagonal_tilt_x_deg", "sensor_tilt_y_deg", "corrector_decenter_x_mm", "corrector_tilt_y_deg",
           "corrector_spacing_mm", "primary.conic", "corrector.back_focus_mm", "corrector.surfaces.0.radius_mm",
           "corrector.surfaces.3.thickness_mm", "corrector.surfaces.6.radius_mm")
    steps = default_steps(wrt, d)
    kw = {"n_rays": 1000, "wavelengths_nm": (500.0, 700.0), "weights": (0.4, 0.6)}
    m = spot_moments(tr, fields, wrt, **kw)
    fd = finite_difference_jacobian(tr, fields, wrt, steps, **kw)
    bad = _compare(m.jacobian, fd)
    assert len(bad) == 0, [(i, MOMENT_NAMES[j], wrt[k], m.jacobian[i, j, k], fd[i, j, k]) for i, j, k in bad[:5]]


def test_moments_agree_with_the_plain_trace(mi):
    """With hard edges far away (on axis, bare) the soft-edged moments equal the numpy moments of
    SequentialTracer.trace on the same pupil points."""
    from optics.sequential import pupil_uniform

    d = with_perturbation(load_design("bare"), sensor_piston_um=200.0)
    tr = SequentialTracer(d, mi)
    m = spot_moments(tr, [[0.0, 0.0]], n_rays=4000, soft_eps_mm=1e-4)
    px, py = pupil_uniform(4000, tr.layout.r_primary, seed=0)
    r = tr.trace((0.0, 0.0), px, py)
    w = r.transmission * r.ok
    cu = np.average(r.u, weights=w)
    assert m.get("cu_mm")[0] == pytest.approx(cu, abs=1e-9)
    assert m.get("muu_mm2")[0] == pytest.approx(np.average((r.u - cu) ** 2, weights=w), rel=1e-6)
    assert m.get("throughput")[0] == pytest.approx(w.sum() / len(px), rel=1e-3)
