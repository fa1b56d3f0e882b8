"""The ART pupil's diffraction PSF against POPPY: encircled energy at 450, 650 and 850 nm, and the spikes.

The reference (``tests/data/peers/poppy/``) was computed by POPPY itself with the script beside it (its own
environment; POPPY is not needed here), from the pupil of ``optics/designs/art.toml``: the 400 mm primary,
the diagonal's holder (102.5 mm radius, 19 mm off centre) and four 2 mm spider vanes. newtsim computes the
PSF of the same design with a perfect primary (the corrector disabled, the detector at the paraboloid's
focus), so both see the pupil's own diffraction only. POPPY's ``exit`` pupil is that screen as the
paraboloid's converging beam presents it to the focus (in direction cosines, with the energy of each ray
tube), which newtsim's Debye integral over the traced rays sees; its ``flat`` pupil is the textbook flat
screen behind a thin lens, which differs from a paraboloid by design (docs/validation.md)."""

import json
from pathlib import Path

import numpy as np
import pytest

from optics import load_design
from optics.design import Design
from optics.psf import compute_psf
from optics.sequential import SequentialTracer

HERE = Path(__file__).parents[1] / "data" / "peers" / "poppy"
WAVELENGTHS = (450, 650, 850)


def spike_fraction(img, r_in=8.0, r_out=40.0, half_width=1):
    """Energy in the spikes of a centred image of 1 um pixels: the pixels within 1 px of the u or v axis at
    8-40 um, less as many along the diagonals (the round halo) (the reference script's definition)."""
    n = img.shape[0]
    c = (n - 1) // 2
    y, x = np.mgrid[0:n, 0:n] - c
    r = np.hypot(x, y)
    ring = (r >= r_in) & (r <= r_out)
    axes = ring & ((np.abs(x) <= half_width) | (np.abs(y) <= half_width))
    diag = ring & ((np.abs(x - y) <= half_width) | (np.abs(x + y) <= half_width))
    return float(img[axes].sum() - img[diag].sum() * axes.sum() / diag.sum())


@pytest.fixture(scope="module")
def reference():
    return json.loads((HERE / "psf.json").read_text()), np.load(HERE / "psf.npz")


@pytest.fixture(scope="module")
def psfs(mi, reference):
    """newtsim's PSFs of the perfect-primary ART at the reference's pixels (1 um, 81 x 81; 8 x 8 internal
    samples per pixel for the encircled energy)."""
    meta, _ = reference
    data = load_design("art").model_dump()
    data["corrector"]["enabled"] = False
    data["focal_plane"]["defocus_mm"] = 0.0
    tracer = SequentialTracer(Design.model_validate(data), mi)
    return {lam: compute_psf(tracer, (0.0, 0.0), [float(lam)], sampling_um=meta["pixel_um"],
                             size_px=meta["size_px"], n_pupil=512, oversample=8) for lam in WAVELENGTHS}


def test_reference_records_the_peer_pupil_and_command(reference):
    meta, arrays = reference
    assert meta["peer"] == "POPPY" and meta["version"] and "make_psf_reference.py" in meta["command"]
    design = load_design("art")
    p = meta["pupil"]
    assert p["radius_mm"] == design.primary.diameter_mm / 2
    assert p["obstruction_radius_mm"] == pytest.approx(design.secondary.minor_axis_mm / 2)
    assert p["vane_width_mm"] == design.spider.width_mm
    for lam in WAVELENGTHS:
        for kind in ("flat", "exit"):
            ee = arrays[f"{kind}_ee_{lam}"]
            assert np.all(np.diff(ee) >= -1e-9) and 0.95 < ee[-1] < 1.0


def test_newtsims_traced_pupil_is_the_peers_pupil(mi, reference):
    """The pupil POPPY was given (from the design file) is the one newtsim's tracer stops rays with."""
    meta, _ = reference
    data = load_design("art").model_dump()
    data["corrector"]["enabled"] = False
    data["focal_plane"]["defocus_mm"] = 0.0
    tracer = SequentialTracer(Design.model_validate(data), mi)
    p = meta["pupil"]
    c = (np.arange(800) + 0.5) / 800 * 2 - 1
    X, Y = (a.ravel() * p["radius_mm"] for a in np.meshgrid(c, c))
    clear = (np.hypot(X, Y) <= p["radius_mm"]) & (np.hypot(X - p["obstruction_centre_x_mm"], Y)
                                                  > p["obstruction_radius_mm"])
    hw = p["vane_width_mm"] / 2
    for along, across in ((X, Y), (-X, Y), (Y, X), (-Y, X)):
        clear &= ~((along >= p["vane_from_mm"]) & (np.abs(across) <= hw))
    assert np.array_equal(tracer.trace((0.0, 0.0), X, Y, 650.0).ok, clear)


@pytest.mark.parametrize("lam", WAVELENGTHS)
def test_encircled_energy_within_1_percent_of_poppy(psfs, reference, lam):
    _, arrays = reference
    r = arrays["ee_radius_um"]
    ours = np.interp(r, psfs[lam].ee_radius_um, psfs[lam].ee)
    peer = arrays[f"exit_ee_{lam}"]
    sel = r >= 0.5
    err = np.abs(ours - peer)[sel]
    assert err.max() < 0.01, f"{lam} nm: |EE - EE_POPPY| up to {err.max():.4f} at r = {r[sel][err.argmax()]} um"
    halo = r >= 5.0
    assert np.max(np.abs(ours / peer - 1)[halo]) < 0.01
    # against the textbook flat screen: the same halo (the paraboloid's 1 % pupil distortion shows in the core)
    flat = arrays[f"flat_ee_{lam}"]
    assert np.max(np.abs(ours / flat - 1)[halo]) < 0.01
    assert np.max(np.abs(ours - flat)[sel]) < 0.03


@pytest.mark.parametrize("lam", WAVELENGTHS)
def test_spikes_lie_along_the_vanes_with_a_known_excess(psfs, reference, lam):
    """The spider's spikes: along u and v, their energy 1.1-1.5x POPPY's (docs/validation.md: newtsim's pupil
    is sampled as a binary 512-point grid of directions, so the 2 mm vanes and the circles' edges are
    staircases whose diffraction also runs along the grid's axes, which are the vanes' axes)."""
    _, arrays = reference
    res = psfs[lam]
    img = res.image * res.energy_in_stamp
    ratio = spike_fraction(img) / spike_fraction(arrays[f"exit_image_{lam}"])
    assert 1.1 < ratio < 1.5, ratio
    # both the u and the v spikes: the energy along each axis alone, as a share of POPPY's, agrees within 35 %
    n = img.shape[0]
    y, x = np.mgrid[0:n, 0:n] - n // 2
    ring = (np.hypot(x, y) >= 8) & (np.hypot(x, y) <= 40)
    for strip in (np.abs(y) <= 1, np.abs(x) <= 1):
        ours, peer = img[ring & strip].sum(), arrays[f"exit_image_{lam}"][ring & strip].sum()
        assert abs(ours / peer - 1) < 0.35, (lam, ours, peer)
