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
