"""Band-by-band characterisation (issue 12): the pieces of detector.calbands against whole-array references, and
characterize / camera_twin giving the same numbers whatever the band height.

Independent references: ``detector.stats.subsample`` on the whole array, ``astropy.io.fits.getdata``,
``scipy.ndimage.gaussian_filter`` on the whole image, and the one-band run of the same analysis.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from astropy.io import fits
from scipy import ndimage

from detector.calbands import BandStore, FitsRows, Gather, Sampler, bands, halo_rows
from detector.characterize import camera_twin, characterize, prnu_and_vignetting, write_twin
from detector.stats import subsample


@pytest.mark.parametrize("shape,max_n,region,rows", [
    ((37, 53), 100, None, 5), ((37, 53), 10_000, None, 7), ((64, 48), 97, (3, 50, 5, 40), 6),
    ((64, 48), 50, (0, 64, 0, 48), 64), ((40, 41), 13, (10, 11, 0, 41), 3)])
def test_sampler_reproduces_subsample(shape, max_n, region, rows):
    a = np.arange(shape[0] * shape[1], dtype=np.float64).reshape(shape) * 1.5
    ref = subsample(a if region is None else a[region[0]:region[1], region[2]:region[3]], max_n)
    s = Sampler(shape, max_n, region=region)
    g = Gather()
    for r0, r1 in bands(shape, rows):
        band = a[r0:r1]
        g.add("x", s.take(r0, band))
        g.add("y", s.take(r0, band[:, ::-1][:, ::-1]))  # a non-contiguous view: the indexing path
    assert np.array_equal(g.get("x"), ref) and np.array_equal(g.get("y"), ref)


def test_fits_rows_and_band_store(tmp_path):
    rng = np.random.default_rng(0)
    u16 = rng.integers(0, 65535, (50, 30)).astype(np.uint16)
    f32 = rng.normal(0, 1, (1, 50, 30)).astype(np.float32)  # a singleton axis
    fits.writeto(tmp_path / "u.fits", u16)
    fits.writeto(tmp_path / "f.fits", f32)
    for name, ref in (("u.fits", u16), ("f.fits", f32[0])):
        r = FitsRows(tmp_path / name)
        assert r.shape == ref.shape
        got = np.concatenate([r.rows(a, b) for a, b in bands(r.shape, 16)])
        r.close()
        assert got.dtype == ref.dtype and np.array_equal(got, ref)
    st = BandStore((50, 30), np.float32)
    for a, b in bands((50, 30), 7):
        st.write(a, f32[0, a:b])
    assert np.array_equal(np.asarray(st), f32[0]) and np.array_equal(st.rows(45, 60), f32[0, 45:])
    st.close()


def test_banded_smoothing_is_the_whole_frame_filter():
    rng = np.random.default_rng(2)
    img = 1000 + rng.normal(0, 10, (300, 90))
    img[40, 7] = 1e5  # an outlier the cleaning replaces
    whole = prnu_and_vignetting(img, 4.0, smooth_px=3.0)
    from detector.characterize import _Bands

    banded = prnu_and_vignetting(img, 4.0, smooth_px=3.0, B=_Bands(img.shape, band_pixels=16 * 90))
    assert banded == whole
    assert halo_rows(3.0) == 12 and halo_rows(16.0) == 64  # scipy's radius int(4 sigma + 0.5)
    # and the filter itself: band + halo equals the whole image's filter on the band
    sm = ndimage.gaussian_filter(img, 3.0, mode="nearest")
    a, b, h = 100, 140, halo_rows(3.0)
    assert np.array_equal(ndimage.gaussian_filter(img[a - h:b + h], 3.0, mode="nearest")[h:-h], sm[a:b])


@pytest.fixture(scope="module")
def calset(tmp_path_factory):
    """2 biases, darks at 10/30/90 s, 2 flats of a 96 x 80 camera with column offsets, hot pixels and PRNU."""
    d = tmp_path_factory.mktemp("cal")
    rng = np.random.default_rng(11)
    h, w, g, read = 96, 80, 2.0, 4.0
    bias = 800 + rng.normal(0, 2, w)[None, :] + np.zeros((h, 1))
    rate = 0.5 * (1 + 0.2 * rng.standard_normal((h, w)))
    hot = rng.random((h, w)) < 0.01
    rate[hot] = rng.uniform(5, 60, hot.sum())
    prnu = 1 + 0.01 * rng.standard_normal((h, w))

    def frame(name, t, light=0.0):
        e = rng.poisson(rate * t * g + light * prnu * g) / g
        x = np.clip(np.round(bias + e + rng.normal(0, read, (h, w))), 0, 65535).astype(np.uint16)
        hd = fits.Header()
        hd["EXPTIME"] = t
        fits.writeto(d / name, x, hd)
        return str(d / name)

    b = [frame(f"b{k}.fits", 0.0) for k in range(2)]
    dk = [frame(f"d{t}.fits", float(t)) for t in (10, 30, 90)]
    fl = [frame(f"f{k}.fits", 1.0, 8000.0) for k in range(2)]
    return b, dk, fl, d


def _close(a, b, path=""):
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            if k != "band_rows":
                _close(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, rel=1e-9, abs=1e-12), path
    else:
        assert a == b, path


def test_characterize_does_not_depend_on_the_bands(calset, tmp_path):
    b, dk, fl, _ = calset
    one = characterize(b, dk, fl)
    many = characterize(b, dk, fl, band_pixels=16 * 80)  # 16-row bands: 6 of them
    assert one["frame"]["band_rows"] == 96 and many["frame"]["band_rows"] == 16
    _close(one, many)
    m1, i1 = camera_twin(one, b, dk, fl)
    calls = []
    m2, i2 = camera_twin(many, b, dk, fl, band_pixels=16 * 80, progress=lambda *a: calls.append(a))
    _close(i1, i2)
    assert calls and all(c[2] == 6 for c in calls)  # progress: 6 bands per pass
    for k in ("bias_adu", "dark_rate_e_per_s", "dark_rate_se_e_per_s", "flat", "flat_se", "vignetting"):
        x, y = np.asarray(m1[k]), np.asarray(m2[k])
        assert x.dtype == np.float32 and np.allclose(x, y, rtol=1e-6, atol=0), k
    for k in ("x", "y", "rate_e_per_s"):
        assert np.array_equal(m1["defects"][k], m2["defects"][k]), k
    # the FITS maps written band by band read back as the maps
    write_twin(tmp_path / "cam.toml", many, m2, i2)
    with fits.open(tmp_path / "cam_dark.fits") as hd:
        assert np.array_equal(hd[0].data, np.asarray(m2["dark_rate_e_per_s"]))
        assert np.array_equal(hd["SIGMA"].data, np.asarray(m2["dark_rate_se_e_per_s"]))
    with fits.open(tmp_path / "cam_flat.fits") as hd:
        assert np.array_equal(hd["VIGNETTING"].data, np.asarray(m2["vignetting"]))


def test_out_of_memory_is_one_line(calset, monkeypatch, capsys):
    import detector.characterize as ch
    from scenes.app.cli import main

    b, dk, _, _ = calset

    def boom(*a, **k):
        raise MemoryError("Unable to allocate 1.12 GiB")

    monkeypatch.setattr(ch, "_first_pass", boom)
    with pytest.raises(SystemExit) as e:
        main(["characterize", "--bias", *b, "--dark", *dk])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "out of memory" in err[0] and "Traceback" not in err[0]
