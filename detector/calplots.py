"""Figures of a calibration-frame characterisation (:func:`detector.characterize.characterize`).

Everything is drawn from the result dict alone (its ``plot_data`` entries), so the figures can be re-made
from a saved ``--json`` file. Matplotlib's Agg canvas is used directly (no ``pyplot``, no global backend
switch), so this works headless and does not disturb an interactive session.

Figures (PNG, in the output folder):

* ``bias_noise.png``: single-bias-frame histogram (level + fixed pattern + read noise), the pair-difference
  histogram with the normal of the fitted std, and the normal QQ plot of the pair difference with the
  Shapiro-Wilk / Jarque-Bera / Kolmogorov-Smirnov p-values;
* ``dark_current.png``: inlier-mean dark level against exposure with the straight-line fit (thesis
  regression) and the hold-out prediction; counts of pixels above the thresholds against exposure;
* ``hot_pixels.png``: histogram of the hot pixels' time-to-double (log bins) with the fitted Weibull and
  exponential laws (expected counts per bin) and the detection limit;
* ``photon_transfer.png`` (with flats): variance against signal (bias point, 4x4 flat tiles) with the
  lines of the photon-transfer and header gains, and the smoothed flat (vignetting) map.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import stats


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _hist_step(ax, hist: dict, **kw):
    e = np.asarray(hist["edges"], float)
    c = np.asarray(hist["counts"], float)
    ax.stairs(c, e, **kw)
    return e, c


def _hist_with_normal(ax, hist, mu: float, sd: float, xlabel: str, label: str | None = None) -> None:
    """A stored histogram as a step line with the normal of the same area, mean ``mu`` and std ``sd``."""
    e, c = _hist_step(ax, hist, color="k", label=label)
    x = np.linspace(e[0], e[-1], 400)
    ax.plot(x, c.sum() * np.diff(e).mean() * stats.norm.pdf(x, mu, sd), "r-", lw=1, label=f"normal, std {sd:.2f} ADU")
    ax.set_yscale("log")
    ax.set_ylim(0.5, None)
    ax.set_xlabel(xlabel)


def plot_bias(result: dict, path: Path) -> Path | None:
    b = result["bias"]
    pdat = b.get("plot_data") or {}
    fig = _figure(13, 4)
    axs = fig.subplots(1, 3)
    if "single_frame_hist" in pdat:
        mu, sd = pdat.get("single_frame_mean_std", [b["level_mean_adu"], b["single_frame_std_adu"]])
        _hist_with_normal(axs[0], pdat["single_frame_hist"], mu, sd, "bias frame value [ADU]")
        axs[0].set_ylabel("pixels")
        axs[0].set_title(f"bias level {b['level_median_adu']:.1f} ADU (median)")
        axs[0].legend(fontsize=8)
    if "pair_diff_hist" in pdat:
        _hist_with_normal(axs[1], pdat["pair_diff_hist"], b.get("pair_difference_mean_adu") or 0.0,
                          b["read_noise_adu"] * math.sqrt(2), "pair difference [ADU]", label="b1 - b2")
        axs[1].set_title(f"read noise {b['read_noise_adu']:.2f} ADU = {b['read_noise_e']:.2f} e-")
        axs[1].legend(fontsize=8)
    else:
        axs[1].text(0.5, 0.5, "one bias frame:\nno pair difference", ha="center", va="center",
                    transform=axs[1].transAxes)
    if "qq" in pdat:
        th = np.asarray(pdat["qq"]["theoretical"])
        sm = np.asarray(pdat["qq"]["sample_adu"])
        n = b["normality"]
        axs[2].plot(th, sm, ".", ms=3, color="k")
        axs[2].plot(th, n["mean"] + n["std"] * th, "r-", lw=1)
        axs[2].set_xlabel("normal quantile")
        axs[2].set_ylabel("pair difference quantile [ADU]")
        txt = "\n".join(f"{lab}: p = {n[k]['p_value']:.3g}" for k, lab in
                        (("shapiro_wilk", "Shapiro-Wilk"), ("jarque_bera", "Jarque-Bera"),
                         ("kolmogorov_smirnov", "Kolmogorov-Smirnov")) if k in n)
        axs[2].text(0.03, 0.97, txt + f"\n(n = {n['n']})", transform=axs[2].transAxes, va="top", fontsize=8)
        axs[2].set_title("QQ plot of the pair difference")
    fig.savefig(path)
    return path


def plot_darks(result: dict, path: Path) -> Path | None:
    d = result["dark"]
    pdat = d.get("plot_data") or {}
    t = np.asarray(pdat.get("t", d["exposures_s"]), float)
    fig = _figure(12, 4.5)
    ax, ax2 = fig.subplots(1, 2)
    ax.plot(t, pdat["inlier_mean"], "ko", label="inlier mean (3-sigma clipped)")
    ax.plot(t, pdat["median"], "s", mfc="none", color="0.5", label="median")
    f = d["fit"]
    tt = np.linspace(0, t.max() * 1.05, 100)
    ax.plot(tt, f["intercept"] + f["slope"] * tt, "r-",
            label=f"fit: {f['intercept']:.2f} + {f['slope']:.4f} t  ({d['dark_current_e_per_s']:.3g} e-/s)")
    ax.axhline(result["bias"]["level_mean_adu"], color="b", ls=":", lw=1, label="bias level")
    ho = d.get("holdout") or {}
    if ho.get("predictions"):
        hf = ho["fit"]
        ax.plot(tt, hf["intercept"] + hf["slope"] * tt, "g--", lw=1,
                label=f"fit on {', '.join(f'{x:g}' for x in ho['fit_exposures_s'])} s")
        for p in ho["predictions"]:
            m = p["mean_adu"]
            ax.errorbar([p["exposure_s"]], [m["predicted"]], yerr=[m.get("predicted_se") or 0], fmt="g^",
                        label=f"predicted at {p['exposure_s']:g} s ({100 * p['dark_signal_adu']['rel_error']:+.1f} % "
                              "dark signal)")
    ax.set_xlabel("exposure [s]")
    ax.set_ylabel("dark level [ADU]")
    ax.set_title("dark level against exposure")
    ax.legend(fontsize=7)
    for k, counts in (pdat.get("counts") or {}).items():
        c = np.asarray(counts, float)
        ok = c > 0
        ax2.plot(t[ok], c[ok], "o-", label=f"> {k} ADU above bias")
        for p in ho.get("predictions", []):
            e = p["count_above_bias_adu"].get(k)
            if e:
                ax2.plot([p["exposure_s"]], [e["per_pixel_extrapolation"]], "kx")
                if e.get("t_double_law"):
                    ax2.plot([p["exposure_s"]], [e["t_double_law"]], "k+", ms=10)
    ax2.plot([], [], "kx", label="hold-out: per-pixel lines")
    ax2.plot([], [], "k+", label="hold-out: t_double law")
    ax2.set_xscale("log")
    ax2.set_yscale("log")
    ax2.set_xlabel("exposure [s]")
    ax2.set_ylabel("pixels")
    ax2.set_title("pixels above thresholds")
    ax2.legend(fontsize=7)
    fig.savefig(path)
    return path


def plot_hot_pixels(result: dict, path: Path) -> Path | None:
    hp = result["hot_pixels"]
    pdat = hp.get("plot_data") or {}
    if "t_double_hist" not in pdat:
        return None
    fig = _figure(7, 4.5)
    ax = fig.subplots()
    e, c = _hist_step(ax, pdat["t_double_hist"], color="k", label=f"hot pixels (n = {hp['n_hot']})")
    fits = hp.get("fits", {})
    n = c.sum()
    mid = np.sqrt(e[:-1] * e[1:])
    if "weibull" in fits:
        w = fits["weibull"]
        exp_w = n * np.diff(stats.weibull_min.cdf(e, w["shape"], 0, w["scale_s"]))
        ax.plot(mid, exp_w, "r-", label=f"Weibull k = {w['shape']:.3f}, scale = {w['scale_s']:.4g} s "
                                        f"(AIC {w['aic']:.6g})")
    if "exponential" in fits:
        x = fits["exponential"]
        exp_e = n * np.diff(stats.expon.cdf(e, 0, x["scale_s"]))
        ax.plot(mid, exp_e, "b--", label=f"exponential, scale = {x['scale_s']:.4g} s (AIC {x['aic']:.6g})")
    lim = hp.get("t_double_detection_limit_s")
    if lim:
        ax.axvline(lim, color="0.5", ls=":", label=f"detection limit {lim:.4g} s")
    ax.set_xscale("log")
    ax.set_xlabel("time to double t2 = B / r [s]")
    ax.set_ylabel("pixels per bin")
    ax.set_title(f"hot pixels: preferred law {fits.get('preferred', '-')}")
    ax.legend(fontsize=7)
    fig.savefig(path)
    return path


def plot_photon_transfer(result: dict, path: Path) -> Path | None:
    fl = result.get("flat")
    if not fl:
        return None
    pt = fl["photon_transfer"]
    pdat = pt.get("plot_data") or {}
    fig = _figure(12, 4.5)
    ax, ax2 = fig.subplots(1, 2)
    pts = np.asarray(pdat.get("tiles_signal_variance", []), float)
    rv = pdat.get("read_variance_adu2", result["bias"]["read_noise_adu"] ** 2)
    if pts.size:
        ax.plot(pts[:, 0], pts[:, 1], "k.", label="flat-pair tiles (4x4)")
    ax.plot([0], [rv], "bs", label="bias pair (read noise)")
    smax = max(pt["signal_adu"], pts[:, 0].max() if pts.size else 0) * 1.1
    s = np.linspace(0, smax, 50)
    K = pt["gain_e_per_adu"]
    ax.plot(s, s / K + rv, "r-", label=f"photon transfer K = {K:.3f} e-/ADU")
    g = result["gain"].get("header_e_per_adu")
    if g:
        ax.plot(s, s / g + rv, "g--", label=f"header gain {g:.3f} e-/ADU")
    ax.set_xlabel("signal (bias subtracted) [ADU]")
    ax.set_ylabel("temporal variance [ADU^2]")
    ax.set_title("photon transfer")
    ax.legend(fontsize=8)
    m = fl.get("prnu", {}).get("plot_data", {}).get("smooth_map_rel")
    if m is None:
        m = (fl.get("plot_data") or {}).get("smooth_map_rel")
    if m is not None:
        im = ax2.imshow(np.asarray(m, float), origin="lower", cmap="viridis")
        fig.colorbar(im, ax=ax2, label="smoothed flat / centre")
        v = fl["vignetting"]
        ax2.set_title(f"vignetting: corner/centre {v['corner_over_centre_mean']:.3f}, PRNU "
                      f"{100 * fl['prnu_rel']:.2f} %")
        ax2.set_xlabel("x (decimated)")
        ax2.set_ylabel("y (decimated)")
    fig.savefig(path)
    return path


def write_plots(result: dict, outdir) -> list[str]:
    """Write every figure that the result supports into ``outdir`` (created). Returns the file paths."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    made = []
    for fn, name in ((plot_bias, "bias_noise.png"), (plot_darks, "dark_current.png"),
                     (plot_hot_pixels, "hot_pixels.png"), (plot_photon_transfer, "photon_transfer.png")):
        p = fn(result, out / name)
        if p is not None:
            made.append(str(p))
    return made
