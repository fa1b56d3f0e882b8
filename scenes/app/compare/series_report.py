"""The HTML report of a series comparison or diagnosis (``--series ... --report OUT.html``): one file.

Sections: the verdict and the separation (what told the winner from its nearest rival, as a table and a
plot of each candidate's pattern fitted frame by frame against exposure time and signal), the frames side
by side (their residual statistics and residual maps), the candidates, the calibration regressions and the
ledger.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from detector.errors import DetectorError

from .report import _CSS, _e, _fig_html, _figure, _fmt, _png_file, _section, _table

#: side of the residual thumbnails [blocks]
THUMB = 64


def _verdict(d: dict) -> str:
    b = d["baseline"]
    body = (f"<p><b>{_e(d.get('verdict', 'comparison only'))}</b></p>"
            f"<p>{b['n_frames']} frames, {b['n_compared']} pixels compared; chi2/dof {_fmt(b['chi2_per_dof'])} "
            f"(levels refitted: {_fmt(b['chi2_per_dof_levels'])}); levels shared by the series: "
            f"{_e(', '.join(d.get('shared_levels') or []) or 'none')}</p>")
    sep = d.get("separation")
    if sep:
        body += f"<p>{_e(sep['statement'])}</p>"
    return _section("verdict", "Verdict", body)


def _separation(d: dict) -> str:
    sep = d.get("separation")
    if not sep:
        return ""
    rows = sep["frames"]
    keys = [k for k in ("best", "rival") if sep.get(k)]
    header = ["frame", "exposure [s]", "signal [e-]"]
    for k in keys:
        header += [f"{sep[k]}: delta chi2", f"{sep[k]}: amplitude"]
    table = []
    for r in rows:
        line = [r["label"], r["exposure_s"], r["signal_e"]]
        for k in keys:
            a = r.get(f"amplitude_{k}")
            e = r.get(f"amplitude_error_{k}")
            line += [r.get(f"delta_chi2_{k}"), "" if a is None else f"{a:.4g} +- {e:.2g}"]
        table.append(line)
    html = _table(header, table, numeric={1, 2, 3, 5})
    fig, axes = _figure(2, 1, width=10, height=3.4)
    for ax, xkey, xlabel in ((axes[0], "exposure_s", "exposure time [s]"), (axes[1], "signal_e", "signal [e-]")):
        for k, style in zip(keys, ("o-", "s--")):
            pts = [(r[xkey], r[f"amplitude_{k}"], r.get(f"amplitude_error_{k}") or 0.0) for r in rows
                   if r.get(f"amplitude_{k}") is not None]
            if pts:
                x, y, e = (np.array(v, float) for v in zip(*pts))
                ax.errorbar(x, y, yerr=e, fmt=style, ms=4, label=f"{sep[k]} ({(sep.get('scaling') or {}).get(k)})")
        ax.axhline(1.0, color="grey", lw=0.8, ls=":")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("pattern fitted per frame / joint fit")
        ax.legend(fontsize=8)
    caption = ("Each shared candidate's own pattern fitted to every frame alone (the series' shared levels held), "
               "relative to its joint fit: an effect of the right scaling stays at 1 in every frame; one of the wrong "
               "scaling drifts with exposure or signal.")
    plot = _fig_html(fig, caption) if any(r.get("amplitude_best") is not None for r in rows) else ""
    curve = sep.get("residual_vs_signal")
    if curve:
        fig, axes = _figure(1, 1, width=6, height=3.4)
        ax = axes[0]
        x = np.array([c["signal_e"] for c in curve])
        ax.plot(x, [100 * c["residual_rel"] for c in curve], "ko", label="measured (data - model) / light")
        for k, style in zip(keys, ("-", "--")):
            pts = [(c["signal_e"], 100 * c[f"{k}_rel"]) for c in curve if f"{k}_rel" in c]
            if pts:
                ax.plot(*zip(*sorted(pts)), style, label=f"{sep[k]} predicts")
        ax.axhline(0.0, color="grey", lw=0.8, ls=":")
        ax.set_xlabel("signal [e-]")
        ax.set_ylabel("residual [% of the light]")
        ax.legend(fontsize=8)
        plot += _fig_html(fig, "The lit frames' mean residual against their signal level, the series' shared light "
                          "level (fitted without any candidate) removed: a non-linearity is a deficit growing with the "
                          "signal, a lamp-level error a constant.")
    return _section("separation", "What told the candidates apart", html + plot)


def _frames(d: dict, compares: list[dict] | None) -> str:
    rows = [[f["label"], Path(f["file"]).name, f["light_source"], f["exposure_s"], f["signal_e"], f["chi2_per_dof"],
             f.get("chi2_per_dof_levels"), f["misfit"], f["n_compared"],
             (f.get("residual_morphology") or {}).get("explanation", "")] for f in d["frames"]]
    html = _table(["frame", "file", "light", "exposure [s]", "signal [e-]", "chi2/dof", "chi2/dof (levels)", "misfit",
                   "pixels", "residual looks like"], rows, numeric={3, 4, 5, 6, 7, 8})
    if compares:
        n = len(compares)
        ncol = min(n, 5)
        nrow = (n + ncol - 1) // ncol
        fig, axes = _figure(ncol, nrow, width=2.4 * ncol, height=2.5 * nrow)
        for ax, c, f in zip(axes, compares, d["frames"]):
            res = c["_residuals"]
            z = np.where(res.fit, (res.data_adu - res.model_adu) / np.sqrt(np.maximum(res.var_adu2, 1e-12)), np.nan)
            b = max(1, max(z.shape) // THUMB)
            h, w = (z.shape[0] // b) * b, (z.shape[1] // b) * b
            zb = np.nanmean(z[:h, :w].reshape(h // b, b, w // b, b), axis=(1, 3)) * b  # sigma of a block mean
            ax.imshow(zb, origin="lower", cmap="RdBu_r", vmin=-5, vmax=5)
            ax.set_title(f"{f['label']} ({f['exposure_s']:.3g} s)", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
        for ax in axes[n:]:
            ax.axis("off")
        html += _fig_html(fig, "Residual (data - model) of every frame in block means, in units of the block mean's "
                          "standard deviation (-5 .. 5), the levels not refitted.")
    return _section("frames", "The frames side by side", html)


def _candidates(d: dict) -> str:
    if not d.get("candidates"):
        return ""
    rows = [[c["effect"], c.get("scaling", ""), "shared" if c.get("shared") else "per frame", c["delta_bic"],
             c.get("heldout_delta"), c["chi2_per_dof"], "yes" if c["significant"] else "no",
             c.get("implausible_because") or c.get("rejected") or c["explanation"]] for c in d["candidates"][:15]]
    return _section("candidates", "Candidates over the series",
                    _table(["effect", "scaling", "fitted", "delta BIC", "held out (leave one frame out)",
                            "chi2/dof after", "significant", "explanation / why not"], rows, numeric={3, 4, 5}))


def _calibration(d: dict) -> str:
    cal = d.get("calibration") or {}
    parts = []
    for key, title in (("dark_regression", "Dark level against exposure time"),
                       ("linearity", "Flat signal against exposure time")):
        e = cal.get(key)
        if not e:
            continue
        rows = [[lab, t, m, mo] for lab, t, m, mo in zip(e["frames"], e["exposure_s"], e["measured_adu"],
                                                        e["model_adu"])]
        text = (f"<p>{title}: slope measured {_fmt(e['measured_slope_adu_per_s'])} ADU/s, model "
                f"{_fmt(e['model_slope_adu_per_s'])} ADU/s"
                + (f" (dark rate {_fmt(e['measured_rate_e_per_s'])} against {_fmt(e['model_rate_e_per_s'])} e-/s)"
                   if "measured_rate_e_per_s" in e else "")
                + (f"; largest deviation from a straight line {100 * e['max_linearity_deviation']:.3g} %"
                   if "max_linearity_deviation" in e else "") + "</p>")
        parts.append(text + _table(["frame", "exposure [s]", "measured median [ADU]", "model median [ADU]"], rows,
                                   numeric={1, 2, 3}))
    for r in cal.get("read_noise", []):
        parts.append(f"<p>Read noise from the bias pair {_e(' / '.join(r['frames']))}: {_fmt(r['measured_e'])} e- "
                     f"(scene {_fmt(r['scene_e'])} e-)</p>")
    for r in cal.get("photon_transfer", []):
        parts.append(f"<p>Gain by photon transfer from the flat pair {_e(' / '.join(r['frames']))} at "
                     f"{_fmt(r['signal_adu'])} ADU: {_fmt(r['measured_gain_e_per_adu'])} +- {_fmt(r['gain_se'])} e-/ADU "
                     f"(scene {_fmt(r['scene_gain_e_per_adu'])} e-/ADU)</p>")
    return _section("calibration", "Calibration of the series", "".join(parts)) if parts else ""


def _ledger(d: dict) -> str:
    led = d.get("ledger")
    if not led:
        return ""
    img = _png_file(led.get("plot"))
    rows = [[r["round"], r["chi2_per_dof"], r["misfit"], r.get("applied") or ""] for r in led["rounds"]]
    return _section("ledger", "The series' error round by round",
                    _table(["round", "chi2/dof", "misfit", "applied"], rows, numeric={1, 2}) + (img or ""))


def render_series_html(d: dict, compares: list[dict] | None = None, title: str | None = None) -> str:
    title = title or f"newtsim series: {Path(d.get('series') or d['baseline'].get('series_file', '')).name}"
    body = "".join([_verdict(d), _separation(d), _frames(d, compares), _candidates(d), _calibration(d), _ledger(d)])
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_e(title)}</title><style>{_CSS}</style>"
            f"</head><body><h1>{_e(title)}</h1>{body}</body></html>")


def write_series_report(d: dict, path, compares: list[dict] | None = None) -> Path:
    """Write the series report (``d``: :func:`.series.run_series_diagnose` or the compare's result) as one
    self-contained HTML file."""
    p = Path(path)
    try:
        p.write_text(render_series_html(d, compares), encoding="utf-8")
    except OSError as exc:
        raise DetectorError(f"cannot write the report ({exc.strerror or exc})", file=str(p),
                            expected="a writable file in an existing folder") from None
    return p
