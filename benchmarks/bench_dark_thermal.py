"""The exponential form of dark_gradient costs its Gauss-Newton on the search sample: the dark_gradient signature's
fit with both forms against the linear ramp alone and against bias_gradient's fit, in the same run, on synthetic
residuals of an ML11002 600 s dark with a 4 K x -2 K temperature gradient (binned 8x8: 167k pixels, the search
sample is every pixel; binned 2x2: 2.7M pixels, a 300k-pixel search sample). Prints JSON."""

from __future__ import annotations

import json
import time

import numpy as np

from detector import make_sensor, registry
from detector.effects import thermal
from detector.signatures import LinearSignature, Residuals, SpikeStats


def residuals(binning: int, t: float = 600.0) -> Residuals:
    s = make_sensor("ml11002", {"binning": binning})
    h, w = s.output_shape
    b, g = s.binning, s.gain_e_per_adu
    ys, xs = b * np.arange(h) + (b - 1) / 2.0, b * np.arange(w) + (b - 1) / 2.0
    dark = np.full((h, w), s.dark_current_e_per_s * t * b * b)
    extra = thermal.thermal_rate(ys, xs, s.sensor_height_px, s.sensor_width_px, s.dark_current_e_per_s, 4.0, -2.0,
                                 thermal.doubling_interval_k(s.temperature_c)) * t * b * b
    rng = np.random.default_rng(1)
    charge = dark + extra
    data = s.bias_adu + (charge + rng.normal(0, 1, (h, w)) * np.sqrt(charge + s.read_noise_e ** 2)) / g
    f32 = np.float32
    return Residuals(data.astype(f32), (s.bias_adu + dark / g).astype(f32),
                     ((dark + s.read_noise_e ** 2) / g ** 2).astype(f32), np.ones((h, w), bool),
                     np.zeros((h, w), f32), dark.astype(f32), ys, xs, s, t, SpikeStats(0, 0, 0, 0, 0),
                     SpikeStats(0, 0, 0, 0, 0))


def timed(fn, repeat=3):
    best = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        best = dt if best is None else min(best, dt)
    return best, out


def main():
    reg = registry()
    sig = reg["dark_gradient"].signature
    linear_only = LinearSignature(lambda r: [next(iter(thermal._variants(r)))], sig.explain, extra_k=0,
                                  adds_charge=True)
    out = {}
    for b in (8, 2):
        res = residuals(b)
        fresh = lambda: Residuals(**{k: getattr(res, k) for k in res.__dataclass_fields__ if k != "_flat"})  # noqa: E731
        t_both, fit = timed(lambda: sig.fit(fresh(), "dark_gradient"))
        t_lin, _ = timed(lambda: linear_only.fit(fresh(), "dark_gradient"))
        t_bias, _ = timed(lambda: reg["bias_gradient"].signature.fit(fresh(), "bias_gradient"))
        out[f"binning_{b}"] = {"pixels": int(res.data_adu.size), "dark_gradient_both_forms_s": round(t_both, 3),
                               "reference_linear_ramp_only_s": round(t_lin, 3),
                               "reference_bias_gradient_s": round(t_bias, 3), "fitted": fit.params}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
