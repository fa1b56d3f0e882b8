"""Fixtures of the scenes tests: the one that selects Mitsuba's variant (DESIGN.md convention 6), and a
stand-in for the optics' SIP cache while ``optics.distortion.cached_sip`` is being written."""

import pytest


@pytest.fixture(scope="session")
def mi():
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'newtsim[optics]')")
    from optics.llvm import init_mitsuba

    return init_mitsuba()


@pytest.fixture
def optics_sip(mi, monkeypatch):
    """``optics.distortion.cached_sip`` (design, pitch_um, shape, order) -> the ``fit_sip`` dict: the optics'
    own function when it exists, else a local stand-in that fits the chief rays (9 x 9 field points) without
    the disk cache. Returns the function the scene will call."""
    import optics.distortion as od
    from optics.sequential import SequentialTracer

    if not hasattr(od, "cached_sip"):
        def cached_sip(design, pitch_um: float, shape: tuple, order: int = 5) -> dict:
            return od.fit_sip(SequentialTracer(design, mi), pitch_um, order=order, grid=9, shape=tuple(shape))

        monkeypatch.setattr(od, "cached_sip", cached_sip, raising=False)
    return od.cached_sip


@pytest.fixture
def optics_psf_grid(mi, monkeypatch, tmp_path):
    """``optics.psf.cached_psf_grid`` (design, pitch_um, nx, ny) -> Path of a PSF cube: the optics' own when it
    exists, else a stand-in that traces a geometric grid (rays only, fast; cells of half a pixel) into
    ``tmp_path``. Returns the function the scene will call."""
    import optics.psf as op
    from optics.sequential import SequentialTracer

    if not hasattr(op, "cached_psf_grid"):
        def cached_psf_grid(design, pitch_um: float, nx: int = 3, ny: int = 3):
            path = tmp_path / f"psf-{design.name}-{pitch_um}-{nx}x{ny}.fits"
            if not path.is_file():
                tracer = SequentialTracer(design, mi)
                grid = op.psf_grid(tracer, op.detector_fields(design, nx, ny), geometric=True,
                                   sampling_um=pitch_um / 2, size_px=61, n_rays=20000)
                op.write_psf_fits(grid, path)
            return path

        monkeypatch.setattr(op, "cached_psf_grid", cached_psf_grid, raising=False)
    return op.cached_psf_grid
