"""FITS writing: streamed, atomic, readable by astropy; damaged files are refused with their name."""

import os

import numpy as np
import pytest
from astropy.io import fits

from detector import Detector, DetectorError, make_sensor
from detector.fits_io import (
    primary_header,
    read_image,
    table_hdu,
    write_image,
    write_streamed,
)


def test_uint16_round_trip_with_extensions(tmp_path):
    img = np.array([[0, 1, 32767], [32768, 65534, 65535]], dtype=np.uint16)
    t = np.zeros(2, dtype=[("x", "i4"), ("kind", "S4")])
    t["x"], t["kind"] = [3, 4], [b"hot", b"warm"]
    p = write_image(tmp_path / "a.fits", img, {"GAIN": (1.5, "[e-/ADU]")}, [table_hdu("HOTPIX", t)])
    with fits.open(p) as h:
        assert h[0].data.dtype == np.uint16 and (h[0].data == img).all()
        assert h[0].header["GAIN"] == 1.5 and h["HOTPIX"].data["kind"][1] == "warm"
    f32 = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    with fits.open(write_image(tmp_path / "b.fits", f32)) as h:
        np.testing.assert_array_equal(h[0].data, f32)


def test_streamed_frame_equals_in_memory_frame(tmp_path):
    s = make_sensor("ml11002", {"width": 600, "height": 500})
    det = Detector(s)
    mem = det.expose(50.0, 2.0, frame_seed=4)
    hdr = primary_header(s.output_shape, np.uint16)
    write_streamed(tmp_path / "s.fits", hdr, det.iter_frame(50.0, 2.0, 4), s.output_shape, np.uint16)
    with fits.open(tmp_path / "s.fits") as h:
        np.testing.assert_array_equal(h[0].data, mem)


def test_failure_mid_frame_leaves_nothing_behind(tmp_path):
    s = make_sensor("ml11002", {"width": 200, "height": 960})
    sig = np.full(s.shape, 5.0, dtype=np.float32)
    sig[900, 3] = np.nan  # in the last band: earlier bands are already on disk when it fails
    hdr = primary_header(s.output_shape, np.uint16)
    with pytest.raises(DetectorError):
        write_streamed(tmp_path / "x.fits", hdr, Detector(s).iter_frame(sig, 1.0, 1), s.output_shape, np.uint16)
    assert os.listdir(tmp_path) == []


def test_damaged_files_are_named(tmp_path):
    p = write_image(tmp_path / "ok.fits", np.ones((100, 100), dtype=np.float32))
    raw = p.read_bytes()
    (tmp_path / "trunc.fits").write_bytes(raw[: len(raw) // 2])
    (tmp_path / "junk.fits").write_bytes(b"not a fits file at all" * 200)
    for name in ("trunc.fits", "junk.fits", "missing.fits"):
        with pytest.raises(DetectorError, match=name):
            read_image(tmp_path / name)
    data, hdr = read_image(p)
    assert data.shape == (100, 100)
