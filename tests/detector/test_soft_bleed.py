"""Blooming's soft form: the spill deposited along the column with a geometric (exponential) profile, the
overflow drained. Charge accounting, the profile against the per-pixel capture law, the logarithmic trail
length after the full-well clip, and the diagnosis picking the soft form over the charge-conserving fill."""

import numpy as np
import pytest

from detector.effects.blooming import bleed_columns, soft_bleed_columns


@pytest.mark.parametrize("length,up", [(1.0, 0.5), (4.0, 0.7), (2.5, 0.0)])
def test_the_soft_bleed_keeps_the_charge_and_deposits_the_geometric_law(length, up):
    """Every pixel the spill reaches keeps 1 - q of what arrives (q = exp(-1 / L)): the k-th pixel up holds
    up (1 - q) q^(k - 1) of the excess (renormalised over the 8 L kept), down likewise with 1 - up; the
    charge before is the charge after plus what left the image (nothing here), and the other columns stay."""
    img = np.zeros((201, 3))
    img[100, 1] = 11_000.0
    lost = soft_bleed_columns(img, 1000.0, length, up)
    assert lost == pytest.approx(0.0, abs=1e-6) and img.sum() == pytest.approx(11_000.0)
    assert img[100, 1] == pytest.approx(1000.0) and not img[:, [0, 2]].any()
    q = np.exp(-1 / length)
    k = np.arange(1, int(np.ceil(8 * length)) + 1)
    law = (1 - q) * q ** (k - 1)
    law /= law.sum()
    assert np.allclose(img[100 + k, 1], up * 10_000.0 * law, rtol=1e-9, atol=1e-9)
    assert np.allclose(img[100 - k, 1], (1 - up) * 10_000.0 * law, rtol=1e-9, atol=1e-9)
    # the mean distance of the upward deposit: 1 / (1 - q) for the untruncated law, 3e-3 L off at 8 L
    if up:
        mean = float(np.sum(k * img[100 + k, 1]) / np.sum(img[100 + k, 1]))
        assert mean == pytest.approx(1 / (1 - q), rel=5e-3)


def test_the_soft_trail_grows_with_the_logarithm_of_the_excess_after_the_clip():
    """Clipped at the full well (the overflow drain), the pixel k up is full while up E (1 - q) q^(k-1) >= FW:
    n = 1 + floor(ln(up E (1 - q) / FW) / ln(1 / q)) full pixels, i.e. L ln(E) + const; the charge-conserving
    fill makes up E / FW of them instead."""
    fw, length, up = 1000.0, 3.0, 1.0
    q = np.exp(-1 / length)
    for excess in (2e4, 2e5, 1.5e6):
        img = np.zeros((2001, 1))
        img[200, 0] = fw + excess
        soft_bleed_columns(img, fw, length, up)
        n_full = int(np.count_nonzero(np.minimum(img[201:, 0], fw) >= fw * (1 - 1e-9)))
        norm = 1 - q ** np.ceil(8 * length)  # the kept law's sum before renormalising
        expect = 1 + int(np.floor(np.log(up * excess * (1 - q) / norm / fw) / np.log(1 / q)))
        assert n_full == expect, (excess, n_full, expect)
        fill = np.zeros((2001, 1))
        fill[200, 0] = fw + excess
        bleed_columns(fill, fw, up)
        assert np.count_nonzero(fill[201:, 0] >= fw) == int(excess // fw)


def test_the_soft_bleed_is_the_effect_with_a_length_and_the_fill_without():
    from helpers import small_sensor

    from detector import Detector, build_effects

    s = small_sensor("ml11002", x0=0, y0=0, full_well_e=20000.0, read_noise_e=0.0, dark_current_e_per_s=0.0)
    sig = np.zeros(s.shape, dtype=np.float32)
    sig[300, 300] = 20000.0 * 41
    soft = Detector(s, build_effects({"blooming": {"length_px": 3.0, "up_fraction": 1.0}}, s)).expose(
        sig, 1.0, 1, noiseless=True)
    assert soft.sum() == pytest.approx(sig.sum(), rel=1e-6)  # the mean charge, before the full-well clip
    soft = np.minimum(soft, 20000.0)  # the chain's clip (the overflow drain), which the noiseless mean leaves out
    fill = Detector(s, build_effects({"blooming": {"up_fraction": 1.0}}, s)).expose(sig, 1.0, 1, noiseless=True)
    assert (fill[300:341, 300] == 20000.0).all()  # 40 full-well pixels of excess: a 40 px trail
    # soft: 40 FW of excess, (1 - q) of it in the first pixel: full pixels while 40 (1 - q) q^(k-1) >= 1
    q = np.exp(-1 / 3.0)
    n = 1 + int(np.floor(np.log(40 * (1 - q) / (1 - q ** 24)) / np.log(1 / q)))
    assert np.count_nonzero(soft[301:, 300] >= 20000.0) == n and soft.sum() < sig.sum()
    assert not soft[:300, 300].any()


def test_the_diagnosis_finds_the_soft_form_and_its_profile(tmp_path):
    """A 30 s star field whose saturated stars bleed softly (4 px profile, 75 % up): the blooming candidate
    is the soft form with the length and share of the truth (on the diagnosis's grid), and the best fill
    form (whose trail is as long as the excess) leaves far more chi2."""
    from helpers import star_field_toml

    from detector.effects.base import registry
    from scenes.app.compare import run_compare
    from scenes.app.render import render
    from scenes.scene import load_scene

    base = star_field_toml(256).replace("time_s = 10.0", "time_s = 30.0")
    (tmp_path / "model.toml").write_text(base)
    (tmp_path / "truth.toml").write_text(base + "[effects.blooming]\nlength_px = 4.0\nup_fraction = 0.75\n")
    render(load_scene(str(tmp_path / "truth.toml")), tmp_path / "m.fits", seed=3)
    res = run_compare(load_scene(str(tmp_path / "model.toml")), tmp_path / "m.fits")["_residuals"]
    fit = registry()["blooming"].signature.fit(res, "blooming")
    assert fit is not None and fit.delta_bic < -1000, fit
    assert fit.params["length_px"] == 4.0 and fit.params["up_fraction"] == 0.75, fit.params
    assert fit.note.startswith("soft")
    from detector.effects.blooming import _blooming_variants
    from detector.signatures import fit_variant, search_sample

    ctx = search_sample(res)
    d = {v.label: fit_variant(res, v, ctx["idx"], ctx["r"], ctx["w"])[1] for v in _blooming_variants(res)}
    soft = min(v for k, v in d.items() if k.startswith("soft"))
    fill = min(v for k, v in d.items() if not k.startswith("soft"))
    assert soft < fill - 1e5, (fill, soft)  # the soft form removes far more chi2 than the best fill
