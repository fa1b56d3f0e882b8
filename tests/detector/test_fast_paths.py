"""The chain's fast paths give the same numbers as the plain formulas they replace (docs/performance.md:
same seeds, same bytes), and a frame-sized image is built only where an effect needs it."""

import numpy as np

from detector import Detector, build_effects, make_sensor
from detector.chain import SHOT_BLOCK_PIXELS, bin_sum, bin_sum_digital, shot_noise
from detector.effects.base import Stage


def test_digital_binning_sums_equal_the_reshaped_float64_sums():
    """Strided float64 sums of b x b digitised codes (and of non-integer stuck values) equal bin_sum's."""
    rng = np.random.default_rng(3)
    for b in (2, 3, 4):
        a = rng.integers(0, 65536, size=(12 * b, 10 * b)).astype(np.float32)
        a[::7, ::5] = np.float32(1234.567)  # a stuck value off the integer codes
        got = bin_sum_digital(a, b)
        assert got.dtype == np.float64
        assert np.array_equal(got, bin_sum(a.astype(np.float64), b))


def test_blocked_poisson_draw_is_the_single_call_draw():
    """The generator fills in C order: row blocks drawn in turn are the numbers of one call (eq. 31)."""
    mean = np.random.default_rng(1).uniform(0.0, 80.0, size=(240, 600)).astype(np.float32)
    blocked = shot_noise(np.random.default_rng(7), mean)
    whole = np.random.default_rng(7).poisson(mean).astype(np.float32)
    assert mean.size > 2 * SHOT_BLOCK_PIXELS  # several blocks
    assert np.array_equal(blocked, whole)


def _imx411_window(**effects):
    s = make_sensor("imx411", {"width": 1024, "height": 480})
    return s, Detector(s, build_effects(effects, s), workers=2)


def test_gain_regions_multiply_each_block_by_its_float32_gain():
    s, det = _imx411_window(gain_regions={"nx": 3, "ny": 2, "sigma": 0.05})
    eff = det.effects[0]
    t = det.tiles(1.0, 0)[0]
    data = np.random.default_rng(0).uniform(0, 1000, size=t.shape).astype(np.float32)
    expected = data * eff.gains[np.ix_(*_region_index(eff, t))].astype(np.float32)
    eff.apply(Stage.READ, t, data)
    assert np.array_equal(data, expected)


def _region_index(eff, t):
    from detector.effects.pixel_response import region_index

    ys, xs = t.pixel_centres()
    p, s = eff.params, eff.sensor
    return region_index(ys, xs, p.nx, p.ny, s.sensor_height_px, s.sensor_width_px, p.splits_y, p.splits_x)


def test_amp_glow_edge_law_in_row_blocks_adds_the_rate_map_times_t():
    s, det = _imx411_window(amp_glow={"model": "edge", "edge": "bottom-right", "amplitude_e_per_s": 5.0,
                                      "scale_px": 3000.0})
    eff = det.effects[0]
    t = det.tiles(2.0, 0)[0]
    data = np.full(t.shape, 3.0, np.float32)
    m = eff.rate_map(t)
    m *= np.float32(2.0)
    expected = data + m
    eff.apply(Stage.DARK, t, data)
    assert np.array_equal(data, expected)
    ys, xs = t.pixel_centres()  # A t exp(-d / L), d the distance to the bottom-right corner
    d = np.hypot(ys[0], s.sensor_width_px - 1 - xs[-1])
    assert np.isclose(data[0, -1], 3.0 + 2.0 * 5.0 * np.exp(-d / 3000.0), rtol=1e-6)
    assert data[0, -1] > data[0, 0] > 3.0  # rising towards the corner


def test_uniform_signal_below_full_well_needs_no_frame_image_and_gives_the_same_frame():
    """Blooming leaves a uniform image below its threshold as it is: the chain keeps the number (no
    frame-sized array) and the frame is the bytes of the whole-image path; above the threshold it spills."""
    s, det = _imx411_window(blooming={"up_fraction": 0.5}, prnu={"sigma": 0.01})
    assert not det.needs_field_image(40.0)
    assert det.needs_field_image(2.0 * s.full_well_e)
    fast = det.expose(40.0, 1.0, frame_seed=5)
    state = det.frame_state(1.0, 5)
    whole = det.field_signal(40.0, 1.0, 5, state)  # the path taken before: the whole image through blooming
    assert np.array_equal(det.expose(whole, 1.0, frame_seed=5), fast)


def test_a_finished_tile_releases_its_hardware_maps():
    """A tile keeps its drawn map while it is processed (one draw per map) and drops it when released."""
    s, det = _imx411_window(prnu={"sigma": 0.01})
    t = det.tiles(1.0, 0)[0]

    def draw(rng, shape):
        return rng.standard_normal(shape, dtype=np.float32)

    m1 = t.hardware_map("prnu", draw)
    assert t.hardware_map("prnu", draw) is m1
    t.release()
    m2 = t.hardware_map("prnu", draw)
    assert m2 is not m1 and np.array_equal(m1, m2)  # drawn again from the hardware seed: the same map


def _box_muller_reference(seed: int, n: int, block: int) -> np.ndarray:
    """The Box-Muller transform written out deviate by deviate block (float64 throughout, then rounded)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(0, n, block):
        k = min(block, n - i)
        h = (k + 1) // 2
        u1 = rng.random(h)
        u2 = rng.random(h, dtype=np.float32).astype(np.float64)
        r = np.sqrt(-2.0 * np.log(1.0 - u1))
        theta = 2.0 * np.pi * u2
        out += [r * np.cos(theta), (r * np.sin(theta))[:k - h]]
    return np.concatenate(out)


def test_box_muller_normals_are_the_transform_of_the_generators_uniforms():
    """standard_normal_f32 is r cos(2 pi u2), r sin(2 pi u2), r = sqrt(-2 ln(1 - u1)) (Box & Muller 1958) of
    the generator's uniforms, to float32 rounding and the float32 trigonometry's few ulps; an odd count and a
    partial last block included; the same state gives the same deviates."""
    from detector.rng import NORMAL_BLOCK, standard_normal_f32

    n = 2 * NORMAL_BLOCK + 1001
    got = standard_normal_f32(np.random.default_rng(11), (n,))
    assert got.dtype == np.float32 and got.shape == (n,)
    ref = _box_muller_reference(11, n, NORMAL_BLOCK)
    assert np.max(np.abs(got - ref)) < 3e-6  # |z| <= 5.5 here: a few float32 ulps of r plus the angle's rounding
    assert np.array_equal(standard_normal_f32(np.random.default_rng(11), (n,)), got)
    two_d = standard_normal_f32(np.random.default_rng(11), (3, 7))
    assert np.array_equal(two_d.ravel(), standard_normal_f32(np.random.default_rng(11), (21,)))


def test_box_muller_normals_are_standard_normal():
    """Moments and quantiles of 2e6 deviates against N(0, 1): mean, variance, skewness, excess kurtosis within
    5 standard errors, the two-sided tail beyond 3 and 4 sigma within 5 binomial errors, and no two
    deviates of a block's cosine and sine halves correlated (r cos, r sin are independent)."""
    from scipy.special import ndtr

    from detector.rng import NORMAL_BLOCK, standard_normal_f32

    n = 2_000_000
    z = standard_normal_f32(np.random.default_rng(5), (n,)).astype(np.float64)
    se = 1.0 / np.sqrt(n)
    assert abs(z.mean()) < 5 * se
    assert abs(z.var() - 1.0) < 5 * np.sqrt(2.0) * se
    assert abs(np.mean(z ** 3)) < 5 * np.sqrt(15.0) * se
    assert abs(np.mean(z ** 4) - 3.0) < 5 * np.sqrt(96.0) * se
    for k in (1.0, 2.0, 3.0, 4.0):
        p = 2.0 * ndtr(-k)
        assert abs(np.mean(np.abs(z) > k) - p) < 5 * np.sqrt(p * (1 - p) / n)
    h = NORMAL_BLOCK // 2
    blocks = z[: (n // NORMAL_BLOCK) * NORMAL_BLOCK].reshape(-1, NORMAL_BLOCK)
    c, s = blocks[:, :h].ravel(), blocks[:, h:].ravel()
    assert abs(np.corrcoef(c, s)[0, 1]) < 5 / np.sqrt(c.size)
    assert abs(np.corrcoef(c ** 2, s ** 2)[0, 1]) < 5 / np.sqrt(c.size)


def test_separable_vignetting_map_equals_fitpacks_grid_evaluation():
    """The map's tensor-product spline as two design-matrix products equals RectBivariateSpline's grid
    evaluation (bicubic and linear axes, points beyond the map held at its edge) to 1e-14 relative; a map
    finer than SEPARABLE_MAP_COEFS keeps fitpack's evaluation (the same callable's numbers exactly)."""
    from scipy.interpolate import RectBivariateSpline

    from detector.effects.optical import SEPARABLE_MAP_COEFS, map_interpolator

    rng = np.random.default_rng(2)
    for nv, nu in ((9, 9), (3, 12), (12, 2), (5, SEPARABLE_MAP_COEFS + 8)):
        v, u = np.linspace(-15.0, 15.0, nv), np.linspace(-20.0, 20.0, nu)
        ri = 1.0 - 0.002 * (u[None, :] ** 2 + v[:, None] ** 2) / 4 + 0.01 * rng.random((nv, nu))
        f = map_interpolator(u, v, ri)
        vv, uu = np.linspace(-17.0, 16.0, 37), np.linspace(-21.0, 23.0, 301)
        kv, ku = (3 if nv >= 4 else 1), (3 if nu >= 4 else 1)
        ref = RectBivariateSpline(v, u, ri, kx=kv, ky=ku)(np.clip(vv, v[0], v[-1]), np.clip(uu, u[0], u[-1]))
        got = f(vv, uu)
        assert got.shape == (vv.size, uu.size)
        tol = 0.0 if nu > SEPARABLE_MAP_COEFS + 4 else 1e-14
        assert np.max(np.abs(got - ref) / np.abs(ref)) <= tol


def test_corner_glow_distance_from_exact_squares_equals_hypot_to_an_ulp_and_the_map_to_the_bit():
    """A corner's distance sqrt(dy^2 + dx^2) of half-integer pixel centres (exact squares: the correctly rounded
    distance) is within 1 ulp of libm's hypot, and the float32 glow (peak exp(-d / L)) of every corner of a
    binned and an unbinned window is the hypot form's, bit for bit."""
    from detector.effects.glow import _exact_squares, edge_rate

    ys, xs = np.arange(0.0, 10640.0, 7.5), np.arange(0.5, 14192.0, 3.5)
    assert _exact_squares(ys) and _exact_squares(xs) and not _exact_squares(np.array([0.25]))
    d = np.sqrt(np.add.outer(ys * ys, xs * xs))
    h = np.hypot(ys[:, None], xs[None, :])
    assert np.max(np.abs(d - h) / np.spacing(h)) <= 1.0
    for binning in (1, 2):
        s = make_sensor("imx411", {"width": 1024, "height": 480, "binning": binning})
        det = Detector(s, build_effects({}, s), workers=1)
        t = det.tiles(1.0, 0)[0]
        y, x = t.pixel_centres()
        for corner in ("bottom-left", "bottom-right", "top-left", "top-right"):
            fast, ref = (np.zeros(t.shape, np.float32) for _ in range(2))
            edge_rate(y, x, s.sensor_height_px, s.sensor_width_px, corner, 5.0, 400.0, fast)
            edge_rate(y, x, s.sensor_height_px, s.sensor_width_px, corner, 5.0, 400.0, ref, exact=False)
            assert np.array_equal(fast, ref)
