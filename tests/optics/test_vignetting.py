"""Vignetting maps: two-circle formula, obstruction, symmetry, error bars, FITS round trip."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from optics import load_design
from optics.sequential import SequentialTracer
from optics.vignetting import diagonal_two_circle, read_fits, vignetting_map, write_fits


@pytest.fixture(scope="module")
def bare_map(mi):
    tr = SequentialTracer(load_design("bare"), mi)
    return vignetting_map(tr, grid=5, rays=200_000, seed=1)


def test_on_axis_relative_illumination_is_one_and_throughput_is_the_obstruction(bare_map):
    d = load_design("bare")
    ri = bare_map.relative_illumination
    assert ri[2, 2] == pytest.approx(1.0, abs=3 * bare_map.throughput_err[2, 2] / bare_map.on_axis_throughput)
    D, m, sp = d.primary.diameter_mm, d.secondary.minor_axis_mm, d.spider
    expected = 1 - (m / D) ** 2 - sp.vanes * sp.width_mm * (D - m) / 2 / (math.pi * D * D / 4)
    assert bare_map.on_axis_throughput == pytest.approx(expected, abs=0.002)
    assert bare_map.on_axis_throughput == pytest.approx(d.collecting_area_m2 / (math.pi * (D / 2000) ** 2), abs=0.002)


def test_vignetting_grows_toward_the_corners_and_is_mirror_symmetric_in_v(bare_map):
    ri = bare_map.relative_illumination
    assert ri.min() == ri[[0, 0, -1, -1], [0, -1, 0, -1]].min()          # darkest at a corner
    assert np.all(ri <= 1 + 4 * bare_map.throughput_err.max() / bare_map.on_axis_throughput)
    # the fold is in the x-z plane: +v and -v see the same telescope
    assert np.allclose(ri, ri[::-1, :], atol=4 * bare_map.throughput_err.max() / bare_map.on_axis_throughput)


def test_unobstructed_design_matches_the_diagonal_two_circle_formula(mi):
    """Without obstructions the only loss is the diagonal's outline: RI = two-circle overlap fraction."""
    d = load_design("bare")
    tr = SequentialTracer(d, mi, obstruct="none")
    res = vignetting_map(tr, grid=(1, 5), rays=200_000, seed=2)
    for j, fy in enumerate(res.field_y_deg):
        assert res.throughput[j, 0] == pytest.approx(diagonal_two_circle(d, abs(fy)), abs=0.01)


def test_error_bars_shrink_as_one_over_sqrt_n(mi):
    tr = SequentialTracer(load_design("bare"), mi)
    small = vignetting_map(tr, grid=1, rays=10_000, seed=3)
    large = vignetting_map(tr, grid=1, rays=40_000, seed=3)
    assert small.on_axis_err / large.on_axis_err == pytest.approx(2.0, rel=0.05)
    # and different seeds scatter within a few sigma
    other = vignetting_map(tr, grid=1, rays=40_000, seed=9)
    assert abs(other.on_axis_throughput - large.on_axis_throughput) < 5 * large.on_axis_err


def test_fits_map_round_trips(bare_map, tmp_path):
    path = write_fits(bare_map, tmp_path / "vig.fits", "bare")
    u, v, ri = read_fits(path)
    assert np.allclose(u, bare_map.u_mm) and np.allclose(v, bare_map.v_mm)
    assert np.allclose(ri, bare_map.relative_illumination, atol=1e-6)


def test_json_has_the_contract_keys(bare_map):
    j = bare_map.to_json()
    for key in ("field_x_deg", "field_y_deg", "relative_illumination", "on_axis_throughput"):
        assert key in j
    assert np.asarray(j["relative_illumination"]).shape == (5, 5)


def test_map_agrees_with_the_float64_code_it_replaced(mi):
    """The float32 counting kernel on drjit-made pupil points against maps stored by the float64 code it
    replaced (commit c5d8434: float64 kernel, numpy pupil points, grid 3, 200 000 rays per field, seed 5;
    tests/data/optics/vignetting_float64_reference.json): every field within 5 rays (2.5e-5 in throughput,
    0.03 of the binomial error of 9e-4), the bare Newtonian and the ART design with its corrector."""
    ref = json.loads((Path(__file__).parents[1] / "data" / "optics" / "vignetting_float64_reference.json").read_text())
    n = ref["rays"]
    for name, want in ref["designs"].items():
        res = vignetting_map(SequentialTracer(load_design(name), mi), ref["grid"], n, ref["wavelength_nm"], ref["seed"])
        got = np.rint(res.throughput * n).astype(int)
        assert np.abs(got - np.asarray(want["through"])).max() <= 5, name
        assert abs(round(res.on_axis_throughput * n) - want["through_axis"]) <= 5, name
        assert 5 / n < 0.05 * res.throughput_err.min()


def test_map_in_chunks_of_pupil_points_is_the_same_map(mi, monkeypatch):
    """Pupil points beyond CHUNK are made and traced chunk by chunk (memory bounded for any --rays): the
    chunks continue the same sequence, so the counts are those of one pass."""
    import optics.vignetting as vig

    tr = SequentialTracer(load_design("bare"), mi)
    whole = vignetting_map(tr, 2, 10_000, seed=4)
    monkeypatch.setattr(vig, "CHUNK", 4096)
    chunked = vignetting_map(tr, 2, 10_000, seed=4)
    assert np.array_equal(whole.throughput, chunked.throughput)
    assert whole.loss_fractions == chunked.loss_fractions
