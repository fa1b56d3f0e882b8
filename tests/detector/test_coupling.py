"""Inter-pixel capacitance seen in the noise: the diagnosis' physical test of a fitted coupling."""

import numpy as np
def test_ipc_is_refused_when_the_sky_noise_is_not_coupled():
    """IPC couples the shot noise too: on a shot-dominated frame whose noise is white, a fitted 2 % coupling is
    refused (it would correlate neighbours by 0.038, the 80 000 pairs measure +-0.0035); the same frame whose
    noise went through the coupling keeps it. Neighbour correlation of a coupled flat: Moore et al. 2004."""
    from types import SimpleNamespace

    from detector.effects.coupling import ipc_check, ipc, ipc_noise_correlation

    rng = np.random.default_rng(5)
    shape, q, gain = (200, 200), 10_000.0, 1.0
    white = rng.normal(0.0, np.sqrt(q), shape)
    coupled = ipc(q + white, 0.02, 0.0) - q
    fit = SimpleNamespace(params={"alpha": 0.02})
    for noise, refused in ((white, True), (coupled, False)):
        res = SimpleNamespace(sensor=SimpleNamespace(binning=1), var_adu2=np.full(shape, q, np.float32),
                              data_adu=(q + noise).astype(np.float32), model_adu=np.full(shape, q, np.float32),
                              fit=np.ones(shape, bool), photo_adu=np.full(shape, q, np.float32),
                              background_photo_adu=np.full(shape, q, np.float32),
                              charge_e=np.full(shape, q, np.float32), gain=gain)
        why = ipc_check(fit, res)
        assert bool(why) is refused, why
    assert abs(ipc_noise_correlation(0.02) - 0.0433) < 1e-3


def test_a_small_ipc_on_light_alone_is_the_image_of_a_blur_unless_the_frame_tells_the_stage():
    """A 0.17 % coupling of a frame whose charge is all light, with too few quiet pairs to see the coupled noise
    (0.0034 implied, +-0.0035 measured), is the image of a PSF changed by that kernel: the IPC says it cannot be
    told from psf_blur. Hot pixels in the dark charge (charge that is not light) or a coupling the noise test
    can see (2 %: 0.043) tell the stage."""
    from types import SimpleNamespace

    from detector.effects.coupling import ipc_untold_from

    shape, q = (200, 200), 100.0
    idx = np.arange(shape[0] * shape[1])
    data = (q + np.random.default_rng(3).normal(0.0, np.sqrt(q), shape)).astype(np.float32)

    def frame(dark):
        return SimpleNamespace(sensor=SimpleNamespace(binning=1), var_adu2=np.full(shape, q, np.float32),
                               data_adu=data, model_adu=np.full(shape, q, np.float32),
                               fit=np.ones(shape, bool), photo_adu=np.full(shape, q, np.float32),
                               background_photo_adu=np.full(shape, q, np.float32), charge_e=q + dark,
                               dark_e=dark, gain=1.0, flat_profiled=lambda: (idx, None, np.full(idx.size, 1 / q)))

    small, large = SimpleNamespace(params={"alpha": 0.0017}), SimpleNamespace(params={"alpha": 0.02})
    no_dark = np.zeros(shape, np.float32)
    hot = no_dark.copy()
    hot[50, 50] = hot[120, 30] = 50_000.0
    assert ipc_untold_from(small, frame(no_dark)) == ("psf_blur",)
    assert ipc_untold_from(small, frame(np.full(shape, 30.0, np.float32))) == ("psf_blur",)  # a uniform dark
    assert ipc_untold_from(small, frame(hot)) == ()
    assert ipc_untold_from(large, frame(no_dark)) == ()
